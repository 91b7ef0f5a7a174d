"""can_defs: the CAN contract of the ESO-DKMPC controller node.

The DBC (`DBC_PATH`), typed frames (`can_defs.frames`), encode/decode on cantools
(`can_defs.codec`), CRC-8 SAE J1850 (`can_defs.crc`) and the receiver's E2E checks
(`can_defs.e2e`). Pure: no python-can bus objects, no clock, no control.
"""
from can_defs.codec import DecodedFrame, FrameSender, decode, encode, prepare
from can_defs.crc import crc8_j1850, e2e_crc
from can_defs.dbc import DBC_PATH, load_database
from can_defs.e2e import E2EMonitor, E2EReceiver, E2EResult, E2EStats, E2EStatus
from can_defs.errors import (CanDefsError, DbcLoadError, DecodeError, EncodeError,
                             FrameLengthError, UndefinedValueError, UnknownFrameError)
from can_defs.frames import (E2E_FRAME_IDS, FRAME_CLASSES, FRAME_LENGTH, HANDSHAKE_TICK,
                             HIL_FRAME_IDS, PLANT_SAMPLE_FRAME_IDS, TICK_STEP_MS, CtrlDiag,
                             CtrlMode, Frame, FrameId, HilSync, HilSyncAck, PlannerReq,
                             QpStatus, SteerTorqueCmd, VehDyn, VehPoseXY, VehPoseYaw)

__all__ = [
    "DBC_PATH", "load_database",
    "crc8_j1850", "e2e_crc",
    "FrameId", "CtrlMode", "QpStatus", "Frame", "FRAME_CLASSES", "FRAME_LENGTH",
    "HIL_FRAME_IDS", "E2E_FRAME_IDS", "PLANT_SAMPLE_FRAME_IDS", "HANDSHAKE_TICK",
    "TICK_STEP_MS",
    "HilSync", "HilSyncAck", "VehDyn", "VehPoseXY", "VehPoseYaw", "PlannerReq",
    "SteerTorqueCmd", "CtrlDiag",
    "encode", "decode", "DecodedFrame", "FrameSender", "prepare",
    "E2EStatus", "E2EResult", "E2EStats", "E2EReceiver", "E2EMonitor",
    "CanDefsError", "DbcLoadError", "EncodeError", "DecodeError", "UnknownFrameError",
    "FrameLengthError", "UndefinedValueError",
]
