# The one compute-time benchmark (studies/bench.py, docs/timing.md): every registered
# controller fed the same recorded lane-change samples side by side, one process, BLAS
# single-threaded; step p50 / p99 / max, solver share, ratio to LMPC, the ECU's overhead.
# The ECU's deadlines in real time are `make timing` (mk/timing.mk).
.PHONY: bench

## compute time per step of every controller and the ECU overhead -> results/bench.{md,json}
bench: setup
	OPENBLAS_NUM_THREADS=1 $(PY) -m studies.bench --out results/bench.md --json results/bench.json
	$(PROVENANCE_STAMP) results/bench.md results/bench.json --command "make bench" \
		--inputs $(PROVENANCE_HIL) --modules studies.bench
