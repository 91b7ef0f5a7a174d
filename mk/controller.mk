# Controllers (controller/): tests, the closed-loop check and the ESO sweep (their compute
# time per step: `make bench`, mk/bench.mk).
.PHONY: controller-test controller-closed-loop eso-sweep

CONTROLLER_TESTS := tests/test_reference.py tests/test_controller_tuning.py tests/test_controller_doubles.py \
	tests/test_controller_qp.py tests/test_controller_nmpc.py tests/test_controller_registry.py

## tests of the control laws, the reference path and the tuning
controller-test: setup
	$(PY) -m pytest -q $(CONTROLLER_TESTS)

# All four controllers through both double lane changes on the four-wheel plant (slow, ~3 min).
## the four controllers through both lane changes on the four-wheel plant (slow)
controller-closed-loop: setup
	OPENBLAS_NUM_THREADS=1 $(PY) -m pytest -q -s -m slow tests/test_controller_closed_loop.py

# ESO-DKMPC's observer poles and horizon decay against DKMPC, both lane changes (~1 min):
# results/eso_dkmpc_sweep.{md,png,json}
## ESO-DKMPC observer poles and horizon decay against DKMPC -> results/eso_dkmpc_sweep.*
eso-sweep: setup
	@mkdir -p results
	OPENBLAS_NUM_THREADS=1 $(PY) -m studies.eso_sweep --out results
	$(PROVENANCE_STAMP) $(addprefix results/eso_dkmpc_sweep.,md png json) --command "make eso-sweep" \
		--inputs $(PROVENANCE_CLOSED_LOOP) --modules studies.eso_sweep
	@$(MAKE) --no-print-directory readme  # README.md includes these results
