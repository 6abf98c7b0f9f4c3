# The two commands of the README: `make demo` (main job) and `make test` (whole suite).
# Both create the virtual environment on first use; `make demo` without the test toolchain.
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
RUNTIME_STAMP := $(VENV)/.runtime
RUNTIME := $(VENV)/bin/python
# Test processes (pytest-xdist). Most tests wait on peers, processes and sockets rather than
# compute, so two per core keep a 2-core machine busy; whole files go to one process
# (--dist loadfile): a file's fixed loopback addresses and module fixtures stay in it.
TEST_JOBS ?= 4
# One BLAS thread per process: with several test processes (and the daemons and workers they
# start) a threaded BLAS oversubscribes the cores and spins; single-threaded it is faster.
# Bytecode written: the suite starts hundreds of daemons and workers, and with
# PYTHONDONTWRITEBYTECODE set (some images set it) each would compile vgripd from source again.
TEST_ENV := OPENBLAS_NUM_THREADS=1 OMP_NUM_THREADS=1 PYTHONDONTWRITEBYTECODE=

# make explore: the property tests with fresh random examples, ROUNDS runs (tests/conftest.py)
ROUNDS ?= 10

.PHONY: demo test lint bench explore install clean

# Two stamps: `make demo` installs the runtime only (the package and its dependencies);
# `make test` and `make lint` add the test extra (pytest, ruff, mypy and the third-party peers
# the tests talk to, pypylon among them).
$(RUNTIME):
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip

$(RUNTIME_STAMP): pyproject.toml | $(RUNTIME)
	$(PY) -m pip install -q -e .
	touch $(RUNTIME_STAMP)

$(STAMP): pyproject.toml | $(RUNTIME)
	$(PY) -m pip install -q -e '.[test]'
	touch $(RUNTIME_STAMP) $(STAMP)

demo: $(RUNTIME_STAMP)
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

# Every bench writes its own section of bench/RESULTS.md (grouped by subject, bench/harness.py);
# the link bench once per link. Several benches take minutes: a single one is `$(PY) bench/NAME.py`.
BENCH_LINKS := modbus rtu s7 opcua robot_socket ur_rtde
bench: $(STAMP)
	for f in $$(ls bench/bench_*.py | grep -v bench_link.py); do $(PY) $$f || exit 1; done
	for l in $(BENCH_LINKS); do $(PY) bench/bench_link.py --link $$l || exit 1; done

# The systemd service (systemd/README.md): venv in /opt/vgripd, unit, first config; as root.
install:
	systemd/install.sh $(INSTALL_ARGS)

clean:
	rm -rf $(VENV) build *.egg-info
