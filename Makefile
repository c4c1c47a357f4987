# Two set-up commands do everything on a fresh machine (Python 3.11, pip, gcc):
#   make demo   create .venv, install, run a simulated approach, write a trial log and a report
#   make test   create .venv, install with dev extras, run the whole test suite
PYTHON ?= python3.11
VENV := .venv
BIN := $(VENV)/bin
STAMP_RUN := $(VENV)/.installed-run
STAMP_DEV := $(VENV)/.installed-dev
RUNS ?= runs

.PHONY: demo test lint bench clean

$(BIN)/python:
	@command -v $(PYTHON) >/dev/null 2>&1 || { echo "error: $(PYTHON) not found (set PYTHON=...)"; exit 1; }
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip

$(STAMP_RUN): pyproject.toml | $(BIN)/python
	$(BIN)/pip install --quiet -e .
	@touch $@

$(STAMP_DEV): pyproject.toml | $(BIN)/python
	$(BIN)/pip install --quiet -e '.[dev,cluster]'
	@touch $@ $(STAMP_RUN)

demo: $(STAMP_RUN)
	$(BIN)/satgrasp demo --out-dir $(RUNS)

test: $(STAMP_DEV)
	$(BIN)/python -m pytest -n 2 -q

lint: $(STAMP_DEV)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .

bench: $(STAMP_RUN)
	$(BIN)/satgrasp bench render
	$(BIN)/satgrasp bench estimate --system corners --system lines --system ellipses
	$(BIN)/satgrasp bench loop

clean:
	rm -rf $(VENV) build *.egg-info $(RUNS)
