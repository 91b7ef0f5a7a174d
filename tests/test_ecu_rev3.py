"""Contract revision 3 in the Python ECU: the control task released by the plant's samples
(``EcuConfig.control_release = "sample"``, ``firmware_sim.clock.SampleRelease``).

The release rule alone on integer ns (a 10 ms plant of revision 2, a 25 ms plant, a lost
sample, samples faster than the period, a late loop, a restarted plant), then the ECU in
lockstep with the scripted controller of ``test_ecu_lockstep`` (release ticks, the sample's
age at the task start, the watchdog, determinism) and the option's validation. Both ECUs
on the bus: ``tests/test_conformance_rev3.py``.
"""
from __future__ import annotations

import random

import pytest
from can_defs.frames import CtrlMode, FrameId

from firmware_sim.clock import SampleRelease
from firmware_sim.config import (MIN_RELEASE_SPACING_NS, NS_PER_MS, SAMPLE_WATCHDOG_NS,
                                 SAMPLE_WINDOW_EARLY_NS, EcuConfig)
from firmware_sim.errors import ConfigError
from hil.ecu_harness import commands
from test_ecu_lockstep import Rig, buses, moving_plant  # noqa: F401 (buses: the fixture)

MS = NS_PER_MS


def new_release(plant_ms: int = 25) -> SampleRelease:
    return SampleRelease(25 * MS, SAMPLE_WINDOW_EARLY_NS, SAMPLE_WATCHDOG_NS, MIN_RELEASE_SPACING_NS,
                         100 * MS, plant_ms * MS)


def releases(sample_ms: list[float], until_ms: int, step_ms: float = 0.5,
             plant_ms: int = 25) -> list[tuple[float, str]]:
    """(time ms, "sample" | "watchdog") of every release, time advancing in ``step_ms``
    with the samples at ``sample_ms`` (the ECU's order: windows closed first, then the
    sample), the ECU told the plant's period ``plant_ms``."""
    release = new_release(plant_ms)
    pending = sorted(sample_ms)
    out = []
    t = 0.0
    while t <= until_ms:
        now = round(t * MS)
        if release.on_time(now)[0]:
            out.append((t, "watchdog"))
        while pending and pending[0] <= t:
            if release.on_sample(round(pending.pop(0) * MS)):
                out.append((t, "sample"))
        t += step_ms
    return out


def test_a_10_ms_plant_releases_on_the_sample_nearest_each_25_ms_instant() -> None:
    """Revision 2's plant, unchanged: one sample in every window, spacing 30 / 20 ms, a
    25 ms mean period, never the watchdog."""
    got = releases([10.0 * k for k in range(41)], 400, plant_ms=10)
    print("releases:", got)
    times = [t for t, _ in got]
    assert all(kind == "sample" for _, kind in got)
    assert times == [0, 30, 50, 80, 100, 130, 150, 180, 200, 230, 250, 280, 300, 330, 350, 380, 400]
    assert (times[-1] - times[0]) / (len(times) - 1) == 25.0


def test_a_25_ms_plant_releases_on_every_sample_whatever_its_phase() -> None:
    """The grid anchors at the first sample, so a 25 ms plant at any phase is served on
    arrival, also with 2 ms of jitter either way."""
    for phase in (0.0, 7.0, 13.5, 24.0):
        samples = [phase + 25.0 * k + (2.0 if k % 2 else -2.0) * (k > 0) for k in range(20)]
        got = releases(samples, round(samples[-1]) + 1)
        assert [t for t, _ in got] == [pytest.approx(s, abs=0.5) for s in samples], (phase, got)
        assert all(kind == "sample" for _, kind in got)


def test_a_lost_sample_still_gives_a_cycle_at_the_watchdog() -> None:
    """25 ms plant, the sample of 50 ms lost: the watchdog releases at 50 + 7.5 ms, and the
    next sample is served at 75 ms again."""
    got = releases([0, 25, 75, 100], 110)
    print("releases:", got)
    assert got == [(0, "sample"), (25, "sample"), (57.5, "watchdog"), (75, "sample"), (100, "sample")]


def test_samples_faster_than_the_period_release_once_per_instant_at_least_15_ms_apart() -> None:
    """A 1 ms burst of samples: one release per 25 ms instant, never closer than the
    minimum spacing."""
    got = releases([float(t) for t in range(0, 200)], 200, plant_ms=10)
    times = [t for t, _ in got]
    print("releases:", got)
    assert len(times) == 9  # instants 0, 25, ... 200
    assert min(b - a for a, b in zip(times, times[1:])) >= MIN_RELEASE_SPACING_NS / MS


def test_a_late_loop_releases_the_newest_instant_and_skips_the_older_ones() -> None:
    release = new_release()
    assert release.on_sample(0)
    due, skipped = release.on_time(80 * MS)  # windows of 25, 50 and 75 (closes 82.5) ...
    assert due and skipped == 1              # ... 25 and 50 closed unreleased: one runs
    assert release.instant_ns == 75 * MS and not release.on_time(81 * MS)[0]


def test_a_restarted_plant_anchors_the_grid_again() -> None:
    """No sample for more than 100 ms (SAFE_STOP): the next one anchors the grid anew and
    runs the task, unless the watchdog ran it less than 15 ms before (then that release
    stands for the instant and the next sample runs the task: a 25 ms plant's grid anchors
    at the sample, so that it is served at any phase against the old grid). A 10 ms plant's
    grid anchors at the release (one of its samples is in every window), at most 35 ms
    between releases."""
    got = releases([0, 25, 50, 275, 300], 310)
    print("releases:", got)
    assert [t for t, kind in got if kind == "sample"] == [0, 25, 50, 275, 300]
    assert [t for t, kind in got if kind == "watchdog"][-1] == 257.5
    got = releases([0, 25, 50, 261, 286], 290)
    assert [t for t, kind in got if kind == "sample"] == [0, 25, 50, 286]  # 261: 3.5 ms after 257.5
    for gap in (7.5, 10.0, 12.0, 14.5):  # anchored at 257.5, these samples came after every window
        restart = 257.5 + gap
        samples = [restart + 25.0 * k for k in range(6)]
        got = releases([0, 25, 50, *samples], round(samples[-1]) + 1)
        assert [t for t, kind in got if t > 257.5] == [pytest.approx(s, abs=0.5) for s in samples[1:]], (gap, got)
        assert all(kind == "sample" for t, kind in got if t > 257.5), (gap, got)
    for gap in (0.0, 5.0, 7.5, 10.0, 14.5):  # a 10 ms plant restarted at any phase
        samples = [257.5 + gap + 10.0 * k for k in range(12)]
        got = releases([0, 10, 20, 30, 40, 50, *samples], round(samples[-1]) + 1, plant_ms=10)
        times = [t for t, _ in got]
        assert max(b - a for a, b in zip(times, times[1:]) if a >= 257.5) <= 35.0, (gap, got)


def test_a_25_ms_plant_off_its_window_moves_the_grid() -> None:
    """A 25 ms plant whose first sample came 7.5 ms before its next one (the phase of the
    following ones), or whose clock drifts 0.5 ms per period either way: its sample outside
    the pending instant's window anchors the grid again (one instant to the watchdog), and
    each sample that releases the task moves the instant to its arrival (drift followed)."""
    got = releases([0.0, *[7.5 + 25.0 * k for k in range(1, 12)]], 290)
    print("late first sample:", got)
    assert got[-10:] == [(pytest.approx(7.5 + 25.0 * k, abs=0.5), "sample") for k in range(2, 12)]
    for drift in (0.5, -0.5):
        samples = [(25.0 + drift) * k for k in range(60)]
        got = releases(samples, round(samples[-1]) + 1)
        watchdog = [t for t, kind in got if kind == "watchdog"]
        print(f"drift {drift} ms per period: watchdog releases at {watchdog}")
        assert len(watchdog) <= 2 and all(kind == "sample" for _, kind in got[-20:]), got
        assert min(b - a for (a, _), (b, _) in zip(got, got[1:])) >= MIN_RELEASE_SPACING_NS / MS


def test_a_10_ms_plant_off_a_window_does_not_move_the_grid() -> None:
    """The rules above are the 25 ms plant's: a 10 ms plant's samples between two windows only
    refresh the newest sample, as in revision 2 (the releases of the first test)."""
    release = new_release(plant_ms=10)
    assert release.on_sample(0)
    release.on_time(10 * MS)
    assert not release.on_sample(10 * MS) and release.instant_ns == 25 * MS


def test_a_10_ms_plant_after_a_clock_release_sits_inside_its_windows_at_any_phase() -> None:
    """The first sample of a 10 ms plant comes 0-15 ms after a release of the ECU's clock
    (or 0.4 ms before it, stamped first and taken after): that release stands for the
    instant, and the grid anchors in phase with the samples, so that each sits at its
    instant or 5 ms after it, 2.5 ms inside both edges of its window. With 1 ms of jitter
    either way no instant goes to the watchdog. Anchored at the release itself (the rule
    until 2026-12-05), the phases within 1 ms of an edge lost samples to the watchdog: 18
    of the 61 phases here, 1 to 6 instants each."""
    rng = random.Random(7)
    failed = []
    for phase in [-0.4, *(0.25 * k for k in range(60))]:
        release = new_release(plant_ms=10)
        release.note_release(0)
        release.note_release(25 * MS)
        samples = [25.0 + phase + 10.0 * k + rng.uniform(-1.0, 1.0) for k in range(60)]
        watchdog, offsets = 0, []
        for sample in samples:
            watchdog += release.on_time(round(sample * MS))[0]
            if release.on_sample(round(sample * MS)):
                offsets.append(sample - release.instant_ns / MS)  # after its instant, ms
        if watchdog:
            failed.append((phase, watchdog))
        # 0 or 5 ms, give or take the anchoring sample's jitter and its own
        assert len(offsets) >= 20 and -2.0 - 1e-6 <= min(offsets) and max(offsets) <= 7.0 + 1e-6, (phase, offsets)
    assert not failed, f"(phase ms, watchdog releases): {failed}"


def _watchdog_releases(samples_ms: list[float]) -> tuple[int, list[float]]:
    """A 10 ms plant whose first sample comes 12 ms after a release of the ECU's clock:
    (watchdog releases, each releasing sample's offset from its instant in ms)."""
    release = new_release(plant_ms=10)
    release.note_release(0)
    watchdog, offsets = 0, []
    for sample in samples_ms:
        watchdog += release.on_time(round(sample * MS))[0]
        if release.on_sample(round(sample * MS)):
            offsets.append((sample - release.instant_ns / MS) % 5.0)
    return watchdog, offsets


def _drifting_plant(rng: random.Random, anchor_error_ms: float, drift_ms: float, n: int) -> list[float]:
    """Samples of a 10 ms plant: the first at 12 ms, the next ones ``anchor_error_ms`` off its
    phase, the plant's clock ``drift_ms`` slower per sample, 0.7 ms of jitter either way."""
    return [12.0] + [12.0 + anchor_error_ms + (10.0 + drift_ms) * k + rng.uniform(-0.7, 0.7) for k in range(1, n)]


@pytest.mark.parametrize("anchor_error_ms, drift_ms", [(2.0, 0.0), (2.2, 0.0), (0.0, 0.01), (0.0, -0.01),
                                                       (1.5, 0.005)])
def test_a_10_ms_plant_s_grid_follows_the_samples_phase(monkeypatch, anchor_error_ms: float,
                                                        drift_ms: float) -> None:
    """The first sample in real time can come apart from the next ones' phase (-0.8 to
    +1.5 ms in make timing), and a plant's clock can drift against the ECU's (1000 ppm here:
    0.01 ms per sample, 20 ms over the run). Either puts samples at a window's edge, where
    jitter gives instants to the watchdog. Each releasing sample moves the instant by 1/8 of
    its phase error, so the samples settle at their instant or 5 ms after it: no watchdog
    release after the first 0.5 s. With the grid fixed (the rule until 2026-12-06) the same
    samples give instants to the watchdog."""
    import firmware_sim.clock as clock
    samples = _drifting_plant(random.Random(11), anchor_error_ms, drift_ms, 2000)
    watchdog, offsets = _watchdog_releases(samples)
    settled = [min(o, 5.0 - o) for o in offsets[20:]]  # distance from the nearest of 0 and 5 ms
    print(f"followed: {watchdog} watchdog releases, phase error up to {max(settled):.2f} ms after 0.5 s")
    assert watchdog == 0 and max(settled) < 1.0
    monkeypatch.setattr(clock, "PHASE_FOLLOW_DIVISOR", 10**15)  # the grid fixed
    watchdog_fixed, _ = _watchdog_releases(samples)
    print(f"fixed grid: {watchdog_fixed} watchdog releases")
    assert watchdog_fixed > 0


def test_a_10_ms_plant_s_phase_follow_is_nothing_in_lockstep() -> None:
    """Samples and instants on the 5 ms ticks: the phase error is 0 and the grid is the one
    the in-phase anchor gives, 25 ms apart for the whole run."""
    release = new_release(plant_ms=10)
    release.note_release(0)
    instants = set()
    for k in range(1, 400):
        release.on_time(10 * k * MS)
        release.on_sample(10 * k * MS)
        instants.add(release.instant_ns)
    assert all(instant % (25 * MS) == 0 for instant in instants)


def test_control_release_is_checked() -> None:
    assert EcuConfig().control_release == "clock"  # revision 2 unless asked
    EcuConfig(control_release="sample")
    with pytest.raises(ConfigError, match=r"control_release must be one of clock, sample, got 'fast'"):
        EcuConfig(control_release="fast")


def test_plant_sample_period_is_checked_and_counted_by_the_continuity_check() -> None:
    assert EcuConfig().plant_sample_period_ms == 10
    EcuConfig(control_release="sample", plant_sample_period_ms=25)
    with pytest.raises(ConfigError, match=r"plant_sample_period_ms 25 needs control_release 'sample'"):
        EcuConfig(plant_sample_period_ms=25)
    with pytest.raises(ConfigError, match=r"plant_sample_period_ms must be 10 or 25, got 20"):
        EcuConfig(control_release="sample", plant_sample_period_ms=20)


def test_the_plant_publishes_every_25_ms_when_asked() -> None:
    from hil.errors import HilError
    from hil.plant_node import PlantNode
    from hil.scenario import load_scenario

    smoke = load_scenario("dlc_smoke")
    plant = PlantNode(smoke, sample_period_ms=25)
    assert [len(plant.frames_due(t)) for t in range(0, 105, 5)] == [3 if t % 25 == 0 else 0 for t in range(0, 105, 5)]
    assert len(PlantNode(smoke).frames_due(10)) == 3
    with pytest.raises(HilError, match="sample_period_ms must be 10 or 25, got 20"):
        PlantNode(smoke, sample_period_ms=20)


# ------------------------------------------------------------------ the ECU in lockstep
def sample_rig(buses) -> Rig:
    rig = Rig(*buses, config=EcuConfig(control_release="sample"))
    rig.handshake()
    return rig


def sample_ages(rig: Rig) -> list[float]:
    """Wraps the ECU's control task: the newest sample's age at each task start, ms."""
    ages: list[float] = []
    task = rig.ecu._control_task

    def probe(now_ns: int, release_jitter_s: float) -> None:
        arrival = rig.ecu._rx.newest_sample_arrival_ns
        ages.append(float("nan") if arrival is None else (now_ns - arrival) / MS)
        task(now_ns, release_jitter_s)

    rig.ecu._control_task = probe
    return ages


def command_ticks(rig: Rig) -> list[int]:
    return [t for t, sent in sorted(rig.log.items()) if commands(sent)]


def test_in_lockstep_a_10_ms_plant_is_served_on_fresh_samples(buses) -> None:
    rig = sample_rig(buses)
    ages = sample_ages(rig)
    rig.run(0, 500)
    ticks = command_ticks(rig)
    print("command ticks:", ticks, "sample age at task start (ms):", ages)
    assert ticks == [t for t in range(0, 505, 10) if t % 50 in (0, 30)]
    assert max(ages) <= 0.0  # the task runs in the tick of its sample: age 0 (clock: 0 or 5 ms)
    assert all(rig.command_at(t).ctrl_mode is CtrlMode.ACTIVE for t in ticks[1:])


def test_in_lockstep_a_lost_sample_gives_a_cycle_at_the_watchdog_under_degraded_rules(buses) -> None:
    """10 ms plant, the samples of 100 to 140 ms lost: the watchdog runs the tasks of the
    instants 100 and 125 in the first tick at or after their windows' end (110 and 135 ms),
    on the newest good sample (90 ms: 20 ms old, still fresh; then 45 ms, DEGRADED), and
    the sample of 150 ms runs the next one on time."""
    rig = sample_rig(buses)
    ages = sample_ages(rig)
    # a plant standing still: the position stays continuous across the gap
    rig.run(0, 200, plant=lambda t: None if 100 <= t <= 140 else {"vx": 10.0, "x": 1.0, "y": 0.0})
    ticks = command_ticks(rig)
    print("command ticks:", ticks, "ages:", ages, "modes:", [rig.command_at(t).ctrl_mode.name for t in ticks])
    assert ticks == [0, 30, 50, 80, 110, 135, 150, 180, 200]
    assert ages[4:7] == [20.0, 45.0, 0.0]
    assert [rig.command_at(t).ctrl_mode for t in (110, 135, 150)] == [
        CtrlMode.ACTIVE, CtrlMode.DEGRADED, CtrlMode.ACTIVE]
    assert rig.diag_at(135).faults & 0b0001 and not rig.diag_at(150).faults & 0b0001


def test_in_lockstep_two_runs_with_sample_release_send_the_same_frames(buses) -> None:
    import can
    import uuid

    runs = []
    for _ in range(2):
        channel = f"ecu-rev3-{uuid.uuid4()}"
        pair = (can.Bus(interface="virtual", channel=channel), can.Bus(interface="virtual", channel=channel))
        try:
            rig = sample_rig(pair)
            sent = rig.run(0, 400)
            runs.append([(m.arbitration_id, bytes(m.data)) for m in sent
                         if m.arbitration_id == FrameId.STEER_TORQUE_CMD])
        finally:
            for bus in pair:
                bus.shutdown()
    assert runs[0] == runs[1] and len(runs[0]) == 17
