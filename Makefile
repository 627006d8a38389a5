# Every target sets itself up: a fresh clone needs nothing but python3 (and apt for mosquitto).
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: mosquitto postgis chromium poppler isoxml-js demo test reliability lint typecheck \
	bench schemas dist clean lock system-test system-test-tools

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

# the farm server's tests (tests/gateway/farm_server) use the PostgreSQL on 127.0.0.1:5432
# (trust auth, user postgres) with PostGIS from Debian; each test makes its own database
postgis:
	@test -f /usr/share/postgresql/15/extension/postgis.control || \
	  { (apt-get update -qq && apt-get install -y -qq postgresql-15-postgis-3) || \
	    { echo "PostGIS is needed for the farm server tests: apt-get install -y postgresql-15-postgis-3" >&2; exit 1; }; }

# the dashboard's browser tests drive Debian's chromium headless (Playwright, no browser download)
chromium:
	@test -x /usr/bin/chromium || \
	  { (apt-get update -qq && apt-get install -y -qq chromium) || \
	    { echo "chromium is needed for the dashboard's browser tests: apt-get install -y chromium" >&2; exit 1; }; }

# isoxml-js (npm `isoxml`, locked in tests/isoxml_js/package-lock.json) reads the ISO-XML
# export in the tests, as a second reader independent of ours; node_modules stays untracked
ISOXML_JS := tests/isoxml_js/node_modules/.package-lock.json
isoxml-js: $(ISOXML_JS)
$(ISOXML_JS): tests/isoxml_js/package.json tests/isoxml_js/package-lock.json
	@command -v npm >/dev/null 2>&1 || \
	  { (apt-get update -qq && apt-get install -y -qq nodejs npm) || \
	    { echo "node and npm are needed for the ISO-XML export tests: apt-get install -y nodejs npm" >&2; exit 1; }; }
	cd tests/isoxml_js && npm ci --no-audit --no-fund --silent
	touch $@

# the PDF report's test renders its pages with poppler's pdftoppm and reads text positions
# with pdftotext -bbox
poppler:
	@command -v pdftoppm >/dev/null 2>&1 || \
	  { (apt-get update -qq && apt-get install -y -qq poppler-utils) || \
	    { echo "poppler-utils is needed for the PDF report's test: apt-get install -y poppler-utils" >&2; exit 1; }; }

demo: $(STAMP)
	@command -v mosquitto >/dev/null 2>&1 || test -x /usr/sbin/mosquitto || \
	  echo "note: without mosquitto (make mosquitto) the demo runs without its web dashboard" >&2
	$(BIN)/sowgate demo --dashboard

# The suite on TEST_WORKERS parallel pytest-xdist workers, one per core of a 2-core box: most
# tests wait on real time (simulated drives, brokers, ptys, child processes), not on the CPU
# (tests/integration serially: 757 s wall, 87 s CPU). --dist loadfile keeps each test file on
# one worker (module fixtures are shared; xdist_group marks do nothing under pytest 9.2).
# The fault matrix runs first, on its own: its rows judge duty and timing to tenths of a
# second, its groups already run side by side in processes of their own, and beside another
# busy xdist worker its simulated devices were starved (rows failed on the harness's
# lateness, not the daemon's). Its table goes to build/reliability.md.
TEST_WORKERS ?= 2
test: $(STAMP) mosquitto postgis chromium poppler isoxml-js system-test-tools
	$(BIN)/ruff check gateway drivers protocol simulator tests benchmarks
	$(BIN)/mypy
	$(BIN)/lint-imports
	$(BIN)/pytest -q tests/reliability
	$(BIN)/pytest -q -n $(TEST_WORKERS) --dist loadfile --ignore=tests/reliability
	$(MAKE) system-test

# The fault matrix alone (also part of `make test`, which writes its table to
# build/reliability.md): regenerates docs/reliability.md from this run. Needs root (tmpfs).
reliability: $(STAMP) mosquitto
	SOWGATE_RELIABILITY_COMMAND="make reliability" \
	  $(BIN)/pytest -q tests/reliability --reliability-report=docs/reliability.md

# every benchmark, to docs/benchmarks.md: a generated page, rewritten by each run (review the
# diff, then commit it). `python -m benchmarks bench_x` alone writes benchmarks/latest.md.
bench: $(STAMP) mosquitto chromium
	$(BIN)/python -m benchmarks --output docs/benchmarks.md

# the offline install bundles for the cab box (docs/deployment.md): the wheel, every dependency
# as a wheel at its constraints.txt version, units, udev rule, example config, install.sh.
# dist/sowgate-<version>-linux-<arch>.tar.gz per arch; dependency wheels cached in build/.
DIST_ARCHES ?= x86_64 aarch64
dist: $(STAMP)
	rm -rf build/lib build/bdist.* dist/sowgate-*   # setuptools would reuse stale files
	$(BIN)/pip wheel --no-deps --quiet -w dist .
	$(BIN)/python systemd/bundle.py --wheel dist/sowgate-*.whl $(addprefix --arch ,$(DIST_ARCHES))

# The x86_64 bundle installed by its install.sh in a throwaway Debian 12 and booted under qemu
# with systemd as PID 1 (docs/deployment.md "System test"); image and kernel cached in build/.
system-test-tools:
	@command -v qemu-system-x86_64 >/dev/null && command -v debootstrap >/dev/null && \
	  test -x /bin/busybox && command -v depmod >/dev/null || \
	  { (apt-get -o DPkg::Lock::Timeout=600 update -qq && \
	     apt-get -o DPkg::Lock::Timeout=600 install -y -qq --no-install-recommends \
	      qemu-system-x86 qemu-utils debootstrap busybox-static kmod e2fsprogs >/dev/null) || \
	    { echo "make test/system-test: cannot install the system test's tools (needs root and \
apt): apt-get install qemu-system-x86 qemu-utils debootstrap busybox-static kmod e2fsprogs" >&2; \
	      exit 1; }; }
	@test "$$(id -u)" = 0 || { echo "make test/system-test: the system test needs root \
(debootstrap, chroot, mkfs -d): run make as root" >&2; exit 1; }

# The bundle is built into build/system-test/dist (not dist/): the run leaves nothing outside
# build/. Non-root or no apt: it fails naming what is missing, it never skips.
ST_DIST := build/system-test/dist
system-test: $(STAMP) system-test-tools
	rm -rf build/lib build/bdist.* $(ST_DIST)   # setuptools would reuse stale files
	$(BIN)/pip wheel --no-deps --quiet -w $(ST_DIST) .
	$(BIN)/python systemd/bundle.py --wheel $(ST_DIST)/sowgate-*.whl --arch x86_64 --out $(ST_DIST)
	$(BIN)/python tests/system/run.py $(ST_DIST)/sowgate-*-linux-x86_64.tar.gz

schemas: $(STAMP)
	$(BIN)/python -m gateway.link.payloads --write docs/schemas
	$(BIN)/python -m gateway.core.alarm_codes --write docs/mqtt.md

clean:
	rm -rf $(VENV) .pytest_cache .mypy_cache .ruff_cache build dist
