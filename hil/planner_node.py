"""Planner node: PLANNER_REQ every 25 ms with the engage request, the scenario's target
speed at that instant and the scenario's reference path ID.

Like the plant node it holds no clock: the time master asks for `frames_due(tick_ms)`.
"""
from __future__ import annotations

from collections.abc import Callable

import can

from can_defs.codec import FrameSender
from can_defs.frames import PlannerReq
from hil.scenario import Scenario

#: Publishing period of PLANNER_REQ (contract: 25 ms).
PLANNER_PERIOD_MS = 25


def engage_from_start(time_s: float) -> bool:
    """Default engage schedule: automated control requested from t = 0 on."""
    return True


class PlannerNode:
    """The HIL planner.

    Args:
        scenario: speed profile and path ID.
        engage: engage request as a function of virtual time (s); default always engaged.
        path_id: override of the scenario's path ID (tests of an unknown PATH_ID).
    """

    def __init__(self, scenario: Scenario,
                 engage: Callable[[float], bool] = engage_from_start,
                 path_id: int | None = None) -> None:
        self.scenario = scenario
        self.engage = engage
        self.path_id = scenario.path_id if path_id is None else path_id
        self._sender = FrameSender()

    def frames_due(self, tick_ms: int) -> list[can.Message]:
        """PLANNER_REQ when ``tick_ms`` is a multiple of 25 ms, else nothing."""
        if tick_ms % PLANNER_PERIOD_MS:
            return []
        time_s = tick_ms / 1000.0
        request = PlannerReq(engage=bool(self.engage(time_s)),
                             target_speed=self.scenario.target_speed(time_s),
                             path_id=self.path_id)
        return [can.Message(arbitration_id=int(PlannerReq.FRAME_ID),
                            data=self._sender.encode(request), is_extended_id=False)]

    def receive(self, message: can.Message, tick_ms: int) -> None:
        """The planner listens to nothing."""

    def advance(self, tick_ms: int, dt_s: float) -> None:
        """The planner has no dynamics."""
