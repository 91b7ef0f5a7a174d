# Controllers (controller/): tests, the closed-loop check and the per-step timing benchmark.
.PHONY: controller-test controller-closed-loop controller-bench eso-sweep

CONTROLLER_TESTS := tests/test_reference.py tests/test_controller_tuning.py tests/test_controller_doubles.py \
	tests/test_controller_qp.py tests/test_controller_nmpc.py tests/test_controller_registry.py

## tests of the control laws, the reference path and the tuning
controller-test: setup
	$(PY) -m pytest -q $(CONTROLLER_TESTS)

# All four controllers through both double lane changes on the four-wheel plant (slow, ~3 min).
## the four controllers through both lane changes on the four-wheel plant (slow)
controller-closed-loop: setup
	OPENBLAS_NUM_THREADS=1 $(PY) -m pytest -q -s -m slow tests/test_controller_closed_loop.py

# Per-step compute time of each controller (DLC 35 km/h, mu 0.85): results/controller_timing.md
## per-step compute time of each controller -> results/controller_timing.md
controller-bench: setup
	@mkdir -p results
	OPENBLAS_NUM_THREADS=1 $(PY) -m studies.controller_timing --out results/controller_timing.md
	$(PROVENANCE_STAMP) results/controller_timing.md --command "make controller-bench" \
		--inputs $(PROVENANCE_CLOSED_LOOP) --modules studies.controller_timing

# ESO-DKMPC's observer poles and horizon decay against DKMPC, both lane changes (~1 min):
# results/eso_dkmpc_sweep.{md,png,json}
## ESO-DKMPC observer poles and horizon decay against DKMPC -> results/eso_dkmpc_sweep.*
eso-sweep: setup
	@mkdir -p results
	OPENBLAS_NUM_THREADS=1 $(PY) -m studies.eso_sweep --out results
	$(PROVENANCE_STAMP) $(addprefix results/eso_dkmpc_sweep.,md png json) --command "make eso-sweep" \
		--inputs $(PROVENANCE_CLOSED_LOOP) --modules studies.eso_sweep
	@$(MAKE) --no-print-directory readme  # README.md includes these results
