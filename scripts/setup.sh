#!/usr/bin/env bash
# Create the project-local virtual environment .venv and install skinid into it.
#
# Python: the first of python3.12, python3.13, python3 (or $PYTHON) that is >= 3.12.
# DOLFINx: if that interpreter already imports dolfinx (conda-forge / apt install), the venv
# is created with --system-site-packages and uses it; otherwise the PyPI wheel
# dolfinx-solver-real (DOLFINx 0.11 + PETSc + MPICH) is installed.
set -euo pipefail
cd "$(dirname "$0")/.."
VENV=${VENV:-.venv}

usable() { "$1" -c 'import sys; sys.exit(0 if sys.version_info >= (3, 12) else 1)' >/dev/null 2>&1; }

find_python() {
    local c
    for c in ${PYTHON:-} python3.12 python3.13 python3; do
        if command -v "$c" >/dev/null 2>&1 && usable "$c"; then echo "$c"; return 0; fi
    done
    # pyenv installs that are not on the active version list
    for c in "${PYENV_ROOT:-$HOME/.pyenv}"/versions/3.1[2-9]*/bin/python3; do
        if [ -x "$c" ] && usable "$c"; then echo "$c"; return 0; fi
    done
    return 1
}

if [ ! -x "$VENV/bin/python" ]; then
    PY=$(find_python) || { echo "error: no Python >= 3.12 found (set PYTHON=/path/to/python3.12)" >&2; exit 1; }
    if "$PY" -c 'import dolfinx' >/dev/null 2>&1; then
        echo "using the DOLFINx that $PY already provides"
        "$PY" -m venv --system-site-packages "$VENV"
    else
        "$PY" -m venv "$VENV"
    fi
fi

"$VENV/bin/python" -m pip install -q --upgrade pip
if "$VENV/bin/python" -c 'import dolfinx' >/dev/null 2>&1; then
    "$VENV/bin/python" -m pip install -q -e ".[dev]"
else
    "$VENV/bin/python" -m pip install -q -e ".[fem,dev]"
fi
"$VENV/bin/python" -c 'import skinfem, surrogate, inference; print("skinid installed in '"$VENV"'")'
touch "$VENV/.installed"
