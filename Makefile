# skinid — the two commands a user needs: `make test` and `make demo`.
# Each bootstraps .venv on a fresh machine (scripts/setup.sh).
VENV ?= .venv
PY := $(VENV)/bin/python
export OMP_NUM_THREADS ?= 1

.PHONY: setup test test-fast demo benchmarks clean

$(VENV)/.installed: pyproject.toml scripts/setup.sh
	VENV=$(VENV) bash scripts/setup.sh

setup: $(VENV)/.installed

test: setup
	$(PY) -m pytest -q tests

test-fast: setup
	$(PY) -m pytest -q -m "not slow and not mpi" tests

demo: setup
	$(VENV)/bin/skinid mesh --config small
	$(VENV)/bin/skinid simulate --config small --mu 0.0012 --k1 0.017 --k2 12 --kappa 0.28 \
		--theta 30 --alpha11 0.05 --alpha22 -0.05 --out out/demo/simulation.h5 \
		--fields out/demo/fields.xdmf

benchmarks: setup
	$(PY) benchmarks/forward.py timing
	$(PY) benchmarks/forward.py convergence

clean:
	rm -rf out/ meshes/*.msh .pytest_cache
