"""Typed frames of the CAN contract (docs/can-contract.md, "Frames" and "Signals").

One frozen dataclass per frame, holding physical values in SI units; field names are the
DBC signal names in snake case (``YAW_RATE`` -> ``yaw_rate``). The E2E signals CRC and
CNT are not fields: the codec fills and checks them.
"""
from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum
from typing import ClassVar

FRAME_LENGTH = 8
"""Every frame of the contract has an 8-byte payload."""

HANDSHAKE_TICK = 0xFFFFFFFF
"""TICK of the lockstep start-up handshake (HIL_SYNC / HIL_SYNC_ACK)."""

TICK_STEP_MS = 5
"""Lockstep virtual time advances in ticks of 5 ms; any other TICK is refused."""


class FrameId(IntEnum):
    """11-bit arbitration IDs of the contract's frames."""

    HIL_SYNC = 0x080
    HIL_SYNC_ACK = 0x081
    VEH_DYN = 0x100
    VEH_POSE_XY = 0x101
    VEH_POSE_YAW = 0x102
    PLANNER_REQ = 0x110
    STEER_TORQUE_CMD = 0x200
    CTRL_DIAG = 0x201


HIL_FRAME_IDS: frozenset[FrameId] = frozenset({FrameId.HIL_SYNC, FrameId.HIL_SYNC_ACK})
"""Lockstep frames: no CRC / CNT; checked by length and TICK only."""

E2E_FRAME_IDS: frozenset[FrameId] = frozenset(FrameId) - HIL_FRAME_IDS
"""Frames carrying CRC (byte 0) and CNT (bits 8..11)."""

PLANT_SAMPLE_FRAME_IDS: tuple[FrameId, ...] = (
    FrameId.VEH_DYN, FrameId.VEH_POSE_XY, FrameId.VEH_POSE_YAW)
"""The three plant frames of one sample instant (they carry the same CNT)."""


class CtrlMode(IntEnum):
    """STEER_TORQUE_CMD.CTRL_MODE: mode of the controller ECU."""

    INIT = 0
    STANDBY = 1
    ACTIVE = 2
    DEGRADED = 3
    SAFE_STOP = 4
    FAULT = 5


class QpStatus(IntEnum):
    """CTRL_DIAG.QP_STATUS: optimiser status of the control cycle; also the control law's
    own solver outcome (``controller.base.SolverStatus`` is this enum)."""

    SOLVED = 0
    SOLVED_INACCURATE = 1
    MAX_ITERATIONS = 2
    INFEASIBLE = 3
    NUMERICAL_ERROR = 4
    NOT_RUN = 15


@dataclass(frozen=True, slots=True)
class HilSync:
    """Time master -> ECU: run everything due up to virtual time `tick` [ms]."""

    FRAME_ID: ClassVar[FrameId] = FrameId.HIL_SYNC
    tick: int


@dataclass(frozen=True, slots=True)
class HilSyncAck:
    """ECU -> time master: tick `tick` [ms] completed."""

    FRAME_ID: ClassVar[FrameId] = FrameId.HIL_SYNC_ACK
    tick: int


@dataclass(frozen=True, slots=True)
class VehDyn:
    """Plant -> ECU: body-frame velocities of the centre of gravity [m/s] and yaw rate
    [rad/s, counter-clockwise positive]."""

    FRAME_ID: ClassVar[FrameId] = FrameId.VEH_DYN
    vx: float
    vy: float
    yaw_rate: float


@dataclass(frozen=True, slots=True)
class VehPoseXY:
    """Plant -> ECU: global position of the centre of gravity [m]."""

    FRAME_ID: ClassVar[FrameId] = FrameId.VEH_POSE_XY
    pos_x: float
    pos_y: float


@dataclass(frozen=True, slots=True)
class VehPoseYaw:
    """Plant -> ECU: heading [rad, wrapped to [-pi, pi)], measured front wheel angle [rad]
    and measured total wheel torque [N m]."""

    FRAME_ID: ClassVar[FrameId] = FrameId.VEH_POSE_YAW
    yaw: float
    steer_angle: float
    drive_torque: float


@dataclass(frozen=True, slots=True)
class PlannerReq:
    """Planner -> ECU: engage request, target speed Vx,r [m/s], reference path to follow."""

    FRAME_ID: ClassVar[FrameId] = FrameId.PLANNER_REQ
    engage: bool
    target_speed: float
    path_id: int


@dataclass(frozen=True, slots=True)
class SteerTorqueCmd:
    """ECU -> plant: mode, validity, front wheel angle command [rad] and total drive
    torque command [N m] (negative brakes)."""

    FRAME_ID: ClassVar[FrameId] = FrameId.STEER_TORQUE_CMD
    ctrl_mode: CtrlMode
    cmd_valid: bool
    steer_angle_cmd: float
    drive_torque_cmd: float


@dataclass(frozen=True, slots=True)
class CtrlDiag:
    """ECU -> any: optimiser status and timing [us], iterations, overruns since start and
    the FAULTS bits of the current cycle (bit 0 input timeout, 1 E2E error, 2 solver
    fallback, 3 model/observer reset)."""

    FRAME_ID: ClassVar[FrameId] = FrameId.CTRL_DIAG
    qp_status: QpStatus
    solve_time_us: int
    cycle_time_us: int
    qp_iter: int
    overruns: int
    faults: int


Frame = HilSync | HilSyncAck | VehDyn | VehPoseXY | VehPoseYaw | PlannerReq | SteerTorqueCmd | CtrlDiag

FRAME_CLASSES: dict[FrameId, type] = {
    cls.FRAME_ID: cls
    for cls in (HilSync, HilSyncAck, VehDyn, VehPoseXY, VehPoseYaw, PlannerReq,
                SteerTorqueCmd, CtrlDiag)
}
"""Frame class of every arbitration ID."""
