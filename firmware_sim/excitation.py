"""Identification excitation superimposed on the controller's command while ACTIVE.

``python -m firmware_sim ... --excite PROGRAM`` adds a known steering (and, optionally,
drive torque) signal to whatever the control law commands, so that a drive along a path
records the vehicle's response over a band of frequencies (docs/identification.md). The
controller keeps the vehicle on its path; the excitation makes the recording informative.

Everything here is a pure function of time and state: no bus, no clock, no file I/O in
the functions the control task calls (`excitation_offsets`, `rate_limited`,
`superimpose`). `Excitation` only holds the state of one engagement (start time, the
applied offset, whether it stopped) and exposes ``reset()`` / ``step()``.

Shipped programs (`SHIPPED_PROGRAMS`); the steering amplitude is speed-scaled to a
lateral acceleration, ``amplitude(vx) = min(steer_amplitude_rad, lateral_accel_mps2 *
wheelbase_m / vx^2)`` (the kinematic steer angle of that acceleration), so one program
excites alike at 3 and at 30 m/s:

- ``chirp``: a sine whose frequency rises linearly from 0.1 to 2.0 Hz over 40 s, repeated;
  1.5 m/s^2, at most 0.03 rad.
- ``prbs``: a pseudo-random binary sequence of +-amplitude, a new bit every 0.2 s (power
  mostly below 1 / (2 x 0.2 s) = 2.5 Hz); 1.5 m/s^2, at most 0.03 rad.
- ``steps``: +amplitude for 2 s, 0 for 2 s, -amplitude for 2 s, 0 for 2 s, repeated
  (step responses); 1.5 m/s^2, at most 0.03 rad.
- ``prbs-torque``: ``prbs`` plus a drive torque PRBS of +-300 N m, a new bit every 1 s.

Every program starts 2 s after the ECU enters ACTIVE (the controller settles first).
Program files: a TOML file with the fields of `ExcitationProgram` (``kind`` one of
``chirp``, ``prbs``, ``steps``), or a CSV table ``time_s,steer_rad[,torque_nm]``
(linear interpolation, zero before the first and after the last row, ``kind = table``).

Limits: the excitation's share of the steering command changes by at most
``steer_rate_limit_rad_s`` x Ts per control cycle (default 0.5 rad/s, also when it ramps
in and out), the sum of command and excitation is clipped to the command limits, and the
ECU's final guard still checks what goes on the bus. The excitation is off outside ACTIVE
(DEGRADED, SAFE_STOP, STANDBY send the law's or the fixed reaction's command alone), and it
stops for the rest of the engagement, ramping out at the rate limit, once the lateral
deviation from the path exceeds ``lateral_error_bound_m`` (default 1.5 m).
"""
from __future__ import annotations

import bisect
import csv
import math
import tomllib
from dataclasses import dataclass, fields
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from firmware_sim.errors import ConfigError
from models.input_files import EXCITE_FILE_MAX_BYTES, InputFileError, bounded_lines, csv_number

PROGRAM_KINDS = ("chirp", "prbs", "steps", "table")
_MASK64 = (1 << 64) - 1

#: Largest value of each numeric field of a program, checked at load the same in the C ECU
#: (firmware/src/ecu_excite.c); the lower bounds are ``> 0`` or ``>= 0`` (`ExcitationProgram`).
#: Every bound keeps the step's arithmetic finite: frequencies up to the control rate's
#: Nyquist frequency (20 Hz at 25 ms), times up to an hour, torque within the command limit.
FIELD_LIMITS: dict[str, float] = {
    "steer_amplitude_rad": 0.3, "lateral_accel_mps2": 20.0, "wheelbase_m": 10.0,
    "chirp_start_hz": 20.0, "chirp_end_hz": 20.0, "chirp_period_s": 3600.0, "hold_s": 3600.0,
    "torque_hold_s": 3600.0, "torque_amplitude_nm": 3000.0, "delay_s": 3600.0,
    "steer_rate_limit_rad_s": 10.0, "lateral_error_bound_m": 100.0,
}
#: |table time_s| and |table torque_nm| at most these (steer_rad: the steering limit 0.3 rad).
TABLE_TIME_LIMIT_S = 86400.0
TABLE_TORQUE_LIMIT_NM = 3000.0
#: How a stop reason starts when the program itself failed (logged as an error).
FAILED_PREFIX = "excitation failed: "
#: Rows of a table program, in both ECUs (the C ECU holds the table in static storage).
TABLE_MAX_ROWS = 20000
#: A seed's magnitude must stay below this (the C ECU holds it in a signed 64-bit integer).
SEED_LIMIT = (1 << 63) - 1


def _finite(value: float) -> bool:
    """Whether a number is finite; an int too large for a float is not."""
    try:
        return math.isfinite(value)
    except OverflowError:
        return False


@dataclass(frozen=True)
class ExcitationProgram:
    """One excitation program (SI units; times relative to entering ACTIVE).

    Attributes:
        name: shown in logs and docs.
        kind: ``chirp``, ``prbs``, ``steps`` or ``table``.
        steer_amplitude_rad: largest steering amplitude (the cap at low speed).
        lateral_accel_mps2: speed scaling of the amplitude (see the module docstring);
            0 disables the scaling (the amplitude is ``steer_amplitude_rad`` at any speed).
        wheelbase_m: wheelbase used by that scaling.
        chirp_start_hz / chirp_end_hz / chirp_period_s: linear sweep, repeated.
        hold_s: PRBS bit length; the length of each phase of ``steps``.
        seed: PRBS seed (steering bits; the torque bits use ``seed + 1``).
        torque_amplitude_nm / torque_hold_s: drive torque PRBS (0: no torque excitation).
        delay_s: time after entering ACTIVE before the program starts.
        steer_rate_limit_rad_s: largest rate of change of the steering offset.
        lateral_error_bound_m: |e_Y| above this stops the program for this engagement.
        table_time_s / table_steer_rad / table_torque_nm: the ``table`` kind's rows.
    """

    name: str
    kind: str
    steer_amplitude_rad: float = 0.03
    lateral_accel_mps2: float = 1.5
    wheelbase_m: float = 2.8
    chirp_start_hz: float = 0.1
    chirp_end_hz: float = 2.0
    chirp_period_s: float = 40.0
    hold_s: float = 0.2
    seed: int = 0
    torque_amplitude_nm: float = 0.0
    torque_hold_s: float = 1.0
    delay_s: float = 2.0
    steer_rate_limit_rad_s: float = 0.5
    lateral_error_bound_m: float = 1.5
    table_time_s: tuple[float, ...] = ()
    table_steer_rad: tuple[float, ...] = ()
    table_torque_nm: tuple[float, ...] = ()

    def __post_init__(self) -> None:
        where = f"excitation program {self.name!r}"
        if self.kind not in PROGRAM_KINDS:
            raise ConfigError(f"{where}: kind {self.kind!r} is not one of {', '.join(PROGRAM_KINDS)}")
        positive = ("steer_amplitude_rad", "wheelbase_m", "chirp_start_hz", "chirp_end_hz",
                    "chirp_period_s", "hold_s", "torque_hold_s", "steer_rate_limit_rad_s",
                    "lateral_error_bound_m")
        non_negative = ("lateral_accel_mps2", "torque_amplitude_nm", "delay_s")
        for name in positive + non_negative:
            value = getattr(self, name)
            if not isinstance(value, (int, float)) or isinstance(value, bool) or not _finite(value) \
                    or value < 0 or (name in positive and value == 0):
                rule = "> 0" if name in positive else ">= 0"
                raise ConfigError(f"{where}: {name} must be a finite number {rule}, got {value!r}")
        if self.steer_amplitude_rad > 0.3:
            raise ConfigError(f"{where}: steer_amplitude_rad {self.steer_amplitude_rad} exceeds the "
                              "steering limit 0.3 rad")
        for name, limit in FIELD_LIMITS.items():
            if getattr(self, name) > limit:
                raise ConfigError(f"{where}: {name} {float(getattr(self, name))!r} exceeds its limit {limit!r}")
        if not (isinstance(self.seed, int) and abs(self.seed) < SEED_LIMIT):
            raise ConfigError(f"{where}: seed {self.seed!r} must be an integer of magnitude below 2^63 - 1")
        if self.chirp_end_hz < self.chirp_start_hz:
            raise ConfigError(f"{where}: chirp_end_hz {self.chirp_end_hz} < chirp_start_hz "
                              f"{self.chirp_start_hz}")
        if self.kind == "table":
            self._check_table(where)

    def _check_table(self, where: str) -> None:
        times = self.table_time_s
        if len(times) < 2:
            raise ConfigError(f"{where}: a table needs at least 2 rows, got {len(times)}")
        if len(self.table_steer_rad) != len(times) or (
                self.table_torque_nm and len(self.table_torque_nm) != len(times)):
            raise ConfigError(f"{where}: table columns differ in length")
        values = (*times, *self.table_steer_rad, *self.table_torque_nm)
        if not all(math.isfinite(v) for v in values):
            raise ConfigError(f"{where}: table holds a value that is not finite")
        if any(b <= a for a, b in zip(times, times[1:])):
            raise ConfigError(f"{where}: table time_s must increase strictly")
        if max(abs(v) for v in self.table_steer_rad) > 0.3:
            raise ConfigError(f"{where}: table steer_rad exceeds the steering limit 0.3 rad")
        if max(abs(v) for v in times) > TABLE_TIME_LIMIT_S:
            raise ConfigError(f"{where}: table time_s exceeds its limit {TABLE_TIME_LIMIT_S!r} s in magnitude")
        if self.table_torque_nm and max(abs(v) for v in self.table_torque_nm) > TABLE_TORQUE_LIMIT_NM:
            raise ConfigError(f"{where}: table torque_nm exceeds its limit {TABLE_TORQUE_LIMIT_NM!r} N m "
                              "in magnitude")


#: The shipped programs by name (``--excite chirp``); amplitudes and bands in the
#: module docstring and docs/identification.md.
SHIPPED_PROGRAMS: dict[str, ExcitationProgram] = {
    "chirp": ExcitationProgram("chirp", "chirp"),
    "prbs": ExcitationProgram("prbs", "prbs"),
    "steps": ExcitationProgram("steps", "steps", hold_s=2.0),
    "prbs-torque": ExcitationProgram("prbs-torque", "prbs", torque_amplitude_nm=300.0),
}


# ---------------------------------------------------------------- pure functions
def _bit(seed: int, index: int) -> float:
    """+1 or -1 for bit ``index`` of a seeded sequence (splitmix64 of seed and index):
    a pure function of the index, so the sequence needs no state."""
    value = (seed * 0x9E3779B97F4A7C15 + index + 1) & _MASK64
    value = ((value ^ (value >> 30)) * 0xBF58476D1CE4E5B9) & _MASK64
    value = ((value ^ (value >> 27)) * 0x94D049BB133111EB) & _MASK64
    value ^= value >> 31
    return 1.0 if value & 1 else -1.0


def steer_amplitude(program: ExcitationProgram, vx: float) -> float:
    """Steering amplitude (rad) at longitudinal speed ``vx`` (m/s), see the module docstring."""
    if program.lateral_accel_mps2 == 0.0:
        return program.steer_amplitude_rad
    speed = max(abs(vx), 1.0)
    return min(program.steer_amplitude_rad, program.lateral_accel_mps2 * program.wheelbase_m / speed ** 2)


def _table_value(times: tuple[float, ...], values: tuple[float, ...], t: float) -> float:
    if not values or t < times[0] or t > times[-1]:
        return 0.0
    k = bisect.bisect_left(times, t, 1)   # the first row from 1 on with t <= its time
    if k < len(times):
        share = (t - times[k - 1]) / (times[k] - times[k - 1])
        return values[k - 1] + share * (values[k] - values[k - 1])
    return values[-1]


def excitation_offsets(program: ExcitationProgram, time_active_s: float, vx: float) -> tuple[float, float]:
    """(steering offset rad, torque offset N m) the program asks for ``time_active_s``
    seconds after entering ACTIVE at speed ``vx``, before the rate limit."""
    t = time_active_s - program.delay_s
    if not math.isfinite(t) or t < 0.0:
        return 0.0, 0.0
    torque = 0.0
    if program.torque_amplitude_nm > 0.0:
        torque = program.torque_amplitude_nm * _bit(program.seed + 1, int(t // program.torque_hold_s))
    if program.kind == "table":
        return (_table_value(program.table_time_s, program.table_steer_rad, t),
                _table_value(program.table_time_s, program.table_torque_nm, t) + torque)
    amplitude = steer_amplitude(program, vx)
    if program.kind == "chirp":
        tau = t % program.chirp_period_s
        rate = (program.chirp_end_hz - program.chirp_start_hz) / program.chirp_period_s
        phase = 2.0 * math.pi * (program.chirp_start_hz * tau + 0.5 * rate * tau * tau)
        return amplitude * math.sin(phase), torque
    if program.kind == "prbs":
        return amplitude * _bit(program.seed, int(t // program.hold_s)), torque
    phase = int(t // program.hold_s) % 4  # steps: +, 0, -, 0
    return amplitude * (1.0, 0.0, -1.0, 0.0)[phase], torque


def rate_limited(previous: float, target: float, max_step: float) -> float:
    """``target`` reached from ``previous`` by at most ``max_step`` (>= 0) in either direction."""
    return previous + min(max(target - previous, -max_step), max_step)


def superimpose(steer_cmd: float, torque_cmd: float, steer_offset: float, torque_offset: float,
                steer_range: tuple[float, float], torque_range: tuple[float, float]) -> tuple[float, float]:
    """The law's command plus the offsets, clipped to the command limits. A non-finite
    command stays non-finite, so the final guard still refuses it (fallback)."""
    steer = steer_cmd + steer_offset
    torque = torque_cmd + torque_offset
    if math.isfinite(steer):
        steer = min(max(steer, steer_range[0]), steer_range[1])
    if math.isfinite(torque):
        torque = min(max(torque, torque_range[0]), torque_range[1])
    return steer, torque


# ---------------------------------------------------------------- state of one engagement
@dataclass(frozen=True)
class ExcitationStatus:
    """What the excitation did in one cycle (for logs and tests)."""

    steer_offset: float
    torque_offset: float
    running: bool
    stopped_reason: str | None


class Excitation:
    """State of the excitation over one engagement: ``reset()`` on entering ACTIVE from
    STANDBY (a new engagement), ``step()`` every control cycle."""

    def __init__(self, program: ExcitationProgram, period_s: float) -> None:
        self.program = program
        self._max_step = program.steer_rate_limit_rad_s * period_s
        self.reset()

    def reset(self) -> None:
        """A new engagement: the program starts again; a stop is forgotten."""
        self._started_s: float | None = None
        self._steer_offset = 0.0
        self.stopped_reason: str | None = None

    def step(self, now_s: float, active: bool, vx: float, lateral_error: float | None,
             steer_cmd: float, torque_cmd: float, steer_range: tuple[float, float],
             torque_range: tuple[float, float]) -> tuple[float, float, ExcitationStatus]:
        """The command of this cycle with the excitation superimposed (never raises).

        Args:
            now_s: the ECU's time of this control task (virtual time in lockstep).
            active: the ECU is in ACTIVE this cycle (else the excitation is off).
            vx: measured longitudinal speed (m/s), scales the amplitude.
            lateral_error: e_Y (m) of the vehicle to its path, None when unknown.
            steer_cmd, torque_cmd: the law's command.
        """
        if not active:
            self._steer_offset = 0.0
            return steer_cmd, torque_cmd, ExcitationStatus(0.0, 0.0, False, self.stopped_reason)
        if self._started_s is None:
            self._started_s = now_s
        bound = self.program.lateral_error_bound_m
        if (self.stopped_reason is None and lateral_error is not None
                and not abs(lateral_error) <= bound):
            self.stopped_reason = f"|e_Y| = {abs(lateral_error):.2f} m > {bound} m"
        target_steer, torque_offset = 0.0, 0.0
        if self.stopped_reason is None and math.isfinite(vx):
            target_steer, torque_offset = excitation_offsets(self.program, now_s - self._started_s, vx)
            if not (math.isfinite(target_steer) and math.isfinite(torque_offset)):
                # ends the excitation for this engagement; the law's command this cycle
                self.stopped_reason = (f"{FAILED_PREFIX}target not finite (steer {target_steer!r}, "
                                       f"torque {torque_offset!r})")
                return steer_cmd, torque_cmd, ExcitationStatus(self._steer_offset, 0.0, False,
                                                               self.stopped_reason)
        self._steer_offset = rate_limited(self._steer_offset, target_steer, self._max_step)
        steer, torque = superimpose(steer_cmd, torque_cmd, self._steer_offset, torque_offset,
                                    steer_range, torque_range)
        running = (self.stopped_reason is None and target_steer != 0.0) or self._steer_offset != 0.0
        return steer, torque, ExcitationStatus(self._steer_offset, torque_offset, running,
                                               self.stopped_reason)


# ---------------------------------------------------------------- loading (start-up only)
def load_program(spec: str) -> ExcitationProgram:
    """``--excite`` argument -> program: a shipped name, a ``.toml`` or a ``.csv`` file.

    Raises:
        ConfigError: unknown name, unreadable file or a field that fails its check (the
            message names the file and the field).
    """
    if spec in SHIPPED_PROGRAMS:
        return SHIPPED_PROGRAMS[spec]
    path = Path(spec)
    if path.suffix.lower() not in (".toml", ".csv"):
        raise ConfigError(f"--excite {spec!r}: not a shipped program ({', '.join(SHIPPED_PROGRAMS)}) "
                          "nor a .toml / .csv program file")
    lines = bounded_lines(path, EXCITE_FILE_MAX_BYTES)
    try:  # every line bounded as it is read; a table parsed line by line, as in the C ECU
        if path.suffix.lower() == ".csv":
            return _table_program(path, lines)
        text = "".join(lines)
    except InputFileError as error:
        raise ConfigError(f"--excite {error}") from None
    except OSError as error:
        raise ConfigError(f"--excite {path}: cannot read: {getattr(error, 'strerror', None) or error}") from error
    try:
        raw = tomllib.loads(text)
    except tomllib.TOMLDecodeError as error:
        raise ConfigError(f"--excite {path}: not valid TOML: {error}") from error
    return _toml_program(path, raw)


def program_file(spec: str) -> Path | None:
    """The file of an ``--excite`` argument (a ``.toml`` or ``.csv`` program), None for a
    shipped program's name."""
    if spec in SHIPPED_PROGRAMS or Path(spec).suffix.lower() not in (".toml", ".csv"):
        return None
    return Path(spec)


def load_excitation(spec: str | None) -> ExcitationProgram | None:
    """The ``--excite`` program (None without it); ConfigError names the file and field."""
    return None if spec is None else load_program(spec)


def _toml_program(path: Path, raw: dict[str, Any]) -> ExcitationProgram:
    known = {f.name: f for f in fields(ExcitationProgram)}
    unknown = sorted(set(raw) - set(known))
    if unknown:
        raise ConfigError(f"--excite {path}: unknown field(s) {', '.join(unknown)}; known: "
                          f"{', '.join(known)}")
    if "kind" not in raw:
        raise ConfigError(f"--excite {path}: field 'kind' missing (one of {', '.join(PROGRAM_KINDS[:3])})")
    if raw["kind"] == "table":
        raise ConfigError(f"--excite {path}: a table program is a CSV file time_s,steer_rad[,torque_nm]")
    values: dict[str, Any] = {"name": path.stem}
    for name, value in raw.items():
        if name.startswith("table_"):
            raise ConfigError(f"--excite {path}: field {name} belongs in a CSV table program")
        if name == "seed" and not (isinstance(value, int) and not isinstance(value, bool)):
            raise ConfigError(f"--excite {path}: field seed must be an integer, got {value!r}")
        values[name] = value
    try:
        return ExcitationProgram(**values)
    except TypeError as error:
        raise ConfigError(f"--excite {path}: {error}") from error


def _table_program(path: Path, lines: Iterable[str]) -> ExcitationProgram:
    """The table of a CSV program, parsed as its lines are read (one line, one row)."""
    rows = csv.reader(line.rstrip("\r\n") for line in lines)
    try:
        header = [cell.strip() for cell in next(rows, [])]
        if header not in (["time_s", "steer_rad"], ["time_s", "steer_rad", "torque_nm"]):
            raise ConfigError(f"--excite {path}: line 1: header must be time_s,steer_rad[,torque_nm], "
                              f"got {','.join(header)!r}")
        return _table_rows(path, header, enumerate(rows, start=2))
    except csv.Error as error:
        raise ConfigError(f"--excite {path}: line {rows.line_num}: not a CSV row: {error}") from None


def _table_rows(path: Path, header: list[str], numbered: Iterable[tuple[int, list[str]]]) -> ExcitationProgram:
    columns: list[list[float]] = [[] for _ in header]
    for number, row in numbered:
        if not row or not any(cell.strip() for cell in row):
            continue
        if len(row) != len(header):
            raise ConfigError(f"--excite {path}: line {number}: expected {len(header)} values, got {len(row)}")
        if len(columns[0]) == TABLE_MAX_ROWS:
            raise ConfigError(f"--excite {path}: line {number}: more than {TABLE_MAX_ROWS} rows (the table "
                              "limit of both ECUs)")
        for j, (column, cell) in enumerate(zip(columns, row), start=1):
            try:
                column.append(csv_number(cell))
            except ValueError:
                raise ConfigError(f"--excite {path}: line {number}: not a number in column {j}: {cell!r}") from None
    return ExcitationProgram(path.stem, "table", table_time_s=tuple(columns[0]),
                             table_steer_rad=tuple(columns[1]),
                             table_torque_nm=tuple(columns[2]) if len(columns) == 3 else ())


def describe(program: ExcitationProgram) -> str:
    """One line for the ECU's log."""
    if program.kind == "table":
        return (f"excitation {program.name}: table of {len(program.table_time_s)} rows over "
                f"{program.table_time_s[-1] - program.table_time_s[0]:.1f} s")
    band = {"chirp": f"{program.chirp_start_hz}-{program.chirp_end_hz} Hz sweep over {program.chirp_period_s} s",
            "prbs": f"PRBS, bit {program.hold_s} s",
            "steps": f"steps of {program.hold_s} s"}[program.kind]
    torque = (f", torque PRBS +-{program.torque_amplitude_nm} N m" if program.torque_amplitude_nm else "")
    return (f"excitation {program.name}: {band}, {program.lateral_accel_mps2} m/s^2 up to "
            f"{program.steer_amplitude_rad} rad{torque}, from {program.delay_s} s after ACTIVE, "
            f"stops at |e_Y| > {program.lateral_error_bound_m} m")
