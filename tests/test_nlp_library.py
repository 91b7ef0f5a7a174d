"""NLPs compiled to a shared library (controller/nlp_library.py, issue 37 item 5): the same
iterates as CasADi's virtual machine, a cache that builds once, a damaged library built
again, and clear errors (with the virtual machine kept) when no compiler can build it."""
from __future__ import annotations

import logging

import casadi as ca
import numpy as np
import pytest

from controller.base import VehicleSample
from controller.nlp_library import NlpLibraryError, cache_dir, compiled_solver
from controller.reference import ReferencePath
from controller.registry import create_controller

OPTIONS = {"print_time": False, "ipopt": {"print_level": 0, "sb": "yes"}}


def _small_problem() -> dict[str, ca.SX]:
    """min (x0 - p)^2 + sin(x1)^2 + x0 x1 s.t. x0 + x1 >= 1: enough operations to compare."""
    x, p = ca.SX.sym("x", 2), ca.SX.sym("p")
    return {"x": x, "p": p, "f": (x[0] - p) ** 2 + ca.sin(x[1]) ** 2 + x[0] * x[1], "g": x[0] + x[1]}


def _solve(solver) -> np.ndarray:
    return np.asarray(solver(x0=[0.3, 0.2], p=0.7, lbg=1.0, ubg=np.inf)["x"]).ravel()


def test_a_small_nlp_compiles_once_and_gives_the_virtual_machines_iterates(tmp_path, monkeypatch):
    monkeypatch.setenv("NLP_LIBRARY_DIR", str(tmp_path))
    reference = _solve(ca.nlpsol("small", "ipopt", _small_problem(), {**OPTIONS, "expand": True}))
    compiled = _solve(compiled_solver("small", _small_problem(), OPTIONS))
    assert np.array_equal(compiled, reference)
    libraries = list(tmp_path.glob("small_*.so"))
    assert len(libraries) == 1 and not list(tmp_path.glob(".*"))   # no partial file or scratch left
    built = libraries[0].stat().st_mtime_ns
    compiled_solver("small", _small_problem(), OPTIONS)              # cached: not built again
    assert libraries[0].stat().st_mtime_ns == built


def test_a_damaged_cached_library_is_built_again(tmp_path, monkeypatch):
    monkeypatch.setenv("NLP_LIBRARY_DIR", str(tmp_path))
    compiled_solver("small", _small_problem(), OPTIONS)
    (library,) = tmp_path.glob("small_*.so")
    library.write_bytes(b"not a shared library")
    solver = compiled_solver("small", _small_problem(), OPTIONS)
    assert library.read_bytes()[:4] == b"\x7fELF"
    reference = _solve(ca.nlpsol("small", "ipopt", _small_problem(), {**OPTIONS, "expand": True}))
    assert np.array_equal(_solve(solver), reference)


@pytest.mark.parametrize("cc, message", [("/nonexistent/cc", "no C compiler '/nonexistent/cc'"),
                                         ("false", "failed on small_nlp.c")])
def test_no_compiler_or_a_failing_one_is_named(tmp_path, monkeypatch, cc, message):
    monkeypatch.setenv("NLP_LIBRARY_DIR", str(tmp_path))
    monkeypatch.setenv("CC", cc)
    with pytest.raises(NlpLibraryError, match=message):
        compiled_solver("small", _small_problem(), OPTIONS)
    assert not list(tmp_path.glob("*.so"))


def test_an_unwritable_cache_folder_is_named(tmp_path, monkeypatch):
    blocked = tmp_path / "file"
    blocked.write_text("a file where the folder should be")
    monkeypatch.setenv("NLP_LIBRARY_DIR", str(blocked / "nlp"))
    with pytest.raises(NlpLibraryError, match="cannot generate the NLP's C code in"):
        compiled_solver("small", _small_problem(), OPTIONS)


def _nmpc_commands(budget: float | None, steps: int) -> list[tuple[float, int, float]]:
    controller = create_controller("nmpc")
    controller.set_path(ReferencePath.double_lane_change())
    controller.set_time_budget(budget)
    sample = VehicleSample(12.0, 0.1, 0.05, 0.01, 0.2, 0.0, 0.01, 0.0, 12.0)
    out = []
    for k in range(steps):
        command, debug = controller.step(sample)
        out.append((command.steer_angle, debug.iterations, debug.cost))
        # move the sample along so that every step solves a new problem
        sample = VehicleSample(12.0, 0.1 + 0.01 * k, 0.05, 0.01 + 0.3 * k, 0.2, 0.0, 0.01, 0.0, 12.0)
    return out


def test_nmpc_in_real_time_runs_the_compiled_nlp_with_the_same_plans():
    """A budget long enough never to stop IPOPT: the compiled NLP (real time) and the
    virtual machine (lockstep) give the same commands, iterations and costs to the bit."""
    assert _nmpc_commands(60.0, 6) == _nmpc_commands(None, 6)
    assert list(cache_dir().glob("nmpc_*.so"))


def test_nmpc_without_a_compiler_keeps_the_virtual_machine_and_says_so(tmp_path, monkeypatch, caplog):
    monkeypatch.setenv("NLP_LIBRARY_DIR", str(tmp_path))
    monkeypatch.setenv("CC", "/nonexistent/cc")
    with caplog.at_level(logging.WARNING, logger="controller.nmpc"):
        assert _nmpc_commands(60.0, 2) == _nmpc_commands(None, 2)
    assert "NMPC's NLP not compiled (no C compiler '/nonexistent/cc'" in caplog.text
