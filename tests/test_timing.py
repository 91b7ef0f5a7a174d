"""Real-time run of the ESO-DKMPC ECU against the plant, as separate processes (issue 9).

20 s of 40 Hz control: the ECU process (its CLI) pinned to one core, the plant process to
the other, SCHED_FIFO where the OS permits it (the test prints what it got), over the
loopback CAN hub (`hil.timing.hub`, python-can's socketcand interface). Asserted with
ample margin: no overrun at 25 ms, no lost STEER_TORQUE_CMD at the plant, task time p99
under half the period.

Precondition: the machine must get its CPUs. On a virtual machine the hypervisor may run
other work while this one has work ready (CPU steal, /proc/stat); no priority inside the
guest protects a deadline against that (measured here: 18 % steal while another job kept
one core busy gave 1-3 overruns and task-time maxima of 26-46 ms under SCHED_FIFO). The
run is repeated once when more than `MAX_STEAL` of the CPU time was stolen, and the test
is skipped, saying so, only when both runs were; otherwise it asserts. With little steal
(~1-2 %) it measured task time p99 about 2.5 ms, no overrun, nothing lost.
"""
from __future__ import annotations

import pytest

from studies.timing.report import RunFigures, percentile_table, run_figures, summary_table
from studies.timing.runner import run_timing

SECONDS = 20.0
HALF_PERIOD_MS = 12.5
MAX_STEAL = 0.03


def _run(tmp_path, attempt: int) -> RunFigures:
    run = run_timing("eso-dkmpc", SECONDS, tmp_path / f"attempt{attempt}")
    figures = run_figures(run, f"attempt {attempt}")
    print(f"\nscheduling: {run.scheduling}")
    # the real-time ECU leaves its start-up objects out of the collector's full collections
    assert "start-up objects frozen" in run.ecu_log
    print("\n".join(summary_table([figures]) + percentile_table([figures])))
    return figures


@pytest.mark.timing
@pytest.mark.slow
def test_eso_dkmpc_meets_25_ms_in_real_time_against_the_plant_process(tmp_path):
    figures = _run(tmp_path, 1)
    if not figures.steal_share <= MAX_STEAL:   # NaN (no /proc/stat) counts as unknown: retry
        figures = _run(tmp_path, 2)
    if figures.steal_share > MAX_STEAL:
        pytest.skip(f"the hypervisor stole {100 * figures.steal_share:.1f} % of this machine's "
                    f"CPU time in both runs (more than {100 * MAX_STEAL:.0f} %): deadlines "
                    "cannot be judged; figures printed above")
    expected_cycles = (SECONDS - 1.0) / 0.025
    assert figures.cycles >= 0.95 * expected_cycles, "the ECU did not run every 25 ms"
    assert figures.modes.get("ACTIVE", 0) >= 0.95 * figures.cycles, figures.modes
    # Zero overruns is make timing's goal on pinned, otherwise idle cores; this test runs on a
    # shared CI machine, so it allows a rare late cycle (at most 1 %) and checks the rest.
    assert figures.overruns <= 0.01 * figures.cycles, figures.overruns
    assert figures.commands_lost == 0 and figures.command_e2e_errors == 0
    assert figures.plant_commands_rejected == 0
    assert figures.commands_received >= figures.cycles
    assert figures.stats["task_time"][1] < HALF_PERIOD_MS
    assert figures.lateral_error_max_m < 0.5   # it was really controlling the car


@pytest.mark.timing
def test_the_c_ecu_runs_in_the_timing_study(tmp_path):
    """`make timing`'s runner with the C ECU executable (issue 18): started with the Python
    ECU's options, ready line awaited, pinned as asked, its --timing-out record read as the
    Python ECU's. A few seconds with generous margins on a busy machine: most cycles ACTIVE,
    the commands reach the plant; deadlines are the long study's (make timing)."""
    import math

    from firmware_sim.native import DEFAULT_LIBRARY
    from studies.timing.runner import C_ECU_EXECUTABLE

    if not C_ECU_EXECUTABLE.is_file() or not DEFAULT_LIBRARY.is_file():
        pytest.skip("the C ECU is not built (make firmware; make test builds it)")
    seconds = 4.0
    run = run_timing("eso-dkmpc", seconds, tmp_path, ecu="c")
    figures = run_figures(run, "idle")
    print(f"\nscheduling: {run.scheduling}")
    print("\n".join(summary_table([figures]) + percentile_table([figures])))
    assert run.controller == figures.controller == "eso-dkmpc (C)"
    assert "SCHED_" in run.scheduling["ecu"]  # the executable's "scheduling:" line was read
    assert "ready: controller eso-dkmpc" in run.ecu_log
    expected_cycles = (seconds - 1.0) / 0.025
    assert figures.cycles >= 0.8 * expected_cycles
    assert figures.modes.get("ACTIVE", 0) + figures.modes.get("DEGRADED", 0) >= 0.8 * figures.cycles, figures.modes
    assert figures.commands_received >= 0.8 * figures.cycles and figures.command_e2e_errors == 0
    assert figures.plant_commands_rejected == 0
    task_p50, task_p99 = figures.stats["task_time"][:2]
    assert 0 < task_p50 <= task_p99 < 25.0 and math.isfinite(figures.stats["release_jitter"][1])
    assert figures.lateral_error_max_m < 0.5
