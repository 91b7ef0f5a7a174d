"""The fault injector of the HIL: bus faults on the frames the HIL nodes send, and vehicle
faults in the plant, both deterministic for a seed.

One mechanism for the bus: `FaultInjector.outgoing` is the time master's send hook
(``hil.time_master``), so every frame the plant and the planner send at a tick passes
through it before it reaches the bus; it may drop, hold back (delay, reorder), duplicate,
corrupt or rewrite frames and add frames of a babbling node. HIL_SYNC is the master's own
and is never touched (lockstep would just stop). Vehicle faults change the plant that the
injector builds (`FaultInjector.vehicle`): mass, an offset and extra lag of the steering
actuator (the offset: ``hil.fault_vehicle``), the rear tyres' cornering stiffness; sensor
bias / noise on VY and YAW_RATE is a rewrite of VEH_DYN on the bus (the plant's
measurement, not its state). The road friction step stays the plant's own (``[faults]
mu_step``, hil/plant_node.py).

The spec (`FaultSpec`) and its ``[faults]`` table: ``hil.faults``.

Randomness: one ``numpy.random.Generator`` per fault, spawned from the seed in spec order,
so a run is reproducible and adding a fault does not change the draws of the others.
"""
from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any

import can
import numpy as np

from can_defs.codec import decode, encode
from can_defs.crc import e2e_crc
from can_defs.frames import FRAME_LENGTH, FrameId, HilSync, VehDyn
from hil.fault_frames import FaultRecord, lookalike, rewrite_frame, standard_frame
from hil.fault_vehicle import OffsetSteeringVehicle
from hil.faults import TICK_MS, BusFault, FaultSpec, VehicleFaults, frame_fields, frame_template
from models.vehicle import FourWheelVehicle


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
            sync = standard_frame(int(FrameId.HIL_SYNC), encode(HilSync(fault.params["sync_tick"])))
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
                return [message, standard_frame(frame_id, bytes(data))]
            return [message]
        if kind == "bitflip":
            if self.rng.random() < p["rate"]:
                bit = int(self.rng.integers(0, 8 * len(data)))
                data[bit // 8] ^= 1 << (bit % 8)
                self.record.note(tick_ms)
                return [standard_frame(frame_id, bytes(data))]
            return [message]
        if kind == "wrong_crc":
            if self.rng.random() < p["rate"]:
                data[0] ^= 0xFF
                self.record.note(tick_ms)
                return [standard_frame(frame_id, bytes(data))]
            return [message]
        if kind == "frozen_counter":
            counter = self.frozen.setdefault(frame_id, (data[1] & 0x0F))
            data[1] = (data[1] & 0xF0) | counter
            data[0] = e2e_crc(frame_id, bytes(data))
            if bytes(data) != bytes(message.data):
                self.record.note(tick_ms)
            return [standard_frame(frame_id, bytes(data))]
        if kind == "override":
            if p["field"] not in frame_fields(frame_template(frame_id)):
                return [message]  # another frame of the sender
            self.record.note(tick_ms)
            return [rewrite_frame(message, {p["field"]: p["value"]})]
        if kind == "lookalike":
            self.record.note(tick_ms)
            return [message, lookalike(message, p["frame_kind"])]
        if kind == "engage_toggle":
            elapsed = tick_ms - round(self.fault.start_s * 1000)
            engage = (elapsed // p["period_ms"]) % 2 == 1
            self.record.note(tick_ms)
            return [rewrite_frame(message, {"engage": engage})]
        raise AssertionError(f"unhandled bus fault kind {kind}")  # parse refuses unknown kinds

    def _replay(self, tick_ms: int, frames: list[can.Message]) -> list[can.Message]:
        """Keep the target frames of every tick (also before the window) and, inside it,
        re-send those of ``age_ms`` earlier unchanged."""
        p = self.fault.params
        self.history[tick_ms] = [m for m in frames if m.arbitration_id in self.fault.ids]
        self.history.pop(tick_ms - p["age_ms"] - TICK_MS, None)   # older than needed
        if not self.fault.active(tick_ms):
            return frames
        replayed = [standard_frame(m.arbitration_id, bytes(m.data))
                    for m in self.history.get(tick_ms - p["age_ms"], [])]
        if replayed:
            self.record.note(tick_ms, len(replayed))
        kept = [m for m in frames if not (p["replace"] and m.arbitration_id in self.fault.ids)]
        return kept + replayed

    def _babble(self, tick_ms: int, frames: list[can.Message]) -> list[can.Message]:
        p = self.fault.params
        flood = [standard_frame(p["babble_id"], self.rng.integers(0, 256, FRAME_LENGTH, dtype=np.uint8).tobytes())
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
        return rewrite_frame(message, {"vy": dyn.vy + s.vy_bias + s.vy_noise * noise[0],
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
