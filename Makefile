# Two entry points for a fresh Debian/Ubuntu machine with python3 and make:
#   make demo   set everything up and run the main job
#   make test   set everything up and run lint, types and the test suite
# any Python >= 3.11 (make PYTHON=python3.11 where python3 is older)
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: demo test lint setup clean

$(STAMP): pyproject.toml deploy/bootstrap.sh
	PYTHON=$(PYTHON) sh deploy/bootstrap.sh
	$(PY) -m pip install --quiet --upgrade pip
	PYTHONWARNINGS="ignore:Editable installation" $(PY) -m pip install --quiet -e '.[dev]'
	touch $(STAMP)

# compile the solver kernels into numba's on-disk cache, so that no command a person types
# waits for them (a second or so when they are cached already)
setup: $(STAMP)
	$(VENV)/bin/posecast warm

demo: setup
	$(VENV)/bin/posecast demo

lint: setup
	$(VENV)/bin/ruff check .
	$(VENV)/bin/mypy

test: lint
	$(VENV)/bin/pytest

clean:
	rm -rf $(VENV) build *.egg-info
