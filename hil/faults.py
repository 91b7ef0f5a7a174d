"""Fault injection for the HIL: bus faults on the frames the HIL nodes send, and vehicle
faults in the plant, both deterministic for a seed.

One mechanism for the bus: `FaultInjector.outgoing` is the time master's send hook
(``hil.time_master``), so every frame the plant and the planner send at a tick passes
through it before it reaches the bus; it may drop, hold back (delay, reorder), duplicate,
corrupt or rewrite frames and add frames of a babbling node. HIL_SYNC is the master's own
and is never touched (lockstep would just stop). Vehicle faults change the plant that the
injector builds (`FaultInjector.vehicle`): mass, an offset and extra lag of the steering
actuator, the rear tyres' cornering stiffness; sensor bias / noise on VY and YAW_RATE is a rewrite of VEH_DYN on the bus (the
plant's measurement, not its state). The road friction step stays the plant's own
(``[faults] mu_step``, hil/plant_node.py).

A fault spec comes from a scenario's ``[faults]`` table (or the CLI, hil/commands/faults.py)::

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

Randomness: one ``numpy.random.Generator`` per fault, spawned from the seed in spec order,
so a run is reproducible and adding a fault does not change the draws of the others.

Two faults of the contract's revision 2 cannot be frames of the HIL nodes, so they are bus
wrappers for a run that drives the ECU itself (studies/fault_campaign.py): a jump of
virtual time (`TimeShiftingBus`, between the time master and the bus) and a lost bus
(`LosableBus`, between the ECU and the bus).
"""
from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import can
import numpy as np

from can_defs.codec import decode, encode
from can_defs.crc import e2e_crc
from can_defs.errors import CanDefsError
from can_defs.frames import FRAME_LENGTH, HANDSHAKE_TICK, FrameId, HilSync, VehDyn
from hil.errors import HilError
from models.vehicle import FourWheelVehicle, VehicleCommand

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
        frames = [_template(frame_id) for frame_id in ids]
        if not any(params["field"] in _fields(frame) for frame in frames):
            raise FaultSpecError(f"{where}.field = {params['field']!r}: not a field of "
                                 f"{', '.join(type(f).__name__ for f in frames)}")
        value = params["value"]
        if isinstance(value, bool):
            params["value"] = int(value)
        elif not isinstance(value, (int, float)) or not math.isfinite(value):
            raise FaultSpecError(f"{where}.value = {value!r}: must be a finite number")


def _fields(frame: Any) -> set[str]:
    return {f.name for f in dataclasses.fields(frame)}


@functools.lru_cache(maxsize=None)
def _template(frame_id: int) -> Any:
    """A zero frame of ``frame_id`` (to know its fields)."""
    try:
        return decode(frame_id, bytes(FRAME_LENGTH)).frame
    except CanDefsError as e:
        raise FaultSpecError(f"0x{frame_id:03X} is not a frame the HIL nodes send: {e}") from e


# --- the injector ------------------------------------------------------------------------


@dataclass
class FaultRecord:
    """What one fault did: frames it acted on and the first tick it acted (ms)."""

    description: str
    actions: int = 0
    first_action_ms: int | None = None

    def note(self, tick_ms: int, count: int = 1) -> None:
        self.actions += count
        if self.first_action_ms is None:
            self.first_action_ms = tick_ms


def _message(frame_id: int, data: bytes) -> can.Message:
    return can.Message(arbitration_id=frame_id, data=data, is_extended_id=False)


def _rewrite(message: can.Message, change: Mapping[str, Any], counter_step: int = 0) -> can.Message:
    """Same frame with fields replaced and the counter moved on by ``counter_step``, CRC
    recomputed (a faulty sender)."""
    decoded = decode(message.arbitration_id, bytes(message.data))
    frame = dataclasses.replace(decoded.frame, **change)
    return _message(message.arbitration_id, encode(frame, ((decoded.counter or 0) + counter_step) % 16))


def lookalike(message: can.Message, frame_kind: str) -> can.Message:
    """``message`` as a frame of another kind with the same ID number (contract rev. 2: never
    a contract frame): fd / extended carry the frame with the next counter (CRC valid), a
    remote frame asks for 8 bytes and carries none, an error frame keeps the bytes."""
    flag = LOOKALIKE_KINDS[frame_kind]
    if frame_kind in ("fd", "extended"):
        data = bytes(_rewrite(message, {}, counter_step=1).data) \
            if message.arbitration_id != FrameId.HIL_SYNC else bytes(message.data)
    else:
        data = b"" if frame_kind == "remote" else bytes(message.data)
    flags = {"is_extended_id": False, flag: True}
    return can.Message(arbitration_id=message.arbitration_id, data=data, dlc=FRAME_LENGTH, **flags)


class _BusFaultState:
    """One bus fault's state between ticks (held frames, bursts, its RNG)."""

    def __init__(self, fault: BusFault, rng: np.random.Generator) -> None:
        self.fault = fault
        self.rng = rng
        self.record = FaultRecord(fault.describe())
        self.held: list[tuple[int, can.Message]] = []   # (release tick, frame)
        self.burst_left: dict[int, int] = {}
        self.frozen: dict[int, int] = {}
        self.swap_pending: list[can.Message] | None = None
        self.history: dict[int, list[can.Message]] = {}   # replay: tick -> target frames

    def apply(self, tick_ms: int, frames: list[can.Message]) -> list[can.Message]:
        fault = self.fault
        out = [m for due, m in self.held if due <= tick_ms]
        self.held = [(due, m) for due, m in self.held if due > tick_ms]
        if fault.kind == "replay":
            return out + self._replay(tick_ms, frames)
        if fault.kind == "reorder" and self.swap_pending is not None and \
                any(m.arbitration_id in fault.ids for m in frames):
            # The held instant goes out after the next one: CNT k+1 arrives before k.
            late, self.swap_pending = self.swap_pending, None
            return out + frames + late
        if not fault.active(tick_ms):
            return out + frames
        if fault.kind == "babble":
            return out + self._babble(tick_ms, frames)
        if fault.kind == "lookalike" and fault.params["sync_tick"] >= 0:
            sync = _message(int(FrameId.HIL_SYNC), encode(HilSync(fault.params["sync_tick"])))
            out.append(lookalike(sync, fault.params["frame_kind"]))
            self.record.note(tick_ms)
        if fault.kind == "reorder":
            targets = [m for m in frames if m.arbitration_id in fault.ids]
            if targets and self.rng.random() < fault.params["rate"]:
                self.swap_pending = targets
                self.record.note(tick_ms, len(targets))
                return out + [m for m in frames if m.arbitration_id not in fault.ids]
            return out + frames
        for message in frames:
            if message.arbitration_id not in fault.ids:
                out.append(message)
            else:
                out.extend(self._one(tick_ms, message))
        return out

    def _one(self, tick_ms: int, message: can.Message) -> list[can.Message]:
        """The frames that go out instead of ``message`` (a frame of a target ID)."""
        kind, p, frame_id = self.fault.kind, self.fault.params, message.arbitration_id
        data = bytearray(message.data)
        if kind == "silent":
            self.record.note(tick_ms)
            return []
        if kind == "drop":
            left = self.burst_left.get(frame_id, 0)
            if left == 0 and self.rng.random() < p["rate"]:
                left = p["burst"]
            if left:
                self.burst_left[frame_id] = left - 1
                self.record.note(tick_ms)
                return []
            return [message]
        if kind == "delay":
            self.held.append((tick_ms + p["delay_ms"], message))
            self.record.note(tick_ms)
            return []
        if kind == "duplicate":
            if self.rng.random() < p["rate"]:
                self.record.note(tick_ms)
                return [message, _message(frame_id, bytes(data))]
            return [message]
        if kind == "bitflip":
            if self.rng.random() < p["rate"]:
                bit = int(self.rng.integers(0, 8 * len(data)))
                data[bit // 8] ^= 1 << (bit % 8)
                self.record.note(tick_ms)
                return [_message(frame_id, bytes(data))]
            return [message]
        if kind == "wrong_crc":
            if self.rng.random() < p["rate"]:
                data[0] ^= 0xFF
                self.record.note(tick_ms)
                return [_message(frame_id, bytes(data))]
            return [message]
        if kind == "frozen_counter":
            counter = self.frozen.setdefault(frame_id, (data[1] & 0x0F))
            data[1] = (data[1] & 0xF0) | counter
            data[0] = e2e_crc(frame_id, bytes(data))
            if bytes(data) != bytes(message.data):
                self.record.note(tick_ms)
            return [_message(frame_id, bytes(data))]
        if kind == "override":
            if p["field"] not in _fields(_template(frame_id)):
                return [message]  # another frame of the sender
            self.record.note(tick_ms)
            return [_rewrite(message, {p["field"]: p["value"]})]
        if kind == "lookalike":
            self.record.note(tick_ms)
            return [message, lookalike(message, p["frame_kind"])]
        if kind == "engage_toggle":
            elapsed = tick_ms - round(self.fault.start_s * 1000)
            engage = (elapsed // p["period_ms"]) % 2 == 1
            self.record.note(tick_ms)
            return [_rewrite(message, {"engage": engage})]
        raise AssertionError(f"unhandled bus fault kind {kind}")  # parse refuses unknown kinds

    def _replay(self, tick_ms: int, frames: list[can.Message]) -> list[can.Message]:
        """Keep the target frames of every tick (also before the window) and, inside it,
        re-send those of ``age_ms`` earlier unchanged."""
        p = self.fault.params
        self.history[tick_ms] = [m for m in frames if m.arbitration_id in self.fault.ids]
        self.history.pop(tick_ms - p["age_ms"] - TICK_MS, None)   # older than needed
        if not self.fault.active(tick_ms):
            return frames
        replayed = [_message(m.arbitration_id, bytes(m.data))
                    for m in self.history.get(tick_ms - p["age_ms"], [])]
        if replayed:
            self.record.note(tick_ms, len(replayed))
        kept = [m for m in frames if not (p["replace"] and m.arbitration_id in self.fault.ids)]
        return kept + replayed

    def _babble(self, tick_ms: int, frames: list[can.Message]) -> list[can.Message]:
        p = self.fault.params
        flood = [_message(p["babble_id"], self.rng.integers(0, 256, FRAME_LENGTH, dtype=np.uint8).tobytes())
                 for _ in range(p["frames_per_tick"])]
        self.record.note(tick_ms, len(flood))
        if p["starve"]:
            # Lower priority (higher ID) frames never win arbitration against the flood.
            return flood + [m for m in frames if m.arbitration_id < p["babble_id"]]
        return flood + frames


class FaultInjector:
    """The state of one run's faults; `outgoing` is the time master's send hook.

    Args:
        spec: what to inject.
    """

    def __init__(self, spec: FaultSpec) -> None:
        self.spec = spec
        children = np.random.SeedSequence(spec.seed).spawn(len(spec.bus) + 1)
        self._bus = [_BusFaultState(f, np.random.default_rng(s)) for f, s in zip(spec.bus, children)]
        self._sensor_rng = np.random.default_rng(children[-1])
        self.sensor_record = FaultRecord("sensor bias/noise on VY, YAW_RATE")

    def outgoing(self, tick_ms: int, frames: Sequence[can.Message]) -> list[can.Message]:
        """The frames that reach the bus at ``tick_ms`` instead of ``frames`` (in order)."""
        out = [self._sensor(tick_ms, m) for m in frames]
        for state in self._bus:
            out = state.apply(tick_ms, out)
        return out

    def _sensor(self, tick_ms: int, message: can.Message) -> can.Message:
        s = self.spec.sensor
        if not s.any or message.arbitration_id != FrameId.VEH_DYN or tick_ms < s.start_s * 1000:
            return message
        dyn = decode(message.arbitration_id, bytes(message.data)).frame
        assert isinstance(dyn, VehDyn)
        noise = self._sensor_rng.standard_normal(2)
        self.sensor_record.note(tick_ms)
        return _rewrite(message, {"vy": dyn.vy + s.vy_bias + s.vy_noise * noise[0],
                                  "yaw_rate": dyn.yaw_rate + s.yaw_rate_bias + s.yaw_rate_noise * noise[1]})

    def vehicle(self, scenario: Any) -> FourWheelVehicle | None:
        """The plant's ``models.vehicle.FourWheelVehicle`` for ``scenario`` with the
        vehicle faults and the scenario's disturbances (None when there are no vehicle
        faults: the plant builds its own, ``Scenario.vehicle``)."""
        v = self.spec.vehicle
        if v == VehicleFaults():
            return None
        params = scenario.vehicle_params()
        params = dataclasses.replace(
            params, mass=params.mass + v.mass_offset_kg,
            steer_time_constant=params.steer_time_constant + v.steer_extra_lag_s,
            cornering_stiffness_rear_scale=params.cornering_stiffness_rear_scale * v.cornering_stiffness_rear_scale)
        if v.steer_offset_rad == 0.0:
            return scenario.vehicle(params)
        return OffsetSteeringVehicle(params, v.steer_offset_rad, disturbances=scenario.disturbances)

    def records(self) -> list[FaultRecord]:
        """What each fault did (bus faults in spec order, then the sensor fault if any)."""
        out = [state.record for state in self._bus]
        if self.spec.sensor.any:
            out.append(self.sensor_record)
        return out

    @property
    def first_action_ms(self) -> int | None:
        """Earliest tick at which any bus or sensor fault acted (None: none did)."""
        ticks = [r.first_action_ms for r in self.records() if r.first_action_ms is not None]
        return min(ticks) if ticks else None


class OffsetSteeringVehicle(FourWheelVehicle):
    """A vehicle whose steering actuator settles at command + offset (a misaligned rack);
    the measured STEER_ANGLE is the true wheel angle, offset included. (A scenario's
    ``[disturbances] steer_offset_rad`` is the other kind: the wheels sit off the
    actuator's state, which STEER_ANGLE reports, so the offset is not seen.)"""

    def __init__(self, params: Any, offset_rad: float, disturbances: Any = None) -> None:
        super().__init__(params, disturbances=disturbances)
        self.steer_offset_rad = offset_rad

    def step(self, command: VehicleCommand, dt: float) -> Any:
        """Step with the offset added to the steering command (the model saturates it)."""
        return super().step(VehicleCommand(drive_torque=command.drive_torque,
                                           steer_angle=command.steer_angle + self.steer_offset_rad), dt)


# --- bus wrappers: faults of the time base and of the ECU's own bus ----------------------


class TimeShiftingBus:
    """The time master's bus with virtual time jumping ahead: from master TICK
    ``from_tick_ms`` on, every HIL_SYNC goes out with TICK + ``ahead_ms`` and every
    HIL_SYNC_ACK of such a TICK comes back as the master's TICK, so the master and the
    plant run on while the ECU sees its clock jump once (contract rev. 2, "jump of
    virtual time"). The handshake passes unchanged.

    Args:
        bus: the master's open bus (shut down with this wrapper).
        from_tick_ms: first master TICK sent shifted (ms, a multiple of 5).
        ahead_ms: how far the ECU's clock jumps (ms, a multiple of 5).
    """

    def __init__(self, bus: can.BusABC, from_tick_ms: int, ahead_ms: int) -> None:
        self.bus = bus
        self.from_tick_ms = from_tick_ms
        self.ahead_ms = ahead_ms
        self.record = FaultRecord(f"HIL_SYNC {ahead_ms / 1000:g} s ahead from "
                                  f"{from_tick_ms / 1000:g} s on (virtual time jumps once)")

    @staticmethod
    def _tick(message: can.Message, frame_id: FrameId) -> int | None:
        if (message.arbitration_id != frame_id or message.is_extended_id
                or len(message.data) != FRAME_LENGTH):
            return None
        return int.from_bytes(bytes(message.data[0:4]), "little")

    def send(self, message: can.Message, timeout: float | None = None) -> None:
        """Send, HIL_SYNC of a TICK at or after ``from_tick_ms`` shifted ahead."""
        tick = self._tick(message, FrameId.HIL_SYNC)
        if tick is not None and tick != HANDSHAKE_TICK and tick >= self.from_tick_ms:
            self.record.note(tick)
            message = _message(int(FrameId.HIL_SYNC), encode(HilSync(tick + self.ahead_ms)))
        self.bus.send(message, timeout)

    def recv(self, timeout: float | None = None) -> can.Message | None:
        """Receive, an ACK of a shifted TICK shifted back to the master's TICK."""
        message = self.bus.recv(timeout)
        tick = None if message is None else self._tick(message, FrameId.HIL_SYNC_ACK)
        if tick is not None and tick != HANDSHAKE_TICK and tick >= self.from_tick_ms + self.ahead_ms:
            data = bytearray(message.data)
            data[0:4] = (tick - self.ahead_ms).to_bytes(4, "little")
            message = _message(int(FrameId.HIL_SYNC_ACK), bytes(data))
        return message

    def shutdown(self) -> None:
        self.bus.shutdown()


class BusDownError(can.CanOperationError):
    """What a lost bus raises on every receive and send (an interface that went down)."""


class LosableBus:
    """The ECU's bus that can go away: after `lose`, every receive and send raises
    `BusDownError` (as python-can's SocketCAN bus does when the interface goes down), and
    the receive calls made meanwhile are counted (a busy loop shows as thousands).

    Args:
        bus: the ECU's open bus (shut down with this wrapper).
    """

    def __init__(self, bus: can.BusABC) -> None:
        self.bus = bus
        self.lost = False
        self.calls_while_lost = 0

    def lose(self) -> None:
        """From now on the bus is gone."""
        self.lost = True

    def _check(self) -> None:
        if self.lost:
            self.calls_while_lost += 1
            raise BusDownError("CAN interface down (fault injection: lost bus)")

    def recv(self, timeout: float | None = None) -> can.Message | None:
        self._check()
        return self.bus.recv(timeout)

    def send(self, message: can.Message, timeout: float | None = None) -> None:
        self._check()
        self.bus.send(message, timeout)

    def shutdown(self) -> None:
        self.bus.shutdown()
