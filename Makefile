# The two commands a new user runs on a fresh machine:
#   make run    trains PPO-Lag on the embedded default (no accounts, no servers)
#   make test   runs the default (fast) test suite
# Both create .venv and install the package into it when missing.

PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed

.PHONY: run test test-slow bench install clean

install: $(STAMP)

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[test]'
	touch $(STAMP)

run: $(STAMP)
	$(PY) -m sg_torchrl.train --preset make-run

test: $(STAMP)
	$(PY) -m pytest -q

test-slow: $(STAMP)
	$(PY) -m pytest -q -m slow

bench: $(STAMP)
	$(PY) benchmarks/env_throughput.py
	$(PY) benchmarks/train_throughput.py

clean:
	rm -rf $(VENV) runs
