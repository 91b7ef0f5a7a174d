"""Reading recorded CAN logs of any python-can format, robustly, and their sidecar metadata.

- `read_log(path)`: every frame of a log through python-can's readers (`can.LogReader`
  picks the reader by suffix: ``.log`` candump ``-L``, ``.asc``, ``.blf``, ``.csv``,
  ``.trc``, ... and ``.gz`` variants of these). A damaged file never raises a parser's
  traceback: a candump line that is not a frame is skipped and counted; a reader that
  fails in the middle of a file (truncated BLF, garbled ASC) ends the read there with a
  warning saying how many frames were read. Only a file with no readable frame at all is
  an error (`LogReadError`); an unknown suffix is `LogFormatError`.
- `LogContents`: the frames plus counts (frames per contract ID, IDs outside the DBC,
  error / remote / extended frames, skipped lines) and the warnings.
- `frame_times(messages)`: the time base of a log. Lockstep logs (with HIL_SYNC) are
  timed by virtual time (`TickStamper`): an input frame belongs to the TICK of the
  HIL_SYNC that follows it (the master sends the frames due at t, then HIL_SYNC t), an
  ECU frame to the TICK it answered (the HIL_SYNC before it). Other logs use their
  timestamps relative to the first frame. The recorder stamps lockstep logs with the
  same rule (wall-clock start + virtual time), so every tool sees the drive's true speed.
- Sidecar ``<log>.json`` (`LogMetadata`): which controller and reference paths produced
  a log, so `eso-hil replay` needs no flags for logs written by ``make run``.
"""
from __future__ import annotations

import dataclasses
import io
import json
import math
import re
import zlib
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path, PurePath
from typing import Any

import can

from can_defs.frames import HANDSHAKE_TICK, FrameId
from hil.errors import HilError

#: Suffixes python-can reads without optional packages (``.mf4`` needs asammdf), each also
#: gzip-compressed (``.log.gz``).
SUPPORTED_SUFFIXES: tuple[str, ...] = (".log", ".asc", ".blf", ".csv", ".db", ".trc")

#: Frames the ECU sends; every other frame of a log is an input of the ECU.
ECU_OUTPUT_IDS: frozenset[int] = frozenset(
    {FrameId.HIL_SYNC_ACK, FrameId.STEER_TORQUE_CMD, FrameId.CTRL_DIAG})

#: Version of the sidecar JSON layout (2 added ``wall_start`` / ``wall_end``; 1 is read too).
SIDECAR_VERSION = 2

#: Root of the checkout: relative paths in sidecars are relative to it.
REPO_ROOT = Path(__file__).resolve().parent.parent

# A candump -L line: "(timestamp) channel ID#DATA [R|T]", DATA in hex bytes, "R[dlc]"
# for a remote frame, or "#F" + hex for CAN FD. Anything else in a .log is damage.
_CANDUMP_LINE = re.compile(
    r"^\(\d+(\.\d+)?\)\s+\S+\s+([0-9A-Fa-f]{3}|[0-9A-Fa-f]{8})#"
    r"(([0-9A-Fa-f]{2})*|[Rr]\d*|#[0-9A-Fa-f]([0-9A-Fa-f]{2})*)(\s+[RTrt])?$")

#: How many damaged line numbers a warning quotes.
_QUOTED_LINES = 5


class LogError(HilError):
    """A log file cannot be used (the message names the file and what is wrong)."""


class LogFormatError(LogError):
    """The file suffix names no log format python-can reads."""


class LogReadError(LogError):
    """The log is missing, unreadable, or holds no readable frame."""


class SidecarError(LogError):
    """The sidecar ``<log>.json`` is malformed (the message names the field)."""


@dataclass
class LogContents:
    """Frames of one log in file order, with what reading them found.

    ``messages`` holds every frame read (error, remote and foreign frames included, so a
    player can put them back on a bus); the counts say what they are.
    """

    path: Path
    messages: list[can.Message]
    complete: bool = True
    warnings: list[str] = field(default_factory=list)
    skipped_lines: int = 0
    frames_by_id: Counter[int] = field(default_factory=Counter)
    unknown_ids: Counter[int] = field(default_factory=Counter)
    error_frames: int = 0
    remote_frames: int = 0
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
                             (extended_label, self.extended_frames),
                             ("damaged lines skipped", self.skipped_lines),
                             ("timestamps going backwards", self.timestamps_backwards)):
            if count:
                lines.append(f"  {label}: {count}")
        return lines


def log_suffix(path: str | Path) -> str:
    """Format suffix of a log path, looking through ``.gz`` (``run.log.gz`` -> ``.log``)."""
    pure = PurePath(path)
    suffixes = [s.lower() for s in pure.suffixes]
    if suffixes and suffixes[-1] == ".gz":
        return suffixes[-2] if len(suffixes) >= 2 else ""
    return suffixes[-1] if suffixes else ""


def check_log_suffix(path: str | Path) -> str:
    """The format suffix of ``path``; `LogFormatError` when python-can has no reader for it."""
    suffix = log_suffix(path)
    if suffix not in SUPPORTED_SUFFIXES:
        raise LogFormatError(
            f"{path}: unknown log format {suffix or '(no suffix)'!r}; supported: "
            f"{', '.join(SUPPORTED_SUFFIXES)} (optionally .gz compressed)")
    return suffix


def read_log(path: str | Path) -> LogContents:
    """Every frame of a log, with counts and warnings (see the module docstring).

    Raises:
        LogFormatError: the suffix names no supported format.
        LogReadError: the file is missing or unreadable, or no frame could be read.
    """
    path = Path(path)
    suffix = check_log_suffix(path)
    if not path.is_file():
        raise LogReadError(f"{path}: no such log file")
    from models.input_files import LOG_FILE_MAX_BYTES, check_file_size

    check_file_size(path, LOG_FILE_MAX_BYTES, LogReadError)   # before any reader takes it whole
    contents = LogContents(path=path, messages=[])
    if suffix == ".log":
        _read_candump(path, contents)
    else:
        _read_with_python_can(path, contents)
    if not contents.messages:
        problem = "; ".join(contents.warnings) or "the file holds no frame"
        raise LogReadError(f"{path}: no readable CAN frame ({problem})")
    _count(contents)
    return contents


def _open_text(path: Path) -> tuple[str, str | None]:
    """Text of a (possibly gzip-compressed) candump file and what was wrong with the
    compression, if anything. A truncated or damaged gzip stream yields the text that
    decompressed before the damage."""
    raw = path.read_bytes()
    if path.suffix.lower() != ".gz":
        return raw.decode("ascii", errors="replace"), None
    inflater = zlib.decompressobj(wbits=31)  # 31: gzip header and trailer
    chunks: list[bytes] = []
    problem = None
    step = 1 << 16
    try:
        for start in range(0, len(raw), step):
            chunks.append(inflater.decompress(raw[start:start + step]))
            if inflater.eof:
                break
        if not inflater.eof:
            problem = "the gzip stream is truncated"
    except zlib.error as error:
        problem = f"the gzip stream is corrupt ({error})"
    text = b"".join(chunks).decode("ascii", errors="replace")
    if problem is not None and not text.endswith("\n"):
        text = text[: text.rfind("\n") + 1]  # the last line is cut: drop it
    return text, problem


def _read_candump(path: Path, contents: LogContents) -> None:
    """candump ``-L`` lines: keep the well-formed ones, count and quote the others, then
    parse the kept lines with python-can's `CanutilsLogReader`."""
    try:
        text, problem = _open_text(path)
    except OSError as error:
        raise LogReadError(f"{path}: cannot read: {error}") from error
    if problem is not None:
        contents.complete = False
        contents.warnings.append(f"{problem}: the frames before the damage are kept")
    lines = text.splitlines()
    if problem is None and lines and text and not text.endswith(("\n", "\r")):
        # candump and python-can end every line: a last line without its end was cut
        # while being written, and may still look like a (shorter) frame.
        contents.complete = False
        contents.warnings.append(f"the last line ({len(lines)}) is incomplete (no line end): "
                                 "dropped; the file was cut while being written")
        lines.pop()
    good: list[str] = []
    damaged: list[int] = []
    for number, line in enumerate(lines, start=1):
        stripped = line.strip()
        if not stripped:
            continue
        if _CANDUMP_LINE.match(stripped):
            good.append(stripped)
        else:
            damaged.append(number)
    if damaged:
        contents.skipped_lines = len(damaged)
        quoted = ", ".join(str(n) for n in damaged[:_QUOTED_LINES])
        more = "" if len(damaged) <= _QUOTED_LINES else f", ... ({len(damaged)} in all)"
        contents.warnings.append(f"{len(damaged)} line(s) that are not candump frames were "
                                 f"skipped: line {quoted}{more}")
        contents.complete = False
    reader = can.CanutilsLogReader(io.StringIO("\n".join(good)))
    _drain(reader, contents, path)


def _read_with_python_can(path: Path, contents: LogContents) -> None:
    try:
        reader = can.LogReader(path)
    except (OSError, ValueError, EOFError) as error:
        raise LogReadError(f"{path}: cannot open: {error}") from error
    except Exception as error:  # noqa: BLE001 - a reader's own parse error on the header
        raise LogReadError(f"{path}: not a readable {log_suffix(path)} log: "
                           f"{type(error).__name__}: {error}") from error
    _drain(reader, contents, path)


def _drain(reader: Any, contents: LogContents, path: Path) -> None:
    """Iterate a python-can reader to its end or to its first failure.

    The readers are third-party parsers of untrusted files and raise whatever their
    parsing hits (ValueError, struct.error, zlib.error, IndexError, their own errors); any
    of these ends the read with the frames so far and a warning.
    """
    try:
        for message in reader:
            contents.messages.append(message)
    except Exception as error:  # noqa: BLE001 - see the docstring
        contents.complete = False
        contents.warnings.append(
            f"reading stopped after {len(contents.messages)} frame(s): the file is truncated "
            f"or corrupt ({type(error).__name__}: {error})")
    finally:
        try:
            reader.stop()
        except Exception:  # noqa: BLE001 - closing a damaged file is best effort
            pass


def _count(contents: LogContents) -> None:
    known = {int(fid) for fid in FrameId}
    previous = -math.inf
    for message in contents.messages:
        if message.timestamp < previous:
            contents.timestamps_backwards += 1
        previous = message.timestamp
        if message.is_error_frame:
            contents.error_frames += 1
        elif message.is_remote_frame:
            contents.remote_frames += 1
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


def is_contract_data_frame(message: can.Message) -> bool:
    """An 11-bit data frame (not error, not remote)."""
    return not (message.is_error_frame or message.is_remote_frame or message.is_extended_id)


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
class LogMetadata:
    """What produced a log: ``controller`` (registry name), ``mode`` ("lockstep" or
    "realtime"), reference ``paths`` (PATH_ID -> CSV file), optionally the scenario, and
    the wall clock of the recording (Unix time, s): ``wall_start`` (its first frame) and
    ``wall_end`` (its last). A lockstep log's frames are stamped ``wall_start`` + virtual
    time, so these two are the only wall-clock record of such a run."""

    controller: str
    mode: str
    paths: dict[int, str]
    scenario: str | None = None
    wall_start: float | None = None
    wall_end: float | None = None

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
        return data


def sidecar_path(log_path: str | Path) -> Path:
    """The sidecar of a log: the log's name plus ``.json`` (``run.log`` -> ``run.log.json``)."""
    log_path = Path(log_path)
    return log_path.with_name(log_path.name + ".json")


def write_sidecar(log_path: str | Path, metadata: LogMetadata) -> Path:
    """Write ``<log>.json`` next to the log; returns its path.

    Path files inside the repository are stored relative to the repository root so the
    sidecar stays valid in another checkout.
    """
    target = sidecar_path(log_path)
    stored = {}
    for path_id, file in metadata.paths.items():
        resolved = Path(file).resolve()
        try:
            stored[path_id] = resolved.relative_to(REPO_ROOT).as_posix()
        except ValueError:
            stored[path_id] = str(resolved)
    data = dataclasses.replace(metadata, paths=stored).as_dict()
    try:
        target.write_text(json.dumps(data, indent=2) + "\n", encoding="utf-8")
    except OSError as error:
        raise LogError(f"cannot write the sidecar {target}: {error}") from error
    return target


def read_sidecar(log_path: str | Path) -> LogMetadata | None:
    """Metadata of a log from its sidecar, None when there is none.

    Relative path files are resolved against the sidecar's folder first, then the
    repository root.

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
        candidate = Path(file)
        if not candidate.is_absolute():
            beside = target.parent / candidate
            candidate = beside if beside.exists() else REPO_ROOT / candidate
        paths[path_id] = str(candidate)
    scenario = data.get("scenario")
    wall = {}
    for name in ("wall_start", "wall_end"):
        value = data.get(name)
        if value is not None and (isinstance(value, bool) or not isinstance(value, (int, float))):
            raise SidecarError(f"{target}: field {name!r} must be a number (Unix time, s), "
                               f"got {value!r}")
        wall[name] = None if value is None else float(value)
    return LogMetadata(controller=controller, mode=mode, paths=paths,
                       scenario=scenario if isinstance(scenario, str) else None, **wall)
