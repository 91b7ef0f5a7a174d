"""Input files of the ECUs and tools (issue 38): every array of a model finite, size bounds
checked before reading, no input ever overwritten by an output of the same command."""
from __future__ import annotations

import math
import shutil
from pathlib import Path

import can
import numpy as np
import pytest

from can_defs.frames import CtrlMode
from firmware_sim.controller_factory import model_controller_factory
from firmware_sim.ecu import Ecu
from models.koopman import KoopmanError, KoopmanModel

ROOT = Path(__file__).resolve().parent.parent
ARTIFACT = ROOT / "models" / "artifacts" / "dk_d5"


def broken_artifact(tmp_path: Path, array: str, index: tuple[int, ...], value: float) -> Path:
    """A copy of the default artefact with one entry of ``array`` set to ``value``."""
    target = tmp_path / "broken"
    shutil.copy(ARTIFACT.with_suffix(".json"), target.with_suffix(".json"))
    with np.load(ARTIFACT.with_suffix(".npz")) as weights:
        arrays = {key: weights[key].copy() for key in weights.files}
    arrays[array][index] = value
    np.savez(target.with_suffix(".npz"), **arrays)
    return target


@pytest.mark.parametrize("array, index", [("encoder_w0", (0, 0)), ("encoder_b2", (5,)), ("A_n", (0, 1, 2))])
@pytest.mark.parametrize("value", [math.inf, math.nan])
def test_every_array_of_a_koopman_artifact_must_be_finite(tmp_path: Path, array: str, index: tuple[int, ...],
                                                          value: float) -> None:
    model = broken_artifact(tmp_path, array, index, value)
    with pytest.raises(KoopmanError) as error:
        KoopmanModel.load(model)
    assert str(error.value) == (f"{model}.npz: array {array!r} has a non-finite entry ({value} at index "
                                f"{index})")


def test_a_model_built_with_a_non_finite_encoder_is_refused() -> None:
    names_x, names_u = ("vx", "vy", "yaw_rate"), ("torque", "steer")
    weights = np.zeros((4, 3))
    weights[1, 2] = math.inf
    with pytest.raises(KoopmanError, match=r"encoder layer 0 W has non-finite entries \(inf at index \(1, 2\)\)"):
        KoopmanModel(np.eye(7), np.zeros((7, 2)), None, [(weights, np.zeros(4))], 0.025, names_x, names_u)


def test_the_ecu_latches_fault_for_a_model_with_an_infinite_encoder_weight(tmp_path: Path) -> None:
    """The contract's rule for a model that fails to load: FAULT, latched, CMD_VALID = 0
    (before, the ECU ran ACTIVE on a fallback of steer 0 every cycle)."""
    model = broken_artifact(tmp_path, "encoder_w0", (0, 0), math.inf)
    bus = can.Bus(interface="virtual", channel="infinite-encoder")
    try:
        ecu = Ecu(bus, "eso-dkmpc", {1: ROOT / "hil" / "paths" / "dlc.csv"},
                  controller_factory=model_controller_factory("eso-dkmpc", model))
        assert ecu.mode is CtrlMode.FAULT
        assert ecu.load_error is not None and "array 'encoder_w0' has a non-finite entry" in ecu.load_error
    finally:
        bus.shutdown()


def test_the_ecus_refuse_a_model_of_another_sample_time(tmp_path: Path, capsys) -> None:
    """A Koopman model trained with --ts 0.05 (the artefact's ts as stored): the Python ECU
    latches FAULT, as for any model that fails to load, and the C data-file writer refuses
    it, both with the C core's text (tests/test_firmware_c_core.py: the data file)."""
    import json

    from test_firmware_c_core import _tool

    model = tmp_path / "slow"
    shutil.copy(ARTIFACT.with_suffix(".npz"), model.with_suffix(".npz"))
    meta = json.loads(ARTIFACT.with_suffix(".json").read_text())
    meta["ts"] = 0.05
    model.with_suffix(".json").write_text(json.dumps(meta))
    expected = (f"{model}.json: the model's sample time ts 0.05 s differs from the control period 0.025 s "
                "(train it with --ts 0.025)")
    bus = can.Bus(interface="virtual", channel="slow-model")
    try:
        ecu = Ecu(bus, "dkmpc", {1: ROOT / "hil" / "paths" / "dlc.csv"},
                  controller_factory=model_controller_factory("dkmpc", model))
        assert ecu.mode is CtrlMode.FAULT
        assert ecu.load_error == f"controller 'dkmpc' failed to load: {expected}"
    finally:
        bus.shutdown()
    assert _tool("ecu_data").main(["--out", str(tmp_path / "slow.bin"), "--model", str(model)]) == 2
    assert capsys.readouterr().err == f"error: {expected}\n"
    assert not (tmp_path / "slow.bin").exists()


def test_koopman_train_never_overwrites_an_output_without_replace(tmp_path: Path, capsys) -> None:
    """``--out`` is required (no default at the committed artefact), an existing artefact
    or a ``--logs`` folder holding its outputs needs ``--replace``, and ``--out`` is never
    an input: each is one ``error:`` line, exit 2, before any training (issue 38, item 11)."""
    from models import koopman_cli

    data = tmp_path / "data"
    data.mkdir()
    existing = tmp_path / "model"
    existing.with_suffix(".npz").write_bytes(b"artefact")
    folder = tmp_path / "from_logs"
    folder.mkdir()
    (folder / "koopman.npz").write_bytes(b"artefact")
    log = tmp_path / "drive.log"
    log.write_text("")
    cases = [
        (["--data", str(data)], "error: --out is required"),
        (["--data", str(data), "--out", str(existing)],
         f"error: --out {existing}.npz: file exists (give --replace to overwrite it)"),
        (["--logs", str(log), "--out", str(folder)],
         f"error: --out {folder}: holds another run's outputs (koopman.npz); give --replace to replace them"),
        (["--data", str(data), "--out", str(tmp_path / "prior"), "--compare-with", str(tmp_path / "prior.json")],
         f"error: --out {tmp_path / 'prior.json'}: is one of the inputs of this run ({tmp_path / 'prior.json'})"),
    ]
    for argv, message in cases:
        assert koopman_cli.main([*argv, "--no-progress"]) == 2, argv
        assert capsys.readouterr().err.strip().startswith(message), argv
    assert existing.with_suffix(".npz").read_bytes() == b"artefact"
    assert (folder / "koopman.npz").read_bytes() == b"artefact"
    assert koopman_cli.build_parser().get_default("out") is None


def test_every_input_file_has_a_size_bound_checked_before_reading(tmp_path: Path, capsys) -> None:
    """``/dev/zero`` or a file over its bound as a DBC, a model, a bicycle or a training log:
    one message naming the file and the bound, memory bounded (issue 38, items 8 and 10)."""
    from can_defs.dbc import load_database
    from can_defs.errors import DbcLoadError
    from firmware_sim import cli
    from models import koopman_cli
    from models.bicycle_fit import BicycleFitError, load_bicycle_params
    from models.input_files import (DBC_FILE_MAX_BYTES, LOG_FILE_MAX_BYTES, MODEL_FILE_MAX_BYTES,
                                    read_bounded)

    zero = Path("/dev/zero")
    with pytest.raises(DbcLoadError, match=f"cannot load DBC /dev/zero: larger than {DBC_FILE_MAX_BYTES} bytes"):
        load_database(zero)
    status = cli.main(["--interface", "virtual", "--channel", "bounds", "--controller", "lmpc", "--path",
                       f"1={ROOT / 'hil' / 'paths' / 'dlc.csv'}", "--lockstep", "--dbc", str(zero)])
    assert status == 2
    assert capsys.readouterr().err.strip().endswith(f"/dev/zero: larger than {DBC_FILE_MAX_BYTES} bytes "
                                                    "(the limit of this file)")
    with pytest.raises(BicycleFitError, match=f"/dev/zero: larger than {MODEL_FILE_MAX_BYTES} bytes"):
        load_bicycle_params(zero)
    big = tmp_path / "big"   # a sparse file over the bound: only limit + 1 bytes are read
    with open(big.with_suffix(".json"), "wb") as handle:
        handle.truncate(MODEL_FILE_MAX_BYTES + 10)
    big.with_suffix(".npz").write_bytes(b"")
    with pytest.raises(KoopmanError, match=f"big.json: larger than {MODEL_FILE_MAX_BYTES} bytes"):
        KoopmanModel.load(big)
    with pytest.raises(Exception, match="larger than 10 bytes"):
        read_bounded(big.with_suffix(".json"), 10)
    log = tmp_path / "huge.log"
    with open(log, "wb") as handle:
        handle.truncate(LOG_FILE_MAX_BYTES + 1)
    for source, message in ((log, f"error: {log}: larger than {LOG_FILE_MAX_BYTES} bytes"),
                            (zero, "error: /dev/zero: not a regular file")):
        assert koopman_cli.main(["--logs", str(source), "--out", str(tmp_path / "o"), "--no-progress"]) == 2
        assert capsys.readouterr().err.strip().startswith(message)


def test_solver_output_goes_through_the_rate_limited_log(capsys, caplog) -> None:
    """A solver that prints two stderr lines every step (OSQP on a huge but finite model):
    over 4 s of control, at most one log line a second and nothing straight on stderr
    (issue 38, item 14)."""
    import logging
    import sys
    import time
    import uuid

    from controller.base import Command, SolverStatus, StepDebug
    from hil.ecu_harness import PeerNodes, ScriptedController, pump

    class Noisy(ScriptedController):
        def step(self, sample):
            print("ERROR in LDL_factor: Error in KKT matrix LDL factorization", file=sys.stderr)
            print("ERROR in osqp_update_data_mat: KKT matrix factorization", file=sys.stderr)
            return Command(0.0, 0.0), StepDebug(SolverStatus.NUMERICAL_ERROR, 0, 0.0)

    channel = f"noisy-{uuid.uuid4()}"
    ecu_bus, peer_bus = can.Bus(interface="virtual", channel=channel), can.Bus(interface="virtual", channel=channel)
    try:
        ecu = Ecu(ecu_bus, "scripted", {1: Path("p.csv")}, lockstep=True, controller_factory=lambda name: Noisy(),
                  path_loader=lambda path: "path")
        peers = PeerNodes(peer_bus)
        peers.send_handshake()
        pump(ecu, ecu_bus)
        started = time.monotonic()
        with caplog.at_level(logging.WARNING, logger="firmware_sim.ecu"):
            for t in range(0, 4000, 5):
                if t % 10 == 0:
                    peers.send_plant(vx=10.0, x=0.01 * t, y=0.0)
                if t % 25 == 0:
                    peers.send_planner(engage=True, target_speed=10.0, path_id=1)
                peers.send_sync(t)
                pump(ecu, ecu_bus)
                peers.received()
        assert ecu.mode is CtrlMode.ACTIVE
        lines = [r.getMessage() for r in caplog.records if "solver output" in r.getMessage()]
        print(len(lines), lines[:2])
        wall_s = time.monotonic() - started
        # 160 steps x 2 lines printed; logged at most once a second of wall clock
        assert 1 <= len(lines) <= 1 + wall_s
        assert "LDL_factor" not in capsys.readouterr().err
    finally:
        ecu_bus.shutdown()
        peer_bus.shutdown()


def _free_port() -> int:
    import socket

    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def test_no_socketcand_server_at_start_up_is_one_error_not_a_flood(tmp_path: Path) -> None:
    """python-can's socketcand interface retries its connection for 10 s without a pause
    and logs every try (294,000 lines); the ECU makes one try: exit 1 at once, one line."""
    import json
    import os
    import subprocess
    import sys
    import time

    port = _free_port()
    environment = {**os.environ, "CAN_CONFIG": json.dumps({"host": "127.0.0.1", "port": port})}
    started = time.monotonic()
    result = subprocess.run([sys.executable, "-m", "firmware_sim", "--interface", "socketcand", "--channel",
                             "vcan0", "--controller", "lmpc", "--path", f"1={ROOT / 'hil' / 'paths' / 'dlc.csv'}",
                             "--lockstep"], cwd=ROOT, env=environment, capture_output=True, text=True,
                            timeout=60, check=False)
    elapsed = time.monotonic() - started
    print(f"{elapsed:.1f} s", result.stderr)
    assert result.returncode == 1
    assert result.stderr.count("\n") <= 2 and "Failed to connect to server" not in result.stderr
    assert f"no socketcand server at 127.0.0.1:{port}" in result.stderr
    assert elapsed < 9.5   # python-can alone spins 10 s before it gives up


def test_a_socketcand_server_that_stays_down_is_retried_once_a_second_quietly(monkeypatch, caplog) -> None:
    """The server goes away during a run: the lost bus is logged at most once a second,
    the reopening tries are a second apart and python-can writes nothing (before, about
    32,000 lines a second at 60 % CPU)."""
    import json
    import logging
    import threading
    import time

    from firmware_sim.can_bus import open_ecu_bus
    from test_ecu_cli import FakeSocketcand

    server = FakeSocketcand()
    monkeypatch.setenv("CAN_CONFIG", json.dumps({"host": "127.0.0.1", "port": server.port}))
    accepting = threading.Thread(target=server.accept, args=(10.0,))
    accepting.start()
    bus = open_ecu_bus("socketcand", "vcan0", None)
    accepting.join()
    ecu = Ecu(bus, "lmpc", {}, controller_factory=lambda name: None,
              reopen_bus=lambda: open_ecu_bus("socketcand", "vcan0", None))
    stop = threading.Event()
    with caplog.at_level(logging.INFO):
        runner = threading.Thread(target=ecu.run, args=(stop,))
        runner.start()
        server.close()          # the server is gone and stays gone
        cpu_before = time.process_time()
        time.sleep(3.0)
        cpu = time.process_time() - cpu_before
        stop.set()
        runner.join(10.0)
    ecu.close()
    python_can = [r for r in caplog.records if r.name.startswith("can.")]
    ecu_lines = [r for r in caplog.records if r.name.startswith("firmware_sim")]
    print(f"CPU {cpu:.2f} s in 3 s;", len(python_can), "python-can lines;", [r.getMessage() for r in ecu_lines])
    assert ecu.bus_lost and not runner.is_alive()
    assert len(python_can) <= 3
    assert 1 <= len(ecu_lines) <= 5
    assert cpu < 1.5


def test_a_scenario_file_is_bounded_and_utf8(tmp_path: Path) -> None:
    from hil.errors import ScenarioError
    from hil.scenario import SCENARIO_FILE_MAX_BYTES, load_scenario

    with pytest.raises(ScenarioError, match=f"/dev/zero: larger than {SCENARIO_FILE_MAX_BYTES} bytes"):
        load_scenario(Path("/dev/zero"))
    latin = tmp_path / "latin.toml"
    latin.write_bytes('name = "caf\u00e9"\n'.encode("latin-1"))
    with pytest.raises(ScenarioError, match=f"{latin}: not UTF-8 text"):
        load_scenario(latin)


def test_logs_over_the_bound_are_refused_before_reading(tmp_path: Path) -> None:
    """A recorded CAN log (``hil replay`` / ``decode``, ``koopman_train --logs``) larger
    than ``LOG_FILE_MAX_BYTES``: one error naming the file and the bound, nothing read."""
    from hil.logio import LogReadError, read_log
    from models.can_log_data import LogDataError, read_frames
    from models.input_files import LOG_FILE_MAX_BYTES

    log = tmp_path / "huge.log"
    with open(log, "wb") as handle:
        handle.truncate(LOG_FILE_MAX_BYTES + 1)
    with pytest.raises(LogReadError, match=f"larger than {LOG_FILE_MAX_BYTES} bytes"):
        read_log(log)
    with pytest.raises(LogDataError, match=f"larger than {LOG_FILE_MAX_BYTES} bytes"):
        read_frames(log)
