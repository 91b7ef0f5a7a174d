"""``--excite PROGRAM`` in the C ECU executable (firmware/src/ecu_excite.c) against the
Python ECU's (firmware_sim/excitation.py): the same STEER_TORQUE_CMD frames in lockstep on
``dlc_smoke`` for a shipped program and a CSV table program (equal byte for byte, which
the equivalence rule's 1 LSB allows), the excitation visible in those frames, and the same
one-line errors for a bad program."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from can_defs.codec import decode
from can_defs.frames import FrameId
from studies.bench_native import run_on_hub
from test_firmware_c_core import native  # noqa: F401 (the fixture: the firmware built)

ROOT = Path(__file__).resolve().parent.parent
ECU = ROOT / os.environ.get("ECU_EXE", "build/firmware/ecu")
#: The C ECU's table limit (ECU_EXCITE_TABLE_MAX in firmware/src/ecu_excite.h).
TABLE_MAX = 20000


def commands(raw) -> list[tuple[int, bytes]]:
    """(tick ms, payload) of the STEER_TORQUE_CMD frames of a run."""
    return [(tick, data) for tick, frame_id, data in raw if frame_id == FrameId.STEER_TORQUE_CMD]


def run_both(program: str, controller: str, tmp_path: Path) -> tuple[dict[str, list[tuple[int, bytes]]],
                                                                     dict[str, str]]:
    """Both ECUs with ``--excite program``: their commands and their output."""
    runs, outputs = {}, {}
    for which in ("python", "c"):
        raw, _, status, output = run_on_hub(which, "dlc_smoke", controller, tmp_path / f"{which}.log",
                                            executable=ECU, extra=("--excite", program))
        assert status == 0, output[-2000:]
        assert "excitation " in output   # the program's one-line description, logged at start-up
        runs[which], outputs[which] = commands(raw), output
    return runs, outputs


def steer(data: bytes) -> float:
    return decode(FrameId.STEER_TORQUE_CMD, data).frame.steer_angle_cmd


def table_program(tmp_path: Path) -> Path:
    """A CSV table: a steering doublet of +-0.02 rad and a torque pulse, 0.5 s to 1.6 s."""
    path = tmp_path / "doublet.csv"
    path.write_text("time_s,steer_rad,torque_nm\n0.0,0.0,0.0\n0.5,0.02,100.0\n0.8,-0.02,0.0\n"
                    "1.1,0.02,-100.0\n1.6,0.0,0.0\n")
    return path


def stopping_program(tmp_path: Path) -> Path:
    """Steps of 0.05 rad from 0.5 s on, stopped at |e_Y| > 0.05 m (the bound's path)."""
    path = tmp_path / "stops.toml"
    path.write_text('kind = "steps"  # step responses\nhold_s = 0.5\ndelay_s = 0.5\n'
                    "steer_amplitude_rad = 0.05\nlateral_accel_mps2 = 0\nlateral_error_bound_m = 0.05\n")
    return path


def seeded_program(tmp_path: Path) -> Path:
    """A PRBS with a seed a double cannot hold (2^53 + 1) and a torque PRBS of its own."""
    path = tmp_path / "seeded.toml"
    path.write_text('kind = "prbs"\nseed = 9007199254740993\ndelay_s = 0.5\nhold_s = 0.1\n'
                    "torque_amplitude_nm = 200\ntorque_hold_s = 0.3\n")
    return path


@pytest.mark.parametrize("program", ["prbs-torque", "table", "stops", "seeded"])
def test_c_excitation_equals_python_in_lockstep(native, program: str, tmp_path: Path) -> None:
    """Both ECUs on the hub with the same program: every STEER_TORQUE_CMD equal byte for
    byte; and the program shows (the excited run's commands differ from an unexcited run's
    in the steering after the program's delay); "stops" leaves its e_Y bound in both."""
    files = {"table": table_program, "stops": stopping_program, "seeded": seeded_program}
    spec = str(files[program](tmp_path)) if program in files else program
    runs, outputs = run_both(spec, "lmpc", tmp_path)
    if program == "stops":
        for output in outputs.values():
            assert "excitation stopped for this engagement: |e_Y| = " in output and "> 0.05 m" in output
    python, c = runs["python"], runs["c"]
    assert len(c) == len(python) > 100
    first = next((i for i, (a, b) in enumerate(zip(python, c)) if a != b), None)
    assert first is None, (f"first differing STEER_TORQUE_CMD at tick {python[first][0]} ms: "
                           f"Python {steer(python[first][1])}, C {steer(c[first][1])}")
    raw, _, status, output = run_on_hub("c", "dlc_smoke", "lmpc", tmp_path / "plain.log", executable=ECU)
    assert status == 0, output[-2000:]
    plain = commands(raw)
    changed = [tick for (tick, a), (_, b) in zip(c, plain) if abs(steer(a) - steer(b)) > 1e-3]
    print(f"{program}: {len(c)} commands equal; {len(changed)} steered > 1 mrad off the unexcited run, "
          f"from {changed[:1]} ms")
    delay_ms = 500 if program in ("stops", "seeded") else 2000
    assert len(changed) >= 10 and min(changed) >= delay_ms   # starts after its delay, not before


def cli_error(which: str, program: str) -> tuple[int, str]:
    """Exit status and last stderr line of an ECU started with ``--excite program``."""
    common = ["--controller", "lmpc", "--path", "1=hil/paths/dlc.csv", "--lockstep", "--excite", program]
    if which == "c":
        command = [str(ECU), "--interface", "socketcand", "--channel", "vcan0", *common]
    else:
        command = [sys.executable, "-m", "firmware_sim", "--interface", "virtual", "--channel", "x", *common]
    result = subprocess.run(command, cwd=ROOT, capture_output=True, text=True, timeout=60, check=False)
    return result.returncode, (result.stderr.strip().splitlines() or [""])[-1]


@pytest.mark.parametrize("name, text", [
    ("unknown", None),
    ("missing.toml", None),
    ("bad_field.toml", 'kind = "chirp"\nchirp_hz = 2.0\n'),
    ("no_kind.toml", "hold_s = 0.5\n"),
    ("too_large.toml", 'kind = "prbs"\nsteer_amplitude_rad = 0.5\n'),
    ("negative.toml", 'kind = "steps"\nhold_s = -1.0\n'),
    ("seed.toml", 'kind = "prbs"\nseed = 1.5\n'),
    ("header.csv", "t,steer\n0,0\n"),
    ("short.csv", "time_s,steer_rad\n0.0,0.01\n"),
    ("decreasing.csv", "time_s,steer_rad\n0.0,0.01\n1.0,0.0\n0.5,0.0\n"),
    ("wide.csv", "time_s,steer_rad\n0.0,0.01,3\n"),
    # every field has a finite range, the same in both ECUs (issue 38, item 1)
    ("huge_chirp.toml", 'kind = "chirp"\nchirp_start_hz = 1e308\nchirp_end_hz = 1e308\ndelay_s = 0\n'
                        "lateral_accel_mps2 = 0\n"),
    ("fast_chirp.toml", 'kind = "chirp"\nchirp_end_hz = 25.0\n'),
    ("late.toml", 'kind = "prbs"\ndelay_s = 1e300\n'),
    ("torque.toml", 'kind = "prbs"\ntorque_amplitude_nm = 5000.0\n'),
    ("big_seed.toml", 'kind = "prbs"\nseed = 9223372036854775807\n'),
    ("far_table.csv", "time_s,steer_rad\n0.0,0.01\n1e300,0.0\n"),
    ("torque_table.csv", "time_s,steer_rad,torque_nm\n0.0,0.01,0\n1.0,0.0,4000\n"),
    # a table is parsed as its lines are read in both ECUs: the first bad line decides
    ("wide_then_nul.csv", "time_s,steer_rad\n0.0,0.01,3\n1.0\x00,0\n"),
    ("header_then_nul.csv", "t,steer\n0.0,0.01\n1.0\x00,0\n"),
])
def test_bad_program_is_the_python_ecus_error_line(native, name: str, text: str | None, tmp_path: Path) -> None:
    program = name if text is None and "." not in name else str(tmp_path / name)
    if text is not None:
        (tmp_path / name).write_text(text)
    python_status, python_line = cli_error("python", program)
    c_status, c_line = cli_error("c", program)
    assert python_line.startswith("error: ") and python_status == 2
    assert (c_status, c_line) == (python_status, python_line)


#: TOML that Python's tomllib refuses, and the line both ECUs name (before, the C ECU took
#: the last of two values, a float without a leading digit, and a byte that is not UTF-8).
TOML_PROBES = {
    "twice.toml": (b'kind = "prbs"\nhold_s = 0.5\nhold_s = 0.6\n', 3),
    "no_leading_digit.toml": (b'kind = "prbs"\nhold_s = .5\n', 2),
    "no_trailing_digit.toml": (b'kind = "prbs"\nhold_s = 5.\n', 2),
    "leading_zero.toml": (b'kind = "prbs"\nhold_s = 05\n', 2),
    "latin1_comment.toml": (b'kind = "prbs"  # caf\xe9\nhold_s = 0.5\n', 1),
    "latin1_table.csv": (b"time_s,steer_rad\n0.0,0.0\n1.0,0.01\xe9\n", 3),
}


@pytest.mark.parametrize("name", TOML_PROBES)
def test_what_tomllib_refuses_both_ecus_refuse_naming_the_line(native, name: str, tmp_path: Path) -> None:
    """One verdict on a program file the TOML grammar (or UTF-8) refuses: exit 2 and one
    ``error: --excite FILE:`` line naming the line; a byte that is not UTF-8 is the same
    line from both ECUs (models/input_files.py and firmware/src/ecu_lines.c)."""
    content, line = TOML_PROBES[name]
    program = tmp_path / name
    program.write_bytes(content)
    verdicts = {which: cli_error(which, str(program)) for which in ("python", "c")}
    for which, (status, text) in verdicts.items():
        assert status == 2, (which, text)
        assert text.startswith(f"error: --excite {program}: "), (which, text)
        assert f"line {line}" in text, (which, text)
    if name.startswith("latin1"):
        assert verdicts["c"] == verdicts["python"] == (2, f"error: --excite {program}: line {line}: not UTF-8")


def test_toml_numbers_and_utf8_comments_that_tomllib_takes_the_c_ecu_takes(native, tmp_path: Path) -> None:
    """The other side of the probes: underscores between digits, an exponent, a sign,
    hexadecimal, octal and binary integers and a comment in UTF-8 (2- and 4-byte characters)
    load in both ECUs to the same program (its one-line description; the C ECU then stops
    at the bus, which exists nowhere here)."""
    from firmware_sim.excitation import describe, load_program

    program = tmp_path / "ok.toml"
    program.write_bytes('kind = "prbs"  # caf\u00e9 \U0001d11e\nhold_s = 1_0.5e-1\ndelay_s = +0.5\n'
                        "seed = 0x1_f\ntorque_hold_s = 0o7\nwheelbase_m = 0b1_0\n".encode())
    expected = describe(load_program(str(program)))
    assert "bit 1.05 s" in expected and "from 0.5 s after ACTIVE" in expected
    result = subprocess.run([str(ECU), "--interface", "socketcand", "--channel", "vcan0", "--port", "1",
                             "--controller", "lmpc", "--path", "1=hil/paths/dlc.csv", "--lockstep", "--excite",
                             str(program)], cwd=ROOT, capture_output=True, text=True, timeout=60, check=False)
    assert expected in result.stderr, result.stderr[-2000:]
    assert "cannot open CAN bus" in result.stderr


def test_a_table_over_the_static_limit_is_refused_naming_file_and_limit(native, tmp_path: Path) -> None:
    """The C ECU keeps a table program in a static table (no heap after start-up): a file
    with more rows is one error line naming the file and the limit, the same from both ECUs
    (one limit in both, issue 38 item 8)."""
    from firmware_sim.excitation import TABLE_MAX_ROWS

    assert TABLE_MAX_ROWS == TABLE_MAX
    path = tmp_path / "long.csv"
    rows = "\n".join(f"{0.01 * k:.2f},0.0" for k in range(TABLE_MAX + 1))
    path.write_text("time_s,steer_rad\n" + rows + "\n")
    expected = f"error: --excite {path}: line {TABLE_MAX + 2}: more than {TABLE_MAX} rows (the table limit of both ECUs)"
    assert cli_error("c", str(path)) == (2, expected)
    assert cli_error("python", str(path)) == (2, expected)


def test_excite_with_replay_is_refused(native) -> None:
    result = subprocess.run([str(ECU), "--controller", "lmpc", "--path", "1=hil/paths/dlc.csv", "--replay",
                             "x.csv", "--excite", "chirp"], cwd=ROOT, capture_output=True, text=True, timeout=60,
                            check=False)
    assert result.returncode == 2
    assert result.stderr.strip() == ("error: --excite runs on the bus (the excitation is added while ACTIVE), "
                                     "not with --replay")


def test_hil_run_passes_the_program_to_the_c_ecu(native, tmp_path: Path) -> None:
    """``hil run --ecu c --excite``: a shipped name as it is, a program file made absolute
    (the executable runs in the checkout)."""
    from hil.scenario import load_scenario
    from hil.session import c_ecu_command, default_options

    scenario = load_scenario("dlc_smoke")
    for program, passed in (("chirp", "chirp"), ("rel/doublet.csv", str(Path("rel/doublet.csv").resolve()))):
        command = c_ecu_command(scenario, default_options("lmpc", ecu="c", excite=program))
        assert command[command.index("--excite") + 1] == passed


@pytest.mark.parametrize("cell", ["1_0", "\u0661"])
def test_a_table_number_is_ascii_without_underscores_in_both_ecus(native, cell: str, tmp_path: Path) -> None:
    """CSV is not TOML: a table cell ``1_0`` (or an Arabic-Indic digit) is not a number for
    either ECU, refused at its line with exit 2 (before, the Python ECU read 10, or 1, and
    then refused the table for a time that does not increase, or took it). The Python
    ECU's line also names the value; the C ECU's names the column only."""
    program = tmp_path / "table.csv"
    program.write_text(f"time_s,steer_rad\n0.0,0.01\n{cell},0.0\n0.5,0.0\n", encoding="utf-8")
    prefix = f"error: --excite {program}: line 3: not a number in column 1"
    python_status, python_line = cli_error("python", str(program))
    c_status, c_line = cli_error("c", str(program))
    assert python_status == c_status == 2
    assert python_line == f"{prefix}: {cell!r}" and c_line.startswith(prefix), (python_line, c_line)
