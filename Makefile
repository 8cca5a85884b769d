# The two commands: `make run` (the server on the simulated cell) and `make test`
# (the whole suite). Each sets itself up on a fresh clone: a virtualenv in .venv
# with the pinned dependencies (constraints.txt). `make test-fast` runs the unit
# tier alone, for the edit loop; `make test-loaded` the reliability tier on a busy
# machine; `make soak` the long soak.
#
# Each target installs only what it needs, once: the server's own dependencies for
# `make run` (about 310 MB), the test extra for the tests and lint, the bench extra
# for the benchmarks (`make test` runs their smoke test too). One stamp per set, so
# `make test` after `make run` adds only the extras; each is redone when
# pyproject.toml or constraints.txt changes.

PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
PIP := $(PY) -m pip install --quiet --disable-pip-version-check -c constraints.txt
RUN_STAMP := $(VENV)/.installed-run
TEST_STAMP := $(VENV)/.installed-test
BENCH_STAMP := $(VENV)/.installed-bench
HOST ?= 127.0.0.1
PORT ?= 8000
DATA ?= data
# Debian packages the suite drives as programs, installed so that no system service is
# started or enabled by them (tools/apt-install-quiet says how).
APT_INSTALL := sh tools/apt-install-quiet

LOADED_LIMIT ?= 30m
SOAK ?= 30m

.PHONY: run line test test-fast test-loaded soak lint bench diagram openapi clean browser node deploy-tools mosquitto promtool

$(PY):
	$(PYTHON) -m venv $(VENV)

$(RUN_STAMP): pyproject.toml constraints.txt | $(PY)
	$(PIP) -e .
	touch $@

$(TEST_STAMP): $(RUN_STAMP)
	$(PIP) -e '.[test]'
	touch $@

$(BENCH_STAMP): $(RUN_STAMP)
	$(PIP) -e '.[bench]'
	touch $@

run: $(RUN_STAMP)
	$(PY) -m server --host $(HOST) --port $(PORT) --data-dir $(DATA)

# A line of three cells on this machine (server/line/demo.py): Debian's mosquitto (MQTT
# on 1883, WebSocket on 9001), cells on 8001-8003 with data in $(DATA)/line/cell-N, and
# the line view on http://127.0.0.1:8080/. Ctrl-C stops them all. LINE_ARGS passes more
# options (python -m server.line.demo --help), e.g. LINE_ARGS="--mqtt-port 1884".
LINE_ARGS ?=
line: $(RUN_STAMP) mosquitto
	$(PY) -m server.line.demo --host $(HOST) --data-dir $(DATA)/line $(LINE_ARGS)

# The whole suite includes the benchmarks' smoke test (tests/integration/test_bench_smoke.py).
# Every tier but reliability runs on WORKERS pytest-xdist workers (two per core by
# default: most tests spend most of their time waiting on a device, a timeout or a
# browser, and with one worker per core the cores were about 40 % idle). The tests of a
# module that share a fixture set up once (a served cell, rendered frames, the API
# schema run's server) run on one worker, so it is set up once (--dist loadgroup,
# tests/xdist_groups.py). The reliability tier (kills, full disks, random faults, the
# short soak) then runs on its own RELIABILITY_WORKERS (one per core), apart from the
# other tiers: its servers wait on real device timeouts, chosen to hold beside a busy
# loop on every core (`make test-loaded`), not beside the other tiers' servers and
# browsers as well. Last, alone, the one of its tests that keeps every core busy itself
# (marked whole_machine).
# The slowest tests are listed.
WORKERS ?= $(shell echo $$((2 * $$(nproc))))
RELIABILITY_WORKERS ?= auto
test: $(TEST_STAMP) $(BENCH_STAMP) lint browser node deploy-tools mosquitto promtool
	$(PY) -m pytest -n $(WORKERS) --dist loadgroup --durations=20 -m "not reliability"
	$(PY) -m pytest -n $(RELIABILITY_WORKERS) --dist loadgroup --durations=5 -m "not whole_machine" tests/reliability
	$(PY) -m pytest --durations=1 -m whole_machine tests/reliability

# The unit tier only (tests/unit, marked `unit` by tests/conftest.py): no lint, no sockets.
test-fast: $(TEST_STAMP) node
	$(PY) -m pytest -m unit -q

# The reliability tier (tests/reliability) with every core kept busy by as many
# busy loops, at the default priority as a CI runner's other jobs would be: what it
# checks must not depend on a quiet machine. The loops end with the run, however it
# ends; the run is bounded by LOADED_LIMIT (interrupted, so pytest still reports).
test-loaded: $(TEST_STAMP)
	@cores=$$(nproc); load=""; \
	trap 'kill $$load 2>/dev/null' EXIT INT TERM; \
	for i in $$(seq $$cores); do $(PY) -c 'while True: pass' & load="$$load $$!"; done; \
	echo "test-loaded: $$cores busy loops beside the reliability tier (limit $(LOADED_LIMIT))"; \
	timeout --foreground --signal=INT --kill-after=60 $(LOADED_LIMIT) \
		$(PY) -m pytest tests/reliability -q

# The soak (tests/reliability/soak.py) for SOAK (30m; SOAK=2h for longer). It ends a
# hung cycle itself five minutes late; this bounds it to its duration and ten minutes.
soak: $(TEST_STAMP)
	@limit=$$($(PY) -c 'from tests.reliability.soak import parse_duration as d; \
		print(int(d("$(SOAK)")) + 600)'); \
	timeout --foreground --signal=INT --kill-after=60 $$limit \
		$(PY) -m tests.reliability.soak --duration $(SOAK)

# The browser tests drive Debian's Chromium through Playwright (never `playwright install`).
browser:
	@test -x /usr/bin/chromium || { \
		echo "installing Debian's chromium for the browser tests"; \
		SUDO=$$( [ "$$(id -u)" = 0 ] || echo sudo ); \
		$$SUDO $(APT_INSTALL) chromium; }

# The dashboard's geometry module is unit-tested with node's own test runner (no npm).
node:
	@command -v node >/dev/null || { \
		echo "installing Debian's nodejs for the dashboard's unit tests"; \
		SUDO=$$( [ "$$(id -u)" = 0 ] || echo sudo ); \
		$$SUDO $(APT_INSTALL) nodejs; }

# The deployment tests validate docker-compose.yml with Debian's docker-compose (its
# `config` needs no engine) and the systemd unit with systemd-analyze. Without its
# recommends, docker-compose brings no container engine (docker.io, containerd,
# iptables); systemd is only installed where it is missing, and like every install here
# through $(APT_INSTALL), so none of its units is left enabled.
deploy-tools:
	@command -v docker-compose >/dev/null && command -v systemd-analyze >/dev/null || { \
		echo "installing Debian's docker-compose (no engine) and systemd-analyze for the deployment tests"; \
		SUDO=$$( [ "$$(id -u)" = 0 ] || echo sudo ); \
		$$SUDO $(APT_INSTALL) --no-install-recommends \
			docker-compose systemd; }

# The plant-interface tests and the line demo run Debian's MQTT broker as a process.
mosquitto:
	@{ command -v mosquitto || test -x /usr/sbin/mosquitto; } >/dev/null && command -v mosquitto_sub >/dev/null || { \
		echo "installing Debian's mosquitto for the MQTT tests"; \
		SUDO=$$( [ "$$(id -u)" = 0 ] || echo sudo ); \
		$$SUDO $(APT_INSTALL) mosquitto mosquitto-clients; }

# The metrics test pipes a real scrape through promtool's `check metrics`: Debian ships
# promtool in its prometheus package.
promtool:
	@command -v promtool >/dev/null || { \
		echo "installing Debian's prometheus (promtool) for the metrics test"; \
		SUDO=$$( [ "$$(id -u)" = 0 ] || echo sudo ); \
		$$SUDO $(APT_INSTALL) --no-install-recommends prometheus; }

# ruff, then mypy over server/ and clients/ (configured in pyproject.toml: [tool.mypy]).
lint: $(TEST_STAMP)
	$(PY) -m ruff check .
	$(PY) -m ruff format --check .
	$(PY) -m mypy

bench: $(BENCH_STAMP)
	$(PY) -m bench

diagram: $(RUN_STAMP)
	$(PY) -m server.core.machine.diagram --write

openapi: $(RUN_STAMP)
	$(PY) -m server.cli.openapi --write

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache .mypy_cache .hypothesis
