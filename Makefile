# The two commands of the README: `make test` and `make demo`. Both create .venv when it is missing
# and install the project into it, so they work on a fresh machine with only Python >= 3.11.
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed

.PHONY: test lint demo install bench clean postgres chromium

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip

# Reinstall whenever pyproject.toml changes.
$(STAMP): pyproject.toml | $(BIN)/python
	$(BIN)/python -m pip install --quiet -e '.[test,plot,postgres]'
	touch $(STAMP)

install: $(STAMP)

# habits first (seconds), then the suite: lint, format, types on the records / wire / store
lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/mypy

# PostgreSQL, the suite's second engine: Debian's server package when its binaries are missing (as root
# or with password-less sudo); elsewhere the PostgreSQL tests skip and say why
postgres:
	@if ls /usr/lib/postgresql/*/bin/initdb >/dev/null 2>&1 || command -v initdb >/dev/null; then :; \
	elif [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
	  echo "make: installing Debian's postgresql (the suite's second engine)"; \
	  apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends postgresql >/dev/null; \
	elif command -v sudo >/dev/null && sudo -n true 2>/dev/null && command -v apt-get >/dev/null; then \
	  sudo apt-get update -qq && sudo DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends postgresql >/dev/null; \
	else echo "make: PostgreSQL server binaries are missing and cannot be installed here: the PostgreSQL tests will skip"; fi

# Chromium, the dashboard's browser tests' browser (Playwright drives Debian's chromium; no browser
# download): installed with apt when missing (as root or with password-less sudo); elsewhere those tests
# skip and say why
chromium:
	@if [ -x /usr/bin/chromium ]; then :; \
	elif [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
	  echo "make: installing Debian's chromium (the dashboard's browser tests)"; \
	  apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends chromium >/dev/null; \
	elif command -v sudo >/dev/null && sudo -n true 2>/dev/null && command -v apt-get >/dev/null; then \
	  sudo apt-get update -qq && sudo DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends chromium >/dev/null; \
	else echo "make: chromium is missing and cannot be installed here: the dashboard's browser tests will skip"; fi

# two test processes (pytest-xdist), whole files to each so that a module's fixtures (a crowd replay,
# a PostgreSQL server per process) are built once: most tests wait on servers, sockets and child
# processes, so two share CI's 2 cores well (15.1 -> 7.6 min here, the same 899 tests)
test: lint postgres chromium
	$(BIN)/python -m pytest -n 2 --dist loadfile

demo: $(STAMP)
	$(BIN)/hybridloc demo

bench: $(STAMP) postgres chromium
	$(BIN)/python -m benchmarks

clean:
	rm -rf $(VENV) build *.egg-info
