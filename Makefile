# Every target bootstraps .venv on first use, so on a fresh machine each is one command.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed
SECONDS ?= 20

.PHONY: demo test test-long bench soak lint imports wheel-check format typecheck clean suite-table

$(STAMP): pyproject.toml setup.py
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e '.[dev]'
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/cdpr-gateway warmup
	$(BIN)/cdpr-gateway demo --seconds $(SECONDS)

# `make test` runs every test but the few marked `long`; `make test-long` runs those; CI
# (.ci/run) runs both. They run on JOBS pytest-xdist workers (default 2, the machine this
# project is measured on; `make test JOBS=0` runs in one process, `JOBS=auto` one worker per
# core): the tests are single-threaded and CPU-bound, so two workers keep both cores busy
# (figures: docs/performance.md). One BLAS thread: the diagnosis' small
# SVDs ran ~5x slower with OpenBLAS threads contending on a loaded 2-core machine.
# worksteal: the long tests' durations differ by 100x; an idle worker takes queued tests
# from the other's share instead of waiting for the slowest one (test-long: its diagnosis part).
JOBS ?= 2
PYTEST := OPENBLAS_NUM_THREADS=1 $(BIN)/python -m pytest -n $(JOBS) --dist worksteal

test: $(STAMP)
	$(PYTEST) -m "not long"

# The long diagnosis tests (CPU-bound, minutes each) share the two workers; the other long
# tests time a live loop, a soft PLC, signals or a terminal, and run one at a time after
# them: beside a diagnosis on a 2-core machine they missed their windows (top, signals,
# hostile PLC all failed in a parallel run and passed alone). A long diagnosis may take
# 15 minutes on a loaded machine (pytest-timeout is a guard against hangs, not a figure).
test-long: $(STAMP)
	$(PYTEST) --timeout 900 -m long tests/diagnose
	OPENBLAS_NUM_THREADS=1 $(BIN)/python -m pytest -m long --ignore=tests/diagnose

# All benchmarks but the soak (a few minutes); the 600-s soak is `make soak`.
bench: $(STAMP)
	$(BIN)/python -m bench

soak: $(STAMP)
	$(BIN)/python -m bench soak

# ruff, formatting, mypy and the layer contract ([tool.importlinter] in pyproject.toml).
lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/mypy
	$(BIN)/lint-imports

# The import graph between the top-level packages (evidence for the layer contract).
imports: $(STAMP)
	$(BIN)/python .ci/import-graph

# Build the wheel, install it into a fresh venv, run the demo over both buses outside the tree.
wheel-check:
	.ci/wheel-check $(PYTHON)

typecheck: $(STAMP)
	$(BIN)/mypy

format: $(STAMP)
	$(BIN)/ruff format .
	$(BIN)/ruff check --fix .

# Tuning and sealed sets of both suites; a sealed file whose hash the doc does not record is
# refused (--reseal REASON records a new draw). The real recordings: `python -m bench real`.
suite-table: $(STAMP)
	$(BIN)/python -m evaluation.scenarios_table --table docs/diagnose-suite.md
	$(BIN)/python -m tests.foreign_cases --table docs/diagnose-suite.md

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache .mypy_cache .ruff_cache
