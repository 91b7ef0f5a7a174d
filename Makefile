# ESO-DKMPC ECU prototype. `make test` and `make run` set everything up themselves.
SHELL := /bin/bash
PYTHON ?= python3.11
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
APT_STAMP := .venv/.apt-installed
# Debian packages for the real SocketCAN path under user-mode Linux (see README).
APT_PACKAGES := user-mode-linux kmod iproute2 can-utils

.DEFAULT_GOAL := help

CAN_INTERFACE ?= virtual
CAN_CHANNEL ?= vcan0
export CAN_INTERFACE CAN_CHANNEL
# Tiny matrices in the control loop: BLAS threads only add latency on 2 cores.
export OPENBLAS_NUM_THREADS ?= 1
export OMP_NUM_THREADS ?= 1

.PHONY: setup apt-deps test test-fast clean help

# Each capability adds its targets in mk/<name>.mk.
-include mk/*.mk

help:
	@echo "make setup   - create .venv and install the project with its test dependencies"
	@echo "make test    - set up when needed, then run the whole test suite"

setup: $(STAMP) apt-deps

$(STAMP): pyproject.toml
	@command -v $(PYTHON) >/dev/null || { echo "error: $(PYTHON) not found (Python 3.11 is required)"; exit 1; }
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[training,test]'
	touch $(STAMP)

# Installs the user-mode Linux / can-utils packages when running as root and they are
# missing; otherwise says how (the vcan tests then skip with that message, except on CI).
apt-deps:
	@if command -v linux.uml >/dev/null && command -v candump >/dev/null && command -v insmod >/dev/null; then :; \
	elif [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
		echo "installing $(APT_PACKAGES)"; \
		DEBIAN_FRONTEND=noninteractive apt-get update -qq && \
		DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $(APT_PACKAGES) >/dev/null; \
	else echo "note: not root; vcan tests need: sudo apt-get install $(APT_PACKAGES)"; fi

test: setup
	$(PY) -m pytest -q

test-fast: setup
	$(PY) -m pytest -q -m "not slow and not timing and not vcan"

clean:
	rm -rf $(VENV) .pytest_cache .hypothesis

# README.md is assembled from docs/readme/*.md (one section per capability).
.PHONY: readme
readme:
	$(PYTHON) docs/build_readme.py

# The node, frame and signal tables of docs/can-contract.md, from can_defs/vehicle.dbc.
.PHONY: contract-tables
contract-tables: setup
	$(PY) -m can_defs.contract_tables
