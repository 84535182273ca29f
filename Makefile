# Two entry points for a fresh machine: `make demo` and `make test`.
VENV ?= .venv
PYTHON ?= python3
BIN := $(VENV)/bin

.PHONY: setup demo lint test bench clean

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

test: setup lint
	$(BIN)/python -m pytest -q

clean:
	rm -rf $(VENV) demo-output bench-output
