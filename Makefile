# MISS - two commands on a fresh machine: `make run` and `make test`.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
PIP := $(PY) -m pip
WEB := src/miss/web
VALIDATORS := tests/validators

.PHONY: run test test-fast lint format bench web-deps validators vrml-reader chromium pacs-servers postgres clean

$(VENV)/.installed: pyproject.toml setup.py src/miss/measure/_nearest.cpp src/miss/decimate/_placed.cpp
	$(PYTHON) -m venv $(VENV)
	$(PIP) install -q --upgrade pip
	$(PIP) install -q -e '.[test]'
	$(PY) -c "from miss.decimate._schroeder import warm_up; warm_up()"  # compile numba kernels once
	$(PY) -c "from miss.decimate.collapse import warm_up; warm_up()"
	touch $@

$(VENV)/.bench-installed: $(VENV)/.installed
	$(PIP) install -q -e '.[test,bench]'
	touch $@

# Front-end packages (three.js) from the npm registry, served locally: no CDN.
web-deps:
	@if [ -f $(WEB)/package.json ]; then \
		if [ ! -d $(WEB)/node_modules ] || [ $(WEB)/package.json -nt $(WEB)/node_modules ]; then \
			cd $(WEB) && (npm ci --ignore-scripts --no-audit --no-fund --silent || npm install --ignore-scripts --no-audit --no-fund --silent) && touch node_modules; \
		fi; \
	fi

# Reference validators the tests run on MISS's files (Khronos glTF-Validator, from npm).
validators:
	@if [ ! -d $(VALIDATORS)/node_modules ] || [ $(VALIDATORS)/package.json -nt $(VALIDATORS)/node_modules ]; then \
		cd $(VALIDATORS) && (npm ci --ignore-scripts --no-audit --no-fund --silent || npm install --ignore-scripts --no-audit --no-fund --silent) && touch node_modules; \
	fi

# Castle Game Engine's tovrmlx3d (in Debian's view3dscene) reads MISS's VRML in the tests.
vrml-reader:
	@if [ ! -x /usr/bin/tovrmlx3d ]; then \
		echo "installing Debian's view3dscene (tovrmlx3d) for the VRML tests"; \
		apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends view3dscene >/dev/null; \
	fi

# Debian's chromium for the browser tests (Playwright drives /usr/bin/chromium).
chromium:
	@if [ ! -x /usr/bin/chromium ]; then \
		echo "installing Debian's chromium for browser tests"; \
		apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null; \
	fi

# A real PACS for the PACS tests (Debian's Orthanc with its DICOMweb plugin) and David
# Clunie's dciodvfy (dicom3tools), which checks the DICOM files MISS sends.
pacs-servers:
	@if [ ! -x /usr/sbin/Orthanc ] || [ ! -f /usr/share/orthanc/plugins/libOrthancDicomWeb.so ] || [ ! -x /usr/bin/dciodvfy ]; then \
		echo "installing Debian's orthanc, orthanc-dicomweb and dicom3tools for the PACS tests"; \
		apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends orthanc orthanc-dicomweb dicom3tools >/dev/null; \
	fi

# Debian's PostgreSQL for the tests that run the server on it; each test run starts its own
# throw-away cluster (tests/support/pg.py), never the system's service.
postgres:
	@if ! ls /usr/lib/postgresql/*/bin/postgres >/dev/null 2>&1; then \
		echo "installing Debian's postgresql for the PostgreSQL tests"; \
		apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends postgresql >/dev/null; \
	fi

# Starts the web system on embedded defaults: SQLite + data folder ./miss-data, demo volume.
run: $(VENV)/.installed web-deps
	$(VENV)/bin/miss serve $(if $(HOST),--host $(HOST)) $(if $(PORT),--port $(PORT))

# The server tests again on PostgreSQL: PG_TESTS below (the rest is engine-independent).
PG_TESTS := tests/server/test_api.py tests/server/test_rooms.py tests/server/test_faults.py \
	tests/server/test_bad_input.py tests/server/test_schema.py tests/server/test_health.py \
	tests/server/test_backup.py

test: $(VENV)/.bench-installed web-deps validators vrml-reader chromium pacs-servers postgres
	$(VENV)/bin/ruff check src tests benchmarks
	$(VENV)/bin/ruff format --check src tests benchmarks
	$(VENV)/bin/mypy
	$(VENV)/bin/pytest -q
	MISS_TEST_DATABASE=postgres $(VENV)/bin/pytest -q $(PG_TESTS)

# The inner loop of a change: library and API tests, no browser, PACS, PostgreSQL, real
# server or worker processes, nothing marked slow (a few minutes on 2 cores; `make test` is all).
test-fast: $(VENV)/.bench-installed web-deps validators
	$(VENV)/bin/pytest -q -m "not slow" -n auto  # one process a core (pytest-xdist)

lint:
	$(VENV)/bin/ruff check src tests benchmarks
	$(VENV)/bin/mypy

format:
	$(VENV)/bin/ruff format src tests benchmarks
	$(VENV)/bin/ruff check --fix src tests benchmarks

bench: $(VENV)/.bench-installed
	$(PY) benchmarks/paper_tables.py
	$(PY) benchmarks/bounds.py
	$(PY) benchmarks/peers.py
	$(PY) benchmarks/cli.py

clean:
	rm -rf $(VENV) $(WEB)/node_modules $(VALIDATORS)/node_modules .pytest_cache miss-data miss-demo-*
