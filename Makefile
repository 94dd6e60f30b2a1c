# Two entry points for a fresh clone: `make demo` (set up + run the main job on the simulated bench)
# and `make test` (set up + run the test suite). Both create .venv on first use.
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin

.PHONY: setup demo test

$(BIN)/benchctl: pyproject.toml
	@echo "set-up [1/3]: virtual environment $(VENV) (the set-up runs once: about 2 minutes)"
	$(PYTHON) -m venv $(VENV)
	@echo "set-up [2/3]: PyTorch 2.13.0, CPU build (the largest part: about 1 minute)"
	# torch first and pinned: an unpinned resolve would fetch several GB of CUDA wheels
	$(BIN)/python -m pip install --quiet torch==2.13.0
	@echo "set-up [3/3]: benchctl and the packages it needs"
	$(BIN)/python -m pip install --quiet -e '.[test]'
	touch $@
	@echo "set-up done: $(BIN)/benchctl"

setup: $(BIN)/benchctl

demo: setup
	@echo "demo: colour capture on the simulated bench (a first run measures the lookup tables and registers the camera first: about 4 minutes; later runs under 1 minute)"
	$(BIN)/benchctl run procedures/colour_capture.toml

test: setup
	$(BIN)/ruff check .
	$(BIN)/mypy
	$(BIN)/lint-imports --no-cache
	$(BIN)/python -m pytest -q
