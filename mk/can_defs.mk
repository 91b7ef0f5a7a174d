# can_defs: CAN contract (DBC, codec, E2E). Tests and the codec benchmark (docs/can-defs.md).
.PHONY: can-test can-bench

## tests of the contract code: CRC, DBC, codec, E2E, interoperability
can-test: setup
	$(PY) -m pytest -q tests/test_can_crc.py tests/test_can_dbc.py tests/test_can_codec.py tests/test_can_e2e.py tests/test_can_interop.py

## encode/decode/E2E throughput of can_defs -> results/can_defs_bench.txt
can-bench: setup
	@mkdir -p results
	$(PY) -m can_defs.bench | tee results/can_defs_bench.txt
	$(PROVENANCE_STAMP) results/can_defs_bench.txt --command "make can-bench" \
		--inputs $(PROVENANCE_DBC) --modules can_defs.bench
