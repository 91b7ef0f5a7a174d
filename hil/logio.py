"""Recorded CAN logs for the HIL tools: their frames with counts, their time base, and
their sidecar metadata.

- `read_log(path)`: every frame of a log (``can_defs.log_reader``, the project's one log
  reader: python-can's readers, candump lines checked first, damage skipped with
  warnings; an unknown suffix is `LogFormatError`, a file with no readable frame
  `LogReadError`), as `LogContents`: the frames plus counts (frames per contract ID, IDs
  outside the DBC, error / remote / CAN FD / extended frames, skipped lines) and the
  warnings.
- `frame_times(messages)`: the time base of a log. Lockstep logs (with HIL_SYNC) are
  timed by virtual time (`TickStamper`): an input frame belongs to the TICK of the
  HIL_SYNC that follows it (the master sends the frames due at t, then HIL_SYNC t), an
  ECU frame to the TICK it answered (the HIL_SYNC before it). Other logs use their
  timestamps relative to the first frame. The recorder stamps lockstep logs with the
  same rule (wall-clock start + virtual time), so every tool sees the drive's true speed.
- Sidecar ``<log>.json`` (`LogMetadata`): what produced a log (the ECU, its controller,
  reference paths, ``--model`` and ``--excite``, and a SHA-256 of every input file the
  ECU's commands depend on, `InputFile`), so `eso-hil replay` rebuilds the same ECU
  without flags, or refuses when a recorded file has changed (`check_input_files`).
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import math
from collections import Counter
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Iterator

import can

from can_defs import log_reader
from can_defs.frames import HANDSHAKE_TICK, FrameId
from can_defs.log_reader import FrameKind, LogFrames, frame_kind, is_contract_data_frame
from hil.errors import HilError

#: Frames the ECU sends; every other frame of a log is an input of the ECU.
ECU_OUTPUT_IDS: frozenset[int] = frozenset(
    {FrameId.HIL_SYNC_ACK, FrameId.STEER_TORQUE_CMD, FrameId.CTRL_DIAG})

#: Version of the sidecar JSON layout (3 added ``ecu``, ``model``, ``excite`` and
#: ``input_files``; 2 added ``wall_start`` / ``wall_end``; 1 and 2 are read too). A new
#: role of ``input_files`` is no new layout: readers take every role, and a sidecar
#: without one ("default model", "vehicle", "C ECU data" came later) has nothing to check.
SIDECAR_VERSION = 3

#: Root of the checkout: relative paths in sidecars are relative to it.
REPO_ROOT = Path(__file__).resolve().parent.parent

class LogError(HilError):
    """A log file cannot be used (the message names the file and what is wrong)."""


class LogFormatError(LogError):
    """The file suffix names no log format python-can reads."""


class LogReadError(LogError):
    """The log is missing, unreadable, or holds no readable frame."""


class SidecarError(LogError):
    """The sidecar ``<log>.json`` is malformed (the message names the field)."""


@dataclass
class LogContents(LogFrames):
    """Frames of one log in file order (`can_defs.log_reader.LogFrames`: error, remote,
    CAN FD and foreign frames included, so a player can put them back on a bus), with
    counts of what they are. Only classic data frames with an 11-bit ID count per contract
    ID or as IDs outside the DBC."""

    frames_by_id: Counter[int] = field(default_factory=Counter)
    unknown_ids: Counter[int] = field(default_factory=Counter)
    error_frames: int = 0
    remote_frames: int = 0
    fd_frames: int = 0
    extended_frames: int = 0
    timestamps_backwards: int = 0

    @property
    def is_lockstep(self) -> bool:
        """True when the log holds HIL_SYNC frames (a lockstep run)."""
        return self.frames_by_id.get(int(FrameId.HIL_SYNC), 0) > 0

    @property
    def has_ecu_frames(self) -> bool:
        """True when the log holds the ECU's STEER_TORQUE_CMD or CTRL_DIAG."""
        return any(self.frames_by_id.get(int(fid), 0) > 0
                   for fid in (FrameId.STEER_TORQUE_CMD, FrameId.CTRL_DIAG))

    @property
    def contract_frames(self) -> int:
        """Data frames with an 11-bit ID of the contract."""
        return sum(self.frames_by_id.values())

    def counts_by_dbc(self, database: Any) -> tuple[Counter[str], Counter[int]]:
        """Frames per message name of a cantools ``database`` (remote frames included)
        and per ID outside it; error frames count in neither."""
        per_name: Counter[str] = Counter()
        outside: Counter[int] = Counter()
        for message in self.messages:
            if message.is_error_frame:
                continue
            found = dbc_message(database, message)
            if found is not None:
                per_name[found.name] += 1
            else:
                outside[message.arbitration_id] += 1
        return per_name, outside

    def summary_lines(self, database: Any = None, dbc_name: str = "") -> list[str]:
        """Human-readable counts (one line each; the warnings are `warnings`, printed
        once on stderr by the commands); with ``database`` (a
        cantools database of another DBC, named ``dbc_name``) the frames are counted per
        message of that DBC instead of the contract's."""
        lines = [f"{self.path}: {len(self.messages)} frames read"
                 + ("" if self.complete else " (incomplete: see warnings)")]
        if database is None:
            per_id = ", ".join(f"{FrameId(fid).name} {n}"
                               for fid, n in sorted(self.frames_by_id.items()))
            lines.append(f"  contract frames: {self.contract_frames} ({per_id or 'none'})")
            outside = self.unknown_ids
            extended_label = "extended-ID frames (not in the DBC)"
        else:
            per_name, outside = self.counts_by_dbc(database)
            listed = ", ".join(f"{name} {n}" for name, n in per_name.most_common())
            lines.append(f"  frames of {dbc_name or 'the DBC'}: {sum(per_name.values())} "
                         f"({listed or 'none'})")
            extended_label = "extended-ID frames"
        if outside:
            foreign = ", ".join(f"0x{fid:03X} x{n}" for fid, n in sorted(outside.items()))
            lines.append(f"  frames with IDs outside the DBC: {sum(outside.values())} "
                         f"({foreign})")
        for label, count in (("error frames", self.error_frames),
                             ("remote frames", self.remote_frames),
                             ("CAN FD frames", self.fd_frames),
                             (extended_label, self.extended_frames),
                             ("damaged lines skipped", self.skipped_lines),
                             ("timestamps going backwards", self.timestamps_backwards)):
            if count:
                lines.append(f"  {label}: {count}")
        return lines


@contextmanager
def _as_hil_errors() -> Iterator[None]:
    """The log reader's errors as this package's, which the commands report."""
    try:
        yield
    except log_reader.LogFormatError as error:
        raise LogFormatError(str(error)) from error
    except log_reader.LogFileError as error:
        raise LogReadError(str(error)) from error


def check_log_suffix(path: str | Path) -> str:
    """The format suffix of ``path``; `LogFormatError` when python-can has no reader for it."""
    with _as_hil_errors():
        return log_reader.check_log_suffix(path)


def read_log(path: str | Path) -> LogContents:
    """Every frame of a log, with counts and warnings (see the module docstring).

    Raises:
        LogFormatError: the suffix names no supported format.
        LogReadError: the file is missing, unreadable or too large, or no frame could be
            read.
    """
    with _as_hil_errors():
        frames = log_reader.read_log_frames(path, check_file=_check_size)
    contents = LogContents(**{f.name: getattr(frames, f.name)
                              for f in dataclasses.fields(LogFrames)})
    _count(contents)
    return contents


def _check_size(path: Path) -> None:
    """Before any reader takes the file whole."""
    from models.input_files import LOG_FILE_MAX_BYTES, check_file_size

    check_file_size(path, LOG_FILE_MAX_BYTES, LogReadError)


def _count(contents: LogContents) -> None:
    known = {int(fid) for fid in FrameId}
    previous = -math.inf
    for message in contents.messages:
        if message.timestamp < previous:
            contents.timestamps_backwards += 1
        previous = message.timestamp
        kind = frame_kind(message)
        if kind is FrameKind.ERROR:
            contents.error_frames += 1
        elif kind is FrameKind.REMOTE:
            contents.remote_frames += 1
        elif kind is FrameKind.FD:
            contents.fd_frames += 1
        elif message.is_extended_id:
            contents.extended_frames += 1
        elif message.arbitration_id in known:
            contents.frames_by_id[message.arbitration_id] += 1
        else:
            contents.unknown_ids[message.arbitration_id] += 1
    if contents.timestamps_backwards:
        contents.warnings.append(f"{contents.timestamps_backwards} timestamp(s) go backwards; "
                                 "file order is kept")


def dbc_message(database: Any, message: can.Message) -> Any:
    """The message of a cantools ``database`` a log frame belongs to (same ID, same ID
    kind), None for error frames and IDs it does not define."""
    if message.is_error_frame:
        return None
    try:
        found = database.get_message_by_frame_id(message.arbitration_id)
    except KeyError:
        return None
    return found if bool(found.is_extended_frame) == bool(message.is_extended_id) else None


def sync_tick(message: can.Message) -> int | None:
    """TICK of a well-formed HIL_SYNC / HIL_SYNC_ACK frame (ms or HANDSHAKE_TICK), else None."""
    if (not is_contract_data_frame(message)
            or message.arbitration_id not in (FrameId.HIL_SYNC, FrameId.HIL_SYNC_ACK)
            or len(message.data) != 8):
        return None
    return int.from_bytes(bytes(message.data[0:4]), "little")


class TickStamper:
    """Which virtual tick each frame of a lockstep stream belongs to, frame by frame.

    The rule of the contract's lockstep protocol: the master sends the frames due at t,
    then HIL_SYNC t; the ECU answers after it. So HIL_SYNC t belongs to t, a frame the ECU
    sent (HIL_SYNC_ACK, STEER_TORQUE_CMD, CTRL_DIAG) to the TICK before it, and every
    other frame to the TICK of the HIL_SYNC that follows it. Frames before the first TICK
    (the handshake) get the first TICK; frames after the last one get the last one. The
    handshake TICK 0xFFFFFFFF is not a tick.

    A frame's tick may only be known once a later frame has arrived, so `push` returns
    the frames whose tick is settled, in arrival order, and `flush` the rest at the end.
    Used offline (`frame_times`) and live by the recorder (`hil.recorder.BusRecorder`),
    so a lockstep log's timestamps and the replay's time base are one rule.
    """

    def __init__(self) -> None:
        self.previous_tick: int | None = None
        # (frame, tick or None while it waits for the next HIL_SYNC), in arrival order
        self._pending: list[tuple[can.Message, int | None]] = []

    def push(self, message: can.Message) -> list[tuple[can.Message, int]]:
        """Take the next frame; returns the frames whose tick (ms) is now known."""
        tick = sync_tick(message) if message.arbitration_id == FrameId.HIL_SYNC else None
        if tick is not None and tick != HANDSHAKE_TICK:
            self._pending = [(m, tick if t is None else t) for m, t in self._pending]
            self._pending.append((message, tick))
            self.previous_tick = tick
        elif (self.previous_tick is not None and is_contract_data_frame(message)
              and message.arbitration_id in ECU_OUTPUT_IDS):
            self._pending.append((message, self.previous_tick))
        else:
            self._pending.append((message, None))
        settled = 0
        while settled < len(self._pending) and self._pending[settled][1] is not None:
            settled += 1
        ready = [(m, int(t)) for m, t in self._pending[:settled]]  # type: ignore[arg-type]
        del self._pending[:settled]
        return ready

    def flush(self) -> list[tuple[can.Message, int]]:
        """The frames still waiting, with the last TICK (0 when no TICK was seen)."""
        last = self.previous_tick if self.previous_tick is not None else 0
        ready = [(m, last if t is None else t) for m, t in self._pending]
        self._pending = []
        return ready


def has_sync_ticks(messages: list[can.Message]) -> bool:
    """True when a well-formed HIL_SYNC with a real TICK (not the handshake) is present."""
    return any(message.arbitration_id == FrameId.HIL_SYNC
               and sync_tick(message) not in (None, HANDSHAKE_TICK) for message in messages)


def frame_times(messages: list[can.Message]) -> tuple[list[float], str]:
    """Time of every frame (s) and a description of the time base.

    With HIL_SYNC frames: virtual time from the TICKs (`TickStamper`). Without: the
    timestamps relative to the first frame.
    """
    if not has_sync_ticks(messages):
        start = messages[0].timestamp if messages else 0.0
        return [m.timestamp - start for m in messages], "log timestamps (no HIL_SYNC in the log)"
    stamper = TickStamper()
    ticks = [tick for message in messages for _, tick in stamper.push(message)]
    ticks.extend(tick for _, tick in stamper.flush())
    return [tick / 1000.0 for tick in ticks], "virtual time from HIL_SYNC TICKs (lockstep log)"


# --- sidecar metadata ------------------------------------------------------------------


@dataclass(frozen=True)
class InputFile:
    """A file the recorded ECU's commands depend on: its ``role`` ("path 1", "model"
    (``--model``'s), "default model" (the controller's artefact without ``--model``),
    "vehicle" (models/vehicle.toml), "C ECU data" (the C ECU's build/firmware/ecu_data.bin),
    "excite", "tuning"), its ``path`` and the SHA-256 of its bytes (hex)."""

    role: str
    path: str
    sha256: str


def file_sha256(path: str | Path) -> str:
    """SHA-256 of a file's bytes (hex).

    Raises:
        OSError: the file cannot be read.
    """
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def describe_inputs(files: Iterable[tuple[str, str | Path]]) -> tuple[InputFile, ...]:
    """`InputFile` of each (role, path) with its hash, as a recording starts or ends."""
    return tuple(InputFile(role, str(path), file_sha256(path)) for role, path in files)


@dataclass(frozen=True)
class LogMetadata:
    """What produced a log: ``controller`` (registry name), ``mode`` ("lockstep" or
    "realtime"), reference ``paths`` (PATH_ID -> CSV file), optionally the scenario, and
    the wall clock of the recording (Unix time, s): ``wall_start`` (its first frame) and
    ``wall_end`` (its last). A lockstep log's frames are stamped ``wall_start`` + virtual
    time, so these two are the only wall-clock record of such a run.

    Since layout 3: the ECU (``ecu``: "python" or "c"), its ``--model`` (a file or a
    Koopman artefact's stem) and ``--excite`` (a shipped program's name or a program
    file), and ``input_files``: every file the ECU's commands depend on (paths, model,
    excitation program, tuning; without ``--model`` the controller's default model, and the
    vehicle file and the C ECU's data file where they are read) with its hash. None /
    empty in older sidecars."""

    controller: str
    mode: str
    paths: dict[int, str]
    scenario: str | None = None
    wall_start: float | None = None
    wall_end: float | None = None
    ecu: str | None = None
    model: str | None = None
    excite: str | None = None
    input_files: tuple[InputFile, ...] = ()

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready form (PATH_IDs as strings)."""
        data: dict[str, Any] = {
            "version": SIDECAR_VERSION, "controller": self.controller, "mode": self.mode,
            "paths": {str(k): v for k, v in sorted(self.paths.items())},
            "scenario": self.scenario}
        if self.wall_start is not None:
            data["wall_start"] = self.wall_start
            data["wall_end"] = self.wall_end
            data["timestamps"] = ("wall_start + virtual time of the tick"
                                  if self.mode == "lockstep" else "wall clock")
        if self.ecu is not None:
            data.update(ecu=self.ecu, model=self.model, excite=self.excite)
        if self.input_files:
            data["input_files"] = [{"role": f.role, "file": f.path, "sha256": f.sha256}
                                   for f in self.input_files]
        return data


def sidecar_path(log_path: str | Path) -> Path:
    """The sidecar of a log: the log's name plus ``.json`` (``run.log`` -> ``run.log.json``)."""
    log_path = Path(log_path)
    return log_path.with_name(log_path.name + ".json")


def _stored_path(file: str | Path) -> str:
    """A file as a sidecar stores it: relative to the repository root when inside it."""
    resolved = Path(file).resolve()
    try:
        return resolved.relative_to(REPO_ROOT).as_posix()
    except ValueError:
        return str(resolved)


def _read_path(target: Path, file: str) -> str:
    """A file a sidecar names: relative ones against the sidecar's folder first, then the
    repository root."""
    candidate = Path(file)
    if not candidate.is_absolute():
        beside = target.parent / candidate
        candidate = beside if beside.exists() else REPO_ROOT / candidate
    return str(candidate)


def write_sidecar(log_path: str | Path, metadata: LogMetadata) -> Path:
    """Write ``<log>.json`` next to the log; returns its path.

    Files inside the repository are stored relative to the repository root so the
    sidecar stays valid in another checkout.
    """
    target = sidecar_path(log_path)
    stored = {path_id: _stored_path(file) for path_id, file in metadata.paths.items()}
    inputs = tuple(dataclasses.replace(f, path=_stored_path(f.path)) for f in metadata.input_files)
    excite_file = any(f.role == "excite" for f in metadata.input_files)
    data = dataclasses.replace(
        metadata, paths=stored, input_files=inputs,
        model=None if metadata.model is None else _stored_path(metadata.model),
        excite=_stored_path(metadata.excite) if excite_file and metadata.excite else metadata.excite,
    ).as_dict()
    try:
        target.write_text(json.dumps(data, indent=2) + "\n", encoding="utf-8")
    except OSError as error:
        raise LogError(f"cannot write the sidecar {target}: {error}") from error
    return target


def read_sidecar(log_path: str | Path) -> LogMetadata | None:
    """Metadata of a log from its sidecar, None when there is none.

    Relative files are resolved against the sidecar's folder first, then the repository
    root.

    Raises:
        SidecarError: the sidecar exists but is not valid JSON or a field is wrong.
    """
    target = sidecar_path(log_path)
    if not target.is_file():
        return None
    try:
        data = json.loads(target.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
        raise SidecarError(f"{target}: not readable JSON: {error}") from error
    if not isinstance(data, dict):
        raise SidecarError(f"{target}: expected a JSON object, got {type(data).__name__}")
    controller = data.get("controller")
    if not isinstance(controller, str) or not controller:
        raise SidecarError(f"{target}: field 'controller' must be a non-empty string, "
                           f"got {controller!r}")
    mode = data.get("mode", "lockstep")
    if mode not in ("lockstep", "realtime"):
        raise SidecarError(f"{target}: field 'mode' must be 'lockstep' or 'realtime', "
                           f"got {mode!r}")
    raw_paths = data.get("paths", {})
    if not isinstance(raw_paths, dict):
        raise SidecarError(f"{target}: field 'paths' must be an object PATH_ID -> file, "
                           f"got {raw_paths!r}")
    paths: dict[int, str] = {}
    for key, file in raw_paths.items():
        try:
            path_id = int(key)
        except ValueError:
            raise SidecarError(f"{target}: PATH_ID {key!r} in 'paths' is not an integer") from None
        if not isinstance(file, str):
            raise SidecarError(f"{target}: paths[{key}] must be a file name, got {file!r}")
        paths[path_id] = _read_path(target, file)
    scenario = data.get("scenario")
    wall = {}
    for name in ("wall_start", "wall_end"):
        value = data.get(name)
        if value is not None and (isinstance(value, bool) or not isinstance(value, (int, float))):
            raise SidecarError(f"{target}: field {name!r} must be a number (Unix time, s), "
                               f"got {value!r}")
        wall[name] = None if value is None else float(value)
    texts = {}
    for name in ("ecu", "model", "excite"):
        value = data.get(name)
        if value is not None and (not isinstance(value, str) or not value):
            raise SidecarError(f"{target}: field {name!r} must be a non-empty string or null, "
                               f"got {value!r}")
        texts[name] = value
    if texts["ecu"] not in (None, "python", "c"):
        raise SidecarError(f"{target}: field 'ecu' must be 'python' or 'c', got {texts['ecu']!r}")
    input_files = _read_input_files(target, data.get("input_files", []))
    if texts["model"] is not None:
        texts["model"] = _read_path(target, texts["model"])
    if texts["excite"] is not None and any(f.role == "excite" for f in input_files):
        texts["excite"] = _read_path(target, texts["excite"])
    return LogMetadata(controller=controller, mode=mode, paths=paths,
                       scenario=scenario if isinstance(scenario, str) else None, **wall,
                       **texts, input_files=input_files)


def _read_input_files(target: Path, raw: Any) -> tuple[InputFile, ...]:
    if not isinstance(raw, list):
        raise SidecarError(f"{target}: field 'input_files' must be a list, got {raw!r}")
    files = []
    for index, entry in enumerate(raw):
        if not (isinstance(entry, dict)
                and all(isinstance(entry.get(k), str) and entry.get(k)
                        for k in ("role", "file", "sha256"))):
            raise SidecarError(f"{target}: input_files[{index}] must be an object with the "
                               f"strings role, file and sha256, got {entry!r}")
        files.append(InputFile(entry["role"], _read_path(target, entry["file"]), entry["sha256"]))
    return tuple(files)


def check_input_files(files: Iterable[InputFile],
                      skip_roles: Iterable[str] = ()) -> list[tuple[InputFile, str]]:
    """The recorded input files that are missing or whose bytes changed since the
    recording, each with a sentence saying so (its role, path and both hashes); empty when
    each is as recorded. Files of ``skip_roles`` are not looked at (the replay was given
    another file for them)."""
    skipped = set(skip_roles)
    problems = []
    for recorded in files:
        if recorded.role in skipped:
            continue
        path = Path(recorded.path)
        if not path.is_file():
            problems.append((recorded, f"the {recorded.role} file {path} is missing"))
            continue
        try:
            now = file_sha256(path)
        except OSError as error:
            problems.append((recorded, f"the {recorded.role} file {path} cannot be read ({error})"))
            continue
        if now != recorded.sha256:
            problems.append((recorded, f"the {recorded.role} file {path} changed since the "
                             f"recording (SHA-256 {recorded.sha256[:12]}... recorded, "
                             f"{now[:12]}... now)"))
    return problems
