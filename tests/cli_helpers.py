"""Running the ``skinid`` command line from tests (serially or under mpirun)."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

MPIRUN = shutil.which("mpirun", path=str(Path(sys.executable).parent)) or shutil.which("mpirun")


def skinid_command(*args, ranks: int = 1) -> list[str]:
    cmd = [sys.executable, "-m", "skinfem.cli", *map(str, args)]
    return [MPIRUN, "-n", str(ranks), *cmd] if ranks > 1 else cmd


def skinid_env() -> dict[str, str]:
    return {**os.environ, "OMP_NUM_THREADS": "1"}


def skinid(*args, ranks: int = 1, cwd=None) -> subprocess.CompletedProcess:
    """Run ``skinid args...`` to completion and capture its output."""
    return subprocess.run(
        skinid_command(*args, ranks=ranks),
        capture_output=True,
        text=True,
        cwd=cwd,
        env=skinid_env(),
        timeout=600,
    )
