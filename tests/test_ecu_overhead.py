"""The ECU overhead measurement runs and writes its summary (figures are not asserted:
they depend on the machine)."""
from __future__ import annotations

import json

from studies import ecu_overhead as overhead


def test_overhead_measurement_writes_a_summary(tmp_path, capsys):
    out = tmp_path / "ecu_overhead.json"
    assert overhead.main(["--cycles", "40", "--seconds", "0.3", "--out", str(out)]) == 0
    result = json.loads(out.read_text())
    lockstep, realtime = result["lockstep"], result["realtime"]
    print("lockstep task p50 [s]:", lockstep["control_task_time_s"]["p50"],
          "real-time cycles:", realtime["control_cycles"])
    assert lockstep["final_mode"] == "ACTIVE" and lockstep["control_task_time_s"]["n"] == 40
    assert lockstep["tick_wall_time_s"]["n"] == 200
    assert realtime["control_cycles"] >= 5
    assert set(realtime["timing_s"]) == {"release_jitter", "task_time", "solve_time",
                                         "input_age", "rx_to_tx_latency", "overruns"}


def test_overhead_refuses_non_positive_arguments(capsys):
    assert overhead.main(["--cycles", "0"]) == 2
    assert capsys.readouterr().err.startswith("error:")
