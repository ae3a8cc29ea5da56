# The two commands of the README's Quick start are `make demo` and `make test`; both run the
# idempotent set-up first (a second run takes about a second).
VENV ?= $(CURDIR)/.venv
export VENV
BIN := $(VENV)/bin
# Where `make demo` writes its run directory (override: make demo RUN_DIR=/tmp/run1).
RUN_DIR ?=
DEMO_ARGS ?=

.PHONY: setup demo test test-core test-closed-loop bench clean

setup:
	@bash scripts/setup.sh

demo: setup
	@$(BIN)/terrain-demo $(if $(RUN_DIR),--run-dir $(RUN_DIR)) $(DEMO_ARGS)

test: setup
	@$(BIN)/python -m pytest -q

test-core: setup
	@$(BIN)/python -m pytest -q -m "not graph and not closed_loop"

# Issue 8's closed-loop graph tests only (about 6 min; `make test` runs them too).
test-closed-loop: setup
	@$(BIN)/python -m pytest -q -m closed_loop

bench: setup
	@bash scripts/run_benchmarks.sh

clean:
	rm -rf build runs
