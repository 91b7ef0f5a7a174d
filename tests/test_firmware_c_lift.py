"""The lift's vector kernels (firmware/src/ecu_koopman.c) give the same results to the bit on
every instruction set: the host build, which takes the AVX kernels where the CPU has AVX, and a
build with ``-DECU_NO_AVX`` (x86-64's SSE2 kernels) replay recorded samples to the same output,
every command bit for bit, for the three controllers. Each output's sum runs over the inputs in
the same order in both (and as one output at a time), so only a kernel that reorders or fuses
the arithmetic would make them differ. The build goes to ``build/firmware-noavx`` (``build/
firmware`` is not touched; a no-op when up to date)."""
from __future__ import annotations

import subprocess
from pathlib import Path

import pytest

from test_firmware_c_core import native  # noqa: F401 (the fixture: the host firmware built)
from test_firmware_c_cross import replay_rows, write_replay_samples

ROOT = Path(__file__).resolve().parent.parent
NO_AVX_DIR = "build/firmware-noavx"


def _has_avx() -> bool:
    try:
        return " avx " in f" {Path('/proc/cpuinfo').read_text()} ".replace("\n", " ")
    except OSError:
        return False


@pytest.mark.skipif(not _has_avx(), reason="the host has no AVX: both builds run the SSE2 kernels")
def test_avx_and_sse2_lift_replay_bit_for_bit(native, tmp_path: Path) -> None:  # noqa: F811
    build = subprocess.run(["make", "-s", "--no-print-directory", f"FW_DIR={NO_AVX_DIR}",
                            "FW_EXTRA_CFLAGS=-DECU_NO_AVX", f"{NO_AVX_DIR}/ecu"],
                           cwd=ROOT, capture_output=True, text=True, check=False)
    assert build.returncode == 0, build.stdout + build.stderr
    samples_csv = write_replay_samples(tmp_path)
    for name in ("eso-dkmpc", "dkmpc", "lmpc"):
        host = replay_rows(["build/firmware/ecu"], name, samples_csv)
        assert len(host) == len(samples_csv.read_text().splitlines()), name  # a header, then one row a step
        assert replay_rows([f"{NO_AVX_DIR}/ecu"], name, samples_csv) == host, name
