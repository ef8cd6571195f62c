# The two set-up commands of the README: `make demo` and `make test`.
# Each creates .venv and installs the pinned dependencies when missing.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test test-fast chaos lint bench clean

$(STAMP): pyproject.toml constraints.txt
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -c constraints.txt -e '.[test]'
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/pipesentry demo

# Two pytest-xdist workers (WORKERS=1 for one process): most of an e2e test's time is spent waiting
# on real processes, so two share two cores well. Every test has its own files, ports, PostgreSQL
# schema or database, so none depends on running alone. One BLAS thread per worker (as the benchmarks
# run): two workers each starting OpenBLAS's two threads on two cores spin against each other
# (tests/imaging/test_strong_change.py on 2 workers: 64 s with its threads, 38 s with one, 2026-12-07).
WORKERS ?= 2
ONE_THREAD := OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 MKL_NUM_THREADS=1

# It ends with the 25 slowest tests' times: every CI log says where the suite's time goes.
test: $(STAMP) lint
	bash scripts/ensure-test-deps.sh
	$(ONE_THREAD) $(BIN)/python -m pytest -n $(WORKERS) --dist worksteal --durations=25

# The unit tests only (no real processes, PostgreSQL or browser): about a minute.
test-fast: $(STAMP)
	$(ONE_THREAD) $(BIN)/python -m pytest -q -m "not e2e and not postgres and not browser"

# The chaos suite at full size (tests/chaos: more kills and outages, the 16-node soak); `make test` runs
# it reduced. Needs root for the tmpfs mounts of the disk-full cases. About 10 minutes on 2 cores.
chaos: $(STAMP)
	PIPESENTRY_CHAOS_FULL=1 $(BIN)/python -m pytest tests/chaos -s -q

# Lint and type gates (part of `make test`).
lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/mypy
	$(BIN)/lint-imports --no-cache

bench: $(STAMP)
	for b in bench/bench_*.py; do $(BIN)/python $$b || exit 1; done

clean:
	rm -rf $(VENV) .pytest_cache .hypothesis
