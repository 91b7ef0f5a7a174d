"""Cross-compiling the firmware for an ARM target (aarch64 Linux): the build is warning-free
with the same flags, and the executable, run under qemu's user-mode emulation, replays
recorded samples to the host build's output bit for bit. Runs with ECU_CROSS=1
(``make firmware-cross``); needs aarch64-linux-gnu-gcc and qemu-aarch64."""
from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import pytest

from test_firmware_c_core import native  # noqa: F401 (the fixture: the host firmware built)

ROOT = Path(__file__).resolve().parent.parent
CROSS_CC = os.environ.get("ECU_CROSS_CC", "aarch64-linux-gnu-gcc")
SYSROOT = "/usr/aarch64-linux-gnu"
SAMPLE_FIELDS = ("vx", "vy", "yaw_rate", "x", "y", "yaw", "steer_angle", "drive_torque", "target_speed")

pytestmark = pytest.mark.skipif(os.environ.get("ECU_CROSS") != "1",
                                reason="the ARM cross build: make firmware-cross (ECU_CROSS=1)")


def test_arm_build_replays_bit_for_bit(native, tmp_path: Path) -> None:
    for tool in (CROSS_CC, "qemu-aarch64"):
        assert shutil.which(tool), f"{tool} not found (apt-get install gcc-aarch64-linux-gnu qemu-user)"
    build = subprocess.run(["make", "-s", "--no-print-directory", f"FW_CC={CROSS_CC}",
                            "FW_DIR=build/firmware-aarch64", "build/firmware-aarch64/ecu"],
                           cwd=ROOT, capture_output=True, text=True, check=False)
    assert build.returncode == 0, build.stdout + build.stderr
    samples_csv = write_replay_samples(tmp_path)
    for name in ("eso-dkmpc", "dkmpc", "lmpc"):
        host = replay_rows(["build/firmware/ecu"], name, samples_csv)
        arm = replay_rows(["qemu-aarch64", "-L", SYSROOT, "build/firmware-aarch64/ecu"], name, samples_csv,
                          timeout=300)
        assert arm == host, name
        print(f"{name}: {len(host) - 1} steps, aarch64 replay identical to the host's")


def write_replay_samples(folder: Path) -> Path:
    """dlc_smoke's samples as LMPC saw them, as the CSV of ``ecu --replay`` in ``folder``."""
    from studies.bench import record_samples

    samples, _, _ = record_samples(scenario_name="dlc_smoke", driver="lmpc")
    rows = [",".join(repr(float(getattr(s, f))) for f in SAMPLE_FIELDS) for s in samples]
    (folder / "samples.csv").write_text(",".join(SAMPLE_FIELDS) + "\n" + "\n".join(rows) + "\n")
    return folder / "samples.csv"


def replay_rows(command: list[str], name: str, samples_csv: Path, timeout: float | None = None) -> list[str]:
    """``command`` (an ``ecu`` executable) replaying ``samples_csv`` with controller ``name`` on
    dlc.csv and the host build's data file: its output lines, each without its last column
    (the step's wall time)."""
    args = ["--controller", name, "--path", "1=hil/paths/dlc.csv", "--data", "build/firmware/ecu_data.bin",
            "--replay", str(samples_csv)]
    result = subprocess.run([*command, *args], cwd=ROOT, capture_output=True, text=True, check=True, timeout=timeout)
    return [line.rsplit(",", 1)[0] for line in result.stdout.splitlines()]
