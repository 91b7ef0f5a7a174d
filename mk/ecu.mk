# ECU node (firmware_sim): its tests (its own cost per cycle is in `make bench`, mk/bench.mk).
.PHONY: ecu-test

ECU_TESTS := tests/test_modes.py tests/test_firmware_units.py tests/test_ecu_lockstep.py \
	tests/test_ecu_realtime.py tests/test_ecu_cli.py tests/test_ecu_fuzz.py

## tests of the ECU: modes, RX/TX, lockstep, real time, CLI, fuzz
ecu-test: setup
	$(PY) -m pytest -q $(ECU_TESTS)
