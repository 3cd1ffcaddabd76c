# The two commands a new user runs on a fresh machine:
#   make run    trains a safe agent: PPO-Lag on SafetySwimmerVelocity-v1, seeds 0 1 2 in one process,
#               about ten minutes on 2 cores (no accounts, no servers)
#   make test   runs the default (fast) test suite
# Both create .venv and install the package into it when missing.

PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed

# Headless rendering (env.render, record_video) needs EGL or OSMesa; Mesa provides both without a
# GPU. `gl-libs` installs the missing ones with apt-get when it can (root, or password-less sudo)
# and otherwise only says so: it never fails the build, and the rendering tests then skip.
GL_PACKAGES := libegl1 libgl1 libosmesa6

.PHONY: run test test-slow bench install clean gl-libs

install: $(STAMP)

# The tests install the optional MuJoCo Warp backend too (about 400 MB; its kernels compile on Warp's CPU
# device in about a minute on first use), so the warp backend's tests run here, not only on a GPU.
$(STAMP): pyproject.toml Makefile
	-@$(MAKE) --no-print-directory gl-libs
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[test,warp]'
	touch $(STAMP)

# `make run` is the demo, the `make-run` preset (sg_torchrl/train/config.py, where its choices are
# explained): a seed group of three seeds that ends under the cost limit. It prints each seed's and the
# mean EpRet / EpCost (training and evaluation) and draws runs/make-run/curves.png (every seed and the
# mean, with the limit); each seed's run is in runs/make-run/seed-XXX/. Each call starts it afresh
# (--overwrite says so explicitly; sg-train itself never replaces a run unasked). Continue an
# interrupted one with `.venv/bin/sg-train --resume runs/make-run`.
run: $(STAMP)
	$(PY) -m sg_torchrl.train --preset make-run --overwrite

test: $(STAMP)
	$(PY) -m pytest -q

test-slow: $(STAMP)
	$(PY) -m pytest -q -m slow

bench: $(STAMP)
	$(PY) benchmarks/env_throughput.py
	$(PY) benchmarks/reset_time.py
	$(PY) benchmarks/train_throughput.py

gl-libs:
	@command -v apt-get >/dev/null 2>&1 && command -v dpkg-query >/dev/null 2>&1 || exit 0; \
	missing=""; for package in $(GL_PACKAGES); do \
	  dpkg-query -W -f='$${Status}' $$package 2>/dev/null | grep -q "ok installed" || missing="$$missing $$package"; \
	done; \
	[ -n "$$missing" ] || exit 0; \
	if [ "$$(id -u)" = 0 ]; then sudo=""; \
	elif command -v sudo >/dev/null 2>&1 && sudo -n true 2>/dev/null; then sudo="sudo -n"; \
	else echo "note: rendering needs$$missing (apt-get install -y$$missing as root); rendering tests will skip"; exit 0; fi; \
	echo "installing$$missing for headless rendering"; \
	export DEBIAN_FRONTEND=noninteractive; \
	$$sudo apt-get install -y -q --no-install-recommends$$missing >/dev/null 2>&1 || \
	{ $$sudo apt-get update -q >/dev/null 2>&1 && $$sudo apt-get install -y -q --no-install-recommends$$missing >/dev/null; } || \
	echo "note: could not install$$missing; rendering tests will skip"

clean:
	rm -rf $(VENV) runs
