# Quick start: `make demo` and `make test` each create .venv and install on first use.
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed-stamp

.PHONY: install demo test test-all soak lint bench clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)

# constraints.txt pins torch to the CPU wheel; never install without it.
# nanonis-test is the official Nanonis client, installed from PyPI for
# tests/integration/test_nanonis_vendor.py (its licence forbids copying it here).
$(STAMP): $(BIN)/python pyproject.toml constraints.txt Makefile
	$(BIN)/python -m pip install --quiet -c constraints.txt -e '.[dev,nanonis-test]'
	@touch $(STAMP)

install: $(STAMP)

# In a terminal the dashboard keeps serving the finished run (its address ends the
# summary) until Ctrl-C; under CI or a script the demo exits after its summary.
demo: $(STAMP)
	$(BIN)/afmdrift demo

test: $(STAMP)
	$(BIN)/python -m pytest

test-all: $(STAMP)
	$(BIN)/python -m pytest -m ''

# The soak measures the daemon's timing and memory: alone, in one process.
soak: $(STAMP)
	$(BIN)/python -m pytest -m soak -n 0

lint: $(STAMP)
	$(BIN)/ruff check afmdrift tests benchmarks
	$(BIN)/ruff format --check afmdrift tests benchmarks
	$(BIN)/mypy
	$(BIN)/lint-imports

bench: $(STAMP)
	@for b in benchmarks/bench_*.py; do echo "== $$b"; $(BIN)/python $$b || exit 1; done

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache .mypy_cache .ruff_cache
