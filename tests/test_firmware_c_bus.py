"""The C ECU executable on a bus: equivalence and conformance with the Python ECU.

An ECU process - the executable, or ``python -m firmware_sim`` - runs on the socketcand
hub of the timing tests (``hil.timing.hub``, TCP loopback); this process runs the plant,
the planner and the time master of ``hil`` on the same hub (``studies.bench_native.
run_on_hub``). Frames are compared with those of the Python ECU on the same scenario:
STEER_TORQUE_CMD byte for byte, CTRL_DIAG in every field but the wall-clock ones
(SOLVE_TIME_US, CYCLE_TIME_US, OVERRUNS: the contract says those alone are not
repeatable) and the CRC that covers them. ``dlc_smoke`` and three fault cases here
(``make test``); the full lane changes with ECU_EQUIVALENCE_FULL=1, every fault case with
ECU_CONFORMANCE_FULL=1.
"""
from __future__ import annotations

import os
import signal
import subprocess
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import can
import pytest

from can_defs.codec import decode
from can_defs.frames import FrameId
from studies.bench_native import CHANNEL, ecu_command, run_on_hub
from test_firmware_c_core import native  # noqa: F401 (the fixture: the firmware built)

ROOT = Path(__file__).resolve().parent.parent
ECU = ROOT / os.environ.get("ECU_EXE", "build/firmware/ecu")
FULL = os.environ.get("ECU_EQUIVALENCE_FULL") == "1"


def run_c_ecu(scenario_name: str, controller: str, log: Path, path_file: Path | None = None):
    """The scenario with the C ECU on the hub (see `run_on_hub`)."""
    return run_on_hub("c", scenario_name, controller, log, path_file, executable=ECU)


def diag_fields(data: bytes) -> tuple:
    """CTRL_DIAG without its wall-clock fields (SOLVE_TIME_US, CYCLE_TIME_US, OVERRUNS)."""
    frame = decode(FrameId.CTRL_DIAG, data).frame
    return data[1] & 0x0F, int(frame.qp_status), frame.qp_iter, frame.faults


def commands_and_diags(raw) -> tuple[list, list]:
    """(tick, STEER_TORQUE_CMD payload) and (tick, CTRL_DIAG without wall-clock fields)."""
    return ([(t, d) for t, i, d in raw if i == FrameId.STEER_TORQUE_CMD],
            [(t, diag_fields(d)) for t, i, d in raw if i == FrameId.CTRL_DIAG])


def check_equivalent(scenario_name: str, controller: str, tmp_path: Path) -> dict:
    from hil.scenario import load_scenario
    from hil.session import default_options, run_hil

    python_run = run_hil(load_scenario(scenario_name), default_options(controller))
    c_raw, c_tracking, status, output = run_c_ecu(scenario_name, controller, tmp_path / "ecu.log")
    assert status == 0, output
    (ours, our_diags), (theirs, their_diags) = (commands_and_diags(python_run.extra["ecu_frames_raw"]),
                                                commands_and_diags(c_raw))
    differing = sum(a != b for a, b in zip(ours, theirs))
    figures = {"commands": len(ours), "c_commands": len(theirs), "differing": differing,
               "rmse_python": python_run.tracking.lateral.rmse, "rmse_c": c_tracking.lateral.rmse}
    print(f"{controller} on {scenario_name}: {figures}")
    assert len(theirs) == len(ours) and differing == 0
    assert their_diags == our_diags
    return figures


@pytest.mark.parametrize("controller", ["eso-dkmpc", "lmpc"])
def test_c_ecu_on_the_bus_equals_python_ecu_on_dlc_smoke(native, controller: str, tmp_path: Path) -> None:
    check_equivalent("dlc_smoke", controller, tmp_path)


@pytest.mark.slow
@pytest.mark.skipif(not FULL, reason="the full lane changes: make firmware-equivalence (ECU_EQUIVALENCE_FULL=1)")
@pytest.mark.parametrize("scenario", ["dlc_high_mu", "dlc_low_mu"])
@pytest.mark.parametrize("controller", ["eso-dkmpc", "dkmpc", "lmpc"])
def test_c_ecu_on_the_bus_equals_python_ecu_on_full_lane_changes(native, controller: str, scenario: str,
                                                                 tmp_path: Path) -> None:
    check_equivalent(scenario, controller, tmp_path)


def test_a_path_that_does_not_load_latches_fault(native, tmp_path: Path) -> None:
    """As the Python ECU (contract): the handshake is answered, every command is FAULT
    with CMD_VALID = 0, and the reason is on stderr."""
    bad = tmp_path / "bad.csv"
    bad.write_text("x,y,heading\n0,0,0\n0.1,0,0\n")
    raw, _, status, output = run_c_ecu("dlc_smoke", "lmpc", tmp_path / "ecu.log", path_file=bad)
    assert status == 0
    assert "FAULT latched: PATH_ID 1 file" in output and "header must be 'x,y,yaw'" in output
    commands = [decode(i, d).frame for _, i, d in raw if i == FrameId.STEER_TORQUE_CMD]
    assert len(commands) == 160
    assert all(int(c.ctrl_mode) == 5 and not c.cmd_valid and c.drive_torque_cmd == 0.0 for c in commands)


@pytest.mark.parametrize("probe, message", [
    ("x,y,yaw\n0,0,0\n0.1,0," + " " * 4200 + "0,1,2\n", "line 3: longer than 4096 bytes"),
    ("x,y,yaw\n0,0,0\n0.1,0\x00junk,0\n0.2,0,0\n", "line 3: holds a NUL byte"),
])
def test_probe_path_files_latch_the_same_fault_in_both_ecus(native, probe: str, message: str,
                                                            tmp_path: Path) -> None:
    """Conformance on the bus (issue 38, item 9): a path file with a line over the limit or
    a NUL byte, which the C ECU once split or cut and took: both ECUs latch FAULT with the
    same message and send the same frames."""
    bad = tmp_path / "probe.csv"
    bad.write_bytes(probe.encode())
    runs = {}
    for which in ("python", "c"):
        raw, _, status, output = run_on_hub(which, "dlc_smoke", "lmpc", tmp_path / f"{which}.log", bad,
                                            executable=ECU, duration_s=0.5)
        assert status == 0, output[-2000:]
        assert f"FAULT latched: PATH_ID 1 file {bad}: {bad}: {message}" in output, output[-2000:]
        runs[which] = commands_and_diags(raw)
    assert runs["python"] == runs["c"] and len(runs["c"][0]) > 10
    assert all(int(decode(FrameId.STEER_TORQUE_CMD, d).frame.ctrl_mode) == 5 for _, d in runs["c"][0])


def test_a_failing_controller_ends_in_the_same_safe_stop_in_both_ecus(native, tmp_path: Path) -> None:
    """Contract rev. 2, a failing controller, closed loop on the hub: the model with its
    lifted dynamics A(v) x 1e6 (finite, so it loads; the fault campaign's "model A x 1e6")
    makes every step fall back. Both ECUs (the C one on its data file converted from the
    same artefact) send the same frames: FAULTS bit 2 on the first 4 tasks in ACTIVE, then
    SAFE_STOP to the end, every command with CMD_VALID = 1 within the limits."""
    from hil.fault_cases.input_cases import write_bad_input
    from hil.fault_cases.verdicts import check_commands
    from hil.scenario import load_scenario

    path_file = Path(load_scenario("dlc_smoke").path_file)
    runs = {}
    for which in ("python", "c"):
        folder = tmp_path / which
        folder.mkdir()
        bad = write_bad_input("dynamics A x 1e6", folder, path_file, which)
        extra = ("--model", str(bad.model)) if which == "python" else ("--data", str(bad.data))
        raw, _, status, output = run_on_hub(which, "dlc_smoke", "eso-dkmpc", tmp_path / f"{which}.log",
                                            executable=ECU, duration_s=1.0, extra=extra)
        assert status == 0, output[-2000:]
        assert check_commands(raw)[0] == 0, check_commands(raw)
        runs[which] = commands_and_diags(raw)
    (py_commands, py_diags), (c_commands, c_diags) = runs["python"], runs["c"]
    assert c_commands == py_commands and c_diags == py_diags
    modes = [int(decode(FrameId.STEER_TORQUE_CMD, d).frame.ctrl_mode) for _, d in c_commands]
    fallbacks = [bool(fields[3] & 0b0100) for _, fields in c_diags]
    engaged = modes.index(2)
    print(f"modes from the engagement {modes[engaged:engaged + 8]}, fallbacks {fallbacks[engaged:engaged + 8]}")
    assert modes[engaged:engaged + 4] == [2] * 4 and all(fallbacks[engaged:engaged + 4])
    assert set(modes[engaged + 4:]) == {4} and not any(fallbacks[engaged + 4:])


#: Conformance cases (contract rev. 2 faults), each from 1.5 s of dlc_smoke: name -> the
#: ``[faults]`` table or a jump of virtual time. The first ones run in make test.
CONFORMANCE_CASES = {
    "sample_gap_degraded": {"bus": [{"kind": "silent", "sender": "plant", "start_s": 1.5, "duration_s": 0.06}]},
    "delayed_samples": {"bus": [{"kind": "delay", "sender": "plant", "start_s": 1.5, "duration_s": 1.0,
                                 "delay_ms": 15}]},
    "plant_silent_safe_stop": {"bus": [{"kind": "silent", "sender": "plant", "start_s": 1.5, "duration_s": 0.5}]},
    "time_jump": {"jump": (1500, 10_000)},
    "planner_wrong_crc_standby": {"bus": [{"kind": "wrong_crc", "sender": "planner", "start_s": 1.5,
                                           "duration_s": 0.3}]},
    "plant_drops": {"seed": 3, "bus": [{"kind": "drop", "sender": "plant", "start_s": 1.5, "rate": 0.3,
                                        "burst": 2}]},
    "plant_duplicates": {"bus": [{"kind": "duplicate", "sender": "plant", "start_s": 1.5, "rate": 0.5}]},
    "plant_reorder": {"seed": 2, "bus": [{"kind": "reorder", "sender": "plant", "start_s": 1.5, "rate": 0.5}]},
    "plant_bitflips": {"seed": 4, "bus": [{"kind": "bitflip", "sender": "plant", "start_s": 1.5, "rate": 0.2}]},
    "frozen_counter": {"bus": [{"kind": "frozen_counter", "sender": "plant", "start_s": 1.5, "duration_s": 0.2}]},
    "implausible_vx": {"bus": [{"kind": "override", "ids": [0x100], "field": "vx", "value": 100.0,
                                "start_s": 1.5, "duration_s": 0.1}]},
    "engage_toggle": {"bus": [{"kind": "engage_toggle", "sender": "planner", "start_s": 1.5,
                               "duration_s": 1.0, "period_ms": 50}]},
    "extended_lookalikes": {"bus": [{"kind": "lookalike", "sender": "plant", "frame_kind": "extended",
                                     "start_s": 1.5}]},
    "replayed_plant": {"bus": [{"kind": "replay", "sender": "plant", "age_ms": 50, "start_s": 1.5,
                                "duration_s": 0.5}]},
    "babbling_node": {"seed": 5, "bus": [{"kind": "babble", "ids": [0x100], "babble_id": 0x50,
                                          "frames_per_tick": 2, "start_s": 1.5, "duration_s": 0.3}]},
}
IN_MAKE_TEST = ("sample_gap_degraded", "plant_silent_safe_stop", "time_jump")
CONFORMANCE_FULL = os.environ.get("ECU_CONFORMANCE_FULL") == "1"


@pytest.mark.parametrize("case", [pytest.param(name, marks=() if name in IN_MAKE_TEST else [
    pytest.mark.slow, pytest.mark.skipif(not CONFORMANCE_FULL, reason="make firmware-conformance")])
    for name in CONFORMANCE_CASES])
def test_conformance_c_ecu_equals_python_ecu_under_faults(native, case: str, tmp_path: Path) -> None:
    """Both ECUs as processes on the hub, the same faults injected: the same frames (the
    modes, fault bits, fallbacks and commands of the contract's fault reactions)."""
    table = dict(CONFORMANCE_CASES[case])
    jump = table.pop("jump", None)
    runs = {}
    for which in ("python", "c"):
        raw, tracking, status, output = run_on_hub(which, "dlc_smoke", "lmpc", tmp_path / f"{which}.log",
                                                   faults=table or None, jump=jump, executable=ECU)
        assert status == 0, output[-2000:]
        runs[which] = commands_and_diags(raw)
    (py_commands, py_diags), (c_commands, c_diags) = runs["python"], runs["c"]
    modes = sorted({decode(FrameId.STEER_TORQUE_CMD, d).frame.ctrl_mode.name for _, d in py_commands})
    faults = sorted({f[3] for _, f in py_diags})
    print(f"{case}: {len(py_commands)} commands, modes {modes}, FAULTS values {faults}")
    assert len(c_commands) == len(py_commands)
    first = next((i for i, (a, b) in enumerate(zip(py_commands, c_commands)) if a != b), None)
    assert first is None, f"first differing STEER_TORQUE_CMD at tick {py_commands[first][0]} ms"
    assert c_diags == py_diags


def test_c_ecu_in_real_time_tracks_as_the_python_ecu(native, tmp_path: Path) -> None:
    """Real time (every node on the wall clock, absolute 25 ms releases): not repeatable
    frame for frame, so the run is compared by its outcome - the C ECU sends valid
    commands (ACTIVE, DEGRADED on a late sample of a busy host) in at least 90 % of the
    run's control periods and tracks dlc_smoke as the Python ECU does
    (e_Y RMSE within 5 mm). Both ECUs pinned to CPU 0 (``--cpu``)."""
    results = {}
    for which in ("python", "c"):
        raw, tracking, status, output = run_on_hub(which, "dlc_smoke", "lmpc", tmp_path / f"{which}.log",
                                                   realtime=True, executable=ECU, extra=("--cpu", "0"))
        assert status == 0, output[-2000:]
        commands = [decode(i, d).frame for _, i, d in raw if i == FrameId.STEER_TORQUE_CMD]
        active = sum(int(c.ctrl_mode) in (2, 3) and c.cmd_valid for c in commands)  # ACTIVE, DEGRADED
        results[which] = (len(commands), active, tracking.lateral.rmse)
    print(f"real time on dlc_smoke (commands, valid in ACTIVE/DEGRADED, e_Y RMSE m): {results}")
    n_c, active_c, rmse_c = results["c"]
    cycles = round(4.0 / 0.025)  # dlc_smoke: 4 s; the ECU also runs before the plant starts
    assert n_c >= cycles and active_c >= 0.9 * cycles
    assert abs(rmse_c - results["python"][2]) <= 0.005


def _drive(scenario, port: int, seconds: float) -> list:
    """A lockstep rig (``hil.rig``) on the hub at ``port`` for ``seconds``, driving the ECU
    process already there; the ECU's STEER_TORQUE_CMD frames (tick ms, frame)."""
    from hil.bus import BusConfig
    from hil.rig import NoEcu, Rig, RigHooks
    from hil.run_types import RunOptions

    options = RunOptions(controller="(another process)", bus=BusConfig("socketcand", CHANNEL),
                         handshake_timeout_s=30.0, ack_timeout_s=10.0)
    hooks = RigHooks(ecu=lambda rig: NoEcu(), bus_options={"host": "127.0.0.1", "port": port, "tcp_tune": True},
                     before_run=lambda: time.sleep(0.2))  # the hub delivers after its READY_DELAY_S
    with Rig(scenario, options, hooks) as rig:
        rig.run(seconds)
    return rig.monitor.commands


@contextmanager
def _ecu_process(command: list[str], environment: dict[str, str], log: Path) -> Iterator[dict]:
    """The ECU as a process writing to ``log``; SIGTERM at the end, which it must survive:
    its exit status is the yielded dict's ``status``."""
    outcome: dict = {}
    with log.open("w") as output:
        ecu = subprocess.Popen(command, cwd=ROOT, env=environment, stdout=output, stderr=subprocess.STDOUT)
        try:
            yield outcome
        finally:
            ecu.send_signal(signal.SIGTERM)
            outcome["status"] = ecu.wait(timeout=20)


def _wait_for(log: Path, text: str, timeout_s: float = 10.0) -> None:
    deadline = time.monotonic() + timeout_s
    while text not in log.read_text() and time.monotonic() < deadline:
        time.sleep(0.05)


def test_lost_bus_is_reopened(native, tmp_path: Path) -> None:
    """The bus goes away (the hub closes) and comes back on the same port: the C ECU says
    so once, reopens it within about a second, and answers a new handshake (contract rev. 2,
    "lost bus")."""
    from hil.scenario import load_scenario
    from hil.timing.hub import LoopbackCanHub

    scenario = load_scenario("dlc_smoke")
    hub = LoopbackCanHub(port=0).start()
    port = hub.port
    log = tmp_path / "ecu.log"
    command, environment = ecu_command("c", "lmpc", scenario.path_file, port, executable=ECU)
    try:
        with _ecu_process(command, environment, log) as ecu:
            first = _drive(scenario, port, 0.5)
            hub.close()
            time.sleep(0.5)
            hub = LoopbackCanHub(port=port).start()
            _wait_for(log, "bus reopened")
            second = _drive(scenario, port, 0.5)
    finally:
        hub.close()
    output_text = log.read_text()
    assert ecu["status"] == 0, output_text
    assert output_text.count("bus lost") == 1 and "bus reopened after it was lost" in output_text
    assert len(first) == len(second) == 20  # 0.5 s of 25 ms control tasks, each run


#: An LD_PRELOAD shim: once the file named by ECU_TEST_RECV_FAIL_FILE exists, recv() fails
#: with EIO from its next call for the number of milliseconds the file holds, then removes
#: the file: a receive failure of a chosen length that starts when the ECU receives.
_RECV_FAILURE_SHIM = r"""
#define _GNU_SOURCE
#include <dlfcn.h>
#include <errno.h>
#include <stdio.h>
#include <stdlib.h>
#include <sys/socket.h>
#include <time.h>
#include <unistd.h>
static double now_ms(void) {
  struct timespec t;
  clock_gettime(CLOCK_MONOTONIC, &t);
  return 1e3 * (double)t.tv_sec + 1e-6 * (double)t.tv_nsec;
}
ssize_t recv(int fd, void *buf, size_t len, int flags) {
  static ssize_t (*real)(int, void *, size_t, int);
  static double until = -1.0;
  if (!real) real = (ssize_t (*)(int, void *, size_t, int))dlsym(RTLD_NEXT, "recv");
  const char *flag = getenv("ECU_TEST_RECV_FAIL_FILE");
  if (until < 0 && flag) {
    FILE *file = fopen(flag, "r");
    double duration_ms;
    if (file) {
      if (fscanf(file, "%lf", &duration_ms) == 1) until = now_ms() + duration_ms;
      fclose(file);
    }
  }
  if (until >= 0 && now_ms() < until) {
    errno = EIO;
    return -1;
  }
  if (until >= 0) {
    until = -1.0;
    unlink(flag);
  }
  return real(fd, buf, len, flags);
}
"""


def test_receive_errors_are_a_lost_bus_only_once_they_persist_for_100_ms(native, tmp_path: Path) -> None:
    """Contract rev. 2, "lost bus": receive errors that persist for 100 ms are a lost bus,
    a short burst is not. recv() fails (EIO) for 40 ms as the ECU starts dlc_smoke in
    lockstep: it warns once and every command still comes; then for 400 ms while a node
    keeps sending: the bus is lost once ("receive errors for 100 ms"), reopened, and a new
    run works."""
    from hil.scenario import load_scenario
    from hil.timing.hub import LoopbackCanHub

    shim = tmp_path / "recv_failure.so"
    source = tmp_path / "recv_failure.c"
    source.write_text(_RECV_FAILURE_SHIM)
    subprocess.run(["gcc", "-shared", "-fPIC", "-O1", "-o", str(shim), str(source), "-ldl"], check=True)
    failing = tmp_path / "failing"
    scenario = load_scenario("dlc_smoke")
    hub = LoopbackCanHub(port=0).start()
    port = hub.port
    log = tmp_path / "ecu.log"
    command, environment = ecu_command("c", "lmpc", scenario.path_file, port, executable=ECU,
                                       extra=("--log-level", "info"))
    # after the sanitizer runtime where make firmware-asan preloads one
    environment["LD_PRELOAD"] = f"{environment.get('LD_PRELOAD', '')} {shim}".strip()
    environment["ECU_TEST_RECV_FAIL_FILE"] = str(failing)
    try:
        with _ecu_process(command, environment, log) as ecu:
            _wait_for(log, "ready: controller")  # the bus is open
            failing.write_text("40")
            first = _drive(scenario, port, 4.0)
            assert not failing.exists(), "the burst did not happen"
            assert "bus lost" not in log.read_text()
            sender = can.Bus(interface="socketcand", channel=CHANNEL, host="127.0.0.1", port=port, tcp_tune=True)
            try:
                failing.write_text("400")
                end = time.monotonic() + 1.0
                while time.monotonic() < end:  # traffic, so that the ECU keeps receiving
                    sender.send(can.Message(arbitration_id=0x7FF, data=b"\0", is_extended_id=False))
                    time.sleep(0.01)
            finally:
                sender.shutdown()
            _wait_for(log, "bus reopened")
            second = _drive(scenario, port, 0.5)
    finally:
        hub.close()
    output_text = log.read_text()
    assert ecu["status"] == 0, output_text
    assert output_text.count("bus receive failed") == 2, output_text  # the burst, then the persisting errors
    assert output_text.count("bus lost") == 1, output_text
    assert "bus lost (receive errors for 100 ms)" in output_text
    assert "bus reopened after it was lost" in output_text
    assert len(first) == 160 and len(second) == 20  # every 25 ms control task of each run


def test_timing_record_reads_as_the_python_ecus(native, tmp_path: Path) -> None:
    """--timing-out: the C ECU's record of a real-time run loads with
    firmware_sim.timing.load_timing, one row per control task, the fields measured."""
    import numpy as np

    from firmware_sim.timing import TIMING_FIELDS, load_timing

    record_file = tmp_path / "timing.npz"
    raw, _, status, output = run_on_hub("c", "dlc_smoke", "lmpc", tmp_path / "ecu.log", realtime=True,
                                        executable=ECU, duration_s=2.0,
                                        extra=("--timing-out", str(record_file)))
    assert status == 0, output
    record = load_timing(record_file)
    diags = sum(1 for _, i, _ in raw if i == FrameId.CTRL_DIAG)
    assert record.count >= diags >= 70  # the ECU also runs before and after the master
    assert set(TIMING_FIELDS) <= set(record.columns)
    task = record.columns["task_time"]
    assert np.all(np.isfinite(task)) and np.all(task > 0.0) and np.median(task) < 0.025
    assert np.all(np.isfinite(record.columns["release_jitter"]))
    active = record.columns["mode"] == 2
    assert active.sum() >= 60 and np.all(np.isfinite(record.columns["input_age"][active]))
    print(f"C ECU task time p50 {np.median(task) * 1e6:.0f} us, p99 {np.percentile(task, 99) * 1e6:.0f} us "
          f"over {record.count} tasks")


@pytest.mark.parametrize("controller", ["eso-dkmpc"])
def test_hil_run_with_the_c_ecu_equals_the_python_ecu(native, controller: str, tmp_path: Path, capsys) -> None:
    """``hil run --ecu c``: the C executable as the run's ECU process (on the virtual
    interface through the run's own loopback hub) sends the Python ECU's frames on
    dlc_smoke, and the frame log it records holds them."""
    from hil.__main__ import main
    from hil.logio import read_log
    from hil.scenario import load_scenario
    from hil.session import default_options, run_hil

    python_run = run_hil(load_scenario("dlc_smoke"), default_options(controller))
    log = tmp_path / "c.log"
    assert main(["run", "--scenario", "dlc_smoke", "--controller", controller, "--ecu", "c",
                 "--log", str(log), "--out", str(tmp_path / "out")]) == 0
    assert '"bus": "socketcand:vcan0 (loopback hub)"' in capsys.readouterr().out
    c_run = run_hil(load_scenario("dlc_smoke"), default_options(controller, ecu="c"))
    (ours, our_diags), (theirs, their_diags) = (commands_and_diags(python_run.extra["ecu_frames_raw"]),
                                                commands_and_diags(c_run.extra["ecu_frames_raw"]))
    assert len(ours) == 160 and theirs == ours and their_diags == our_diags
    assert c_run.tracking.lateral.rmse == python_run.tracking.lateral.rmse
    logged = [bytes(m.data) for m in read_log(log).messages if m.arbitration_id == FrameId.STEER_TORQUE_CMD]
    assert logged[:len(ours)] == [d for _, d in ours]


def test_hil_run_refuses_a_c_ecu_that_is_not_built(tmp_path: Path, monkeypatch, capsys) -> None:
    """Without build/firmware/ecu: one error line naming make firmware, nothing run or
    written (no --out folder); NMPC, which the C ECU does not have, likewise."""
    import hil.ecu_runners
    from hil.__main__ import main

    monkeypatch.setattr(hil.ecu_runners, "C_ECU_EXECUTABLE", tmp_path / "ecu")  # where check_c_ecu reads it
    out = tmp_path / "out"
    assert main(["run", "--scenario", "dlc_smoke", "--controller", "lmpc", "--ecu", "c", "--out", str(out)]) != 0
    error = capsys.readouterr().err.strip().splitlines()
    assert error == [f"error: the C ECU {tmp_path / 'ecu'} is not built: run make firmware"]
    assert not out.exists()
    monkeypatch.undo()
    assert main(["run", "--scenario", "dlc_smoke", "--controller", "NMPC", "--ecu", "c", "--out", str(out)]) != 0
    assert capsys.readouterr().err.strip().splitlines() == [
        "error: the C ECU has no controller 'nmpc' (it has eso-dkmpc, dkmpc, lmpc); use the Python ECU"]
    assert not out.exists()


def test_hil_run_converts_the_model_for_the_c_ecu_and_refuses_another_shape(native, capsys) -> None:
    """``hil run --ecu c --model``: the artefact is written to its data file
    (firmware/tools/ecu_data.py) and checked against the build before the run; a model of
    another shape is one error line naming both shapes."""
    from hil.__main__ import main

    assert main(["run", "--scenario", "dlc_smoke", "--controller", "lmpc", "--ecu", "c",
                 "--model", "models/artifacts/dk_paper_nominal.npz"]) != 0
    error = capsys.readouterr().err.strip().splitlines()[-1]
    # lmpc takes a fitted bicycle (tests/test_firmware_c_bicycle.py): a Koopman artefact is the wrong kind
    assert error == ("error: --model models/artifacts/dk_paper_nominal.npz: a Koopman artefact, not a fitted "
                     "bicycle file; lmpc takes a fitted bicycle file (JSON: e.g. DIR/bicycle.json of python -m "
                     "models.koopman_train --logs)")
    assert main(["run", "--scenario", "dlc_smoke", "--controller", "eso-dkmpc", "--ecu", "c",
                 "--model", "models/artifacts/dk_paper_nominal.npz"]) != 0
    error = capsys.readouterr().err.strip().splitlines()[-1]
    assert error.startswith("error: the C ECU's data file: ") and "the model's shape (form linear" in error \
        and "differs from this build's (form scheduled" in error
