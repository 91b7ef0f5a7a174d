"""Training from CAN logs (issue 20): time base, samples, formats, bad input, the bicycle
fit, named-column CSVs and ``python -m models.koopman_train --logs``.

The logs are synthesised frame by frame with the contract's codec from a linear bicycle of
known parameters driven by a PRBS steering command, so the expected data (and the
parameters the fit must find) are known exactly.
"""
from __future__ import annotations

import dataclasses
import gzip
import json
import math
from pathlib import Path

import numpy as np
import pytest
from can_defs.codec import FrameSender
from can_defs.frames import (CtrlMode, FrameId, HilSync, SteerTorqueCmd, VehDyn, VehPoseXY,
                             VehPoseYaw)

from models.bicycle import LinearBicycle, nominal_model_params
from models.bicycle_fit import fit_bicycle
from models.can_log_data import LogDataError, load_logs, read_frames
from models.named_csv_data import load_mapping, load_named_csv

TS = 0.025
STEER_LAG_S = 0.03
TRUE_PARAMS = dataclasses.replace(nominal_model_params(), yaw_inertia=3300.0,
                                  cornering_stiffness_rear=0.8 * nominal_model_params().cornering_stiffness_rear)


def simulate(duration_s: float, seed: int = 0) -> dict[str, np.ndarray]:
    """A bicycle of TRUE_PARAMS at 1 ms: speed steps 8-25 m/s, PRBS steering held 25 ms
    (the ECU's command), the wheel angle lagging it (STEER_LAG_S). Returns 1 ms arrays."""
    rng = np.random.default_rng(seed)
    n = int(round(duration_s * 1000))
    t = np.arange(n) / 1000.0
    vx = 8.0 + 17.0 * (np.floor(t / 10.0) % 4) / 3.0
    bits = rng.choice([-1.0, 1.0], size=n // 200 + 1)
    steer = np.empty(n)
    for k in range(0, n, 25):  # the command changes every 25 ms
        steer[k:k + 25] = bits[k // 200] * min(0.03, 2.0 * 2.8 / vx[k] ** 2)
    bicycle = LinearBicycle(TRUE_PARAMS)
    state = np.zeros(2)
    vy, r, wheel = np.empty(n), np.empty(n), np.empty(n)
    angle = 0.0
    for k in range(n):
        vy[k], r[k], wheel[k] = state[0], state[1], angle
        a, b = bicycle.continuous_matrices(float(vx[k]))
        state = state + 1e-3 * (a @ state + b[:, 0] * angle)
        angle += 1e-3 * (steer[k] - angle) / STEER_LAG_S
    return {"t": t, "vx": vx, "vy": vy, "r": r, "steer": steer, "wheel": wheel,
            "torque": 200.0 * np.sin(0.3 * t)}


def frames(sim: dict[str, np.ndarray], lockstep: bool = True, cmd_valid: bool = True,
           jitter_s: float = 0.0, seed: int = 1) -> list[tuple[float, int, bytes]]:
    """(timestamp, id, payload) of the contract's traffic: plant frames every 10 ms (one
    counter), HIL_SYNC every 5 ms in lockstep, the command at every 25 ms after the sync."""
    sender = FrameSender()
    rng = np.random.default_rng(seed)
    out: list[tuple[float, int, bytes]] = []
    stamp0 = 1_700_000_000.0
    x = y = yaw = 0.0
    for tick_ms in range(0, int(sim["t"][-1] * 1000) + 1, 5):
        k = tick_ms  # 1 ms samples
        stamp = stamp0 + tick_ms / 1000.0 + (rng.uniform(-jitter_s, jitter_s) if jitter_s else 0.0)
        if tick_ms % 10 == 0:
            yaw_wrapped = (yaw + math.pi) % (2 * math.pi) - math.pi
            for frame in (VehDyn(sim["vx"][k], sim["vy"][k], sim["r"][k]), VehPoseXY(x, y),
                          VehPoseYaw(yaw_wrapped, sim["wheel"][k], sim["torque"][k])):
                out.append((stamp, int(frame.FRAME_ID), sender.encode(frame)))
        if lockstep:
            out.append((stamp, int(FrameId.HIL_SYNC), sender.encode(HilSync(tick_ms))))
        if tick_ms % 25 == 0:
            command = SteerTorqueCmd(CtrlMode.ACTIVE if cmd_valid else CtrlMode.STANDBY, cmd_valid,
                                     sim["steer"][k], sim["torque"][k])
            out.append((stamp + 0.0005, int(FrameId.STEER_TORQUE_CMD), sender.encode(command)))
        x += sim["vx"][k] * 0.005  # straight enough for the pose frames' continuity
    return out


def write_candump(path: Path, traffic: list[tuple[float, int, bytes]]) -> Path:
    text = "".join(f"({stamp:.6f}) vcan0 {fid:03X}#{data.hex().upper()}\n" for stamp, fid, data in traffic)
    if path.suffix == ".gz":
        path.write_bytes(gzip.compress(text.encode()))
    else:
        path.write_text(text)
    return path


@pytest.fixture(scope="module")
def sim70():
    return simulate(70.0)


@pytest.fixture(scope="module")
def lockstep_log(sim70, tmp_path_factory):
    return write_candump(tmp_path_factory.mktemp("logs") / "drive.log", frames(sim70))




def test_lockstep_log_gives_grid_samples_equal_to_the_plant(sim70, lockstep_log):
    dataset = load_logs([lockstep_log])
    print(dataset.warnings, dataset.metadata()["log_counts"])
    assert dataset.counts[str(lockstep_log)].time_base.startswith("HIL_SYNC")
    assert dataset.seconds == pytest.approx(70.0, abs=0.1)
    assert all(len(run) <= round(30 / TS) + round(30 / TS) for run in dataset.trajectories)
    states = np.concatenate([run.states for run in dataset.trajectories])
    inputs = np.concatenate([run.inputs for run in dataset.trajectories])
    grid_ms = np.arange(len(states)) * 25
    expected = np.column_stack([sim70["vx"][grid_ms], sim70["vy"][grid_ms], sim70["r"][grid_ms],
                                sim70["wheel"][grid_ms]])
    # every other instant (t = 0, 50, 100 ms) is a plant sample: equal up to the frames'
    # quantisation; the others are interpolated between the samples 10 ms apart
    error = np.abs(states - expected)[::2].max(axis=0)
    print("largest state difference at sample instants (quantisation of the frames)", error)
    assert np.all(error <= [0.005 + 1e-9, 0.0005 + 1e-9, 0.00005 + 1e-9, 0.00005 + 1e-9])
    between = np.abs(states - expected)[1::2].max(axis=0)
    print("largest state difference between samples (interpolation)", between)
    assert np.all(between <= [0.01, 0.005, 0.001, 0.005])
    assert np.abs(inputs[:, 1] - sim70["steer"][grid_ms]).max() <= 0.00005 + 1e-9
    assert dataset.warnings == []


def test_counter_time_base_without_hil_sync_matches_the_lockstep_one(sim70, lockstep_log, tmp_path):
    traffic = frames(sim70, lockstep=False, jitter_s=0.003)
    # a stalled recorder: 90 ms late from frame 5000 on (counters go on; nothing was lost)
    traffic = [(stamp + (0.09 if i >= 5000 else 0.0), fid, data) for i, (stamp, fid, data) in enumerate(traffic)]
    log = write_candump(tmp_path / "realtime.log", traffic)
    lockstep = load_logs([lockstep_log])
    counters = load_logs([log])
    print(counters.counts[str(log)].as_dict())
    assert counters.counts[str(log)].time_base.startswith("alive counters")
    a = np.concatenate([r.states for r in lockstep.trajectories])
    b = np.concatenate([r.states for r in counters.trajectories])
    n = min(len(a), len(b))
    difference = np.abs(a[:n] - b[:n]).max(axis=0)
    print("samples", len(a), len(b), "largest difference", difference)
    # the same instants up to the timestamp jitter (3 ms) of the two streams' first frames,
    # which anchor them: at most 3 ms of the states' change
    assert abs(len(a) - len(b)) <= 2
    assert np.all(difference <= [0.01, 0.01, 0.005, 0.005])


@pytest.mark.parametrize("suffix", [".asc", ".blf", ".csv", ".trc", ".db", ".log.gz", ".asc.gz"])
def test_every_python_can_format_reads_the_same_samples(tmp_path, suffix):
    import can

    sim = simulate(12.0)
    traffic = frames(sim)
    path = tmp_path / f"drive{suffix}"
    if suffix == ".log.gz":
        write_candump(path, traffic)
    elif suffix == ".db":  # python-can's SqliteWriter drops frames written this fast: its table directly
        import sqlite3
        with sqlite3.connect(path) as db:
            db.execute("CREATE TABLE messages (ts REAL, arbitration_id INTEGER, extended INTEGER, "
                       "remote INTEGER, error INTEGER, dlc INTEGER, data BLOB)")
            db.executemany("INSERT INTO messages VALUES (?, ?, 0, 0, 0, 8, ?)", traffic)
        db.close()
    else:
        with can.Logger(str(path)) as logger:
            for stamp, fid, data in traffic:
                logger.on_message_received(can.Message(timestamp=stamp, arbitration_id=fid, data=data,
                                                       is_extended_id=False, channel="vcan0"))
    dataset = load_logs([path], min_data_s=10.0)
    print(suffix, dataset.seconds, read_frames(path)[1])
    assert dataset.seconds == pytest.approx(12.0, abs=0.1)


def test_bicycle_fit_recovers_the_parameters(sim70, lockstep_log):
    dataset = load_logs([lockstep_log])
    fit = fit_bicycle(dataset.trajectories, TS)
    found = fit.params
    for name in ("cornering_stiffness_front", "cornering_stiffness_rear", "yaw_inertia"):
        error = getattr(found, name) / getattr(TRUE_PARAMS, name) - 1.0
        print(f"{name}: fitted {getattr(found, name):.1f}, true {getattr(TRUE_PARAMS, name):.1f} ({100 * error:+.2f} %)")
        assert abs(error) < 0.03
    assert found.mass == TRUE_PARAMS.mass and fit.samples_used > 2000


# ---------------------------------------------------------------- bad input
def _corrupt(traffic, every: int, ids=None):
    out = []
    for i, (stamp, fid, data) in enumerate(traffic):
        if i % every == 0 and (ids is None or fid in ids):
            data = bytes([data[0] ^ 0xFF]) + data[1:]
        out.append((stamp, fid, data))
    return out


def test_partial_e2e_failures_are_used_with_a_warning_and_counts(sim70, tmp_path):
    log = write_candump(tmp_path / "crc.log", _corrupt(frames(sim70), 97))
    dataset = load_logs([log])
    print(dataset.warnings)
    assert any("failed the E2E check" in w and "CRC_ERROR" in w for w in dataset.warnings)
    assert dataset.seconds > 60.0


@pytest.mark.parametrize("case, message", [
    ("no_plant", "no VEH_DYN / VEH_POSE_XY / VEH_POSE_YAW frames"),
    ("all_crc", "none of the plant frames passes the E2E check"),
    ("no_commands", "no STEER_TORQUE_CMD (0x200) frames"),
    ("invalid_commands", "CMD_VALID = 0"),
    ("short", "need at least 60 s"),
    ("named_csv", "a named-column CSV"),
    ("missing", "no such log file"),
    ("suffix", "unknown log format"),
])
def test_unusable_logs_are_errors_naming_the_file_and_what_is_missing(sim70, tmp_path, case, message):
    traffic = frames(sim70)
    plant = {int(FrameId.VEH_DYN), int(FrameId.VEH_POSE_XY), int(FrameId.VEH_POSE_YAW)}
    path = tmp_path / f"{case}.log"
    if case == "no_plant":
        write_candump(path, [f for f in traffic if f[1] not in plant])
    elif case == "all_crc":
        write_candump(path, _corrupt(traffic, 1, plant))
    elif case == "no_commands":
        write_candump(path, [f for f in traffic if f[1] != FrameId.STEER_TORQUE_CMD])
    elif case == "invalid_commands":
        write_candump(path, frames(sim70, cmd_valid=False))
    elif case == "short":
        write_candump(path, frames(simulate(20.0)))
    elif case == "named_csv":
        path = tmp_path / "export.csv"
        path.write_text("t,speed\n0,1\n")
    elif case == "suffix":
        path = tmp_path / "drive.mdf"
        path.write_text("x")
    with pytest.raises(LogDataError) as info:
        load_logs([path])
    print(info.value)
    assert message in str(info.value) and str(path) in str(info.value)


# ---------------------------------------------------------------- named CSV
def test_named_csv_with_a_mapping(tmp_path):
    t = np.arange(0, 80.0, 0.01)
    table = np.column_stack([t * 1000.0, 3.6 * (10 + np.sin(0.1 * t)), 0.1 * np.sin(t),
                             100 * (np.sin(0.5 * t) > 0), 50 * (np.sin(0.5 * t) <= 0)])
    data = tmp_path / "sim_export.csv"
    data.write_text("time_ms,speed_kmh,lat_speed,throttle_pct,brake_pct\n"
                    + "".join(",".join(f"{v:.6f}" for v in row) + "\n" for row in table))
    mapping = tmp_path / "map.toml"
    mapping.write_text('sample_time_s = 0.025\ntime_column = "time_ms"\ntime_scale = 0.001\n'
                       '[states]\nvx = { column = "speed_kmh", scale = 0.2777777778 }\nvy = "lat_speed"\n'
                       '[inputs]\nthrottle = { column = "throttle_pct", scale = 0.01 }\n'
                       'brake = { column = "brake_pct", scale = 0.01 }\n')
    runs = load_named_csv([data], load_mapping(mapping))
    first = runs[0]
    assert first.state_names == ("vx", "vy") and first.input_names == ("throttle", "brake")
    assert first.states[0, 0] == pytest.approx(10.0) and first.inputs[:, 0].max() == pytest.approx(1.0)
    assert sum(len(r) for r in runs) * 0.025 == pytest.approx(80.0, abs=0.1)
    bad = tmp_path / "bad.toml"
    bad.write_text('sample_time_s = 0.025\n[states]\nvx = "v"\n[inputs]\nu = "u"\n')
    with pytest.raises(LogDataError, match="exactly one of time_column and file_sample_time_s"):
        load_mapping(bad)
    missing = tmp_path / "missing_column.toml"
    missing.write_text('sample_time_s = 0.025\ntime_column = "time_ms"\n[states]\nvx = "nope"\n[inputs]\nu = "throttle_pct"\n')
    with pytest.raises(LogDataError, match="column\\(s\\) nope of the mapping missing"):
        load_named_csv([data], load_mapping(missing))


# ---------------------------------------------------------------- the CLI, end to end
def test_koopman_train_logs_writes_an_artefact_the_ecu_loads_a_bicycle_and_a_report(lockstep_log, tmp_path, capsys):
    from firmware_sim.controller_factory import model_controller_factory
    from models import koopman_cli

    out = tmp_path / "identified"
    status = koopman_cli.main(["--logs", str(lockstep_log), "--out", str(out), "--epochs", "2",
                                 "--steps-per-epoch", "5", "--no-progress"])
    printed = capsys.readouterr()
    print(printed.out[-2000:], printed.err[-2000:])
    assert status == 0
    meta = json.loads((out / "koopman.json").read_text())
    committed = json.loads(Path("models/artifacts/dk_d5.json").read_text())
    assert (meta["form"], meta["state_names"], meta["input_names"]) == (
        committed["form"], committed["state_names"], committed["input_names"])
    assert meta["data_source"] == "can_logs" and meta["logs"] == [str(lockstep_log)]
    report = json.loads((out / "report.json").read_text())
    fitted = report["prediction_errors"]["linear bicycle, fitted to the logs"]["yaw_rate"]["open_loop_rmse"]
    nominal = report["prediction_errors"]["linear bicycle, nominal"]["yaw_rate"]["open_loop_rmse"]
    print("yaw-rate 1 s RMSE on held-out pieces: fitted bicycle", fitted, "nominal", nominal)
    assert fitted < nominal  # the data's bicycle has 20 % less rear stiffness
    assert "| Koopman, identified from the logs | vx |" in (out / "report.md").read_text()
    assert model_controller_factory("eso-dkmpc", out / "koopman")("eso-dkmpc").model.n_x == 4
    assert model_controller_factory("lmpc", out / "bicycle.json")("lmpc").bicycle.params.yaw_inertia > 0


def test_koopman_train_logs_bad_input_is_one_error_line(tmp_path, capsys):
    from models import koopman_cli

    path = tmp_path / "empty.log"
    path.write_text("(1.0) vcan0 123#00\n")
    status = koopman_cli.main(["--logs", str(path), "--out", str(tmp_path / "o"), "--no-progress"])
    err = capsys.readouterr().err
    print(err)
    assert status == 2 and err.startswith("error: ") and str(path) in err and "Traceback" not in err


def test_named_csv_trains_a_study_model_that_the_ecu_refuses(tmp_path, capsys):
    from firmware_sim.controller_factory import model_controller_factory
    from firmware_sim.errors import ConfigError
    from models import koopman_cli

    rng = np.random.default_rng(3)
    t = np.arange(0, 90.0, 0.025)
    throttle = np.repeat(rng.uniform(0, 1, size=len(t) // 40 + 1), 40)[: len(t)]
    vx = 10.0 + np.cumsum(0.025 * (2.0 * throttle - 1.0))
    data = tmp_path / "export.csv"
    data.write_text("t,v,thr\n" + "".join(f"{a:.3f},{b:.5f},{c:.4f}\n" for a, b, c in zip(t, vx, throttle)))
    mapping = tmp_path / "map.toml"
    mapping.write_text('sample_time_s = 0.025\ntime_column = "t"\n[states]\nvx = "v"\n[inputs]\nthrottle = "thr"\n')
    out = tmp_path / "study"
    status = koopman_cli.main(["--logs", str(data), "--mapping", str(mapping), "--out", str(out),
                                 "--epochs", "1", "--steps-per-epoch", "3", "--no-progress",
                                 "--speed-knots", "5,20"])
    print(capsys.readouterr().out[-600:])
    assert status == 0
    report = json.loads((out / "report.json").read_text())
    assert list(report["prediction_errors"]) == ["Koopman, identified from the data"]
    assert not (out / "bicycle.json").exists()
    with pytest.raises(ConfigError, match="for study only"):
        model_controller_factory("eso-dkmpc", out / "koopman")


def test_lost_frames_on_a_counter_time_base_are_a_gap_of_the_right_length(sim70, tmp_path):
    from models.can_log_data import LogCounts, _decode_streams

    plant = {int(FrameId.VEH_DYN), int(FrameId.VEH_POSE_XY), int(FrameId.VEH_POSE_YAW)}
    traffic = frames(sim70, lockstep=False, jitter_s=0.002)
    start = traffic[0][0]
    # 21 plant samples (210 ms) lost at 30 s: the counter steps by 22 mod 16 = 6
    kept = [f for f in traffic if not (f[1] in plant and 30.0 <= f[0] - start < 30.21)]
    frames_read, _ = read_frames(write_candump(tmp_path / "lost.log", kept))
    stretch = _decode_streams(frames_read, LogCounts())[0]
    steps = np.diff(stretch.sample_time)
    print("largest step between samples", steps.max())
    assert steps.max() == pytest.approx(0.22, abs=1e-6)
    assert np.sum(steps > 0.011) == 1


def test_measured_inputs_come_from_veh_pose_yaw_and_leave_the_state(sim70, lockstep_log, tmp_path):
    traffic = [f for f in frames(sim70) if f[1] != FrameId.STEER_TORQUE_CMD]  # no ECU recorded
    log = write_candump(tmp_path / "plant_only.log", traffic)
    with pytest.raises(LogDataError, match="no STEER_TORQUE_CMD"):
        load_logs([log])
    dataset = load_logs([log], input_source="measured")
    run = dataset.trajectories[0]
    assert run.state_names == ("vx", "vy", "yaw_rate") and run.input_names == ("torque", "steer")
    grid_ms = np.arange(len(run)) * 25
    sample_instants = slice(0, None, 2)  # every 50 ms: a plant sample, no interpolation
    wheel_error = np.abs(run.inputs[sample_instants, 1] - sim70["wheel"][grid_ms][sample_instants]).max()
    torque_error = np.abs(run.inputs[sample_instants, 0] - sim70["torque"][grid_ms][sample_instants]).max()
    print("measured wheel angle / torque against the plant", wheel_error, torque_error)
    assert wheel_error <= 0.00005 + 1e-9 and torque_error <= 0.05 + 1e-9


def test_a_dbc_without_the_contract_frames_is_named(lockstep_log, tmp_path):
    other = tmp_path / "other.dbc"
    other.write_text('VERSION ""\n\nBU_: A B\n\nBO_ 256 OTHER: 8 A\n SG_ X : 0|8@1+ (1,0) [0|255] "" B\n')
    with pytest.raises(LogDataError) as info:
        load_logs([lockstep_log], dbc=other)
    print(info.value)
    assert str(other) in str(info.value) and "DBC has no frame" in str(info.value)
