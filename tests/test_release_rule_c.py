"""Contract revision 3's release rule in the C ECU (firmware/src/ecu_release.c) against the
Python ECU's (firmware_sim.clock.SampleRelease), event for event.

libecu.so exports ``ecu_release_script``: the C rule fed a script of events the way the C
node feeds it (time passing, a good sample set, a release of the node's own clock). The
same scripts go through the Python rule the way the Python node feeds it. The scripts are
those of tests/test_ecu_rev3.py (a 10 ms and a 25 ms plant, a late first sample, drift
either way, a 10 ms plant's phase followed, lost samples, restarts at every phase, a burst, a late loop) and random ones;
every release, skipped instant and pending instant must agree.
"""
from __future__ import annotations

import ctypes
import subprocess
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from firmware_sim.clock import SampleRelease
from firmware_sim.config import (MIN_RELEASE_SPACING_NS, NS_PER_MS, SAMPLE_WATCHDOG_NS,
                                 SAMPLE_WINDOW_EARLY_NS)

ROOT = Path(__file__).resolve().parent.parent
MS = NS_PER_MS
TIME, SAMPLE, CLOCK = 0, 1, 2  # ecu_release.h: ECU_RELEASE_TIME, _SAMPLE, _CLOCK
Script = list[tuple[int, int]]  # (kind, time ns)


@pytest.fixture(scope="module")
def release_script():
    """``ecu_release_script`` of an up-to-date libecu.so (ctypes, argument types set)."""
    build = subprocess.run(["make", "-s", "--no-print-directory", "firmware"], cwd=ROOT,
                           capture_output=True, text=True, check=False)
    assert build.returncode == 0, build.stdout + build.stderr
    from firmware_sim.native import DEFAULT_LIBRARY

    function = ctypes.CDLL(str(DEFAULT_LIBRARY)).ecu_release_script
    i32, i64 = ctypes.POINTER(ctypes.c_int32), ctypes.POINTER(ctypes.c_int64)
    function.argtypes = [ctypes.c_int64, i32, i64, ctypes.c_int32, i32, i32, i64]
    function.restype = ctypes.c_int
    return function


@pytest.fixture(scope="module")
def c_script(release_script):
    """(sample period ns, script) -> (released, skipped, instants) arrays of the C rule."""
    i32, i64 = ctypes.POINTER(ctypes.c_int32), ctypes.POINTER(ctypes.c_int64)

    def run(sample_period_ns: int, script: Script) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        n = len(script)
        kinds = np.array([k for k, _ in script], dtype=np.int32)
        times = np.array([t for _, t in script], dtype=np.int64)
        released, skipped = np.zeros(n, np.int32), np.zeros(n, np.int32)
        instants = np.zeros(n, np.int64)
        status = release_script(sample_period_ns, kinds.ctypes.data_as(i32), times.ctypes.data_as(i64), n,
                                released.ctypes.data_as(i32), skipped.ctypes.data_as(i32),
                                instants.ctypes.data_as(i64))
        assert status == 0
        return released, skipped, instants
    return run


def python_script(sample_period_ns: int, script: Script) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The Python rule fed ``script`` as firmware_sim.ecu.Ecu feeds it (poll: the watchdog
    when anchored; a good sample: the watchdog first, then the sample; a clock release:
    note_release). Same outputs as ``ecu_release_script``."""
    release = SampleRelease(25 * MS, SAMPLE_WINDOW_EARLY_NS, SAMPLE_WATCHDOG_NS, MIN_RELEASE_SPACING_NS,
                            100 * MS, sample_period_ns)
    released, skipped, instants = [], [], []
    for kind, t in script:
        flags, missed = 0, 0
        if kind == CLOCK:
            release.note_release(t)
        elif kind == TIME or release.anchored:
            due, missed = release.on_time(t)
            flags = int(due)
        if kind == SAMPLE:
            flags |= int(release.on_sample(t)) << 1
        released.append(flags)
        skipped.append(missed)
        instants.append(release.instant_ns if release.anchored else 0)
    return np.array(released), np.array(skipped), np.array(instants)


def timeline(sample_ms: list[float], until_ms: float, step_ms: float = 0.5) -> Script:
    """Time advancing in ``step_ms`` with the samples at ``sample_ms`` (the node's order:
    time first, then the sample); before the first sample, the node's own clock releases
    every 25 ms (revision 2's releases, unanchored)."""
    pending = sorted(sample_ms)
    script: Script = []
    t, next_clock = 0.0, 0.0
    first_sample = pending[0] if pending else until_ms + 1
    while t <= until_ms:
        script.append((TIME, round(t * MS)))
        if next_clock <= t < first_sample:
            script.append((CLOCK, round(t * MS)))
            next_clock += 25.0
        while pending and pending[0] <= t:
            script.append((SAMPLE, round(pending.pop(0) * MS)))
        t += step_ms
    return script


def _cases() -> list[tuple[str, int, Script]]:
    """(name, plant period ns, script): the scenarios of tests/test_ecu_rev3.py."""
    cases = [("10 ms plant", 10 * MS, timeline([10.0 * k for k in range(41)], 400)),
             ("lost 25 ms sample", 25 * MS, timeline([0, 25, 75, 100], 110)),
             ("1 ms burst", 10 * MS, timeline([float(t) for t in range(200)], 200)),
             ("late first sample", 25 * MS, timeline([30.0, *[37.5 + 25.0 * k for k in range(1, 12)]], 320)),
             ("restart 3.5 ms after the watchdog", 25 * MS, timeline([0, 25, 50, 261, 286], 290)),
             ("late loop", 25 * MS, [(SAMPLE, 0), (TIME, 80 * MS), (TIME, 81 * MS), (SAMPLE, 83 * MS)])]
    for phase in (0.0, 7.0, 13.5, 24.0):
        samples = [phase + 25.0 * k + (2.0 if k % 2 else -2.0) * (k > 0) for k in range(20)]
        cases.append((f"25 ms plant, phase {phase} ms, 2 ms jitter", 25 * MS, timeline(samples, samples[-1] + 1)))
    for phase in (0.3, 2.4, 2.6, 7.4, 12.6, 14.9):  # anchored in phase with the samples
        samples = [25.0 + phase + 10.0 * k for k in range(12)]
        cases.append((f"10 ms plant, first sample {phase} ms after a clock release", 10 * MS,
                      timeline(samples, samples[-1] + 1, step_ms=0.1)))
    # a sample stamped 0.4 ms before the clock's release and taken after it
    early = [(CLOCK, 0), (CLOCK, 25 * MS), (SAMPLE, round(24.6 * MS))]
    later = timeline([24.6 + 10.0 * k for k in range(1, 12)], 140.0, step_ms=0.1)
    cases.append(("10 ms plant, first sample 0.4 ms before a clock release", 10 * MS,
                  early + [event for event in later if event[0] != CLOCK and event[1] > 25 * MS]))
    for drift in (0.5, -0.5):
        samples = [5.0 + (25.0 + drift) * k for k in range(60)]
        cases.append((f"drift {drift} ms per period", 25 * MS, timeline(samples, samples[-1] + 1)))
    for error, drift in ((1.5, 0.0), (-0.8, 0.0), (0.0, 0.01), (0.0, -0.01), (2.2, 0.005)):
        # a 10 ms plant's grid follows the samples' phase: an anchor off the next samples' phase, drift
        samples = [12.0] + [12.0 + error + (10.0 + drift) * k + (0.3 if k % 3 else -0.4) for k in range(1, 300)]
        cases.append((f"10 ms plant {error} ms off its anchor's phase, drift {drift} ms per sample", 10 * MS,
                      timeline(samples, samples[-1] + 1, step_ms=0.1)))
    for gap in (7.5, 10.0, 12.0, 14.5):
        samples = [0, 25, 50, *[257.5 + gap + 25.0 * k for k in range(6)]]
        cases.append((f"25 ms plant restarted {gap} ms after the watchdog", 25 * MS,
                      timeline(samples, samples[-1] + 1)))
    for gap in (0.0, 5.0, 7.5, 10.0, 14.5):
        samples = [0, 10, 20, 30, 40, 50, *[257.5 + gap + 10.0 * k for k in range(12)]]
        cases.append((f"10 ms plant restarted {gap} ms after the watchdog", 10 * MS,
                      timeline(samples, samples[-1] + 1)))
    return cases


@pytest.mark.parametrize("name, period_ns, script", _cases(), ids=[c[0] for c in _cases()])
def test_the_c_rule_releases_as_the_python_rule(c_script, name: str, period_ns: int, script: Script) -> None:
    c_out, py_out = c_script(period_ns, script), python_script(period_ns, script)
    releases = int(np.count_nonzero(py_out[0]))
    print(f"{name}: {len(script)} events, {releases} releases")
    assert releases > 0                      # a script that releases nothing compares nothing
    for label, c_values, py_values in zip(("released", "skipped", "instant"), c_out, py_out):
        differ = np.flatnonzero(c_values != py_values)
        assert differ.size == 0, (f"{name}: {label} differs first at event {differ[0]} "
                                  f"{script[differ[0]]}: C {c_values[differ[0]]}, Python {py_values[differ[0]]}")


@settings(max_examples=150, deadline=None)
@given(period_ms=st.sampled_from([10, 25]),
       gaps_us=st.lists(st.integers(min_value=0, max_value=140_000), min_size=1, max_size=60),
       step_us=st.sampled_from([250, 500, 1000, 5000]))
def test_random_sample_timelines_release_alike_in_c_and_python(c_script, period_ms: int,
                                                               gaps_us: list[int], step_us: int) -> None:
    """Samples at random gaps (0 to 140 ms: bursts, lost samples, restarts), time polled
    every ``step_us``: the C and Python rules agree on every event."""
    samples = np.cumsum(gaps_us) / 1000.0
    script = timeline(list(samples), float(samples[-1]) + 40.0, step_us / 1000.0)
    for c_values, py_values in zip(c_script(period_ms * MS, script), python_script(period_ms * MS, script)):
        assert np.array_equal(c_values, py_values)


def test_the_script_refuses_bad_input(release_script) -> None:
    kinds, times = (ctypes.c_int32 * 1)(7), (ctypes.c_int64 * 1)(0)
    out32, out32b, out64 = (ctypes.c_int32 * 1)(), (ctypes.c_int32 * 1)(), (ctypes.c_int64 * 1)()
    assert release_script(25 * MS, kinds, times, 1, out32, out32b, out64) == -1   # unknown kind
    assert release_script(25 * MS, kinds, times, -1, out32, out32b, out64) == -1  # n < 0
    assert release_script(25 * MS, None, times, 1, out32, out32b, out64) == -1    # no array
    assert release_script(0, kinds, times, 0, out32, out32b, out64) == -1        # no plant period
    assert release_script(25 * MS, None, None, 0, None, None, None) == 0          # empty script
