# One-stop commands. `make train` and `make test` are the README's first two commands and work on a fresh machine:
# they install into the project's own virtual environment (.venv, created on first use), never into the machine's
# Python, so they see exactly the dependencies the package declares. VENV=/path/to/env uses another environment.
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
export MUJOCO_GL ?= egl

.PHONY: install train test lint format

# Installed once per environment and again only when the package's requirements change (the stamp file)
$(VENV)/.sb3_dsslac_installed: setup.cfg pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	# The CPU build of torch first: a plain `torch` requirement would pull a multi-GB CUDA build
	$(PY) -m pip install --quiet torch==2.13.0
	$(PY) -m pip install --quiet -e ".[all]"
	touch $@

install: $(VENV)/.sb3_dsslac_installed

train: install
	$(PY) examples/train_pointgoal1.py --out runs/pointgoal1_$$(date +%Y%m%d_%H%M%S)

# DSSLAC_VENV lets the tests check that they run inside this environment
test: install
	$(PY) -m ruff check .
	$(PY) -m ruff format --check .
	DSSLAC_VENV="$(abspath $(VENV))" $(PY) -m pytest -q

lint: install
	$(PY) -m ruff check .

format: install
	$(PY) -m ruff format .
