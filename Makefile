# Every target sets itself up: a fresh clone needs nothing but python3 (and apt for mosquitto).
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: mosquitto demo test reliability lint typecheck bench schemas clean

$(STAMP): pyproject.toml
	$(PY) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e '.[dev]'
	touch $(STAMP)

mosquitto:
	@command -v mosquitto >/dev/null 2>&1 || test -x /usr/sbin/mosquitto || \
	  { (apt-get update -qq && apt-get install -y -qq mosquitto) || \
	    { echo "mosquitto is needed for the MQTT tests: apt-get install -y mosquitto" >&2; exit 1; }; }

demo: $(STAMP)
	$(BIN)/sowgate demo

test: $(STAMP) mosquitto
	$(BIN)/ruff check gateway drivers protocol simulator tests benchmarks
	$(BIN)/mypy
	$(BIN)/pytest -q

# The fault matrix alone (also part of `make test`, which writes its table to
# build/reliability.md): regenerates docs/reliability.md from this run. Needs root (tmpfs).
reliability: $(STAMP) mosquitto
	SOWGATE_RELIABILITY_COMMAND="make reliability" \
	  $(BIN)/pytest -q tests/reliability --reliability-report=docs/reliability.md

bench: $(STAMP)
	$(BIN)/python -m benchmarks

schemas: $(STAMP)
	$(BIN)/python -m gateway.payloads --write docs/schemas

clean:
	rm -rf $(VENV) .pytest_cache .mypy_cache .ruff_cache
