"""``python -m firmware_sim``: the ECU command line (see `firmware_sim.cli`)."""
import os

# Before numpy loads: the control loop multiplies tiny matrices, and a threaded BLAS on a
# 2-core ECU only adds latency (15-25 ms stalls measured when the other core was busy).
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

from firmware_sim.cli import main  # noqa: E402

raise SystemExit(main())
