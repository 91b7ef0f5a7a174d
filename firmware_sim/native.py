"""The Python face of the C control core ``build/firmware/libecu.so`` (ctypes).

``NativeController`` is a ``controller.base.Controller`` whose ``step`` is the C core's
``ecu_step_aged`` (firmware/src, docs/firmware.md; the sample's age as data): ``python -m
firmware_sim --native`` puts it in place of the Python control law, and ``studies/bench_native.py`` times it. The library
holds ONE core per process (static storage, as on the ECU): building a second
``NativeController`` reloads that core and the first one must no longer be stepped.

The core reads its data file (tuning, Koopman model, bicycle) written by
``firmware/tools/ecu_data.py``; ``make firmware`` writes the default one,
``build/firmware/ecu_data.bin``, and ``data_file_for_model`` writes one for another
Koopman artefact. ``ECU_LIB`` / ``ECU_DATA`` in the environment point at other builds
(``make firmware-asan`` uses them).
"""
from __future__ import annotations

import ctypes
import hashlib
import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

from controller.base import Command, Controller, SolverStatus, StepDebug, VehicleSample
from controller.reference import ReferencePath
from firmware_sim.errors import ConfigError

ROOT = Path(__file__).resolve().parent.parent
DEFAULT_LIBRARY = ROOT / "build" / "firmware" / "libecu.so"
DEFAULT_DATA = ROOT / "build" / "firmware" / "ecu_data.bin"
#: The controllers the C core implements (NMPC and the ablations stay Python).
NATIVE_CONTROLLERS = ("eso-dkmpc", "dkmpc", "lmpc")
#: ecu_core.h ECU_MAX_PATH_POINTS: the contract's largest path.
MAX_PATH_POINTS = 100_000
#: ecu_core.h ECU_MAX_HORIZON: rows of the predicted arrays.
MAX_HORIZON = 200
_ERROR_BYTES = 512
_SAMPLE_FIELDS = ("vx", "vy", "yaw_rate", "x", "y", "yaw", "steer_angle", "drive_torque", "target_speed")


class _Sample(ctypes.Structure):
    """ecu_sample_t."""

    _fields_ = [(name, ctypes.c_double) for name in _SAMPLE_FIELDS]


class _Output(ctypes.Structure):
    """ecu_output_t."""

    _fields_ = [("steer_angle", ctypes.c_double), ("drive_torque", ctypes.c_double),
                ("status", ctypes.c_int), ("iterations", ctypes.c_int), ("fallback", ctypes.c_int),
                ("observer_reset", ctypes.c_int), ("n_pred", ctypes.c_int),
                ("solve_time_s", ctypes.c_double), ("cost", ctypes.c_double), ("slack_max", ctypes.c_double),
                ("step_time_s", ctypes.c_double),
                ("predicted_pose", ctypes.c_double * 3 * MAX_HORIZON),
                ("predicted_state", ctypes.c_double * 3 * MAX_HORIZON)]


class _E2EResult(ctypes.Structure):
    """ecu_e2e_result_t."""

    _fields_ = [("status", ctypes.c_int), ("lost", ctypes.c_int), ("accepted", ctypes.c_int)]


#: ecu_rx.h's ecu_e2e_status values, by the names of can_defs.e2e.E2EStatus.
E2E_STATUS_NAMES = ("OK", "CRC_ERROR", "REPEATED", "LOST", "SEQUENCE_ERROR", "WRONG_LENGTH", "UNKNOWN_ID",
                    "BAD_TICK")

#: ecu_node.h's ecu_send_fn: (frame ID, payload, length) -> 0.
_SEND_FUNCTION = ctypes.CFUNCTYPE(ctypes.c_int, ctypes.c_uint32, ctypes.POINTER(ctypes.c_uint8), ctypes.c_int)

_library: ctypes.CDLL | None = None


def load_library(path: str | Path | None = None) -> ctypes.CDLL:
    """libecu.so (``path``, else ``ECU_LIB``, else the build's), loaded once per process.

    Raises:
        ConfigError: the library is missing (run ``make firmware``) or does not load.
    """
    global _library
    if _library is not None:
        return _library
    file = Path(path or os.environ.get("ECU_LIB") or DEFAULT_LIBRARY)
    if not file.is_file():
        raise ConfigError(f"{file}: the C core is not built (run make firmware)")
    try:
        library = ctypes.CDLL(str(file.resolve()))
    except OSError as error:
        raise ConfigError(f"{file}: does not load: {error}") from error
    double_p = ctypes.POINTER(ctypes.c_double)
    library.ecu_load.argtypes = [ctypes.c_char_p, ctypes.c_char_p, ctypes.c_char_p, ctypes.c_size_t]
    library.ecu_load.restype = ctypes.c_int
    library.ecu_set_path.argtypes = [double_p, double_p, double_p, double_p, ctypes.c_int, ctypes.c_char_p,
                                     ctypes.c_size_t]
    library.ecu_set_path.restype = ctypes.c_int
    library.ecu_load_path_csv.argtypes = [ctypes.c_char_p, ctypes.c_char_p, ctypes.c_size_t]
    library.ecu_load_path_csv.restype = ctypes.c_int
    library.ecu_path_copy.argtypes = [double_p, double_p, double_p, double_p, ctypes.c_int]
    library.ecu_path_copy.restype = ctypes.c_int
    library.ecu_reset.argtypes = []
    library.ecu_reset.restype = None
    library.ecu_step.argtypes = [ctypes.POINTER(_Sample), ctypes.POINTER(_Output)]
    library.ecu_step.restype = None
    library.ecu_step_aged.argtypes = [ctypes.POINTER(_Sample), ctypes.c_double, ctypes.POINTER(_Output)]
    library.ecu_step_aged.restype = None
    byte_p = ctypes.POINTER(ctypes.c_uint8)
    library.ecu_e2e_crc.argtypes = [ctypes.c_uint32, byte_p]
    library.ecu_e2e_crc.restype = ctypes.c_uint8
    library.ecu_e2e_check.argtypes = [ctypes.c_uint32, byte_p, ctypes.c_int]
    library.ecu_e2e_check.restype = _E2EResult
    library.ecu_e2e_reset.argtypes = []
    library.ecu_e2e_reset.restype = None
    library.ecu_decode.argtypes = [ctypes.c_uint32, byte_p, ctypes.POINTER(ctypes.c_double)]
    library.ecu_decode.restype = ctypes.c_int
    library.ecu_node_init.argtypes = [_SEND_FUNCTION, ctypes.c_char_p]
    library.ecu_node_init.restype = None
    library.ecu_node_receive.argtypes = [ctypes.c_uint32, byte_p, ctypes.c_int, ctypes.c_int]
    library.ecu_node_receive.restype = None
    library.ecu_node_mode.restype = ctypes.c_int
    library.ecu_node_save_timing.argtypes = [ctypes.c_char_p, ctypes.c_char_p, ctypes.c_size_t]
    library.ecu_node_save_timing.restype = ctypes.c_int
    library.ecu_version.restype = ctypes.c_char_p
    library.ecu_build_shapes.restype = ctypes.c_char_p
    _library = library
    return library


def version() -> str:
    """The generator inputs' hashes compiled into libecu.so (``ecu_version()``)."""
    return load_library().ecu_version().decode()


def is_bicycle_file(model: Path) -> bool:
    """Whether ``model`` is a fitted bicycle (models/bicycle_fit.py's JSON, kind
    linear_bicycle) rather than a Koopman artefact."""
    if model.suffix.lower() != ".json":
        return False
    try:
        content = json.loads(model.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return False
    return isinstance(content, dict) and content.get("kind") == "linear_bicycle"


def data_file_for_model(model: Path, out_dir: Path | None = None) -> Path:
    """The C core's data file for ``model`` (written once per content of the model, the
    tuning file and the writer): a Koopman artefact
    in place of the build's, or a fitted bicycle (``is_bicycle_file``) in place of the
    nominal one (LMPC's; the build's Koopman model stays).

    Raises:
        ConfigError: firmware/tools/ecu_data.py refused the file (its message).
    """
    bicycle = is_bicycle_file(model)
    sources = [model] if bicycle else [model.with_suffix(".npz"), model.with_suffix(".json")]
    # The file also holds the tuning, in ecu_data.py's layout: both are in the key, so a
    # retune or a new layout never reuses a file written before it.
    sources += [ROOT / "controller" / "tuning.toml", ROOT / "firmware" / "tools" / "ecu_data.py"]
    digest = hashlib.sha256(b"".join(source.read_bytes() for source in sources)).hexdigest()[:12]
    out = (out_dir or DEFAULT_DATA.parent / "data") / f"{model.stem}-{digest}.bin"
    if not out.is_file():
        result = subprocess.run([sys.executable, str(ROOT / "firmware" / "tools" / "ecu_data.py"),
                                 "--bicycle" if bicycle else "--model", str(model), "--out", str(out)],
                                capture_output=True, text=True, check=False)
        if result.returncode != 0:
            lines = result.stderr.strip().splitlines() or ["ecu_data.py failed"]
            raise ConfigError(f"--model {model}: {lines[-1].removeprefix('error: ')}")
    return out


class NativeController(Controller):
    """A controller whose step runs in libecu.so; same interface as the Python ones."""

    def __init__(self, name: str, data: str | Path | None = None, library: str | Path | None = None) -> None:
        """Load the core for controller ``name`` from ``data`` (default: ``ECU_DATA``, else
        the build's data file).

        Raises:
            ConfigError: unknown name, missing library or data file, or a data file the
                build refuses (the C core's message: file, record, both shapes).
        """
        if name not in NATIVE_CONTROLLERS:
            raise ConfigError(f"--native: controller {name!r} is not in the C core "
                              f"(it has {', '.join(NATIVE_CONTROLLERS)})")
        self.name = name
        self._lib = load_library(library)
        self.data = Path(data or os.environ.get("ECU_DATA") or DEFAULT_DATA)
        error = ctypes.create_string_buffer(_ERROR_BYTES)
        if self._lib.ecu_load(str(self.data).encode(), name.encode(), error, _ERROR_BYTES) != 0:
            raise ConfigError(error.value.decode(errors="replace"))
        self._sample = _Sample()
        self._output = _Output()
        self._path_arrays: tuple[np.ndarray, ...] = ()
        #: The C core's own time of the last ``step`` (s), without the ctypes call.
        self.last_step_time_s = 0.0

    def set_path(self, path: ReferencePath) -> None:
        """Hand the path's arrays (x, y, yaw unwrapped, s; each (n,)) to the core."""
        arrays = tuple(np.ascontiguousarray(a, dtype=float) for a in (path.x, path.y, path.yaw, path.s))
        pointers = [a.ctypes.data_as(ctypes.POINTER(ctypes.c_double)) for a in arrays]
        error = ctypes.create_string_buffer(_ERROR_BYTES)
        if self._lib.ecu_set_path(*pointers, len(arrays[0]), error, _ERROR_BYTES) != 0:
            raise ConfigError(f"{path.name or 'path'}: {error.value.decode(errors='replace')}")
        self._path_arrays = arrays  # the core copied them; kept only for inspection

    def load_path_file(self, file: str | Path) -> None:
        """Read and check a path CSV in C (``ecu_load_path_csv``, as the executable does).

        Raises:
            ConfigError: the C reader's message (file, line, check), as PathError's.
        """
        error = ctypes.create_string_buffer(_ERROR_BYTES)
        if self._lib.ecu_load_path_csv(str(file).encode(), error, _ERROR_BYTES) != 0:
            raise ConfigError(error.value.decode(errors="replace"))

    def path_arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The core's path: x, y, yaw (unwrapped), s, each (n,)."""
        arrays = [np.empty(MAX_PATH_POINTS) for _ in range(4)]
        pointers = [a.ctypes.data_as(ctypes.POINTER(ctypes.c_double)) for a in arrays]
        n = self._lib.ecu_path_copy(*pointers, MAX_PATH_POINTS)
        return tuple(a[:n].copy() for a in arrays)

    def reset(self) -> None:
        """Forget plans, progress and the observer (``ecu_reset``)."""
        self._lib.ecu_reset()

    def step(self, sample: VehicleSample) -> tuple[Command, StepDebug]:
        """One control step in C (``ecu_step_aged``: the sample's age goes with it, as the
        Python controller reads it); predicted arrays (Np, 3), empty when no plan was made."""
        raw = self._sample
        for name in _SAMPLE_FIELDS:
            setattr(raw, name, float(getattr(sample, name)))
        out = self._output
        self._lib.ecu_step_aged(ctypes.byref(raw), float(sample.sample_age_s), ctypes.byref(out))
        self.last_step_time_s = out.step_time_s
        n_pred = out.n_pred
        pose = np.ctypeslib.as_array(out.predicted_pose)[:n_pred].copy()
        state = np.ctypeslib.as_array(out.predicted_state)[:n_pred].copy()
        debug = StepDebug(status=SolverStatus(out.status), iterations=out.iterations,
                          solve_time_s=out.solve_time_s, cost=out.cost if math.isfinite(out.cost) else math.nan,
                          predicted_pose=pose, predicted_state=state, fallback=bool(out.fallback),
                          slack_max=out.slack_max, observer_reset=bool(out.observer_reset))
        return Command(steer_angle=out.steer_angle, drive_torque=out.drive_torque), debug


def _bytes_pointer(data: bytes) -> ctypes.Array:
    """A C copy of ``data`` (at least 8 bytes, zero-padded: the C side reads ``length``)."""
    return (ctypes.c_uint8 * max(len(data), 8)).from_buffer_copy(bytes(data).ljust(8, b"\0"))


class NativeE2EMonitor:
    """The C core's E2E receive (``ecu_e2e_check``): one receiver per contract frame ID.

    Shares the library's one state per process, as ``NativeController`` does.
    """

    def __init__(self) -> None:
        self._lib = load_library()
        self._lib.ecu_e2e_reset()

    def check(self, frame_id: int, data: bytes) -> tuple[str, int, bool]:
        """(status name of can_defs.e2e.E2EStatus, frames lost, accepted) of one frame."""
        result = self._lib.ecu_e2e_check(frame_id, _bytes_pointer(data), len(data))
        return E2E_STATUS_NAMES[result.status], result.lost, bool(result.accepted)

    def reset(self) -> None:
        """Forget every counter reference."""
        self._lib.ecu_e2e_reset()


class NativeNode:
    """The C ECU node (``ecu_node.c``: lockstep) on a loaded core, fed frames from Python;
    what it sends is collected in ``sent`` as (frame ID, payload). Load the core first
    (``NativeController``) and its path (``load_path_file``: PATH_ID 0)."""

    def __init__(self) -> None:
        self._lib = load_library()
        self.sent: list[tuple[int, bytes]] = []

        def send(frame_id: int, data: ctypes.Array, length: int) -> int:
            self.sent.append((int(frame_id), bytes(data[:length])))
            return 0

        self._send = _SEND_FUNCTION(send)  # kept: the C side holds the pointer
        self._lib.ecu_node_init(self._send, None)

    def receive(self, frame_id: int, data: bytes, contract_kind: bool = True) -> None:
        """One received frame (any length, any ID); a HIL_SYNC runs the due tasks."""
        self._lib.ecu_node_receive(frame_id, _bytes_pointer(data), len(data), int(contract_kind))

    @property
    def mode(self) -> int:
        """CTRL_MODE of the node."""
        return int(self._lib.ecu_node_mode())

    def save_timing(self, file: str | Path) -> None:
        """Write the node's timing record (``firmware_sim.timing``'s .npz).

        Raises:
            ConfigError: the file cannot be written.
        """
        error = ctypes.create_string_buffer(_ERROR_BYTES)
        if self._lib.ecu_node_save_timing(str(file).encode(), error, _ERROR_BYTES) != 0:
            raise ConfigError(error.value.decode(errors="replace"))


def e2e_crc(frame_id: int, data: bytes) -> int:
    """The C core's CRC-8 of an 8-byte payload (byte 0 not included)."""
    return int(load_library().ecu_e2e_crc(frame_id, _bytes_pointer(data)))


def decode_values(frame_id: int, data: bytes) -> tuple[float, ...] | None:
    """Physical values of a received frame by the generated C codecs (``ecu_decode``), in
    can_defs.frames' field order; None for a frame ID the ECU does not receive."""
    values = (ctypes.c_double * 3)()
    count = load_library().ecu_decode(frame_id, _bytes_pointer(data), values)
    return None if count < 0 else tuple(values[:count])


def native_controller_factory(controller: str, model: Path | None = None):  # noqa: ANN201 (ECU factory)
    """The ECU's controller factory for ``--native``: the core is loaded here, before the bus
    opens, so a refused data file is an ``error:`` line at start-up.

    Raises:
        ConfigError: as ``NativeController`` or ``data_file_for_model``.
    """
    data = data_file_for_model(model) if model is not None else None
    native = NativeController(controller, data)
    return lambda name: native
