"""Training data from recorded CAN logs of the contract's bus (issue 20).

``load_logs(files)`` turns recordings of any vehicle or plant that speaks the contract
into equally spaced trajectories for ``models.koopman_train`` and ``models.bicycle_fit``:

1. Frames: the project's one log reader, ``can_defs.log_reader`` (candump ``.log`` and
   the other formats python-can reads without extra packages, ``.asc``, ``.blf``,
   ``.csv``, ``.db``, ``.trc``, each also ``.gz``), the same frames the HIL tools see.
   python-can is imported only inside that reader (build time; the run time of this
   package never touches it). Damage (lines that are not frames, a truncated file) is
   left out with a warning. A ``.csv`` whose header is not python-can's is a
   named-column data file (`models.named_csv_data`), not a CAN log. Only classic data
   frames with an 11-bit ID (``is_contract_data_frame``) can be the contract's.
2. Decoding with the DBC (``can_defs.codec``; ``--dbc`` another one) and the E2E checks of
   the contract (``can_defs.e2e.E2EMonitor``: CRC, alive counter); only accepted frames
   are used, the others are counted.
3. Samples: VEH_DYN, VEH_POSE_XY and VEH_POSE_YAW with one counter value form a consistent
   sample (`models.plant_sample`, the ECU's assembler in its mode for recorded logs; a
   torn one is dropped and counted). State [vx, vy, yaw_rate] from VEH_DYN and
   the measured wheel angle (``steer_measured``) from VEH_POSE_YAW; input [torque, steer]
   from STEER_TORQUE_CMD frames with CMD_VALID = 1, or (``inputs="measured"``) the
   measured DRIVE_TORQUE and STEER_ANGLE of VEH_POSE_YAW.
4. Time base: in a lockstep log the HIL_SYNC TICKs (a plant frame belongs to the TICK of
   the HIL_SYNC after it, an ECU frame to the TICK it answered); otherwise each frame's
   alive counter at its period (10 ms plant, 25 ms command), the log timestamps only
   deciding how many counter wraps a gap spans. A handshake in the middle of a log starts
   a new stretch of virtual time (a gap).
5. Resampling to the control period Ts (25 ms): the state linearly interpolated between
   the two samples around t_k (at most 20 ms apart), the input the newest command at or
   before t_k if at most 30 ms old (zero-order hold: u_k acts over [t_k, t_k+1), as the
   plant applies it). Where either is missing, or the vehicle is slower than 1 m/s, the
   data split into segments; segments are cut into pieces of ``piece_s`` (30 s; shorter
   when there is little data) so that training can hold out whole pieces.

Unusable input is a `LogDataError` naming the file and what is missing: no plant frames,
no E2E-valid ones (another DBC or CRC), no command frames, only CMD_VALID = 0, less than a
minute of usable data in all. Partial data are used, with warnings that give the counts.
"""
from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Iterator, Sequence

import numpy as np

from can_defs.codec import decode, prepare
from can_defs.e2e import E2EMonitor
from can_defs.errors import CanDefsError
from can_defs.frames import HANDSHAKE_TICK, FrameId
from can_defs.log_reader import (PYTHON_CAN_CSV_HEADER, LogFileError, csv_header,
                                 is_contract_data_frame, is_python_can_csv, log_suffix,
                                 read_log_frames)
from models.errors import ModelError
from models.input_files import LOG_FILE_MAX_BYTES, check_file_size
from models.koopman_metrics import Trajectory
from models.plant_sample import PlantSampleAssembler

if TYPE_CHECKING:
    import can
STATES = ("vx", "vy", "yaw_rate", "steer_measured")
MEASURED_INPUT_STATES = ("vx", "vy", "yaw_rate")
INPUTS = ("torque", "steer")
INPUT_SOURCES = ("command", "measured")
PLANT_PERIOD_S = 0.010
COMMAND_PERIOD_S = 0.025
#: Largest spacing of the two samples a state is interpolated between (one sample lost).
MAX_SAMPLE_GAP_S = 0.0201
#: Oldest command still taken as the input at a grid instant.
MAX_COMMAND_AGE_S = 0.030
MIN_DATA_S = 60.0
#: Samples slower than this are left out: a standing vehicle shows no lateral dynamics,
#: and the models' 1/vx terms are singular there.
MIN_SPEED_MPS = 1.0
MIN_SEGMENT_S = 2.0
PIECE_S = 30.0
MIN_PIECE_S = 5.0
_PLANT_IDS = (int(FrameId.VEH_DYN), int(FrameId.VEH_POSE_XY), int(FrameId.VEH_POSE_YAW))


class LogDataError(ModelError):
    """A log cannot give training data; the message names the file and what is missing."""


@dataclass
class LogCounts:
    """What one log held and what of it was used."""

    frames: int = 0
    not_contract: int = 0
    e2e_rejected: Counter = field(default_factory=Counter)
    plant_frames: int = 0
    samples: int = 0
    torn_samples: int = 0
    commands_valid: int = 0
    commands_invalid: int = 0
    grid_points: int = 0
    grid_used: int = 0
    time_base: str = ""
    read_warning: str | None = None

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready counts."""
        return {"frames": self.frames, "not_contract_frames": self.not_contract,
                "e2e_rejected": dict(self.e2e_rejected), "plant_frames": self.plant_frames,
                "consistent_samples": self.samples, "torn_samples": self.torn_samples,
                "commands_cmd_valid_1": self.commands_valid,
                "commands_cmd_valid_0": self.commands_invalid,
                "grid_points": self.grid_points, "grid_points_used": self.grid_used,
                "time_base": self.time_base, "read_warning": self.read_warning}


@dataclass
class LogDataset:
    """Trajectories from logs (pieces of at most ``piece_s``), per-file counts, warnings."""

    trajectories: list[Trajectory]
    counts: dict[str, LogCounts]
    warnings: list[str]
    ts: float
    input_source: str

    @property
    def seconds(self) -> float:
        """Usable data in all (s)."""
        return sum(len(t) for t in self.trajectories) * self.ts

    def metadata(self) -> dict[str, Any]:
        """What an artefact's JSON records about its data."""
        return {"data_source": "can_logs", "logs": sorted(self.counts),
                "log_counts": {name: c.as_dict() for name, c in self.counts.items()},
                "input_source": self.input_source, "data_seconds": round(self.seconds, 3),
                "n_runs": len(self.trajectories)}


# ---------------------------------------------------------------- reading frames
def read_frames(path: str | Path) -> tuple[list[can.Message], str | None]:
    """Every frame of a CAN log (``can_defs.log_reader``) and a warning when frames were
    left out (damaged lines, a read that stopped early).

    Raises:
        LogDataError: missing file, unsupported suffix, a named-column CSV, no frame.
    """
    try:
        log = read_log_frames(path, check_file=_refuse_unusable)
    except LogFileError as error:
        raise LogDataError(str(error)) from error
    return log.messages, "; ".join(log.warnings) or None


def _refuse_unusable(path: Path) -> None:
    """Before a reader takes the file: one too large, or a CSV that is not a CAN log."""
    check_file_size(path, LOG_FILE_MAX_BYTES, LogDataError)
    try:
        if log_suffix(path) == ".csv" and not is_python_can_csv(path):
            raise LogDataError(f"{path}: a named-column CSV (header {csv_header(path)[:60]!r}), not a "
                               f"python-can CSV log (header {PYTHON_CAN_CSV_HEADER}): give it "
                               "with a --mapping TOML")
    except OSError as error:
        raise LogDataError(f"{path}: cannot read: {error}") from error


# ---------------------------------------------------------------- decoding and time base
@dataclass
class _Streams:
    """Decoded, E2E-accepted content of one stretch of time."""

    sample_time: list[float] = field(default_factory=list)
    sample: list[tuple[float, ...]] = field(default_factory=list)  # vx, vy, r, steer, torque
    command_time: list[float] = field(default_factory=list)
    command: list[tuple[float, float, bool]] = field(default_factory=list)  # torque, steer, valid


class _CounterClock:
    """Time of a periodic frame from its alive counter; the log timestamps only say how
    many counter wraps (16 periods) lie between two frames."""

    def __init__(self, period_s: float) -> None:
        self.period_s = period_s
        self.last: tuple[float, int, float] | None = None  # time, counter, timestamp

    def time(self, counter: int, timestamp: float) -> float:
        if self.last is None:
            self.last = (timestamp, counter, timestamp)
            return timestamp
        time, last_counter, last_stamp = self.last
        step = (counter - last_counter) % 16
        periods = (timestamp - last_stamp) / self.period_s
        # A late frame of a stalled sender keeps its counter sequence, 16 lost frames do
        # not announce themselves: a gap counts as a wrap only when it is at least 12
        # periods longer than the counter step says (stalls of up to 11 periods are late
        # frames, not lost ones).
        wraps = max(0, math.floor((periods - step) / 16.0 + 0.25))
        time += (step + 16 * wraps) * self.period_s
        self.last = (time, counter, timestamp)
        return time


def _decode_streams(frames: Sequence[can.Message], counts: LogCounts) -> list[_Streams]:
    """Accepted samples and commands with their times, one `_Streams` per stretch of
    continuous time (a handshake in a lockstep log starts a new one)."""
    lockstep = any(f.arbitration_id == FrameId.HIL_SYNC and is_contract_data_frame(f)
                   for f in frames)
    counts.time_base = ("HIL_SYNC TICK (lockstep log)" if lockstep
                        else "alive counters (10 ms plant, 25 ms command)")
    monitor = E2EMonitor()
    clocks = {int(FrameId.VEH_DYN): _CounterClock(PLANT_PERIOD_S),
              int(FrameId.STEER_TORQUE_CMD): _CounterClock(COMMAND_PERIOD_S)}
    stretches = [_Streams()]
    first_stamp = frames[0].timestamp if frames else 0.0
    last_tick: int | None = None
    pending_plant: list[tuple[int, Any, int]] = []  # (id, frame, counter) waiting for a TICK
    assembler = PlantSampleAssembler(interleaved=True)

    def add_plant(frame_id: int, frame: Any, counter: int, time: float | None) -> None:
        sample, torn = assembler.add(frame_id, frame, counter, time)
        counts.torn_samples += torn  # a set that never completed
        if sample is not None:
            stretches[-1].sample_time.append(assembler.sample_time)
            stretches[-1].sample.append((sample.vx, sample.vy, sample.yaw_rate,
                                         sample.steer_angle, sample.drive_torque))
            counts.samples += 1

    for raw in frames:
        counts.frames += 1
        if not is_contract_data_frame(raw) or raw.arbitration_id not in {int(f) for f in FrameId}:
            counts.not_contract += 1
            continue
        payload = bytes(raw.data)
        verdict = monitor.check(raw.arbitration_id, payload)
        if not verdict.accepted:
            counts.e2e_rejected[verdict.status.name] += 1
            continue
        try:
            decoded = decode(raw.arbitration_id, payload)
        except CanDefsError:
            counts.e2e_rejected["UNDECODABLE"] += 1
            continue
        frame_id = raw.arbitration_id
        if frame_id == FrameId.HIL_SYNC:
            tick = decoded.frame.tick
            if tick == HANDSHAKE_TICK:
                if stretches[-1].sample_time or stretches[-1].command_time:
                    stretches.append(_Streams())
                last_tick = None
                pending_plant.clear()
                assembler.reset()
                continue
            last_tick = tick
            for pending_id, pending_frame, pending_counter in pending_plant:
                add_plant(pending_id, pending_frame, pending_counter, tick / 1000.0)
            pending_plant.clear()
        elif frame_id in _PLANT_IDS:
            counts.plant_frames += 1
            if lockstep:
                pending_plant.append((frame_id, decoded.frame, decoded.counter))
            else:
                time = (clocks[frame_id].time(decoded.counter, raw.timestamp - first_stamp)
                        if frame_id == FrameId.VEH_DYN else None)
                add_plant(frame_id, decoded.frame, decoded.counter, time)
        elif frame_id == FrameId.STEER_TORQUE_CMD:
            command = decoded.frame
            if command.cmd_valid:
                counts.commands_valid += 1
            else:
                counts.commands_invalid += 1
            if lockstep:
                if last_tick is None:
                    continue
                time = last_tick / 1000.0
            else:
                time = clocks[frame_id].time(decoded.counter, raw.timestamp - first_stamp)
            stretches[-1].command_time.append(time)
            stretches[-1].command.append((command.drive_torque_cmd, command.steer_angle_cmd,
                                          bool(command.cmd_valid)))
    return stretches


# ---------------------------------------------------------------- resampling
def _segments(stretch: _Streams, ts: float, input_source: str, counts: LogCounts,
              lockstep: bool) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """(states (n, n_x), inputs (n, 2)) of each run of usable grid instants."""
    if len(stretch.sample_time) < 2:
        return
    order = np.argsort(stretch.sample_time, kind="stable")
    sample_time = np.asarray(stretch.sample_time)[order]
    samples = np.asarray(stretch.sample, dtype=float)[order]
    # The grid: the control instants. In lockstep they are multiples of Ts of virtual
    # time; on a counter time base the command frames mark them.
    origin = 0.0 if lockstep or not stretch.command_time else min(stretch.command_time) % ts
    grid = origin + np.arange(math.ceil((sample_time[0] - origin) / ts - 1e-9),
                              math.floor((sample_time[-1] - origin) / ts + 1e-9) + 1) * ts
    counts.grid_points += len(grid)
    upper = np.clip(np.searchsorted(sample_time, grid, side="left"), 1, len(sample_time) - 1)
    lower = upper - 1
    gap = sample_time[upper] - sample_time[lower]
    share = np.where(gap > 0, (grid - sample_time[lower]) / np.where(gap > 0, gap, 1.0), 0.0)
    exact = np.isclose(sample_time[lower], grid, atol=1e-6) | np.isclose(sample_time[upper], grid, atol=1e-6)
    usable = (gap <= MAX_SAMPLE_GAP_S) | exact
    values = samples[lower] + share[:, None] * (samples[upper] - samples[lower])
    usable &= values[:, 0] >= MIN_SPEED_MPS
    if input_source == "measured":
        states = values[:, :3]
        inputs = values[:, [4, 3]]  # measured torque, measured wheel angle
    else:
        states = values[:, :4]
        inputs = np.full((len(grid), 2), np.nan)
        if stretch.command_time:
            order = np.argsort(stretch.command_time, kind="stable")
            command_time = np.asarray(stretch.command_time)[order]
            commands = np.asarray(stretch.command, dtype=float)[order]
            newest = np.searchsorted(command_time, grid + 1e-6, side="right") - 1
            has = newest >= 0
            index = np.where(has, newest, 0)
            fresh = has & (grid - command_time[index] <= MAX_COMMAND_AGE_S) & (commands[index, 2] > 0.5)
            inputs[fresh] = commands[index[fresh], :2]
        usable &= np.isfinite(inputs).all(axis=1)
    counts.grid_used += int(usable.sum())
    edges = np.flatnonzero(np.diff(np.concatenate(([0], usable.astype(int), [0]))))
    for start, stop in zip(edges[::2], edges[1::2]):
        if (stop - start) * ts >= MIN_SEGMENT_S:
            yield states[start:stop], inputs[start:stop]


def pieces(states: np.ndarray, inputs: np.ndarray, piece: int) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """Cut a segment into pieces of about ``piece`` samples (the last one absorbs the rest)."""
    n_pieces = max(1, len(states) // piece)
    bounds = np.linspace(0, len(states), n_pieces + 1).astype(int)
    for start, stop in zip(bounds[:-1], bounds[1:]):
        yield states[start:stop], inputs[start:stop]


def _check_content(path: Path, counts: LogCounts, input_source: str) -> None:
    """The errors of a log that cannot give data (see the module docstring)."""
    if counts.plant_frames == 0 and not counts.e2e_rejected:
        raise LogDataError(f"{path}: no VEH_DYN / VEH_POSE_XY / VEH_POSE_YAW frames (0x100-0x102) in "
                           f"{counts.frames} frames: not a recording of the contract's bus")
    if counts.plant_frames == 0:
        rejected = sum(counts.e2e_rejected.values())
        raise LogDataError(f"{path}: none of the plant frames passes the E2E check ({rejected} frames "
                           f"rejected: {dict(counts.e2e_rejected)}): recorded with another DBC or "
                           "CRC than the contract's?")
    if counts.samples == 0:
        raise LogDataError(f"{path}: no consistent sample (VEH_DYN, VEH_POSE_XY, VEH_POSE_YAW with one "
                           f"counter) among {counts.plant_frames} plant frames")
    if input_source == "command":
        if counts.commands_valid + counts.commands_invalid == 0:
            raise LogDataError(f"{path}: no STEER_TORQUE_CMD (0x200) frames: the ECU's commands were "
                               "not recorded (record the whole bus, or use the measured inputs)")
        if counts.commands_valid == 0:
            raise LogDataError(f"{path}: all {counts.commands_invalid} STEER_TORQUE_CMD frames have "
                               "CMD_VALID = 0: the ECU never commanded the vehicle (was it engaged?)")


def load_logs(files: Sequence[str | Path], ts: float = 0.025, input_source: str = "command",
              dbc: str | Path | None = None, piece_s: float = PIECE_S,
              min_data_s: float = MIN_DATA_S) -> LogDataset:
    """Trajectories (states ``STATES``, or ``MEASURED_INPUT_STATES`` with measured inputs;
    inputs ``INPUTS``) from CAN logs; see the module docstring.

    Raises:
        LogDataError: a file that cannot give data, or less than ``min_data_s`` in all.
    """
    if input_source not in INPUT_SOURCES:
        raise LogDataError(f"input source {input_source!r} is not one of {INPUT_SOURCES}")
    if not files:
        raise LogDataError("no log files given")
    try:
        prepare(dbc)
    except CanDefsError as error:
        raise LogDataError(f"--dbc {dbc}: {error}") from error
    names = STATES if input_source == "command" else MEASURED_INPUT_STATES
    segments: list[tuple[Path, np.ndarray, np.ndarray]] = []
    all_counts: dict[str, LogCounts] = {}
    warnings: list[str] = []
    for file in files:
        path = Path(file)
        frames, read_warning = read_frames(path)
        counts = LogCounts(read_warning=read_warning)
        stretches = _decode_streams(frames, counts)
        _check_content(path, counts, input_source)
        found = 0
        for stretch in stretches:
            for states, inputs in _segments(stretch, ts, input_source, counts,
                                            counts.time_base.startswith("HIL_SYNC")):
                segments.append((path, states[:, :len(names)], inputs))
                found += 1
        all_counts[str(path)] = counts
        warnings.extend(f"{path}: {w}" for w in _warnings(counts))
        if found == 0:
            raise LogDataError(f"{path}: no stretch of at least {MIN_SEGMENT_S} s with consistent "
                               f"samples and {'CMD_VALID = 1 commands' if input_source == 'command' else 'inputs'} "
                               f"({counts.grid_used} usable instants of {ts} s)")
    # Pieces of piece_s, shorter for little data: training holds out whole pieces and
    # needs at least ten to split them into training, validation and test.
    total_s = sum(len(states) for _, states, _ in segments) * ts
    piece = max(1, round(max(MIN_PIECE_S, min(piece_s, total_s / 10.0)) / ts))
    trajectories: list[Trajectory] = []
    numbers: Counter = Counter()
    for path, states, inputs in segments:
        for piece_states, piece_inputs in pieces(states, inputs, piece):
            trajectories.append(Trajectory(f"{path.name}#{numbers[path]:03d}", piece_states,
                                           piece_inputs, names, INPUTS))
            numbers[path] += 1
    dataset = LogDataset(trajectories, all_counts, warnings, ts, input_source)
    if dataset.seconds < min_data_s:
        raise LogDataError(f"{', '.join(str(f) for f in files)}: {dataset.seconds:.1f} s of usable data, "
                           f"need at least {min_data_s:.0f} s (record a longer drive)")
    return dataset


def _warnings(counts: LogCounts) -> list[str]:
    """Partial data: what was left out, with counts."""
    lines = []
    if counts.read_warning:
        lines.append(counts.read_warning)
    rejected = sum(counts.e2e_rejected.values())
    if rejected:
        lines.append(f"{rejected} of {counts.frames} frames failed the E2E check and were left out "
                     f"({', '.join(f'{k} {v}' for k, v in sorted(counts.e2e_rejected.items()))})")
    if counts.torn_samples:
        lines.append(f"{counts.torn_samples} torn plant samples dropped ({counts.samples} consistent)")
    if counts.commands_invalid and counts.commands_valid:
        lines.append(f"{counts.commands_invalid} of {counts.commands_valid + counts.commands_invalid} "
                     "commands have CMD_VALID = 0: those stretches are left out")
    if counts.grid_points and counts.grid_used < counts.grid_points:
        lines.append(f"{counts.grid_used} of {counts.grid_points} instants of the control period used")
    return lines
