# ECU timing as on a vehicle (issue 9, studies/timing/ and the bus nodes in hil/timing/):
#   make timing   - ECU and plant as separate processes pinned to separate cores (SCHED_FIFO
#                   where permitted), 40 Hz control per controller, idle and under a busy-loop
#                   load on both cores -> results/timing.md, results/timing_{idle,stress}.png
#                   (2 min per controller, NMPC 30 s: about 15 min; TIMING_SECONDS=20 for a
#                   quick run)
#   (the compute time per step of the controllers is `make bench`, mk/bench.mk)
#   make timing-test - the 20 s real-time test of ESO-DKMPC (also part of `make test`)
.PHONY: timing timing-test

TIMING_SECONDS ?= 120
TIMING_NMPC_SECONDS ?= 30

## real-time test: ECU and plant as processes, idle and under load -> results/timing.md
timing: setup
	OPENBLAS_NUM_THREADS=1 $(PY) -m studies.timing.bench --seconds $(TIMING_SECONDS) \
		--nmpc-seconds $(TIMING_NMPC_SECONDS) --out results/timing.md --work build/timing
	$(PROVENANCE_STAMP) results/timing.md results/timing_idle.png results/timing_stress.png \
		--command "$(call provenance_command,timing,TIMING_SECONDS TIMING_NMPC_SECONDS)" \
		--inputs $(PROVENANCE_HIL) --modules studies.timing.bench

## the 20 s real-time test of ESO-DKMPC (part of make test)
timing-test: setup
	$(PY) -m pytest -q -s tests/test_timing.py tests/test_timing_units.py
