# Two commands on a fresh clone: `make demo` and `make test`. Each creates .venv and
# installs the project into it (editable, with the dev extra) when missing or stale, then fills numba's
# cache beside the compiled kernels' modules (30 s to a minute on 2 cores), so that no process compiles them.
# `make bench BENCH="routing apps"` runs only the benchmarks named (see tests/bench/__main__.py).
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test test-fast bench lint deploy-check clean

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[dev]'
	$(BIN)/python -m services.launcher.kernels
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/artrack demo

# Three workers on two cores: most integration tests wait on the processes they start (measured: the
# suite took 13 min on two workers, 8.3 min on three). `make test` runs every test (CI does);
# `make test-fast` only the unit tests: no process, no Zenoh session, no whole sequence (markers in
# pyproject.toml, held by tests/conftest.py). Work stealing: xdist's default hands out the tests in
# file order by the block, and the first block held every accuracy and most integration tests, so one
# worker ran them all while the other two, done with the unit tests, stood idle; with `worksteal` an
# idle worker takes half of the others' tests still waiting.
PYTEST := $(BIN)/python -m pytest -q -n 3 --dist worksteal

test: $(STAMP)
	$(PYTEST)

test-fast: $(STAMP)
	$(PYTEST) -m "not integration and not slow"

bench: $(STAMP)
	$(BIN)/python -m tests.bench $(BENCH)

lint: $(STAMP)
	$(BIN)/ruff check protocol services tests
	$(BIN)/mypy

# docker/ checked without a Docker engine: hadolint, compose config, systemd-analyze, the image's
# install step in a fresh venv, tests/unit/test_deploy_files.py (see docker/check.sh).
deploy-check: $(STAMP)
	bash docker/check.sh

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache .mypy_cache build *.egg-info
