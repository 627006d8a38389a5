# Every target sets itself up: a fresh clone needs nothing but python3 (and apt for mosquitto).
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: mosquitto demo test lint typecheck bench bench-publish schemas dist clean

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

# figures to benchmarks/latest.md (untracked, changes every run)
bench: $(STAMP)
	$(BIN)/python -m benchmarks

# the same, to the published page docs/benchmarks.md (review the diff, then commit it)
bench-publish: $(STAMP)
	$(BIN)/python -m benchmarks --output docs/benchmarks.md

# a wheel to install on the cab box (systemd/README.md): sowgate is not on PyPI
dist: $(STAMP)
	rm -rf build dist/sowgate-*.whl   # build/: setuptools would reuse stale files from it
	$(BIN)/pip wheel --no-deps --quiet -w dist .
	@ls dist/sowgate-*.whl

schemas: $(STAMP)
	$(BIN)/python -m gateway.payloads --write docs/schemas

clean:
	rm -rf $(VENV) .pytest_cache .mypy_cache .ruff_cache build dist
