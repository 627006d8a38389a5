# Every target sets itself up: a fresh clone needs nothing but python3 (and apt for mosquitto).
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: mosquitto chromium demo test reliability lint typecheck bench schemas dist clean lock

# Installs come from constraints.txt (every package pinned), so figures are reproducible;
# `make lock` refreshes it within the ranges pyproject.toml allows.
$(STAMP): pyproject.toml constraints.txt
	$(PY) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -c constraints.txt -e '.[dev]'
	touch $(STAMP)

lock:
	rm -rf .venv-lock
	$(PY) -m venv .venv-lock
	.venv-lock/bin/pip install --quiet --upgrade pip
	.venv-lock/bin/pip install --quiet -e '.[dev]'
	{ echo "# Pinned versions of every dependency, resolved within pyproject.toml's ranges."; \
	  echo "# make installs with 'pip install -c constraints.txt'; refresh with 'make lock'."; \
	  .venv-lock/bin/pip freeze --exclude-editable | grep -vi '^sowgate'; } > constraints.txt
	rm -rf .venv-lock

mosquitto:
	@command -v mosquitto >/dev/null 2>&1 || test -x /usr/sbin/mosquitto || \
	  { (apt-get update -qq && apt-get install -y -qq mosquitto) || \
	    { echo "mosquitto is needed for the MQTT tests: apt-get install -y mosquitto" >&2; exit 1; }; }

# the dashboard's browser tests drive Debian's chromium headless (Playwright, no browser download)
chromium:
	@test -x /usr/bin/chromium || \
	  { (apt-get update -qq && apt-get install -y -qq chromium) || \
	    { echo "chromium is needed for the dashboard's browser tests: apt-get install -y chromium" >&2; exit 1; }; }

demo: $(STAMP)
	@command -v mosquitto >/dev/null 2>&1 || test -x /usr/sbin/mosquitto || \
	  echo "note: without mosquitto (make mosquitto) the demo runs without its web dashboard" >&2
	$(BIN)/sowgate demo --dashboard

# The suite on TEST_WORKERS parallel pytest-xdist workers, one per core of a 2-core box: most
# tests wait on real time (simulated drives, brokers, ptys, child processes), not on the CPU
# (tests/integration serially: 757 s wall, 87 s CPU), but the fault matrix's rows judge duty
# and timing and failed next to two other busy workers. --dist loadfile keeps each test file
# on one worker: the fault matrix's campaign is a session fixture (once per worker otherwise)
# and module fixtures are shared (xdist_group marks do nothing under pytest 9.2).
TEST_WORKERS ?= 2
test: $(STAMP) mosquitto chromium
	$(BIN)/ruff check gateway drivers protocol simulator tests benchmarks
	$(BIN)/mypy
	$(BIN)/lint-imports
	$(BIN)/pytest -q -n $(TEST_WORKERS) --dist loadfile

# The fault matrix alone (also part of `make test`, which writes its table to
# build/reliability.md): regenerates docs/reliability.md from this run. Needs root (tmpfs).
reliability: $(STAMP) mosquitto
	SOWGATE_RELIABILITY_COMMAND="make reliability" \
	  $(BIN)/pytest -q tests/reliability --reliability-report=docs/reliability.md

# every benchmark, to docs/benchmarks.md: a generated page, rewritten by each run (review the
# diff, then commit it). `python -m benchmarks bench_x` alone writes benchmarks/latest.md.
bench: $(STAMP) mosquitto chromium
	$(BIN)/python -m benchmarks --output docs/benchmarks.md

# a wheel to install on the cab box (systemd/README.md): sowgate is not on PyPI
dist: $(STAMP)
	rm -rf build dist/sowgate-*.whl   # build/: setuptools would reuse stale files from it
	$(BIN)/pip wheel --no-deps --quiet -w dist .
	@ls dist/sowgate-*.whl

schemas: $(STAMP)
	$(BIN)/python -m gateway.link.payloads --write docs/schemas
	$(BIN)/python -m gateway.core.alarm_codes --write docs/mqtt.md

clean:
	rm -rf $(VENV) .pytest_cache .mypy_cache .ruff_cache build dist
