"""Several C control cores in one process (firmware/src/ecu_core.h, docs/firmware.md).

Each core is an ``ecu_core_t`` of the caller's storage holding one of the generated OSQP
workspaces of its controller (ECU_QP_WORKSPACES per controller). Two ESO-DKMPC cores
stepped in turn on two different closed-loop recordings give, step for step, exactly the
outputs each gives alone: they share no state, the QP solver's included.
"""
from __future__ import annotations

import ctypes
import subprocess
from pathlib import Path

import numpy as np
import pytest

from controller.base import Controller, VehicleSample
from controller.reference import ReferencePath

ROOT = Path(__file__).resolve().parent.parent
#: firmware/tools/generate.py QP_WORKSPACES: cores of one controller a process can hold.
QP_WORKSPACES = 2


@pytest.fixture(scope="module")
def native():
    """firmware_sim.native on an up-to-date build, with the explicit core API declared."""
    build = subprocess.run(["make", "-s", "--no-print-directory", "firmware"], cwd=ROOT,
                           capture_output=True, text=True, check=False)
    assert build.returncode == 0, build.stdout + build.stderr
    from firmware_sim import native as module
    lib = module.load_library()
    double_p = ctypes.POINTER(ctypes.c_double)
    lib.ecu_core_size.restype = ctypes.c_size_t
    lib.ecu_core_load.argtypes = [ctypes.c_void_p, ctypes.c_char_p, ctypes.c_char_p, ctypes.c_char_p,
                                  ctypes.c_size_t]
    lib.ecu_core_load.restype = ctypes.c_int
    lib.ecu_core_unload.argtypes = [ctypes.c_void_p]
    lib.ecu_core_unload.restype = None
    lib.ecu_core_set_path.argtypes = [ctypes.c_void_p, double_p, double_p, double_p, double_p, ctypes.c_int,
                                      ctypes.c_char_p, ctypes.c_size_t]
    lib.ecu_core_set_path.restype = ctypes.c_int
    lib.ecu_core_step.argtypes = [ctypes.c_void_p, ctypes.POINTER(module._Sample), ctypes.POINTER(module._Output)]
    lib.ecu_core_step.restype = None
    return module


class Core:
    """One ecu_core_t in memory of its own (zeroed, 8-byte aligned), loaded for ``name``."""

    def __init__(self, native, name: str) -> None:
        self.lib = native.load_library()
        self.native = native
        self.memory = (ctypes.c_double * (self.lib.ecu_core_size() // 8 + 1))()
        error = ctypes.create_string_buffer(512)
        if self.lib.ecu_core_load(self.memory, str(native.DEFAULT_DATA).encode(), name.encode(), error, 512) != 0:
            raise RuntimeError(error.value.decode())
        self.output = native._Output()

    def set_path(self, path: ReferencePath) -> None:
        arrays = [np.ascontiguousarray(a, dtype=float) for a in (path.x, path.y, path.yaw, path.s)]
        pointers = [a.ctypes.data_as(ctypes.POINTER(ctypes.c_double)) for a in arrays]
        error = ctypes.create_string_buffer(512)
        assert self.lib.ecu_core_set_path(self.memory, *pointers, len(arrays[0]), error, 512) == 0, error.value

    def step(self, sample: VehicleSample) -> tuple:
        """(steer, torque, status, iterations, fallback, observer reset, cost, predicted poses)."""
        raw = self.native._Sample(*(float(getattr(sample, name)) for name in self.native._SAMPLE_FIELDS))
        out = self.output
        self.lib.ecu_core_step(self.memory, ctypes.byref(raw), ctypes.byref(out))
        poses = np.ctypeslib.as_array(out.predicted_pose)[:out.n_pred].tobytes()
        return (out.steer_angle, out.drive_torque, out.status, out.iterations, out.fallback, out.observer_reset,
                out.cost, poses)

    def unload(self) -> None:
        self.lib.ecu_core_unload(self.memory)


class Recorder(Controller):
    """The default core in the closed loop, keeping the path and every sample it got."""

    def __init__(self, native) -> None:
        self.inner = native.NativeController("eso-dkmpc")
        self.name = "eso-dkmpc"
        self.path: ReferencePath | None = None
        self.samples: list[VehicleSample] = []

    def set_path(self, path: ReferencePath) -> None:
        self.path = path
        self.inner.set_path(path)

    def reset(self) -> None:
        self.inner.reset()

    def step(self, sample: VehicleSample):
        self.samples.append(sample)
        return self.inner.step(sample)


def _recording(native, scenario: str) -> Recorder:
    from hil.scenario import load_scenario
    from studies.closed_loop import run_closed_loop

    recorder = Recorder(native)
    assert run_closed_loop(load_scenario(scenario), recorder).completed
    return recorder


def test_two_cores_share_no_state(native) -> None:
    """Two ESO-DKMPC cores stepped in turn on different recordings (dlc_smoke and the first
    160 steps of dlc_high_mu): every output equals, to the bit, that of the same core stepped
    alone; a third core of the controller is refused until one is unloaded."""
    runs = [_recording(native, "dlc_smoke"), _recording(native, "dlc_high_mu")]
    native.NativeController("lmpc")  # the default core gives its eso-dkmpc workspace back
    n_steps = min(len(r.samples) for r in runs)
    alone = []
    for run in runs:
        core = Core(native, "eso-dkmpc")
        core.set_path(run.path)
        alone.append([core.step(sample) for sample in run.samples[:n_steps]])
        core.unload()
    assert alone[0] != alone[1]
    cores = [Core(native, "eso-dkmpc") for _ in runs]
    for core, run in zip(cores, runs):
        core.set_path(run.path)
    together = [[], []]
    for i in range(n_steps):
        for k, (core, run) in enumerate(zip(cores, runs)):
            together[k].append(core.step(run.samples[i]))
    for k in range(2):
        differing = [i for i in range(n_steps) if together[k][i] != alone[k][i]]
        print(f"core {k}: {n_steps} steps, {len(differing)} differ from the core alone")
        assert not differing
    assert QP_WORKSPACES == 2  # both generated eso-dkmpc workspaces are held now
    with pytest.raises(RuntimeError, match="all 2 generated QP workspaces of eso-dkmpc are held by other cores"):
        Core(native, "eso-dkmpc")
    cores[0].unload()
    third = Core(native, "eso-dkmpc")
    third.unload()
    cores[1].unload()


def test_cores_of_other_controllers_beside_the_default_core(native) -> None:
    """A DKMPC and an LMPC core load beside the default core (its own workspaces), and the
    default core's steps are unchanged by their steps in between."""
    run = _recording(native, "dlc_smoke")
    reference = native.NativeController("eso-dkmpc")
    reference.set_path(run.path)
    expected = [reference.step(sample)[0] for sample in run.samples]
    others = [Core(native, "dkmpc"), Core(native, "lmpc")]
    for core in others:
        core.set_path(run.path)
    default = native.NativeController("eso-dkmpc")
    default.set_path(run.path)
    got = []
    for sample in run.samples:
        got.append(default.step(sample)[0])
        for core in others:
            core.step(sample)
    assert got == expected
    for core in others:
        core.unload()
