# skinid — the two commands a user needs: `make test` and `make demo` (`make lint`: ruff, run by CI).
# Each bootstraps .venv on a fresh machine (scripts/setup.sh).
VENV ?= .venv
PY := $(VENV)/bin/python
export OMP_NUM_THREADS ?= 1

.PHONY: setup lint test test-fast demo benchmarks clean

$(VENV)/.installed: pyproject.toml scripts/setup.sh
	VENV=$(VENV) bash scripts/setup.sh

setup: $(VENV)/.installed

LINTED := skinfem surrogate inference tests benchmarks scripts notebooks

lint: setup
	$(VENV)/bin/ruff check $(LINTED)
	$(VENV)/bin/ruff format --check $(LINTED)

test: setup
	$(PY) -m pytest -q tests

test-fast: setup
	$(PY) -m pytest -q -m "not slow and not mpi" tests

demo: setup
	$(PY) scripts/demo.py --out out/demo

benchmarks: setup
	$(PY) benchmarks/forward.py timing
	$(PY) benchmarks/forward.py convergence
	$(PY) benchmarks/sweep.py --config small

clean:
	rm -rf out/ meshes/*.msh .pytest_cache
