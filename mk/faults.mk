# Fault injection and fuzzing of the ECU (issue 10; docs/faults.md).
#   make faults   every fault in the high-mu double lane change, lockstep on the virtual
#                 bus (47 runs with the input-file cases, about 2 min here): results/faults.md, faults.json,
#                 faults_vehicle.png (--replace: rewrites them); FAULTS_ARGS="--only NAME ..."
#                 for a subset. The campaign is the grid studies/campaign/grids/faults.toml
#                 (faults_c.toml for faults-c; runner fault_case, one cell per case and
#                 controller) on the campaign engine, 2 local Ray workers, the wall-clock
#                 cases alone after the others, nothing cached; studies.fault_report renders
#                 the report from the cells' rows, all in one command (studies.fault_campaign)
#   make faults-c the same cases against the C ECU executable (build/firmware/ecu, a process
#                 on a loopback socketcand hub, as `hil run --ecu c`): results/faults_c.md,
#                 faults_c.json, faults_c_vehicle.png, compared with results/faults.json;
#                 the FD / remote / error look-alikes are reported not applicable (the hub
#                 cannot carry those frame kinds; about 1.3 min here)
#   make fuzz     the RX-path fuzz test with FUZZ_EXAMPLES examples (default 200000,
#                 about 14 min here; no pytest timeout); `make test` runs the same test
#                 with 10000 (about 1 min)
.PHONY: faults faults-c fuzz faults-test

FUZZ_EXAMPLES ?= 200000
FAULTS_ARGS ?=

## fault injection campaign, every fault in the high-mu lane change -> results/faults.*
faults: setup
	OPENBLAS_NUM_THREADS=1 $(PY) -m studies.fault_campaign --workers 2 --out results --replace $(FAULTS_ARGS)
	$(PROVENANCE_STAMP) results/faults.md results/faults.json results/faults_vehicle.png \
		--command "$(call provenance_command,faults,FAULTS_ARGS)" \
		--inputs $(PROVENANCE_HIL) studies/campaign/grids/faults.toml --modules studies.fault_campaign

## the fault campaign against the C ECU executable -> results/faults_c.*, compared with faults.*
faults-c: setup firmware
	OPENBLAS_NUM_THREADS=1 $(PY) -m studies.fault_campaign --ecu c --out results --replace $(FAULTS_ARGS)
	$(PROVENANCE_STAMP) results/faults_c.md results/faults_c.json results/faults_c_vehicle.png \
		--command "$(call provenance_command,faults-c,FAULTS_ARGS)" \
		--inputs $(PROVENANCE_HIL) results/faults.json $(wildcard firmware/src/*.[ch]) \
		studies/campaign/grids/faults_c.toml \
		--modules studies.fault_campaign

## the RX-path fuzz test with FUZZ_EXAMPLES examples (default 200000)
fuzz: setup
	FUZZ_EXAMPLES=$(FUZZ_EXAMPLES) $(PY) -m pytest -q -s -p no:cacheprovider -p no:logging --timeout=0 \
		tests/test_fuzz_ecu.py

## tests of the fault injection and the fuzz test (10000 examples)
faults-test: setup
	$(PY) -m pytest -q tests/test_faults.py tests/test_fuzz_ecu.py
