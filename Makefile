# Two entry points for a fresh machine: `make demo` and `make test`; `make check` is the quick
# tier for development (lint + the tests not marked slow).
VENV ?= .venv
PYTHON ?= python3
BIN := $(VENV)/bin
# test processes (pytest-xdist); each test file stays on one, so its fixtures are built once
TEST_WORKERS ?= 2

.PHONY: setup demo lint check test bench clean

setup: $(VENV)/.installed

$(VENV)/.installed: pyproject.toml scripts/install-system-deps.sh
	bash scripts/install-system-deps.sh
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install -q --disable-pip-version-check -e '.[test]'
	touch $@

demo: setup
	$(BIN)/plotmosaic demo demo-output

lint: setup
	$(BIN)/ruff check plotmosaic tests benchmarks
	$(BIN)/ruff format --check plotmosaic tests benchmarks
	$(BIN)/lint-imports

check: setup lint
	$(BIN)/python -m pytest -q -n $(TEST_WORKERS) --dist loadfile --durations=15 -m "not slow"

test: setup lint
	$(BIN)/python -m pytest -q -n $(TEST_WORKERS) --dist loadfile --durations=15

clean:
	rm -rf $(VENV) demo-output bench-output
