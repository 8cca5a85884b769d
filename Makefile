# The two commands: `make run` (the server on the simulated cell) and `make test`
# (the whole suite). Each sets itself up on a fresh clone: a virtualenv in .venv
# with the pinned dependencies (constraints.txt). `make test-fast` runs the unit
# tier alone, for the edit loop.

PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
HOST ?= 127.0.0.1
PORT ?= 8000
DATA ?= data

.PHONY: run test test-fast lint bench diagram openapi clean browser node

$(STAMP): pyproject.toml constraints.txt
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --disable-pip-version-check -c constraints.txt -e '.[test,bench]'
	touch $(STAMP)

run: $(STAMP)
	$(PY) -m server --host $(HOST) --port $(PORT) --data-dir $(DATA)

test: $(STAMP) lint browser node
	$(PY) -m pytest

# The unit tier only (tests/unit, marked `unit` by tests/conftest.py): no lint, no sockets.
test-fast: $(STAMP) node
	$(PY) -m pytest -m unit -q

# The browser tests drive Debian's Chromium through Playwright (never `playwright install`).
browser:
	@test -x /usr/bin/chromium || { \
		echo "installing Debian's chromium for the browser tests"; \
		SUDO=$$( [ "$$(id -u)" = 0 ] || echo sudo ); \
		$$SUDO apt-get update -qq && \
		DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y -qq chromium; }

# The dashboard's geometry module is unit-tested with node's own test runner (no npm).
node:
	@command -v node >/dev/null || { \
		echo "installing Debian's nodejs for the dashboard's unit tests"; \
		SUDO=$$( [ "$$(id -u)" = 0 ] || echo sudo ); \
		$$SUDO apt-get update -qq && \
		DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y -qq nodejs; }

# ruff, then mypy over server/ and clients/ (configured in pyproject.toml: [tool.mypy]).
lint: $(STAMP)
	$(PY) -m ruff check .
	$(PY) -m ruff format --check .
	$(PY) -m mypy

bench: $(STAMP)
	$(PY) -m bench

diagram: $(STAMP)
	$(PY) -m server.core.diagram --write

openapi: $(STAMP)
	$(PY) -m server.openapi --write

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache .mypy_cache .hypothesis
