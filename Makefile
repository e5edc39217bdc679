# The two commands of the README: `make test` and `make demo`. Both create .venv when it is missing
# and install the project into it, so they work on a fresh machine with only Python >= 3.11.
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed

.PHONY: test lint demo install bench clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip

# Reinstall whenever pyproject.toml changes.
$(STAMP): pyproject.toml | $(BIN)/python
	$(BIN)/python -m pip install --quiet -e '.[test,plot]'
	touch $(STAMP)

install: $(STAMP)

# habits first (seconds), then the suite: lint, format, types on the records / wire / store
lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/mypy

test: lint
	$(BIN)/python -m pytest

demo: $(STAMP)
	$(BIN)/hybridloc demo

bench: $(STAMP)
	$(BIN)/python -m pip install --quiet -e '.[test,plot,postgres]'
	$(BIN)/python -m benchmarks

clean:
	rm -rf $(VENV) build *.egg-info
