# ECU timing as on a vehicle (issues 9, 37; studies/timing/ and the bus nodes in hil/timing/):
#   make timing   - ECU and plant as separate processes pinned to separate cores (SCHED_FIFO
#                   where permitted), 40 Hz control, idle and under a busy-loop load on both
#                   cores -> results/timing.md, results/timing_{idle,stress}.png. ESO-DKMPC on
#                   the Python and the C ECU under both control-task releases (clock: contract
#                   revision 2; sample: revision 3), TIMING_REPEATS (3) runs each; the other
#                   controllers once on the clock. 45 s per run, NMPC 30 s: 34 runs, about
#                   28 min (TIMING_SECONDS=20 for a quicker run, about 14 min; with
#                   TIMING_REPEATS=1 about 8 min)
#   (the compute time per step of the controllers is `make bench`, mk/bench.mk)
#   make timing-test - the 20 s real-time test of ESO-DKMPC and the unit tests (also part of `make test`)
.PHONY: timing timing-test

TIMING_SECONDS ?= 45
TIMING_NMPC_SECONDS ?= 30
TIMING_REPEATS ?= 3

## real-time test: ECU and plant as processes, idle and under load -> results/timing.md
timing: setup
	OPENBLAS_NUM_THREADS=1 $(PY) -m studies.timing.bench --seconds $(TIMING_SECONDS) \
		--nmpc-seconds $(TIMING_NMPC_SECONDS) --repeats $(TIMING_REPEATS) \
		--out results/timing.md --work build/timing
	$(PROVENANCE_STAMP) results/timing.md results/timing_idle.png results/timing_stress.png \
		--command "$(call provenance_command,timing,TIMING_SECONDS TIMING_NMPC_SECONDS TIMING_REPEATS)" \
		--inputs $(PROVENANCE_HIL) --modules studies.timing.bench

## the 20 s real-time test of ESO-DKMPC (part of make test)
timing-test: setup
	$(PY) -m pytest -q -s tests/test_timing.py tests/test_timing_units.py tests/test_timing_report.py
