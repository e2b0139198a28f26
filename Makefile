# Two entry points for a fresh Debian/Ubuntu machine with python3 and make:
#   make demo   set everything up and run the main job
#   make test   set everything up and run lint, types and the test suite
# any Python >= 3.11 (make PYTHON=python3.11 where python3 is older)
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
TEST_STAMP := $(VENV)/.installed-for-tests
# the browser spectator: client/web's sources bundled by esbuild (from npm) into
# server/static, which `posecast serve` sends and the wheel ships
WEB := client/web
WEB_BUILT := server/static/index.html
WEB_SOURCES := $(wildcard $(WEB)/src/*) $(WEB)/build.mjs $(WEB)/package.json \
	$(WEB)/package-lock.json
NO_NODE := posecast: building the browser spectator needs Node.js 18+ and npm, and there \
	is no npm here: install them (Debian/Ubuntu: apt-get install nodejs npm) and run make again

.PHONY: demo test lint setup clean web

$(STAMP): pyproject.toml deploy/bootstrap.sh
	PYTHON=$(PYTHON) sh deploy/bootstrap.sh
	$(PY) -m pip install --quiet --upgrade pip
	PYTHONWARNINGS="ignore:Editable installation" $(PY) -m pip install --quiet -e '.[dev]'
	touch $(STAMP)

# compile the solver kernels into numba's on-disk cache, so that no command a person types
# waits for them (a second or so when they are cached already)
setup: $(STAMP) $(WEB_BUILT)
	$(VENV)/bin/posecast warm

web: $(WEB_BUILT)

$(WEB_BUILT): $(WEB_SOURCES) | $(STAMP)
	@command -v npm >/dev/null 2>&1 || { echo "$(NO_NODE)" >&2; exit 1; }
	cd $(WEB) && npm ci --no-audit --no-fund --loglevel=error && node build.mjs

# what the tests need besides (Chromium for the browser spectator's)
$(TEST_STAMP): deploy/bootstrap.sh
	PYTHON=$(PYTHON) sh deploy/bootstrap.sh test
	touch $(TEST_STAMP)

demo: setup
	$(VENV)/bin/posecast demo

lint: setup
	$(VENV)/bin/ruff check .
	$(VENV)/bin/mypy

# two workers, a test file each at a time (a file's module fixtures stay in one
# process): the suite waits on subprocesses, sockets and clocks more than it computes
TEST_WORKERS ?= 2

test: lint $(TEST_STAMP)
	$(VENV)/bin/pytest -n $(TEST_WORKERS) --dist loadfile

clean:
	rm -rf $(VENV) build *.egg-info $(WEB)/node_modules server/static
