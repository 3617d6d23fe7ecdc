# The two commands of the README: `make demo` runs the whole stack on a real pick-and-place task,
# `make test` runs the linters (ruff, mypy) and the test suite. Both set up the machine first (idempotent).
VENV ?= .venv
COMMAND ?= pick up the red cup and place it on the table

.PHONY: setup demo up test lint lint-only bench

setup:
	@bash scripts/setup.sh

demo: setup
	$(VENV)/bin/aermani demo "$(COMMAND)"

up: setup
	$(VENV)/bin/aermani up

# ruff (style, line length, complexity, class docstrings), mypy strict on the shared contract, mypy on the services
# and on the application (aermani/: CLI, launcher, demo, evaluation).
lint-only:
	$(VENV)/bin/ruff check .
	$(VENV)/bin/mypy --strict shared
	$(VENV)/bin/mypy services aermani

lint: setup
	$(MAKE) --no-print-directory lint-only

test:
	@bash scripts/setup.sh --browser
	$(MAKE) --no-print-directory lint-only
	$(VENV)/bin/pytest -n 2 --dist loadgroup

# Every benchmark, then docs/performance.md from that one run (~15 min on 2 cores; BENCH_ARGS=--quick for a
# pipeline check in ~3 min, written to runs/bench/performance.md instead).
bench: setup
	$(VENV)/bin/python benchmarks/run_all.py $(BENCH_ARGS)
