"""Identification excitation in the ECU (issue 20): the programs, their limits, the
|e_Y| stop, program files, ``--excite`` on the ECU and ``hil run``."""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from firmware_sim import cli
from firmware_sim.errors import ConfigError
from firmware_sim.excitation import (SHIPPED_PROGRAMS, Excitation, ExcitationProgram,
                                     excitation_offsets, load_program, steer_amplitude)

TS = 0.025
STEER_RANGE = (-0.3, 0.3)
TORQUE_RANGE = (-3000.0, 3000.0)


def test_offsets_are_zero_before_the_delay_and_bounded_by_the_speed_scaled_amplitude():
    for name, program in SHIPPED_PROGRAMS.items():
        assert excitation_offsets(program, program.delay_s - 0.01, 15.0) == (0.0, 0.0), name
        times = np.arange(program.delay_s, program.delay_s + 120.0, TS)
        for vx in (3.0, 10.0, 30.0):
            steer = np.array([excitation_offsets(program, t, vx)[0] for t in times])
            amplitude = steer_amplitude(program, vx)
            print(name, vx, f"amplitude {amplitude:.4f} max {np.abs(steer).max():.4f}")
            assert np.abs(steer).max() <= amplitude + 1e-12
            assert np.abs(steer).max() > 0.5 * amplitude  # it does excite
    chirp = SHIPPED_PROGRAMS["chirp"]
    # speed scaling: 1.5 m/s^2 * 2.8 m / vx^2, capped at 0.03 rad
    assert steer_amplitude(chirp, 30.0) == pytest.approx(1.5 * 2.8 / 900.0)
    assert steer_amplitude(chirp, 3.0) == 0.03


def test_prbs_is_a_pure_function_of_time_and_seed():
    prbs = SHIPPED_PROGRAMS["prbs"]
    times = np.arange(2.0, 30.0, TS)
    first = [excitation_offsets(prbs, t, 20.0)[0] for t in times]
    again = [excitation_offsets(prbs, t, 20.0)[0] for t in times]
    other = [excitation_offsets(dataclasses.replace(prbs, seed=7), t, 20.0)[0] for t in times]
    assert first == again and first != other
    values = np.sign(first)
    assert set(values) == {-1.0, 1.0} and abs(values.mean()) < 0.3  # balanced
    torque = [excitation_offsets(SHIPPED_PROGRAMS["prbs-torque"], t, 20.0)[1] for t in times]
    assert set(np.abs(torque)) == {300.0}


def test_steps_repeat_plus_zero_minus_zero():
    steps = SHIPPED_PROGRAMS["steps"]
    amplitude = steer_amplitude(steps, 20.0)
    values = [excitation_offsets(steps, steps.delay_s + 1.0 + 2.0 * k, 20.0)[0] for k in range(8)]
    assert values == pytest.approx([amplitude, 0, -amplitude, 0] * 2)


def test_excitation_keeps_the_rate_limit_and_the_command_limits():
    program = dataclasses.replace(SHIPPED_PROGRAMS["prbs"], lateral_accel_mps2=0.0,
                                  steer_amplitude_rad=0.1, delay_s=0.0)
    excitation = Excitation(program, TS)
    offsets, commands = [], []
    for k in range(400):
        steer, torque, status = excitation.step(k * TS, True, 10.0, 0.0, 0.25, 100.0,
                                                STEER_RANGE, TORQUE_RANGE)
        offsets.append(status.steer_offset)
        commands.append(steer)
        assert STEER_RANGE[0] <= steer <= STEER_RANGE[1] and torque == 100.0
    largest_step = np.abs(np.diff([0.0, *offsets])).max()
    print("largest offset step", largest_step, "limit", program.steer_rate_limit_rad_s * TS)
    assert largest_step <= program.steer_rate_limit_rad_s * TS + 1e-12
    assert max(commands) == 0.3  # 0.25 + 0.1 clipped at the limit
    assert min(commands) < 0.2


def test_excitation_is_off_outside_active_and_passes_a_non_finite_command_to_the_guard():
    excitation = Excitation(dataclasses.replace(SHIPPED_PROGRAMS["chirp"], delay_s=0.0), TS)
    for k in range(100):
        excitation.step(k * TS, True, 10.0, 0.0, 0.0, 0.0, STEER_RANGE, TORQUE_RANGE)
    steer, torque, status = excitation.step(2.5, False, 10.0, 0.0, 0.01, 5.0, STEER_RANGE, TORQUE_RANGE)
    assert (steer, torque, status.steer_offset) == (0.01, 5.0, 0.0)
    steer, _, _ = excitation.step(2.525, True, 10.0, 0.0, math.nan, 0.0, STEER_RANGE, TORQUE_RANGE)
    assert math.isnan(steer)


def test_excitation_stops_beyond_the_lateral_error_bound_ramps_out_and_restarts_on_reset():
    program = dataclasses.replace(SHIPPED_PROGRAMS["steps"], delay_s=0.0, lateral_accel_mps2=0.0,
                                  steer_amplitude_rad=0.05)
    excitation = Excitation(program, TS)
    for k in range(40):
        _, _, status = excitation.step(k * TS, True, 10.0, 0.2, 0.0, 0.0, STEER_RANGE, TORQUE_RANGE)
    assert status.steer_offset == pytest.approx(0.05) and status.stopped_reason is None
    _, _, status = excitation.step(1.0, True, 10.0, -1.6, 0.0, 0.0, STEER_RANGE, TORQUE_RANGE)
    print(status.stopped_reason)
    assert "1.60 m > 1.5 m" in status.stopped_reason
    offsets = [excitation.step(1.0 + k * TS, True, 10.0, 0.0, 0.0, 0.0, STEER_RANGE,
                               TORQUE_RANGE)[2].steer_offset for k in range(1, 10)]
    assert offsets[-1] == 0.0 and all(b <= a for a, b in zip(offsets, offsets[1:]))  # ramped out
    excitation.reset()
    _, _, status = excitation.step(5.0, True, 10.0, 0.0, 0.0, 0.0, STEER_RANGE, TORQUE_RANGE)
    assert status.stopped_reason is None and status.steer_offset > 0


def test_program_files_toml_and_csv(tmp_path):
    toml = tmp_path / "slow_chirp.toml"
    toml.write_text('kind = "chirp"\nchirp_end_hz = 1.0\nsteer_amplitude_rad = 0.02\nseed = 3\n')
    program = load_program(str(toml))
    assert (program.name, program.kind, program.chirp_end_hz, program.seed) == ("slow_chirp", "chirp", 1.0, 3)
    table = tmp_path / "doublet.csv"
    table.write_text("time_s,steer_rad,torque_nm\n0,0,0\n1,0.02,100\n2,-0.02,0\n3,0,0\n")
    program = load_program(str(table))
    assert program.kind == "table"
    assert excitation_offsets(program, program.delay_s + 1.5, 20.0) == pytest.approx((0.0, 50.0))
    assert excitation_offsets(program, program.delay_s + 10.0, 20.0) == (0.0, 0.0)
    assert load_program("prbs") is SHIPPED_PROGRAMS["prbs"]


@pytest.mark.parametrize("name, text, message", [
    ("a.toml", 'kind = "chirp"\nwobble = 1\n', "unknown field(s) wobble"),
    ("b.toml", 'kind = "sine"\n', "kind 'sine' is not one of"),
    ("c.toml", 'kind = "prbs"\nsteer_amplitude_rad = 0.5\n', "exceeds the steering limit"),
    ("d.toml", 'kind = "prbs"\nhold_s = -1\n', "hold_s must be a finite number > 0"),
    ("e.toml", 'hold_s = 1\n', "field 'kind' missing"),
    ("f.toml", 'kind = ', "not valid TOML"),
    ("g.csv", "t,steer\n0,0\n", "line 1: header must be time_s,steer_rad"),
    ("h.csv", "time_s,steer_rad\n0,0\n1,x\n", "line 3: not a number"),
    ("i.csv", "time_s,steer_rad\n0,0\n0,0.01\n", "time_s must increase strictly"),
    ("j.txt", "", "not a shipped program"),
    ("k.toml", 'kind = "chirp"\nchirp_start_hz = 1e308\nchirp_end_hz = 1e308\ndelay_s = 0\n',
     "chirp_start_hz 1e+308 exceeds its limit 20.0"),
    ("l.toml", 'kind = "prbs"\nhold_s = 1e9\n', "hold_s 1000000000.0 exceeds its limit 3600.0"),
    ("m.toml", 'kind = "prbs"\nseed = 9223372036854775807\n', "must be an integer of magnitude below 2^63 - 1"),
    ("n.toml", 'kind = "prbs"\ndelay_s = 1' + '0' * 400 + '\n', "delay_s must be a finite number >= 0"),
    ("o.csv", "time_s,steer_rad\n0,0\n1e300,0.01\n", "table time_s exceeds its limit 86400.0 s"),
    ("p.csv", "time_s,steer_rad,torque_nm\n0,0,0\n1,0.01,-3500\n", "table torque_nm exceeds its limit"),
])
def test_bad_program_files_are_named_errors(tmp_path, name, text, message):
    file = tmp_path / name
    file.write_text(text)
    with pytest.raises(ConfigError) as info:
        load_program(str(file))
    print(info.value)
    assert message in str(info.value)
    assert name in str(info.value) or "program" in str(info.value)


def test_ecu_cli_refuses_a_bad_excite_before_opening_the_bus(capsys, tmp_path):
    path = tmp_path / "p.csv"
    path.write_text("x,y,yaw\n0,0,0\n0.5,0,0\n")
    status = cli.main(["--interface", "no-such-interface", "--controller", "lmpc", "--path",
                       f"1={path}", "--lockstep", "--excite", str(tmp_path / "missing.toml")])
    err = capsys.readouterr().err
    print(err)
    assert status == 2 and err.startswith("error: --excite") and "cannot read" in err


def test_hil_run_with_excitation_adds_it_only_while_active_and_within_the_limits():
    from can_defs.frames import CtrlMode
    from hil.scenario import load_scenario
    from hil.session import default_options, run_hil

    scenario = load_scenario("dlc_smoke")
    plain = run_hil(scenario, default_options("lmpc")).ecu_trace
    excited_run = run_hil(scenario, dataclasses.replace(default_options("lmpc"), excite="prbs"))
    excited = excited_run.ecu_trace
    difference = excited["steer_angle_cmd"] - plain["steer_angle_cmd"]
    active = excited["ctrl_mode"] == int(CtrlMode.ACTIVE)
    first_active = excited["time"][active][0]
    early = excited["time"] < first_active + SHIPPED_PROGRAMS["prbs"].delay_s
    print("largest difference", np.abs(difference).max(), "e_Y", excited_run.tracking.lateral.as_dict())
    assert np.all(difference[early] == 0.0)
    assert np.abs(difference[~early]).max() > 0.005
    assert np.all(np.abs(excited["steer_angle_cmd"]) <= 0.3)
    assert excited_run.tracking.lateral.max_abs < 1.5


def test_a_failing_excitation_leaves_the_law_command_and_never_raises(monkeypatch):
    import can
    from firmware_sim.ecu import Ecu
    from firmware_sim.excitation import Excitation as RealExcitation

    bus = can.Bus(interface="virtual", channel="excitation-failure")
    ecu = Ecu(bus, "lmpc", {}, controller_factory=lambda name: None,
              excitation=SHIPPED_PROGRAMS["prbs"])
    try:
        def broken(self, *args, **kwargs):
            raise ValueError("broken")
        monkeypatch.setattr(RealExcitation, "step", broken)

        class Measurement:
            x = y = yaw = 0.0
            vx = 10.0
        assert ecu._excite(1.0, Measurement(), 0.01, 5.0) == (0.01, 5.0)
        assert "excitation failed: broken" in ecu._excitation.stopped_reason
    finally:
        ecu.close()


def test_a_non_finite_target_at_run_time_ends_the_excitation(monkeypatch):
    """A target that is not finite (a program the load checks let through by mistake) ends
    the excitation for the engagement: the law's command this cycle, then a ramp out."""
    import firmware_sim.excitation as excitation_module

    excitation = Excitation(SHIPPED_PROGRAMS["chirp"], TS)
    program = SHIPPED_PROGRAMS["chirp"]
    for k in range(int((program.delay_s + 0.5) / TS)):   # running, with an offset applied
        steer, _, status = excitation.step(k * TS, True, 10.0, 0.0, 0.01, 0.0, STEER_RANGE, TORQUE_RANGE)
    assert status.running and status.steer_offset != 0.0
    monkeypatch.setattr(excitation_module, "excitation_offsets", lambda *args: (math.nan, 0.0))
    steer, torque, status = excitation.step(program.delay_s + 1.0, True, 10.0, 0.0, 0.01, 5.0,
                                            STEER_RANGE, TORQUE_RANGE)
    assert (steer, torque) == (0.01, 5.0)
    assert status.stopped_reason.startswith("excitation failed: target not finite (steer nan")
    later = [excitation.step(program.delay_s + 1.0 + k * TS, True, 10.0, 0.0, 0.01, 0.0, STEER_RANGE,
                             TORQUE_RANGE)[0] for k in range(1, 40)]
    assert all(math.isfinite(value) for value in later) and later[-1] == 0.01   # ramped out


def test_a_table_at_its_row_limit_costs_the_control_task_little():
    """A 20,000-row table (the limit of both ECUs) is searched by bisection: 1,000 lookups
    near its end take far less than one 25 ms control period (a linear search took about
    1.5 ms each; issue 38, item 8)."""
    import time

    from firmware_sim.excitation import TABLE_MAX_ROWS

    times = tuple(0.025 * k for k in range(TABLE_MAX_ROWS))
    program = ExcitationProgram("long", "table", table_time_s=times,
                                table_steer_rad=tuple(0.01 if k % 2 else -0.01 for k in range(TABLE_MAX_ROWS)))
    started = time.perf_counter()
    for _ in range(1000):
        steer, _ = excitation_offsets(program, program.delay_s + times[-2] + 0.0125, 10.0)
    assert time.perf_counter() - started < 0.5
    assert steer == pytest.approx(0.0)   # halfway between -0.01 and +0.01
