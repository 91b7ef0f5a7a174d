# ESO-DKMPC ECU prototype. `make test` and `make run` set everything up themselves.
SHELL := /bin/bash
PYTHON ?= python3.11
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
APT_STAMP := .venv/.apt-installed
# Debian packages for the real SocketCAN path under user-mode Linux (see docs/vcan.md).
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

# `make help` lists every target of this file and of mk/*.mk with its help line: a `## `
# comment at the end of the target's line or on the line just above it. A target without
# one shows "(no help line)", and tests/test_make_help.py fails.
HELP_AWK := FNR == 1 { above = "" } \
	/^[A-Za-z0-9][A-Za-z0-9_.-]*:([^=]|$$)/ { \
		name = $$0; sub(/:.*/, "", name); text = ""; \
		if (match($$0, /\#\# /)) text = substr($$0, RSTART + 3); \
		else if (above ~ /^\#\# /) text = substr(above, 4); \
		if (text == "") text = "(no help line)"; \
		if (!(name in seen)) { \
			seen[name] = 1; \
			if (FILENAME != group) { group = FILENAME; printf "\n%s:\n", group } \
			printf "  make %-24s %s\n", name, text } } \
	{ above = $$0 }

## list every make target with its one-line description (this list)
help:
	@echo "ESO-DKMPC ECU prototype: make TARGET [VAR=value ...]. Start with make test and make run."
	@awk '$(HELP_AWK)' $(MAKEFILE_LIST)

## create .venv and install the project with its test, training and campaign dependencies
setup: $(STAMP) apt-deps

$(STAMP): pyproject.toml
	@command -v $(PYTHON) >/dev/null || { echo "error: $(PYTHON) not found (Python 3.11 is required)"; exit 1; }
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[training,test,campaign]'
	touch $(STAMP)

# Installs the user-mode Linux / can-utils packages when running as root and they are
# missing; otherwise says how (the vcan tests then skip with that message, except on CI).
## install user-mode Linux and can-utils (as root) for the real vcan0 tests
apt-deps:
	@if command -v linux.uml >/dev/null && command -v candump >/dev/null && command -v insmod >/dev/null; then :; \
	elif [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
		echo "installing $(APT_PACKAGES)"; \
		DEBIAN_FRONTEND=noninteractive apt-get update -qq && \
		DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $(APT_PACKAGES) >/dev/null; \
	else echo "note: not root; vcan tests need: sudo apt-get install $(APT_PACKAGES)"; fi

## the whole test suite, slow, timing and vcan tests included
test: setup
	$(PY) -m pytest -q

## the test suite without the slow, timing and vcan tests
test-fast: setup
	$(PY) -m pytest -q -m "not slow and not timing and not vcan"

## remove .venv and the test caches
clean:
	rm -rf $(VENV) .pytest_cache .hypothesis

# README.md is assembled from docs/readme/*.md; the manuals are docs/<capability>.md.
.PHONY: readme
## assemble README.md from docs/readme/*.md and the results files they include
readme:
	$(PYTHON) docs/build_readme.py

# The node, frame and signal tables of docs/can-contract.md, from can_defs/vehicle.dbc.
.PHONY: contract-tables
## regenerate the tables of docs/can-contract.md from can_defs/vehicle.dbc
contract-tables: setup
	$(PY) -m can_defs.contract_tables
