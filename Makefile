# The two commands of the README: `make demo` (main job) and `make test` (whole suite).
# Both create the virtual environment on first use.
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
# Test processes (pytest-xdist). Most tests wait on peers, processes and sockets rather than
# compute, so two per core keep a 2-core machine busy; whole files go to one process
# (--dist loadfile): a file's fixed loopback addresses and module fixtures stay in it.
TEST_JOBS ?= 4
# One BLAS thread per process: with several test processes (and the daemons and workers they
# start) a threaded BLAS oversubscribes the cores and spins; single-threaded it is faster.
TEST_ENV := OPENBLAS_NUM_THREADS=1 OMP_NUM_THREADS=1

# make explore: the property tests with fresh random examples, ROUNDS runs (tests/conftest.py)
ROUNDS ?= 10

.PHONY: demo test lint bench explore clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e '.[test]'
	touch $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/vgripd demo

lint: $(STAMP)
	$(PY) -m ruff check vgripd drivers tests bench
	$(PY) -m mypy

test: lint
	$(TEST_ENV) $(PY) -m pytest -q -n $(TEST_JOBS) --dist loadfile

explore: $(STAMP)
	for i in $$(seq $(ROUNDS)); do \
	    VGRIPD_HYPOTHESIS=explore $(TEST_ENV) $(PY) -m pytest -q -n $(TEST_JOBS) --dist loadfile \
	        $$(grep -rl "^from hypothesis" tests --include='test_*.py') || exit 1; \
	done

bench: $(STAMP)
	for f in bench/bench_*.py; do $(PY) $$f || exit 1; done

clean:
	rm -rf $(VENV) build *.egg-info
