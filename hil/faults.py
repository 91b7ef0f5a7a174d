"""Fault specs of the HIL's fault injection: what to inject into one run (`FaultSpec`: bus,
vehicle and sensor faults and a seed), parsed and checked from a scenario's ``[faults]``
table (or the CLI, hil/commands/faults.py); every error names its field::

    [faults]
    seed = 1                                   # default 0
    mu_step = { time_s = 4.0, mu = 0.5 }       # read by the plant node
    [faults.vehicle]
    mass_offset_kg = 200.0                     # added to the scenario's mass
    steer_offset_rad = 0.02                    # actual wheel angle = command + offset
    steer_extra_lag_s = 0.1                    # added to the actuator's time constant
    cornering_stiffness_rear_scale = 0.8       # rear tyres' cornering stiffness x 0.8
    [faults.sensor]                            # on VEH_DYN from start_s on
    start_s = 0.0
    vy_bias = 0.05                             # m/s
    vy_noise = 0.02                            # m/s, standard deviation
    yaw_rate_bias = 0.01                       # rad/s
    yaw_rate_noise = 0.005                     # rad/s
    [[faults.bus]]
    kind = "drop"                              # see BUS_KINDS
    sender = "plant"                           # plant | planner, or ids = [0x100, ...]
    start_s = 3.0
    duration_s = 0.5                           # default: to the end of the run
    rate = 0.1                                 # per-kind parameters, see BUS_KINDS

The injection itself: ``hil.fault_injector`` (bus and sensor faults on the frames the HIL
nodes send, vehicle faults in the plant it builds), ``hil.fault_vehicle`` (a misaligned
steering rack), ``hil.fault_frames`` (frames as a faulty sender makes them) and
``hil.fault_buses`` (a jump of virtual time, a lost bus).
"""
from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from can_defs.codec import decode
from can_defs.errors import CanDefsError
from can_defs.frames import FRAME_LENGTH, FrameId
from hil.errors import HilError

PLANT_IDS = (int(FrameId.VEH_DYN), int(FrameId.VEH_POSE_XY), int(FrameId.VEH_POSE_YAW))
PLANNER_IDS = (int(FrameId.PLANNER_REQ),)
SENDERS: dict[str, tuple[int, ...]] = {"plant": PLANT_IDS, "planner": PLANNER_IDS}
#: Lockstep tick (ms): delays are whole ticks.
TICK_MS = 5

#: Bus fault kinds and their parameters (name -> (default or None if required)).
BUS_KINDS: dict[str, dict[str, Any]] = {
    # Each frame starts a burst of ``burst`` lost frames (of that ID) with probability rate.
    "drop": {"rate": None, "burst": 1},
    # Every frame (rate 1) held back by delay_ms, a multiple of 5 ms.
    "delay": {"delay_ms": None},
    # The frame is sent twice (same payload: a repeated alive counter).
    "duplicate": {"rate": 1.0},
    # A sample instant's frames are held and sent after the next instant's (swap).
    "reorder": {"rate": None},
    # One random bit of the payload flipped.
    "bitflip": {"rate": None},
    # CNT stuck at the value of the first frame in the window (CRC recomputed: only the
    # counter is wrong).
    "frozen_counter": {},
    # CRC byte inverted.
    "wrong_crc": {"rate": 1.0},
    # Nothing of this sender reaches the bus.
    "silent": {},
    # A node floods ``babble_id`` with random 8-byte payloads; ``starve`` = it is a higher
    # priority ID than the victims and sends back to back, so every frame of a higher ID
    # loses arbitration for the whole window (dropped: the HIL has no TX queue).
    "babble": {"babble_id": None, "frames_per_tick": 10, "starve": True},
    # A signal rewritten to a physical value (saturated to its raw range by the encoder),
    # with a valid CRC and counter: field is the frame dataclass's field (vx, path_id, ...),
    # in the sender's frames that have it.
    "override": {"field": None, "value": None},
    # PLANNER_REQ.ENGAGE alternating every period_ms (starting with 0).
    "engage_toggle": {"period_ms": 50},
    # After each frame, a look-alike of another kind (frame_kind: fd, extended, remote or
    # error) with the same ID number; fd / extended ones carry the frame with the next
    # counter and a valid CRC (taken for a contract frame, it would make the real next
    # frame a repeat). sync_tick >= 0 adds one HIL_SYNC look-alike carrying that TICK per
    # tick (0xFFFFFFFF: the handshake); -1 none.
    "lookalike": {"frame_kind": None, "sync_tick": -1},
    # The sender's frames of age_ms earlier re-sent unchanged (old counters and CRCs), after
    # the real ones; replace = true drops the real ones (a replaying node in their place).
    "replay": {"age_ms": None, "replace": False},
}
#: Frame kinds of ``lookalike`` -> python-can message flags.
LOOKALIKE_KINDS = {"fd": "is_fd", "extended": "is_extended_id", "remote": "is_remote_frame",
                   "error": "is_error_frame"}
#: Largest lockstep TICK (32 bits).
MAX_TICK = 0xFFFFFFFF
#: Largest factor on the rear tyres' cornering stiffness (VehicleParams' own bound).
MAX_REAR_STIFFNESS_SCALE = 2.0
_COMMON = {"kind", "sender", "ids", "start_s", "duration_s"}


class FaultSpecError(HilError):
    """A fault spec (scenario ``[faults]`` table or CLI flag) is invalid; names the field."""


@dataclass(frozen=True)
class BusFault:
    """One bus fault: kind, the frame IDs it acts on, its window (s) and parameters."""

    kind: str
    ids: tuple[int, ...]
    start_s: float
    duration_s: float = math.inf
    params: Mapping[str, Any] = field(default_factory=dict)

    def active(self, tick_ms: int) -> bool:
        """True while the fault acts at virtual time ``tick_ms``."""
        t = tick_ms / 1000.0
        return self.start_s <= t < self.start_s + self.duration_s

    def describe(self) -> str:
        """Short text for tables: kind, targets, parameters, window."""
        targets = "node" if self.kind == "babble" else next(
            (name for name, ids in SENDERS.items() if ids == self.ids),
            "/".join(f"0x{i:03X}" for i in self.ids))
        params = ", ".join(f"{k}={_fmt(k, v)}" for k, v in self.params.items())
        window = (f"{self.start_s:g} s on" if math.isinf(self.duration_s)
                  else f"{self.start_s:g}-{self.start_s + self.duration_s:g} s")
        return f"{self.kind} {targets}" + (f" ({params})" if params else "") + f", {window}"


@dataclass(frozen=True)
class VehicleFaults:
    """Plant changes: mass offset (kg), steering actuator offset (rad) and extra lag (s),
    factor on the rear tyres' cornering stiffness (times the scenario plant's own
    ``VehicleParams.cornering_stiffness_rear_scale``; 1.0: unchanged)."""

    mass_offset_kg: float = 0.0
    steer_offset_rad: float = 0.0
    steer_extra_lag_s: float = 0.0
    cornering_stiffness_rear_scale: float = 1.0


@dataclass(frozen=True)
class SensorFaults:
    """Bias and Gaussian noise (standard deviation) on VEH_DYN's VY (m/s) and YAW_RATE
    (rad/s) from ``start_s`` on."""

    start_s: float = 0.0
    vy_bias: float = 0.0
    vy_noise: float = 0.0
    yaw_rate_bias: float = 0.0
    yaw_rate_noise: float = 0.0

    @property
    def any(self) -> bool:
        """True when the sensor fault changes anything."""
        return any((self.vy_bias, self.vy_noise, self.yaw_rate_bias, self.yaw_rate_noise))


@dataclass(frozen=True)
class FaultSpec:
    """Everything injected into one run (immutable; `FaultInjector` holds the state)."""

    seed: int = 0
    bus: tuple[BusFault, ...] = ()
    vehicle: VehicleFaults = VehicleFaults()
    sensor: SensorFaults = SensorFaults()

    @classmethod
    def from_mapping(cls, table: Mapping[str, Any], source: object = "faults") -> "FaultSpec":
        """Parse a ``[faults]`` table (see the module docstring); ``mu_step`` is the plant's
        and is skipped here.

        Raises:
            FaultSpecError: unknown key or kind, missing or wrong-typed parameter.
        """
        unknown = sorted(set(table) - {"seed", "bus", "vehicle", "sensor", "mu_step"})
        if unknown:
            raise FaultSpecError(f"{source}: unknown key(s) {', '.join(unknown)} in [faults]")
        seed = table.get("seed", 0)
        if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
            raise FaultSpecError(f"{source}: faults.seed = {seed!r}: must be an integer >= 0")
        bus_raw = table.get("bus", [])
        if not isinstance(bus_raw, list):
            raise FaultSpecError(f"{source}: faults.bus must be an array of tables ([[faults.bus]])")
        bus = tuple(_parse_bus(item, f"{source}: faults.bus[{i}]") for i, item in enumerate(bus_raw))
        vehicle = VehicleFaults(**_numbers(table.get("vehicle", {}), VehicleFaults, f"{source}: faults.vehicle"))
        sensor = SensorFaults(**_numbers(table.get("sensor", {}), SensorFaults, f"{source}: faults.sensor"))
        if vehicle.steer_extra_lag_s < 0 or sensor.vy_noise < 0 or sensor.yaw_rate_noise < 0:
            raise FaultSpecError(f"{source}: steer_extra_lag_s and the noise levels must be >= 0")
        if not 0.0 < vehicle.cornering_stiffness_rear_scale <= MAX_REAR_STIFFNESS_SCALE:
            raise FaultSpecError(f"{source}: faults.vehicle.cornering_stiffness_rear_scale = "
                                 f"{vehicle.cornering_stiffness_rear_scale!r}: must be in "
                                 f"(0, {MAX_REAR_STIFFNESS_SCALE:g}]")
        return cls(seed=seed, bus=bus, vehicle=vehicle, sensor=sensor)


def scenario_fault_spec(scenario: Any) -> FaultSpec | None:
    """The fault spec of a scenario's ``[faults]`` table, or None when it injects nothing
    beyond the plant's own ``mu_step`` (``python -m hil run --faults``, campaign cells).

    Raises:
        FaultSpecError: an invalid table (names the scenario file).
    """
    table = dict(scenario.faults)
    if not set(table) & {"bus", "vehicle", "sensor"}:
        return None
    return FaultSpec.from_mapping(table, scenario.source)


def _fmt(key: str, value: Any) -> str:
    if key.endswith("babble_id") and isinstance(value, int):
        return f"0x{value:03X}"
    return f"{value:g}" if isinstance(value, float) else str(value)


def _numbers(raw: Any, cls: type, where: str) -> dict[str, float]:
    if not isinstance(raw, Mapping):
        raise FaultSpecError(f"{where} must be a table")
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(raw) - names)
    if unknown:
        raise FaultSpecError(f"{where}: unknown key(s) {', '.join(unknown)}; known: {', '.join(sorted(names))}")
    out = {}
    for key, value in raw.items():
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise FaultSpecError(f"{where}.{key} = {value!r}: must be a finite number")
        out[key] = float(value)
    return out


def _parse_bus(raw: Any, where: str) -> BusFault:
    if not isinstance(raw, Mapping):
        raise FaultSpecError(f"{where} must be a table")
    kind = raw.get("kind")
    if kind not in BUS_KINDS:
        raise FaultSpecError(f"{where}.kind = {kind!r}: must be one of {', '.join(BUS_KINDS)}")
    defaults = BUS_KINDS[kind]
    unknown = sorted(set(raw) - _COMMON - set(defaults))
    if unknown:
        raise FaultSpecError(f"{where}: unknown key(s) {', '.join(unknown)} for kind {kind!r}")
    if "sender" in raw and "ids" in raw:
        raise FaultSpecError(f"{where}: give sender or ids, not both")
    if "ids" in raw:
        ids = raw["ids"]
        if not isinstance(ids, list) or not ids or not all(
                isinstance(i, int) and not isinstance(i, bool) and 0 <= i <= 0x7FF for i in ids):
            raise FaultSpecError(f"{where}.ids = {ids!r}: must be a non-empty array of 11-bit IDs")
        ids_t = tuple(ids)
    else:
        sender = raw.get("sender", "plant")
        if sender not in SENDERS:
            raise FaultSpecError(f"{where}.sender = {sender!r}: must be one of {', '.join(SENDERS)}")
        ids_t = SENDERS[sender]
    start_s = raw.get("start_s", 0.0)
    duration_s = raw.get("duration_s", math.inf)
    for name, value in (("start_s", start_s), ("duration_s", duration_s)):
        if isinstance(value, bool) or not isinstance(value, (int, float)) or value < 0 \
                or (name == "start_s" and not math.isfinite(value)):
            raise FaultSpecError(f"{where}.{name} = {value!r}: must be a number >= 0")
    params: dict[str, Any] = {}
    for key, default in defaults.items():
        if key not in raw and default is None:
            raise FaultSpecError(f"{where}: kind {kind!r} needs {key}")
        params[key] = raw.get(key, default)
    _check_params(kind, params, ids_t, where)
    return BusFault(kind, ids_t, float(start_s), float(duration_s), params)


def _check_params(kind: str, params: dict[str, Any], ids: tuple[int, ...], where: str) -> None:
    def number(key: str, low: float, high: float) -> None:
        value = params[key]
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not low <= value <= high:
            raise FaultSpecError(f"{where}.{key} = {value!r}: must be a number in [{low}, {high}]")

    for key in ("rate",):
        if key in params:
            number(key, 0.0, 1.0)
    if kind == "drop":
        number("burst", 1, 1000)
        params["burst"] = int(params["burst"])
    if kind == "delay":
        number("delay_ms", TICK_MS, 10_000)
        if params["delay_ms"] % TICK_MS:
            raise FaultSpecError(f"{where}.delay_ms = {params['delay_ms']!r}: must be a multiple of {TICK_MS}")
        params["delay_ms"] = int(params["delay_ms"])
    if kind == "babble":
        number("babble_id", 0, 0x7FF)
        number("frames_per_tick", 1, 200)
        params["babble_id"] = int(params["babble_id"])
        params["frames_per_tick"] = int(params["frames_per_tick"])
        if not isinstance(params["starve"], bool):
            raise FaultSpecError(f"{where}.starve = {params['starve']!r}: must be true or false")
    if kind == "lookalike":
        if params["frame_kind"] not in LOOKALIKE_KINDS:
            raise FaultSpecError(f"{where}.frame_kind = {params['frame_kind']!r}: must be one "
                                 f"of {', '.join(LOOKALIKE_KINDS)}")
        number("sync_tick", -1, MAX_TICK)
        params["sync_tick"] = int(params["sync_tick"])
        if params["sync_tick"] >= 0 and params["frame_kind"] not in ("fd", "extended"):
            raise FaultSpecError(f"{where}.sync_tick: only fd and extended look-alikes carry "
                                 "a payload")
    if kind == "replay":
        number("age_ms", TICK_MS, 10_000)
        if params["age_ms"] % TICK_MS:
            raise FaultSpecError(f"{where}.age_ms = {params['age_ms']!r}: must be a multiple of {TICK_MS}")
        params["age_ms"] = int(params["age_ms"])
        if not isinstance(params["replace"], bool):
            raise FaultSpecError(f"{where}.replace = {params['replace']!r}: must be true or false")
    if kind == "engage_toggle":
        number("period_ms", 25, 10_000)
        if ids != PLANNER_IDS:
            raise FaultSpecError(f"{where}: engage_toggle acts on the planner (sender = \"planner\")")
    if kind == "override":
        if not isinstance(params["field"], str):
            raise FaultSpecError(f"{where}.field = {params['field']!r}: must be a signal field name")
        frames = [frame_template(frame_id) for frame_id in ids]
        if not any(params["field"] in frame_fields(frame) for frame in frames):
            raise FaultSpecError(f"{where}.field = {params['field']!r}: not a field of "
                                 f"{', '.join(type(f).__name__ for f in frames)}")
        value = params["value"]
        if isinstance(value, bool):
            params["value"] = int(value)
        elif not isinstance(value, (int, float)) or not math.isfinite(value):
            raise FaultSpecError(f"{where}.value = {value!r}: must be a finite number")


def frame_fields(frame: Any) -> set[str]:
    return {f.name for f in dataclasses.fields(frame)}


@functools.lru_cache(maxsize=None)
def frame_template(frame_id: int) -> Any:
    """A zero frame of ``frame_id`` (to know its fields)."""
    try:
        return decode(frame_id, bytes(FRAME_LENGTH)).frame
    except CanDefsError as e:
        raise FaultSpecError(f"0x{frame_id:03X} is not a frame the HIL nodes send: {e}") from e
