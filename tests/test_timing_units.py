"""Pieces of the timing benchmark (hil/timing, firmware_sim/timing.py): the loopback CAN
hub, the timing record on disk, the scheduling helper, the long path and the run window."""
from __future__ import annotations

import math
import os
import socket
import time

import can
import numpy as np
import pytest

from firmware_sim.timing import (CONTEXT_FIELDS, TIMING_FIELDS, TimingRecorder,
                                 apply_realtime_policy, load_timing)
from hil.timing.hub import HubError, LoopbackCanHub, ProtocolError, send_to_frame
from studies.timing.stress import StressLoad


def _bus(port: int) -> can.BusABC:
    return can.Bus(interface="socketcand", channel="vcan0", host="127.0.0.1", port=port,
                   tcp_tune=True)


# ------------------------------------------------------------------ hub
def test_hub_delivers_each_frame_to_the_others_but_never_back_to_the_sender():
    with LoopbackCanHub().start() as hub:
        a, b, c = _bus(hub.port), _bus(hub.port), _bus(hub.port)
        try:
            time.sleep(0.25)  # READY_DELAY_S
            sent = can.Message(arbitration_id=0x100, data=bytes(range(8)), is_extended_id=False)
            a.send(sent)
            got_b, got_c, echo = b.recv(2.0), c.recv(2.0), a.recv(0.2)
        finally:
            for bus in (a, b, c):
                bus.shutdown()
    print("b:", got_b, "c:", got_c, "echo:", echo, hub.stats)
    for got in (got_b, got_c):
        assert got is not None and got.arbitration_id == 0x100
        assert bytes(got.data) == bytes(range(8)) and not got.is_extended_id
    assert echo is None and hub.stats.frames_in == 1 and hub.stats.deliveries == 2


def test_hub_keeps_order_and_round_trip_is_fast():
    with LoopbackCanHub().start() as hub:
        a, b = _bus(hub.port), _bus(hub.port)
        try:
            time.sleep(0.25)
            round_trips = []
            for i in range(100):
                started = time.perf_counter()
                a.send(can.Message(arbitration_id=0x200, data=bytes([i, 0, 0, 0, 0, 0, 0, 0]),
                                   is_extended_id=False))
                got = b.recv(2.0)
                round_trips.append(time.perf_counter() - started)
                assert got is not None and got.data[0] == i
        finally:
            a.shutdown()
            b.shutdown()
    median_ms = float(np.median(round_trips)) * 1e3
    print(f"sender -> hub -> receiver: median {median_ms:.3f} ms, max {max(round_trips) * 1e3:.3f} ms")
    assert median_ms < 5.0


def test_hub_refuses_a_non_loopback_address():
    with pytest.raises(HubError, match="loopback only"):
        LoopbackCanHub(host="0.0.0.0")


@pytest.mark.parametrize("command, message", [
    ("< send 100 2 1 >", "DLC"),
    ("< send 1000 1 1 >", "3 or 8 hex digits"),
    ("< send 10G 1 1 >", "bad ID"),
    ("< frame 100 1 1 >", "expected"),
])
def test_bad_send_commands_are_typed_errors(command, message):
    with pytest.raises(ProtocolError, match=message):
        send_to_frame(command, 0.0)


def test_send_command_becomes_a_socketcand_frame():
    can_id, frame = send_to_frame("< send 201 3 a 0 ff >", 12.5)
    assert (can_id, frame) == ("201", "< frame 201 12.500000 0a00ff >")


def test_hub_answers_a_protocol_error_and_keeps_serving():
    with LoopbackCanHub().start() as hub:
        with socket.create_connection(("127.0.0.1", hub.port), timeout=2.0) as raw:
            assert raw.recv(64) == b"< hi >"
            raw.sendall(b"< rawmode >")  # before < open >
            reply = raw.recv(64)
        bus = _bus(hub.port)  # a proper client still connects
        bus.shutdown()
    print("reply:", reply, hub.stats.protocol_errors)
    assert reply == b"< error protocol >" and len(hub.stats.protocol_errors) == 1


# ------------------------------------------------------------------ timing record on disk
def test_timing_record_round_trips_through_npz_with_context(tmp_path):
    recorder = TimingRecorder(capacity=8)
    for cycle in range(11):  # wraps: the last 8 kept
        recorder.record(1e-5 * cycle, 1e-3, 5e-4, math.nan, 2e-3, cycle,
                        start_time=100.0 + 0.025 * cycle, mode=cycle % 3)
    file = recorder.save(tmp_path / "ecu_timing.npz")
    record = load_timing(file)
    print("columns:", sorted(record.columns), "count", record.count, "n", len(record))
    assert set(record.columns) == set(TIMING_FIELDS) | set(CONTEXT_FIELDS)
    assert record.count == 11 and len(record) == 8
    np.testing.assert_allclose(record.columns["start_time"], 100.0 + 0.025 * np.arange(3, 11))
    np.testing.assert_array_equal(record.columns["mode"], np.arange(3, 11) % 3)
    np.testing.assert_array_equal(record.columns["overruns"], np.arange(3, 11))


def test_old_style_record_call_still_works_and_leaves_context_unset():
    recorder = TimingRecorder(capacity=4)
    recorder.record(0.0, 1e-3, 0.0, 0.0, 0.0, 0)
    context = recorder.context_rows()
    assert context.shape == (1, 2) and math.isnan(context[0, 0]) and context[0, 1] == -1


def test_load_timing_names_a_file_that_is_not_a_record(tmp_path):
    other = tmp_path / "other.npz"
    np.savez(other, x=np.zeros(3))
    with pytest.raises(ValueError, match="other.npz: not a timing record"):
        load_timing(other)


# ------------------------------------------------------------------ scheduling helper
def test_realtime_policy_pins_and_reports(tmp_path):
    import subprocess
    import sys
    child = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(30)"])
    try:
        cpu = min(os.sched_getaffinity(0))
        policy = apply_realtime_policy(cpu, None, pid=child.pid)
        print(policy.describe())
        assert policy.cpus == (cpu,) and os.sched_getaffinity(child.pid) == {cpu}
        assert policy.fifo_priority is None and "SCHED_OTHER" in policy.describe()
    finally:
        child.kill()
        child.wait()


def test_realtime_policy_refuses_bad_requests_with_named_errors():
    with pytest.raises(ValueError, match="cpu must be >= 0"):
        apply_realtime_policy(-1, None)
    with pytest.raises(ValueError, match="SCHED_FIFO priority must be in"):
        apply_realtime_policy(None, 1000)


def test_realtime_policy_notes_a_cpu_that_does_not_exist():
    policy = apply_realtime_policy(4096, None)
    print(policy.describe())
    assert policy.notes and "not pinned" in policy.notes[0]


def test_freezing_the_start_up_objects_leaves_them_out_of_full_collections():
    """In a child process (freezing is for the life of a process): the objects alive after
    start-up move to the permanent generation, and a full collection then scans only
    what came after."""
    import subprocess
    import sys
    code = ("import gc, numpy, can, controller.registry\n"
            "from firmware_sim.timing import freeze_start_up_objects\n"
            "frozen = freeze_start_up_objects()\n"
            "after = sum(len(g) for g in (gc.get_objects(0), gc.get_objects(1), gc.get_objects(2)))\n"
            "print(frozen, gc.get_freeze_count(), after)\n")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    print(result.stdout, result.stderr)
    frozen, count, tracked = (int(v) for v in result.stdout.split())
    assert frozen == count > 10_000          # the modules and libraries of start-up
    assert tracked < frozen / 10             # what a later full collection still scans


# ------------------------------------------------------------------ long path
def test_repeated_lane_change_is_continuous_and_long_enough(tmp_path):
    from controller.reference import ReferencePath
    from studies.timing.paths import write_repeated_lane_change

    file = write_repeated_lane_change(tmp_path / "path.csv", 1200.0)
    path = ReferencePath.from_csv(file)  # the ECU's own loader validates spacing
    x, y = np.asarray(path.x), np.asarray(path.y)
    print(f"length {path.length:.0f} m, y in [{y.min():.3f}, {y.max():.3f}] m, "
          f"largest step in y {np.abs(np.diff(y)).max():.4f} m")
    assert path.length >= 1200.0 and x[-1] - x[0] >= 1200.0
    assert np.abs(np.diff(y)).max() < 0.1           # no jump at the joints
    # every second segment is mirrored about Y = -1.65 / 2, so the car returns to its lane
    peak = float(np.max(ReferencePath.double_lane_change().y))
    assert y.max() == pytest.approx(peak, abs=1e-3)
    assert y.min() == pytest.approx(-1.65 - peak, abs=1e-3)


# ------------------------------------------------------------------ run window
def test_run_figures_count_only_cycles_and_overruns_inside_the_window():
    from firmware_sim.timing import TimingRecord
    from studies.timing.report import run_figures
    from studies.timing.runner import TimingRun

    n = 100
    start = 10.0 + 0.025 * np.arange(n)            # 10.0 .. 12.475 s
    overruns = np.where(start < 10.1, 1.0, 2.0)    # one before the plant ran, one at its start
    overruns[start >= 12.0] = 4.0                  # two more inside the window
    columns = {"release_jitter": np.full(n, 1e-4), "task_time": np.full(n, 2e-3),
               "solve_time": np.full(n, 3e-4), "input_age": np.full(n, 5e-3),
               "rx_to_tx_latency": np.full(n, 7e-3), "overruns": overruns,
               "start_time": start, "mode": np.full(n, 2.0)}
    plant = {"started": 10.1, "ended": 12.3, "ticks": 480, "tick_overruns": 0,
             "plant_commands_rejected": 0, "tracking": {"lateral_error_m": {"max_abs": 0.05}},
             "commands": {"received": 96, "lost": 0, "arrivals": list(start + 0.001)}}
    run = TimingRun("lmpc", 2.4, TimingRecord(columns, n), plant, {}, "")
    figures = run_figures(run, "idle", settle_s=0.8)   # window 10.9 .. 12.3 s, plant from 10.1
    print(figures.cycles, figures.overruns, figures.stats["task_time"])
    assert figures.cycles == int(np.sum((start >= 10.9) & (start <= 12.3))) == 57
    assert figures.overruns == 3 and figures.modes == {"ACTIVE": 57}
    assert figures.stats["task_time"][1] == pytest.approx(2.0)
    assert figures.command_gap_max_ms == pytest.approx(25.0)

    assert (figures.release, figures.repeat) == ("clock", 1)

    # the C ECU's row (issue 18) under the sample release: its own goal line, task p99
    # against 0.25 ms; the release and the repeat carried from the run to its figures
    from studies.timing.goals import GOAL_C_TASK_P99_MS, goal_lines

    c_row = run_figures(TimingRun("eso-dkmpc (C)", 2.4, TimingRecord(dict(columns, task_time=np.full(n, 2e-4)), n),
                                  plant, {}, "", "sample"), "idle", settle_s=0.8, repeat=2)
    assert (c_row.release, c_row.repeat) == ("sample", 2)
    lines = goal_lines([figures, c_row])
    assert (f"- idle, sample release: ESO-DKMPC (C ECU) task time p99 <= {GOAL_C_TASK_P99_MS:g} ms: "
            "met (1 of 1 run within), p99 0.200 ms") in lines
    assert any(line.startswith("- idle, sample release: eso-dkmpc (C) overruns at 25 ms") for line in lines)


# ------------------------------------------------------------------ ECU command line options
def test_ecu_cli_refuses_a_fifo_priority_out_of_range(capsys):
    from firmware_sim.cli import main

    status = main(["--interface", "virtual", "--channel", "timing-cli-test", "--controller", "lmpc",
                   "--path", "1=hil/paths/dlc.csv", "--realtime", "--rt-priority", "1000"])
    err = capsys.readouterr().err
    print(status, err)
    assert status == 2 and "error: SCHED_FIFO priority must be in" in err


def test_ecu_cli_writes_its_timing_record_on_exit(tmp_path):
    import threading

    from firmware_sim.cli import main

    out = tmp_path / "ecu_timing.npz"
    stop = threading.Event()
    result: list[int] = []
    thread = threading.Thread(target=lambda: result.append(main(
        ["--interface", "virtual", "--channel", "timing-cli-test-2", "--controller", "lmpc",
         "--path", "1=hil/paths/dlc.csv", "--realtime", "--timing-out", str(out),
         "--cpu", str(min(os.sched_getaffinity(0)))], stop_event=stop)))
    thread.start()
    time.sleep(1.5)   # controller and path load, then some 25 ms cycles in INIT
    stop.set()
    thread.join(20.0)
    os.sched_setaffinity(0, set(range(os.cpu_count() or 1)))  # main() pinned this process
    record = load_timing(out)
    modes = set(record.columns["mode"].tolist())
    print("status", result, "cycles", record.count, "modes", modes)
    assert result == [0] and record.count >= 1 and modes == {0.0}   # INIT: no plant on the bus
    assert np.all(np.isfinite(record.columns["start_time"]))


# ------------------------------------------------------------------ stress load
def test_stress_load_dies_with_its_parent_even_when_the_parent_is_killed():
    import subprocess
    import sys

    code = ("from studies.timing.stress import StressLoad; import time; "
            "s = StressLoad((0,)).start(); print(s._processes[0].pid, flush=True); time.sleep(60)")
    parent = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    child_pid = int(parent.stdout.readline())
    parent.kill()
    parent.wait()
    parent.stdout.close()
    state = "gone"
    for _ in range(50):   # up to 5 s for the SIGTERM to land
        try:
            status = open(f"/proc/{child_pid}/status").read()
        except FileNotFoundError:
            break
        state = next(line for line in status.splitlines() if line.startswith("State"))
        if "Z" in state.split()[1]:
            break
        time.sleep(0.1)
    print("busy loop after its parent was killed:", state)
    if state != "gone" and "Z" not in state.split()[1]:
        os.kill(child_pid, 9)
        pytest.fail(f"busy loop survived its parent: {state}")


def test_stress_load_runs_one_busy_loop_per_cpu_and_stops():
    cpu = min(os.sched_getaffinity(0))
    with StressLoad((cpu,)) as load:
        time.sleep(0.3)
        pid = load._processes[0].pid
        assert os.sched_getaffinity(pid) == {cpu}
        ticks = int(open(f"/proc/{pid}/stat").read().split()[13])  # utime, clock ticks
    print("busy loop user time after 0.3 s:", ticks, "ticks;", load.pinned)
    assert ticks > 0 and not load._processes


def test_cpu_latency_request_writes_the_latency_and_holds_it_while_open(tmp_path):
    from studies.timing.cpu_latency import CpuLatencyRequest

    device = tmp_path / "cpu_dma_latency"
    device.write_bytes(b"")
    with CpuLatencyRequest(7, device=device) as request:
        assert request.held
        assert "held at 7 us" in request.describe()
        assert device.read_bytes() == (7).to_bytes(4, "little", signed=True)
    assert not request.held  # closing the file drops the request


def test_cpu_latency_request_reports_an_unusable_device_and_does_not_raise(tmp_path):
    from studies.timing.cpu_latency import CpuLatencyRequest

    with CpuLatencyRequest(0, device=tmp_path / "missing" / "cpu_dma_latency") as request:
        assert not request.held
        assert request.describe().startswith("not held (")
        assert "missing" in request.describe()
    with pytest.raises(ValueError, match="must be >= 0 us, got -1"):
        CpuLatencyRequest(-1)


def test_cpu_latency_request_not_requested_holds_nothing(tmp_path):
    from studies.timing.cpu_latency import CpuLatencyRequest

    device = tmp_path / "cpu_dma_latency"
    device.write_bytes(b"")
    with CpuLatencyRequest(0, device=device, requested=False) as request:
        assert not request.held
        assert request.describe().startswith("not requested")
    assert device.read_bytes() == b""
