"""Reading recorded CAN logs: every frame of a log of any format python-can reads.

The one reader of log files for the tools above it (``hil.logio`` for replay, decode and
play; ``models.can_log_data`` for identification), so that both see the same frames:

- `read_log_frames(path)`: the frames in file order (`LogFrames`) through python-can's
  readers (``can.LogReader`` picks one by suffix: ``.asc``, ``.blf``, ``.csv``, ``.db``,
  ``.trc`` and their ``.gz`` forms, and ``.mf4``, ASAM MDF 4 through asammdf, which is
  compressed inside and has no ``.gz`` form). Candump ``-L`` files (``.log``,
  ``.log.gz``) are checked line by line first (`CANDUMP_LINE`): a line that is not a
  frame is skipped, counted and quoted, and only the good lines go to python-can's
  ``CanutilsLogReader``. Each frame keeps the direction its format records
  (``is_rx``; CSV and SQLite record none: Rx); no user here selects frames by it.
- Damage never raises a parser's traceback: a truncated or corrupt gzip stream keeps the
  text before the damage; a last candump line without its line end (a recorder killed
  mid-write) is dropped; a cut BLF (`blf_cut`: an object running past the end of the
  file) or ASC (`asc_cut`: a last line without its end, no "End TriggerBlock") keeps the
  frames before the cut; a reader that fails in the middle of a file ends the read there.
  Each case is a warning and marks the read incomplete. Only an unknown suffix
  (`LogFormatError`) or a missing, unreadable or frameless file (`LogReadError`) is an
  error; a cut MF4 is one: its blocks are written when the recording stops, and asammdf
  opens only a whole file.
- `frame_kind(message)`: data / CAN FD / remote / error, the one test of what a frame is;
  `is_contract_data_frame`: the only kind the contract's frames are (classic CAN data
  frame, 11-bit ID).

python-can is imported inside the readers only: importing this module costs nothing, and
the packages that use it keep python-can out of their run time.
"""
from __future__ import annotations

import enum
import gc
import io
import re
import struct
import sys
import zlib
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path, PurePath
from typing import TYPE_CHECKING, Any, Callable, Iterator

from can_defs.errors import CanDefsError

if TYPE_CHECKING:
    import can

#: Suffixes of the log formats read (and recorded), all through python-can (``.mf4`` through
#: asammdf, a dependency of the project).
SUPPORTED_SUFFIXES: tuple[str, ...] = (".log", ".asc", ".blf", ".csv", ".db", ".trc", ".mf4")

#: Formats without a ``.gz`` form: MF4 compresses its own data blocks, and python-can's
#: MF4 writer and reader need a file they can seek in.
NO_GZIP_SUFFIXES: tuple[str, ...] = (".mf4",)

#: The formats in words, for help texts.
FORMATS_TEXT = ".log candump, .asc, .blf, .csv, .db, .trc (optionally .gz), .mf4"

#: The header python-can writes to a CSV log (``can.CSVWriter``).
PYTHON_CAN_CSV_HEADER = "timestamp,arbitration_id,extended,remote,error,dlc,data"

#: A candump -L line: "(timestamp) channel ID#DATA [R|T]", DATA in hex bytes, "R[dlc]"
#: for a remote frame, or "#" + flags nibble + hex bytes for CAN FD. Anything else in a
#: ``.log`` is damage.
CANDUMP_LINE = re.compile(
    r"^\(\d+(\.\d+)?\)\s+\S+\s+([0-9A-Fa-f]{3}|[0-9A-Fa-f]{8})#"
    r"(([0-9A-Fa-f]{2})*|[Rr]\d*|#[0-9A-Fa-f]([0-9A-Fa-f]{2})*)(\s+[RTrt])?$")

#: How many damaged line numbers a warning quotes.
_QUOTED_LINES = 5

#: Compressed bytes inflated per step: a damaged stream fails at the step that holds the
#: damage, and the text of the steps before it is kept.
_INFLATE_STEP = 1 << 16

#: Bytes read for a CSV header: a header line is far shorter.
_HEADER_BYTES = 1 << 16


class LogFileError(CanDefsError):
    """A log file cannot be used (the message names the file and what is wrong)."""


class LogFormatError(LogFileError):
    """The file suffix names no log format python-can reads."""


class LogReadError(LogFileError):
    """The log is missing, unreadable, or holds no readable frame."""


class FrameKind(enum.Enum):
    """What a frame of a log is."""

    DATA = "data"        # classic CAN data frame (8 bytes at most)
    FD = "fd"            # CAN FD data frame
    REMOTE = "remote"    # remote request: an ID, no data
    ERROR = "error"      # error frame: neither ID nor data


def frame_kind(message: can.Message) -> FrameKind:
    """The kind of a python-can message (an error frame first: its other flags mean nothing)."""
    if message.is_error_frame:
        return FrameKind.ERROR
    if message.is_remote_frame:
        return FrameKind.REMOTE
    if message.is_fd:
        return FrameKind.FD
    return FrameKind.DATA


def is_contract_data_frame(message: can.Message) -> bool:
    """A classic CAN data frame with an 11-bit ID: the only kind the contract's frames are."""
    return frame_kind(message) is FrameKind.DATA and not message.is_extended_id


@dataclass
class LogFrames:
    """Frames of one log in file order and what reading them found.

    ``messages`` holds every frame read (error, remote, CAN FD and foreign frames
    included); ``complete`` is False when anything was skipped or the read stopped early,
    and ``warnings`` say what (one sentence each, without the file name).
    """

    path: Path
    messages: list[can.Message]
    complete: bool = True
    warnings: list[str] = field(default_factory=list)
    skipped_lines: int = 0

    def damaged(self, warning: str) -> None:
        """Record what was lost: the read is incomplete."""
        self.complete = False
        self.warnings.append(warning)


def log_suffix(path: str | Path) -> str:
    """Format suffix of a log path, looking through ``.gz`` (``run.log.gz`` -> ``.log``)."""
    suffixes = [s.lower() for s in PurePath(path).suffixes]
    if suffixes and suffixes[-1] == ".gz":
        return suffixes[-2] if len(suffixes) >= 2 else ""
    return suffixes[-1] if suffixes else ""


def check_log_suffix(path: str | Path) -> str:
    """The format suffix of ``path``; `LogFormatError` when python-can has no reader for it."""
    suffix = log_suffix(path)
    if suffix not in SUPPORTED_SUFFIXES:
        raise LogFormatError(
            f"{path}: unknown log format {suffix or '(no suffix)'!r}; supported: "
            f"{FORMATS_TEXT}")
    if suffix in NO_GZIP_SUFFIXES and _is_gzip(PurePath(path)):
        raise LogFormatError(f"{path}: a {suffix} log is compressed inside and has no .gz "
                             f"form; use {suffix}")
    return suffix


def read_log_frames(path: str | Path,
                    check_file: Callable[[Path], None] | None = None) -> LogFrames:
    """Every frame of a log, with warnings (see the module docstring).

    Args:
        path: the log file.
        check_file: called with the path of an existing log before any reader opens it:
            the caller's own refusals (a bound on the size, before a reader takes the file
            whole), raising the caller's error.

    Raises:
        LogFormatError: the suffix names no supported format.
        LogReadError: the file is missing or unreadable, or no frame could be read.
    """
    path = Path(path)
    suffix = check_log_suffix(path)
    if not path.is_file():
        raise LogReadError(f"{path}: no such log file")
    if check_file is not None:
        check_file(path)
    frames = LogFrames(path=path, messages=[])
    if suffix == ".log":
        _read_candump(frames)
    else:
        _read_with_python_can(frames)
    if not frames.messages:
        problem = "; ".join(frames.warnings) or "the file holds no frame"
        raise LogReadError(f"{path}: no readable CAN frame ({problem})")
    return frames


def _inflate(raw: bytes) -> tuple[bytes, str | None]:
    """Decompress a gzip stream as far as it goes: the bytes, and what was wrong with the
    stream (None when it was whole)."""
    inflater = zlib.decompressobj(wbits=31)  # 31: gzip header and trailer
    chunks: list[bytes] = []
    problem = None
    try:
        for start in range(0, len(raw), _INFLATE_STEP):
            chunks.append(inflater.decompress(raw[start:start + _INFLATE_STEP]))
            if inflater.eof:
                break
        if not inflater.eof:
            problem = "the gzip stream is truncated"
    except zlib.error as error:
        problem = f"the gzip stream is corrupt ({error})"
    return b"".join(chunks), problem


def _is_gzip(path: PurePath) -> bool:
    return path.suffix.lower() == ".gz"


def read_log_text(path: Path) -> tuple[str, str | None]:
    """Text of a (possibly gzip-compressed) text log and what was wrong with the
    compression, if anything. A truncated or damaged gzip stream yields the text that
    decompressed before the damage, up to its last whole line.

    Raises:
        OSError: the file cannot be read.
    """
    raw = path.read_bytes()
    if not _is_gzip(path):
        return raw.decode("ascii", errors="replace"), None
    inflated, problem = _inflate(raw)
    text = inflated.decode("ascii", errors="replace")
    if problem is not None and not text.endswith("\n"):
        text = text[: text.rfind("\n") + 1]  # the last line is cut: drop it
    return text, problem


def csv_header(path: Path) -> str:
    """First line of a (possibly gzip-compressed) CSV, stripped.

    Raises:
        OSError: the file cannot be read.
    """
    with open(path, "rb") as handle:
        raw = handle.read(_HEADER_BYTES)
    if _is_gzip(path):
        raw, _ = _inflate(raw)  # only the head was read: the stream is "truncated"
    first = raw.decode("utf-8", errors="replace").split("\n", 1)[0].split("\r", 1)[0]
    return first.strip()


def is_python_can_csv(path: Path) -> bool:
    """A python-can CSV log (its fixed header), as opposed to a named-column data CSV."""
    return csv_header(path).replace(" ", "") == PYTHON_CAN_CSV_HEADER


def _text_of(frames: LogFrames) -> tuple[str, str | None]:
    """`read_log_text` of the log, a damaged gzip stream told as a warning."""
    try:
        text, problem = read_log_text(frames.path)
    except OSError as error:
        raise LogReadError(f"{frames.path}: cannot read: {error}") from error
    if problem is not None:
        frames.damaged(f"{problem}: the frames before the damage are kept")
    return text, problem


def _read_candump(frames: LogFrames) -> None:
    """candump ``-L`` lines: keep the well-formed ones, count and quote the others, then
    parse the kept lines with python-can's ``CanutilsLogReader``."""
    import can

    text, problem = _text_of(frames)
    lines = text.splitlines()
    if problem is None and lines and text and not text.endswith(("\n", "\r")):
        # candump and python-can end every line: a last line without its end was cut
        # while being written, and may still look like a (shorter) frame.
        frames.damaged(f"the last line ({len(lines)}) is incomplete (no line end): "
                       "dropped; the file was cut while being written")
        lines.pop()
    good: list[str] = []
    damaged: list[int] = []
    for number, line in enumerate(lines, start=1):
        stripped = line.strip()
        if not stripped:
            continue
        if CANDUMP_LINE.match(stripped):
            good.append(stripped)
        else:
            damaged.append(number)
    if damaged:
        frames.skipped_lines = len(damaged)
        quoted = ", ".join(str(n) for n in damaged[:_QUOTED_LINES])
        more = "" if len(damaged) <= _QUOTED_LINES else f", ... ({len(damaged)} in all)"
        frames.damaged(f"{len(damaged)} line(s) that are not candump frames were "
                       f"skipped: line {quoted}{more}")
    _drain(can.CanutilsLogReader(io.StringIO("\n".join(good))), frames)


def _read_with_python_can(frames: LogFrames) -> None:
    import can

    path = frames.path
    suffix = log_suffix(path)
    if suffix == ".blf":
        _read_blf(frames)
        return
    if suffix == ".asc":
        _read_asc(frames)
        return
    if suffix == ".mf4":
        _read_mf4(frames)
        return
    try:
        reader = can.LogReader(path)
    except (OSError, ValueError, EOFError) as error:
        raise LogReadError(f"{path}: cannot open: {error}") from error
    except Exception as error:  # noqa: BLE001 - a reader's own parse error on the header
        raise LogReadError(f"{path}: not a readable {log_suffix(path)} log: "
                           f"{type(error).__name__}: {error}") from error
    _drain(reader, frames)


def _drain(reader: Any, frames: LogFrames) -> None:
    """Iterate a python-can reader to its end or to its first failure.

    The readers are third-party parsers of untrusted files and raise whatever their
    parsing hits (ValueError, struct.error, zlib.error, IndexError, their own errors); any
    of these ends the read with the frames so far and a warning.
    """
    try:
        for message in reader:
            frames.messages.append(message)
    except Exception as error:  # noqa: BLE001 - see the docstring
        frames.damaged(
            f"reading stopped after {len(frames.messages)} frame(s): the file is truncated "
            f"or corrupt ({type(error).__name__}: {error})")
    finally:
        try:
            reader.stop()
        except Exception:  # noqa: BLE001 - closing a damaged file is best effort
            pass


# --- cut-off Vector logs ----------------------------------------------------------------
# python-can's BLF and ASC readers end quietly at a cut: a BLF container that runs past the
# end of the file yields the frames of its first part, an ASC file simply stops. The checks
# below find the cut from the file's own structure, so the read is marked incomplete.

#: BLF layout (python-can ``can.io.blf``): the file header's fields up to the object count,
#: the header of every object, and the object type of a log container.
_BLF_FILE_HEADER = struct.Struct("<4sLBBBBBBBBQQL")
_BLF_OBJECT_HEADER = struct.Struct("<4sHHLL")
_BLF_LOG_CONTAINER = 10
#: Bytes of a log container before its data (object header, then method and sizes).
_BLF_CONTAINER_DATA_OFFSET = _BLF_OBJECT_HEADER.size + 16

#: ASC trigger blocks: every "Begin Triggerblock" is closed by an "End TriggerBlock".
_ASC_BEGIN = re.compile(r"^\s*begin\s+triggerblock\b", re.IGNORECASE | re.MULTILINE)
_ASC_END = re.compile(r"^\s*end\s+triggerblock\b", re.IGNORECASE | re.MULTILINE)


@dataclass(frozen=True)
class BlfCut:
    """Where a BLF file is cut: the bytes the reader may take (``readable``: whole objects,
    and the first part of a cut container, whose whole frames python-can yields), and what
    is wrong (None for a whole file)."""

    readable: int
    problem: str | None


def blf_cut(raw: bytes) -> BlfCut:
    """Walk the objects of a BLF file (uncompressed bytes) and find a cut.

    A file is cut when an object (a log container, usually) runs past the end of the file,
    when the file ends inside an object header, or when the file header's size is larger
    than the file. A header that was never finalised (size 144 bytes and no object count:
    the writer was not closed) is told as well. A file that does not start like a BLF is
    left to python-can's reader, which refuses it.
    """
    if len(raw) < _BLF_FILE_HEADER.size or raw[:4] != b"LOGG":
        return BlfCut(len(raw), None)
    header = _BLF_FILE_HEADER.unpack_from(raw)
    header_size, file_size, object_count = header[1], header[10], header[12]
    position = header_size
    objects = 0
    problem = None
    readable = len(raw)
    while position < len(raw):
        remaining = len(raw) - position
        if remaining < _BLF_OBJECT_HEADER.size:
            problem = (f"the file ends inside the header of object {objects + 1} (at byte "
                       f"{position})")
            readable = position
            break
        signature, _, _, object_size, object_type = _BLF_OBJECT_HEADER.unpack_from(raw, position)
        if signature != b"LOBJ" or object_size < _BLF_OBJECT_HEADER.size:
            break  # corrupt, not cut: python-can's reader stops there with its own error
        if object_size > remaining:
            kind = "log container" if object_type == _BLF_LOG_CONTAINER else f"object (type {object_type})"
            problem = (f"its last {kind} (at byte {position}) runs {object_size - remaining} "
                       "bytes past the end of the file")
            # a container's first part still holds whole frames; another object none
            whole_head = object_type == _BLF_LOG_CONTAINER and remaining > _BLF_CONTAINER_DATA_OFFSET
            readable = len(raw) if whole_head else position
            break
        objects += 1
        position += object_size + object_size % 4  # objects are padded as python-can writes
    if problem is None and file_size > len(raw):
        problem = f"the file header says {file_size} bytes"
    if problem is not None:
        said = (f"; the file header says {file_size} bytes and {object_count} frame objects"
                if file_size > header_size else "")
        return BlfCut(readable, f"the BLF file is truncated ({len(raw)} bytes): {problem}{said}")
    if file_size <= header_size and object_count == 0 and objects:
        return BlfCut(len(raw), "the BLF file header was never completed (size and object "
                                "count 0: the writer was not closed): the log may end early")
    return BlfCut(len(raw), None)


def _read_blf(frames: LogFrames) -> None:
    """A BLF file (optionally gzip-compressed) through python-can's ``BLFReader``, after
    `blf_cut` has looked for a cut."""
    import can

    path = frames.path
    try:
        raw = path.read_bytes()
    except OSError as error:
        raise LogReadError(f"{path}: cannot read: {error}") from error
    if _is_gzip(path):
        raw, problem = _inflate(raw)
        if problem is not None:
            frames.damaged(f"{problem}: the frames before the damage are kept")
    cut = blf_cut(raw)
    if cut.problem is not None:
        frames.damaged(f"{cut.problem}: the frames before the cut are kept")
    try:
        reader = can.BLFReader(io.BytesIO(raw[:cut.readable]))
    except Exception as error:  # noqa: BLE001 - the reader's own parse error on the header
        raise LogReadError(f"{path}: not a readable .blf log: "
                           f"{type(error).__name__}: {error}") from error
    _drain(reader, frames)


def asc_cut(text: str) -> tuple[str, list[str]]:
    """The text of an ASC file python-can may read, and what shows it was cut: a last line
    without its line end (dropped: it may still parse as a shorter frame) and a trigger
    block without its "End TriggerBlock" line."""
    problems = []
    if text and not text.endswith(("\n", "\r")):
        cut_at = max(text.rfind("\n"), text.rfind("\r")) + 1
        line = text[:cut_at].count("\n") + 1
        problems.append(f"the last line ({line}) is incomplete (no line end): dropped")
        text = text[:cut_at]
    begins, ends = len(_ASC_BEGIN.findall(text)), len(_ASC_END.findall(text))
    if begins > ends:
        problems.append("the last trigger block has no 'End TriggerBlock' line: the file ends "
                        "early (cut, or the writer was not closed)")
    return text, problems


def _read_asc(frames: LogFrames) -> None:
    """An ASC file (optionally gzip-compressed) through python-can's ``ASCReader``, after
    `asc_cut` has looked for a cut."""
    import can

    text, problem = _text_of(frames)
    text, problems = asc_cut(text)
    for found in problems:
        frames.damaged(f"{found}; the frames before the cut are kept")
    try:
        reader = can.ASCReader(io.StringIO(text))
    except Exception as error:  # noqa: BLE001 - the reader's own parse error
        raise LogReadError(f"{frames.path}: not a readable .asc log: "
                           f"{type(error).__name__}: {error}") from error
    _drain(reader, frames)


# --- MF4 (ASAM MDF 4) -------------------------------------------------------------------

@contextmanager
def _quiet_mdf_finalizer() -> Iterator[None]:
    """asammdf's ``MDF4.__del__`` fails on an object whose opening failed and prints an
    "Exception ignored" traceback when it is collected; an unreadable file is one error
    line here, so only that report is dropped while the reader is opened."""
    previous = sys.unraisablehook

    def hook(unraisable: Any) -> None:
        if getattr(unraisable.object, "__qualname__", "") != "MDF4.__del__":
            previous(unraisable)

    sys.unraisablehook = hook
    try:
        yield
    finally:
        sys.unraisablehook = previous


def _read_mf4(frames: LogFrames) -> None:
    """An MF4 file through python-can's ``MF4Reader`` (asammdf). asammdf refuses a cut or
    unfinished file whole (its blocks are written when the recording stops): an error."""
    import can

    path = frames.path
    failure: Exception | None = None
    with _quiet_mdf_finalizer():
        try:
            reader = can.MF4Reader(path)
        except NotImplementedError as error:  # python-can without asammdf
            raise LogReadError(f"{path}: reading .mf4 needs the asammdf package "
                               "(pip install asammdf)") from error
        except Exception as error:  # noqa: BLE001 - asammdf's own errors on a bad file
            failure = error.with_traceback(None)
        if failure is not None:
            gc.collect()  # the half-opened MDF4 (in a reference cycle) goes now, quietly
    if failure is not None:
        raise LogReadError(
            f"{path}: not a readable .mf4 log (cut, or not closed by its writer: an MF4 is "
            f"complete only once the recording stopped): {type(failure).__name__}: "
            f"{failure}") from failure
    _drain(reader, frames)
