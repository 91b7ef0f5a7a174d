"""hil.rig's hooks at unit level: what the time master is built with (nothing runs; the
ECU is `NoEcu`, so only the master's bus opens, on a private virtual channel).

Runs that use the hooks end to end: the plant restart of tests/test_hil_run.py
(``wrap_plant``), the odd frames on vcan0 of tests/test_vcan_odd_frames.py
(``send_hook``).
"""
from __future__ import annotations

import dataclasses

import can

from can_defs.frames import FrameId
from hil.faults import FaultSpec
from hil.rig import NoEcu, Rig, RigHooks
from hil.run_types import default_options
from hil.scenario import load_scenario

#: The plant silent over the first second: the fault injector drops its frames.
PLANT_SILENT = {"bus": [{"kind": "silent", "sender": "plant", "start_s": 0.0, "duration_s": 1.0}]}


def _started(hooks: RigHooks, faults: dict | None = None) -> Rig:
    """A started rig of dlc_smoke with ``hooks`` (its ECU `NoEcu`), ``faults`` injected."""
    options = default_options("lmpc", faults=None if faults is None else FaultSpec.from_mapping(faults))
    rig = Rig(load_scenario("dlc_smoke"), options, dataclasses.replace(hooks, ecu=lambda rig: NoEcu()))
    rig.start()
    return rig


def _tick_frames(rig: Rig, tick_ms: int) -> list[can.Message]:
    """The plant's and the planner's frames due at ``tick_ms``, as the master collects them."""
    return rig.plant.frames_due(tick_ms) + rig.planner.frames_due(tick_ms)


def test_without_hooks_the_master_drives_the_plant_and_sends_the_frames_as_they_are() -> None:
    rig = _started(RigHooks())
    try:
        assert rig.master.nodes[:3] == [rig.plant, rig.planner, rig.monitor]
        assert rig.master.send_hook is None
    finally:
        rig.close()


def test_wrap_plant_puts_its_node_in_the_plants_place() -> None:
    wrapped = []

    class Wrapper:
        def __init__(self, plant) -> None:
            wrapped.append(plant)

    rig = _started(RigHooks(wrap_plant=Wrapper))
    try:
        assert wrapped == [rig.plant]  # rig.plant stays the plant (its trace)
        assert isinstance(rig.master.nodes[0], Wrapper) and rig.master.nodes[1:3] == [rig.planner, rig.monitor]
    finally:
        rig.close()


def test_send_hook_sees_each_ticks_frames_after_the_fault_injector() -> None:
    seen: list[tuple[int, list[int]]] = []
    extra = can.Message(arbitration_id=0x7FF, data=b"\0", is_extended_id=False)

    def hook(tick_ms: int, frames: list[can.Message]) -> list[can.Message]:
        seen.append((tick_ms, [m.arbitration_id for m in frames]))
        return [*frames, extra]

    alone = _started(RigHooks(send_hook=hook))
    try:
        frames = _tick_frames(alone, 0)
        assert alone.master.send_hook(0, frames) == [*frames, extra]
    finally:
        alone.close()
    assert seen == [(0, [m.arbitration_id for m in frames])] and FrameId.VEH_DYN in seen[0][1]

    seen.clear()
    with_faults = _started(RigHooks(send_hook=hook), faults=PLANT_SILENT)
    try:
        out = with_faults.master.send_hook(0, _tick_frames(with_faults, 0))
    finally:
        with_faults.close()
    planner_ids = [m.arbitration_id for m in with_faults.planner.frames_due(0)]
    assert seen == [(0, planner_ids)], "the hook gets what the injector let through"
    assert [m.arbitration_id for m in out] == [*planner_ids, 0x7FF]
