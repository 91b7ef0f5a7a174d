"""Fixed settings of the ECU: contract thresholds and the safe-stop / guard limits.

The thresholds marked *contract* come from ``docs/can-contract.md`` and must not be tuned; the
others are the ECU's own choice, documented in ``docs/ecu.md``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

from firmware_sim.errors import ConfigError

#: Representable range of STEER_TORQUE_CMD.DRIVE_TORQUE_CMD (16 bit signed, 0.1 N m).
DBC_DRIVE_TORQUE_MIN_NM = -3276.8
DBC_DRIVE_TORQUE_MAX_NM = 3276.7
#: Representable range of STEER_TORQUE_CMD.STEER_ANGLE_CMD (16 bit signed, 0.0001 rad).
DBC_STEER_MIN_RAD = -3.2768
DBC_STEER_MAX_RAD = 3.2767

NS_PER_MS = 1_000_000
NS_PER_S = 1_000_000_000


@dataclass(frozen=True)
class Plausibility:
    """Plausibility of a plant sample (*contract*, rev. 2, "Receiving rules"); SI units.

    A sample passes when VX, |VY|, |YAW_RATE| and |YAW| are inside these bounds and its
    position is continuous with the last good sample: distance <= (max over the two
    samples of hypot(VX, VY) + ``speed_margin_mps``) * elapsed + ``position_slack_m``,
    elapsed = ``sample_period_ms`` * counter difference (mod 16). The continuity check
    applies only while the last good sample is at most ``continuity_window_ms`` old.
    """

    vx_min_mps: float = -5.0
    vx_max_mps: float = 70.0
    vy_max_mps: float = 10.0
    yaw_rate_max_rad_s: float = 2.5
    yaw_max_rad: float = math.pi + 0.0001  # one LSB: both ends of [-pi, pi) encode to +-3.1416
    speed_margin_mps: float = 5.0
    position_slack_m: float = 0.2
    sample_period_ms: int = 10
    continuity_window_ms: int = 100


#: Release of the control task (contract rev. 3): ``"clock"`` the 25 ms clock of revision 2,
#: ``"sample"`` the arrival of a good plant sample set in the window of each 25 ms instant.
CONTROL_RELEASES = ("clock", "sample")
#: Sample periods of the plant the ECU can serve, ms (contract rev. 3: 10 ms as in revision 2,
#: or 25 ms for a plant that knows revision 3; only with the sample release).
PLANT_SAMPLE_PERIODS_MS = (10, 25)
#: Rev. 3 release window of a control instant N: [N - this, N + SAMPLE_WATCHDOG_NS) (*contract*).
SAMPLE_WINDOW_EARLY_NS = 2_500_000
#: Rev. 3 period watchdog: no good sample in the window -> the task is released at N + this.
SAMPLE_WATCHDOG_NS = 7_500_000
#: Rev. 3 minimum spacing of two releases (period - window width), ns (*contract*).
MIN_RELEASE_SPACING_NS = 15_000_000
#: Rev. 3 rule 4: a sample set that releases the task moves a 10 ms plant's pending instant
#: by its phase error divided by this (truncated toward zero, ns), so the grid follows the
#: samples' phase (*contract*).
PHASE_FOLLOW_DIVISOR = 8


#: Lost bus (*contract*, rev. 2): receive errors that persist this long are a lost bus.
BUS_LOST_AFTER_MS = 100
#: Lost bus: wait between attempts to reopen it, s (*contract*: every second).
BUS_REOPEN_INTERVAL_S = 1.0


@dataclass(frozen=True)
class EcuConfig:
    """Timing thresholds and actuator limits of the ECU (times in ms, SI otherwise).

    Attributes:
        control_period_ms: period of the control task (*contract*: 25 ms).
        tick_ms: lockstep tick length (*contract*: 5 ms).
        sample_stale_ms: a plant sample older than this at a control task -> DEGRADED
            (*contract*: 20 ms).
        sample_lost_ms: no good plant sample for longer than this -> SAFE_STOP
            (*contract*: 100 ms).
        planner_timeout_ms: PLANNER_REQ missing longer than this -> STANDBY
            (*contract*: 100 ms).
        controller_failed_cycles: a controller whose step falls back (FAULTS bit 2) on
            this many consecutive control tasks is a failing controller -> SAFE_STOP
            (*contract*, rev. 2: 4 tasks, the 100 ms of ``sample_lost_ms`` at the 25 ms
            period: as long as the ECU drives without a good sample, it drives on no good
            command).
        steer_limit_rad: |STEER_ANGLE_CMD| limit (*contract*: 0.3 rad, eq. 22).
        drive_torque_limit_nm: |DRIVE_TORQUE_CMD| limit enforced by the guard; at most the
            DBC's representable range.
        safe_stop_brake_torque_nm: braking torque (positive number, sent negative) in
            SAFE_STOP until standstill.
        safe_stop_steer_rate_rad_s: rate at which SAFE_STOP returns the steering to straight.
        standstill_speed_mps: |vx| below which a fresh sample counts as standstill.
        max_catch_up_tasks: most control task instants run for one TICK when the master
            skips ticks (the newest ones are run, older ones are skipped and counted as
            overruns) - bounds the work of one TICK.
        timing_capacity: cycles kept by the timing ring buffer.
        solver_budget_ms: wall-clock budget of one control step's solver in real time
            (``Controller.set_time_budget``; only NMPC's varies enough to need it): 15 ms
            leaves the rest of the 25 ms period to the lift, the observer, the frames and a
            busy machine. Never applied in lockstep, whose commands must not depend on the
            machine.
        control_release: what releases the control task (``CONTROL_RELEASES``): ``"clock"``
            (revision 2, the default: every 25 ms on the clock) or ``"sample"`` (revision 3:
            the arrival of a good plant sample set in the window of each 25 ms instant, with
            the period watchdog; ``firmware_sim.clock.SampleRelease``).
        plant_sample_period_ms: the plant's sample period (``PLANT_SAMPLE_PERIODS_MS``):
            10 ms (revisions 2 and 3) or 25 ms (rev. 3, only with the sample release: on the
            clock a 25 ms sample would be up to 25 ms old, DEGRADED); the continuity check
            counts this much time per counter step (``Plausibility.sample_period_ms``).
    """

    control_period_ms: int = 25
    tick_ms: int = 5
    sample_stale_ms: int = 20
    sample_lost_ms: int = 100
    planner_timeout_ms: int = 100
    controller_failed_cycles: int = 4
    steer_limit_rad: float = 0.3
    drive_torque_limit_nm: float = 3000.0
    safe_stop_brake_torque_nm: float = 1500.0
    safe_stop_steer_rate_rad_s: float = 0.2
    standstill_speed_mps: float = 0.1
    max_catch_up_tasks: int = 40
    timing_capacity: int = 1 << 16
    solver_budget_ms: int = 15
    control_release: str = "clock"
    plant_sample_period_ms: int = 10

    def __post_init__(self) -> None:
        for name in ("control_period_ms", "tick_ms", "sample_stale_ms", "sample_lost_ms",
                     "planner_timeout_ms", "controller_failed_cycles", "max_catch_up_tasks",
                     "timing_capacity", "solver_budget_ms"):
            value = getattr(self, name)
            if not isinstance(value, int) or isinstance(value, bool) or value <= 0:
                raise ConfigError(f"EcuConfig.{name} must be a positive integer, got {value!r}")
        for name in ("steer_limit_rad", "drive_torque_limit_nm", "safe_stop_brake_torque_nm",
                     "safe_stop_steer_rate_rad_s", "standstill_speed_mps"):
            value = getattr(self, name)
            if not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
                raise ConfigError(f"EcuConfig.{name} must be a positive finite number, got {value!r}")
        if self.steer_limit_rad > DBC_STEER_MAX_RAD:
            raise ConfigError(f"EcuConfig.steer_limit_rad {self.steer_limit_rad} exceeds the DBC "
                              f"range {DBC_STEER_MAX_RAD}")
        if self.drive_torque_limit_nm > DBC_DRIVE_TORQUE_MAX_NM:
            raise ConfigError(f"EcuConfig.drive_torque_limit_nm {self.drive_torque_limit_nm} exceeds "
                              f"the DBC range {DBC_DRIVE_TORQUE_MAX_NM}")
        if self.solver_budget_ms >= self.control_period_ms:
            raise ConfigError(f"EcuConfig.solver_budget_ms {self.solver_budget_ms} must be below the control "
                              f"period {self.control_period_ms} ms")
        if self.safe_stop_brake_torque_nm > self.drive_torque_limit_nm:
            raise ConfigError(f"EcuConfig.safe_stop_brake_torque_nm {self.safe_stop_brake_torque_nm} "
                              f"exceeds drive_torque_limit_nm {self.drive_torque_limit_nm}")
        if self.control_release not in CONTROL_RELEASES:
            raise ConfigError(f"EcuConfig.control_release must be one of {', '.join(CONTROL_RELEASES)}, "
                              f"got {self.control_release!r}")
        if self.plant_sample_period_ms not in PLANT_SAMPLE_PERIODS_MS:
            raise ConfigError(f"EcuConfig.plant_sample_period_ms must be 10 or 25, "
                              f"got {self.plant_sample_period_ms!r}")
        if self.plant_sample_period_ms == 25 and self.control_release != "sample":
            raise ConfigError("EcuConfig.plant_sample_period_ms 25 needs control_release 'sample', "
                              f"got {self.control_release!r}")
        if self.control_period_ms % self.tick_ms:
            raise ConfigError(f"EcuConfig.control_period_ms {self.control_period_ms} is not a "
                              f"multiple of tick_ms {self.tick_ms}")
