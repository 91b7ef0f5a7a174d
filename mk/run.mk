# HIL over CAN (hil/): `make run` is the main job - the paper's two double lane changes
# with the four controllers, ECU and plant exchanging only CAN frames in lockstep.
# Default: python-can's virtual bus, one process, no set-up.
#   make run CAN_INTERFACE=socketcan CAN_CHANNEL=vcan0   # ECU as its own process on a real vcan
#   make run ECU=c   # the C ECU (build/firmware/ecu, make firmware) with its three controllers
#                    # (no NMPC); on the virtual interface through a loopback socketcand hub
# Writes results/run_*.md, results/run_*.png, results/run_metrics.json, frame logs in
# results/logs/ (candump format, ~40 kB per simulated second: not for git).
.PHONY: run run-uml hil-test vcan-test

RUN_ARGS ?=
# Which ECU: python (firmware_sim) or c (build/firmware/ecu of make firmware; hil run --ecu).
ECU ?= python

## the paper's two lane changes, four controllers, ECU and plant over CAN -> results/run_*
run: setup
	OPENBLAS_NUM_THREADS=1 $(PY) -m studies.run_all --interface $(CAN_INTERFACE) --channel $(CAN_CHANNEL) \
		--out results --logs results/logs --ecu $(ECU) $(RUN_ARGS)
	$(PROVENANCE_STAMP) $(addprefix results/run_,table2_high_mu.md table3_low_mu.md fig8_high_mu.png \
		fig9_low_mu.png metrics.json) \
		--command "$(call provenance_command,run,RUN_ARGS)$(if $(filter-out virtual,$(CAN_INTERFACE)), CAN_INTERFACE=$(CAN_INTERFACE) CAN_CHANNEL=$(CAN_CHANNEL))$(if $(filter-out python,$(ECU)), ECU=$(ECU))" \
		--inputs $(PROVENANCE_HIL) --modules studies.run_all

# `make run` on a real SocketCAN vcan0 inside user-mode Linux, for machines whose kernel has
# no CAN (see docs/vcan.md). Slow (UML system calls); for checking, not timing:
#   make run-uml RUN_ARGS="--controllers lmpc eso-dkmpc --duration 2"
## make run on a real SocketCAN vcan0 inside user-mode Linux (slow)
run-uml: setup
	$(PY) -m hil.vcan --timeout 3600 -- $(PY) -m studies.run_all --interface socketcan --channel vcan0 \
		--out results/uml --logs results/uml/logs $(RUN_ARGS)

HIL_TESTS := tests/test_hil_nodes.py tests/test_hil_time_master.py tests/test_hil_run.py \
	tests/test_hil_third_party.py

## tests of the HIL nodes, the time master and hil run
hil-test: setup
	$(PY) -m pytest -q $(HIL_TESTS)

# The real SocketCAN path: host vcan0 if present, else user-mode Linux (see docs/vcan.md).
## the real SocketCAN path: host vcan0, else user-mode Linux
vcan-test: setup firmware
	$(PY) -m pytest -q -s tests/test_vcan.py tests/test_vcan_odd_frames.py tests/test_firmware_c_vcan.py \
		tests/test_vcan_lost_interface.py
