"""One HIL run over CAN: the ECU, the plant, the planner, a time master and a recorder on
one bus, for one scenario and one controller.

Where the ECU runs depends on the bus:

- python-can's ``virtual`` interface exists only inside one process, so the ECU runs
  in-process: its own bus object and ``firmware_sim.ecu.Ecu`` in a thread;
- any other interface (SocketCAN ``vcan0``, a real adapter) gets the ECU as a separate
  process through its CLI (``eso-ecu``: ``python -m firmware_sim ...``), stopped with SIGTERM at the
  end. Only CAN frames pass between the two, as on a vehicle.

``RunOptions.ecu`` "c" runs the C ECU executable (``build/firmware/ecu``, ``make
firmware``; docs/firmware.md) as that process instead. It speaks SocketCAN and socketcand
only, so on the ``virtual`` interface the run moves to a socketcand hub of its own on TCP
loopback (``hil.timing.hub``, as the firmware's bus tests): every node of this process and
the executable are its clients.

The nodes, buses and ECU are wired by ``hil.rig.Rig``; :func:`run_hil` is a plain run of
it. Results: the plant's true time series (5 ms ticks), the ECU's frames per control cycle,
the tracking metrics of hil/metrics.py on the true pose at the control instants (every
25 ms, as studies/closed_loop.py computes them), and the frame log of the recorder.
"""
from __future__ import annotations

from collections.abc import Callable

# What a run takes and gives, its ECU and its metrics have their own modules; the names
# every caller imports from hil.session stay importable here.
from hil.ecu_runners import (EcuProcess, EcuRunner, InProcessEcu, c_ecu_command,  # noqa: F401
                             check_c_ecu, ecu_command)
from hil.metrics import (CONTROL_PERIOD_MS, control_instant_errors,  # noqa: F401
                         control_instant_metrics, reference_path)
from hil.rig import Rig
from hil.run_types import (C_ECU_CONTROLLERS, C_ECU_EXECUTABLE, ECU_IMPLEMENTATIONS,  # noqa: F401
                           ECU_STOP_TIMEOUT_S, HUB_CHANNEL, REPO_ROOT, HilRunResult, RunOptions,
                           SessionError, default_options)
from hil.scenario import Scenario


def run_hil(scenario: Scenario, options: RunOptions,
            on_tick: Callable[[int], None] | None = None) -> HilRunResult:
    """Run ``scenario`` with ``options.controller`` over CAN (see the module docstring).

    Raises:
        SessionError: the ECU could not start or stopped.
        hil.bus.BusOpenError, hil.recorder.RecorderError, hil.time_master.TimeMasterError.
    """
    rig = Rig(scenario, options)
    with rig:
        rig.run(on_tick=on_tick)
    return rig.result()
