# ECU node (firmware_sim): its tests and the measurement of its own overhead.
.PHONY: ecu-test ecu-overhead

ECU_TESTS := tests/test_modes.py tests/test_firmware_units.py tests/test_ecu_lockstep.py \
	tests/test_ecu_realtime.py tests/test_ecu_cli.py tests/test_ecu_overhead.py tests/test_ecu_fuzz.py

## tests of the ECU: modes, RX/TX, lockstep, real time, CLI, fuzz
ecu-test: setup
	$(PY) -m pytest -q $(ECU_TESTS)

# ECU cost without a control law (lockstep and real time); writes results/ecu_overhead.json
## the ECU's own cost without a control law -> results/ecu_overhead.json
ecu-overhead: setup
	$(PY) -m studies.ecu_overhead --out results/ecu_overhead.json
	$(PROVENANCE_STAMP) results/ecu_overhead.json --command "make ecu-overhead" \
		--inputs $(PROVENANCE_HIL) --modules studies.ecu_overhead
