# Controllers (controller/): tests and the closed-loop check (their compute time per step:
# `make bench`, mk/bench.mk; their tuning: `make tune`, mk/tune.mk).
.PHONY: controller-test controller-closed-loop

CONTROLLER_TESTS := tests/test_reference.py tests/test_controller_tuning.py tests/test_controller_doubles.py \
	tests/test_controller_qp.py tests/test_controller_nmpc.py tests/test_controller_registry.py

## tests of the control laws, the reference path and the tuning
controller-test: setup
	$(PY) -m pytest -q $(CONTROLLER_TESTS)

# All four controllers through both double lane changes on the four-wheel plant (slow, ~3 min).
## the four controllers through both lane changes on the four-wheel plant (slow)
controller-closed-loop: setup
	OPENBLAS_NUM_THREADS=1 $(PY) -m pytest -q -s -m slow tests/test_controller_closed_loop.py
