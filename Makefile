# One command to run the service, one to run the tests; both set up .venv themselves.
#   make serve   install and start the service on its embedded defaults with the demo RSU map
#   make test    install and run the lint, the docs build and the whole test suite (what .ci/run runs)
#   make lint    ruff check, ruff format --check and mypy (strict), as make test runs them
#   make test-under-load  the whole suite 10 times in a row with every CPU core busy (must pass 10 of 10)
#   make bench   install and run the benchmark scripts
#   make openapi regenerate openapi.json from the app
#   make docs    build the docs site into site/ (strict: a broken link or an unlisted page fails)

# The interpreter the venv is built on: the distribution's /usr/bin/python3 when it is 3.11 or newer and can
# make a venv, else the first python3 on PATH (PYTHON=... overrides). Debian links libpython into the
# executable and builds it with profile-guided optimisation (its packaging; here only the speed was checked);
# pyenv's default build (--enable-shared, no --enable-optimizations) took 1.17x the CPU time on a pure-Python
# loop and 1.12x on the rsu_imu pipeline (bench/interpreter_ab.py, docs/benchmarks.md "The interpreter").
# Docker's python:3.11-slim is optimised too.
SYSTEM_PYTHON := /usr/bin/python3
PYTHON ?= $(shell $(SYSTEM_PYTHON) -c 'import sys, venv, ensurepip; sys.exit(sys.version_info < (3, 11))' \
	2>/dev/null && echo $(SYSTEM_PYTHON) || echo python3)
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed

.PHONY: serve test lint test-under-load bench openapi docs clean redis-server chromium wrk

# --clear: a .venv left by another interpreter (an older checkout built it on pyenv's python3) is made
# anew; over it, venv keeps the old links and its pip bootstrap fails (seen on 2026-11-27).
$(STAMP): pyproject.toml client/pyproject.toml
	$(PYTHON) -m venv --clear $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e ./client -e '.[dev]'
	touch $(STAMP)

serve: $(STAMP)
	EDGEPOS_DEMO_RSUS=$${EDGEPOS_DEMO_RSUS:-true} $(BIN)/edgepos serve

# Two test processes (pytest-xdist): most tests wait on a server, a socket or a subprocess, so two share
# a 2-core box well (11.5 min instead of 15 for the whole suite, measured with other jobs running).
# Every test picks its own free ports and temporary directories, so none depends on running alone.
test: $(STAMP) redis-server chromium lint docs
	$(BIN)/python -m pytest -n 2

# Style and types are held by tools: a finding fails the build (pyproject.toml configures both).
lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/mypy

# A test that leans on a quiet machine (fixed sleeps, wall-clock deadlines, unsynchronised threads)
# fails here: one busy-loop process per core, the suite run 10 times with CI=true (bench/suite_under_load.py).
test-under-load: $(STAMP) redis-server chromium
	$(BIN)/python bench/suite_under_load.py --runs 10

# The Redis store's tests start their own redis-server on loopback, and redis-cli joins the local Redis
# Cluster's nodes (Debian's redis-server package brings redis-tools); install them if the machine lacks them.
redis-server:
	@{ command -v redis-server && command -v redis-cli; } >/dev/null || { \
		echo "installing redis-server (Debian package)"; \
		apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq redis-server redis-tools >/dev/null; }

# The operator map's browser test (tests/api/test_api_map_browser.py) drives Debian's chromium through Playwright
# (executable_path=/usr/bin/chromium; `playwright install` is never run, nothing downloads a browser).
chromium:
	@command -v chromium >/dev/null || { \
		echo "installing chromium (Debian package)"; \
		apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null; }

# wrk (a C HTTP load generator, Debian package) drives bench/wrk_load.py.
wrk:
	@command -v wrk >/dev/null || { \
		echo "installing wrk (Debian package)"; \
		apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq wrk >/dev/null; }

bench: $(STAMP) redis-server wrk
	$(BIN)/python bench/filter_step.py
	$(BIN)/python bench/wrk_load.py
	$(BIN)/python bench/service_load.py
	$(BIN)/python bench/redis_store.py
	$(BIN)/python bench/federated.py
	$(BIN)/python bench/cooperative.py

openapi: $(STAMP)
	$(BIN)/python -m edgepos.api.openapi

# MkDocs 1.x prints a banner about its successor on every build; the site is pinned to 1.x (pyproject.toml).
docs: $(STAMP)
	NO_MKDOCS_2_WARNING=1 DISABLE_MKDOCS_2_WARNING=true $(BIN)/mkdocs build --strict --quiet

clean:
	rm -rf $(VENV)
