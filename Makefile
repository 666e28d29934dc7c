# One-stop commands. `make train` and `make test` are the README's first two commands and work on a fresh machine.
PYTHON ?= python3
export MUJOCO_GL ?= egl

.PHONY: install train test lint format

install:
	$(PYTHON) -m pip install --quiet torch==2.13.0
	$(PYTHON) -m pip install --quiet -e ".[all]"

train: install
	$(PYTHON) examples/train_pointgoal1.py --out runs/pointgoal1_$$(date +%Y%m%d_%H%M%S)

test: install
	$(PYTHON) -m ruff check .
	$(PYTHON) -m pytest -q

lint:
	$(PYTHON) -m ruff check .

format:
	$(PYTHON) -m ruff format .
