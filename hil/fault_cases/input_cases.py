"""The fault campaign's input-file cases (`INPUT_CASES`, registered as campaign cases by
``hil.fault_cases.catalogue.input_cases``): a bad file given to the ECU at start-up, and the
verdict both ECUs must give for it. Each case's ``ecu_fault`` (`InputCase.ecu_fault`) is
``{"kind": "input", "defect": NAME, "expect": "refused" | "fault" | "safe_stop", "says": TEXT}``:

- ``refused``: the ECU refuses to start: exit status 2, one ``error:`` line holding
  ``says``, no frame on the bus;
- ``fault``: the ECU starts, latches FAULT at its first control task and sends
  CMD_VALID = 0 throughout; its ``FAULT latched`` line holds ``says``;
- ``safe_stop``: the file loads (nothing in it is out of range) but the controller falls
  back on every step; the ECU must take it for a failing controller (contract rev. 2:
  fallbacks on 4 control tasks in a row) and go to SAFE_STOP (``says`` unused).

``says`` may hold ``{file}``: the bad file's name. The files are written
per run by `write_bad_input` (the defect's writer in `WRITERS`), for the ECU that runs:
the Python ECU's model is a Koopman artefact, the C ECU's its data file
(``build/firmware/ecu_data.bin``'s layout, firmware/tools/ecu_data.py). The runs are
``hil.fault_cases.input_runs``.
"""
from __future__ import annotations

import math
import shutil
import struct
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

#: The controller of the input cases: ESO-DKMPC steps on the Koopman model both ECUs load.
CONTROLLER = "eso-dkmpc"
#: The line of a path file the path cases spoil (1 is the header).
BAD_PATH_LINE = 3
#: Bytes added to that line: over the 4,096-byte line limit of both ECUs.
PADDING_BYTES = 4200
#: Factor on the model's lifted dynamics A(v) of the failing-controller case: finite (the
#: model loads) but absurd (every step's QP fails or gives no finite plan).
ABSURD_A_SCALE = 1e6


@dataclass(frozen=True)
class BadInput:
    """What one input case gives the ECU: each None leaves the run's own input."""

    #: The bad file itself (``{file}`` in the case's ``says``).
    file: Path
    excite: str | None = None
    #: The Python ECU's ``--model`` (a Koopman artefact, without its suffix).
    model: Path | None = None
    #: The C ECU's ``--data``.
    data: Path | None = None
    path_file: Path | None = None


def _chirp_1e308(folder: Path, path_file: Path, ecu: str) -> BadInput:
    """An excitation program whose chirp runs from 1e308 Hz to 1e308 Hz (both ECUs check
    every field's finite range at load)."""
    program = folder / "chirp_1e308.toml"
    program.write_text('kind = "chirp"\nchirp_start_hz = 1e308\nchirp_end_hz = 1e308\ndelay_s = 0\n'
                       "lateral_accel_mps2 = 0\n", encoding="utf-8")
    return BadInput(program, excite=str(program))


def _artefact_copy(folder: Path, name: str, change: Callable[[dict[str, Any]], None]) -> Path:
    """A copy of the default Koopman artefact as ``folder/name`` (.npz + .json, returned
    without its suffix) whose arrays (name -> ``np.ndarray``) ``change`` edited in place."""
    import numpy as np

    from models.koopman import DEFAULT_ARTIFACT

    model = folder / name
    shutil.copy(DEFAULT_ARTIFACT.with_suffix(".json"), model.with_suffix(".json"))
    with np.load(DEFAULT_ARTIFACT.with_suffix(".npz")) as weights:
        arrays = {key: weights[key].copy() for key in weights.files}
    change(arrays)
    np.savez(model.with_suffix(".npz"), **arrays)
    return model


def _first_encoder_weight_infinite(arrays: dict[str, Any]) -> None:
    """``encoder_w0[0, 0]`` (192, 4) = inf."""
    arrays["encoder_w0"][0, 0] = math.inf


def _dynamics_scaled(arrays: dict[str, Any]) -> None:
    """``A_n`` (knots, n_z, n_z) times `ABSURD_A_SCALE`."""
    arrays["A_n"] *= ABSURD_A_SCALE


def _infinite_encoder(folder: Path, path_file: Path, ecu: str) -> BadInput:
    """The default model with its first encoder weight infinite: for the Python ECU a copy
    of the Koopman artefact (``encoder_w0[0, 0]``), for the C ECU a copy of the build's
    data file (``koopman.w0``'s first value, the same weight with the normalisation
    folded in)."""
    if ecu == "c":
        from firmware_sim.native import DEFAULT_DATA

        data = folder / "infinite_encoder.bin"
        data.write_bytes(set_record_value(DEFAULT_DATA.read_bytes(), "koopman.w0", math.inf))
        return BadInput(data, data=data)
    model = _artefact_copy(folder, "infinite_encoder", _first_encoder_weight_infinite)
    return BadInput(model.with_suffix(".npz"), model=model)


def _absurd_dynamics(folder: Path, path_file: Path, ecu: str) -> BadInput:
    """The default model with its lifted dynamics A(v) (``A_n``, every knot) times
    `ABSURD_A_SCALE`: finite, so both ECUs load it, but no step's QP gives a usable plan.
    The Python ECU gets the artefact; the C ECU its data file, converted from that artefact
    by firmware/tools/ecu_data.py as ``hil run --ecu c --model`` converts one, so both run
    the same model."""
    model = _artefact_copy(folder, "absurd_dynamics", _dynamics_scaled)
    if ecu == "c":
        from firmware_sim.native import data_file_for_model

        data = data_file_for_model(model.with_suffix(".npz"), folder)
        return BadInput(model.with_suffix(".npz"), data=data)
    return BadInput(model.with_suffix(".npz"), model=model)


def _spoilt_path(name: str, spoil: Callable[[bytes], bytes]) -> Callable[[Path, Path, str], BadInput]:
    """A writer of the run's path file with line `BAD_PATH_LINE` passed through ``spoil``
    (the line's bytes without its end in, the bad line out)."""
    def write(folder: Path, path_file: Path, ecu: str) -> BadInput:
        lines = path_file.read_bytes().split(b"\n")
        lines[BAD_PATH_LINE - 1] = spoil(lines[BAD_PATH_LINE - 1])
        bad = folder / f"{name}.csv"
        bad.write_bytes(b"\n".join(lines))
        return BadInput(bad, path_file=bad)
    return write


#: The defects' writers: (folder, the run's path file, ECU "python" / "c") -> `BadInput`.
WRITERS: dict[str, Callable[[Path, Path, str], BadInput]] = {
    "chirp 1e308": _chirp_1e308,
    "infinite encoder weight": _infinite_encoder,
    "dynamics A x 1e6": _absurd_dynamics,
    "path line over 4096 bytes": _spoilt_path("long_line", lambda line: line + b" " * PADDING_BYTES),
    "path line with a NUL byte": _spoilt_path("nul", lambda line: line[:1] + b"\x00" + line[1:]),
}


def write_bad_input(defect: str, folder: Path, path_file: Path, ecu: str) -> BadInput:
    """The bad file(s) of ``defect`` in ``folder``, for ``ecu`` ("python", "c")."""
    return WRITERS[defect](folder, path_file, ecu)


def set_record_value(data: bytes, record: str, value: float) -> bytes:
    """An ECU data file (``data``: firmware/tools/ecu_data.py's layout: ``ECUDATA1``, a
    uint32 record count, then per record a 48-byte name, a uint32 rank, four uint32
    dimensions and the float64 values) with the first value of ``record`` set to ``value``.

    Raises:
        ValueError: not such a file, or no record of that name.
    """
    if data[:8] != b"ECUDATA1":
        raise ValueError("not an ECU data file (magic ECUDATA1 missing)")
    at = 12
    for _ in range(struct.unpack_from("<I", data, 8)[0]):
        name = data[at:at + 48].rstrip(b"\0").decode("ascii")
        dims = struct.unpack_from("<4I", data, at + 52)
        values_at = at + 48 + 20
        if name == record:
            return data[:values_at] + struct.pack("<d", value) + data[values_at + 8:]
        at = values_at + 8 * math.prod(dims)
    raise ValueError(f"no record {record!r} in the data file")


@dataclass(frozen=True)
class InputCase:
    """One input-file case: its name in the campaign, the defect (a key of `WRITERS`), the
    verdict expected ("refused", "fault", "safe_stop"), what the ECU's line must hold, and
    a note."""

    name: str
    defect: str
    expect: str
    says: str
    note: str

    def ecu_fault(self) -> dict[str, Any]:
        """The campaign case's ``ecu_fault``."""
        return {"kind": "input", "defect": self.defect, "expect": self.expect, "says": self.says}


#: The input-file cases of `make faults` / `make faults-c` (each ECU as a process on a
#: socketcand hub of the run's own, ``hil.fault_cases.input_runs.run_input_case``).
INPUT_CASES = (
    InputCase("excitation chirp 1e308", "chirp 1e308", "refused", "chirp_start_hz 1e+308 exceeds its limit 20.0",
              "--excite with chirp_start_hz = chirp_end_hz = 1e308: every field has a finite range, "
              "checked at load"),
    InputCase("model with an infinite encoder weight", "infinite encoder weight", "fault", "{file}",
              "--model (Python: the Koopman artefact's encoder_w0[0, 0]; C: --data, koopman.w0) = inf: "
              "every array of a model must be finite"),
    InputCase("path line over 4096 bytes", "path line over 4096 bytes", "fault",
              "{file}: line 3: longer than 4096 bytes",
              "the path file's line 3 padded past the 4,096-byte line limit"),
    InputCase("path line with a NUL byte", "path line with a NUL byte", "fault",
              "{file}: line 3: holds a NUL byte", "a NUL byte in the path file's line 3"),
    InputCase("model A x 1e6", "dynamics A x 1e6", "safe_stop", "",
              "--model with the lifted dynamics A(v) x 1e6 (Python: the Koopman artefact's A_n; C: --data "
              "converted from it): finite, so it loads, but every step falls back; a fallback on 4 control "
              "tasks in a row is a failing controller: SAFE_STOP"),
)
