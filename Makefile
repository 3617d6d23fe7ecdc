# The two commands of the README: `make demo` runs the whole stack on a real pick-and-place task,
# `make test` runs ruff and the test suite. Both set up the machine first (idempotent).
VENV ?= .venv
COMMAND ?= pick up the red cup and place it on the table

.PHONY: setup demo up test lint bench

setup:
	@bash scripts/setup.sh

demo: setup
	$(VENV)/bin/aermani demo "$(COMMAND)"

up: setup
	$(VENV)/bin/aermani up

lint: setup
	$(VENV)/bin/ruff check .

test:
	@bash scripts/setup.sh --browser
	$(VENV)/bin/ruff check .
	$(VENV)/bin/pytest

bench: setup
	for b in benchmarks/*.py; do echo "== $$b"; $(VENV)/bin/python $$b || exit 1; done
