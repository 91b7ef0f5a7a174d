"""The C ECU's footprint: text / data / bss of the executable and the stack use of every
function, as a Markdown report (``make firmware-footprint`` -> results/firmware_footprint.md).

    python firmware/tools/footprint.py --exe build/firmware/ecu --su build/firmware/obj-ecu \
        --su build/firmware/obj --out results/firmware_footprint.md

Sizes are binutils' ``size`` (Berkeley format: text includes read-only data; data the
initialised writable data, here mostly the three generated OSQP workspaces; bss the
zeroed statics). Stack use is gcc's ``-fstack-usage`` (one ``.su`` file per object: bytes
of each function's own frame, ``static`` = fixed, ``dynamic,bounded`` = variable with a
bound gcc proves). A call's worst stack is the sum along its call chain; the largest frames
below say where that sum comes from. The first lines under "Summary" are what README.md
includes.
"""
from __future__ import annotations

import argparse
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

#: Functions listed by name in the report (the largest frames); the rest are counted.
TOP_FUNCTIONS = 12


class FootprintError(Exception):
    """The executable or the stack-use files cannot be read."""


@dataclass(frozen=True)
class Frame:
    """One function's own stack frame from a ``.su`` line."""

    source: str
    function: str
    bytes: int
    qualifier: str


def section_sizes(exe: Path) -> tuple[int, int, int]:
    """(text, data, bss) bytes of ``exe`` from ``size`` (Berkeley format).

    Raises:
        FootprintError: no such file, or ``size`` failed.
    """
    if not exe.is_file():
        raise FootprintError(f"{exe}: no such executable (run make firmware)")
    try:
        result = subprocess.run(["size", str(exe)], capture_output=True, text=True, check=False)
    except OSError as e:
        raise FootprintError(f"size: cannot run binutils' size: {e}") from e
    lines = result.stdout.strip().splitlines()
    if result.returncode != 0 or len(lines) < 2:
        raise FootprintError(f"size {exe}: {result.stderr.strip() or 'no output'}")
    text, data, bss = (int(v) for v in lines[1].split()[:3])
    return text, data, bss


def read_frames(folders: list[Path]) -> list[Frame]:
    """Every function's frame from the ``.su`` files in ``folders``, largest first.

    Raises:
        FootprintError: a folder without ``.su`` files, or a line that is not gcc's format.
    """
    frames = []
    for folder in folders:
        files = sorted(folder.glob("*.su"))
        if not files:
            raise FootprintError(f"{folder}: no .su files (the firmware is built with -fstack-usage: make firmware)")
        for file in files:
            for number, line in enumerate(file.read_text().splitlines(), 1):
                try:
                    where, size, qualifier = line.split("\t")
                    location, function = where.rsplit(":", 1)
                    frames.append(Frame(Path(location.split(":")[0]).name, function, int(size), qualifier))
                except ValueError:
                    raise FootprintError(f"{file}: line {number}: not 'file:line:col:function<TAB>bytes<TAB>kind'") \
                        from None
    return sorted(frames, key=lambda f: (-f.bytes, f.function))


def report(exe: Path, sizes: tuple[int, int, int], frames: list[Frame]) -> str:
    """The Markdown report (the summary first, then the largest frames)."""
    text, data, bss = sizes
    top = frames[:TOP_FUNCTIONS]
    rest = frames[TOP_FUNCTIONS:]
    dynamic = [f for f in frames if f.qualifier != "static"]
    largest = ", ".join(f"`{f.function}` {f.bytes:,} B" for f in top[:4])
    lines = [
        "# C ECU footprint (`make firmware-footprint`)", "",
        "## Summary", "",
        f"`{exe}`: text {text:,} B, data {data:,} B, bss {bss:,} B (binutils `size`); "
        f"stack (gcc `-fstack-usage`, {len(frames)} functions): largest own frames {largest}; "
        f"{len(rest)} functions at most {rest[0].bytes if rest else 0:,} B each.", "",
        "## Stack use per function", "",
        "| function | source | own frame (B) | kind |", "|---|---|---|---|",
        *(f"| `{f.function}` | {f.source} | {f.bytes:,} | {f.qualifier} |" for f in top),
        f"| {len(rest)} others | | at most {rest[0].bytes if rest else 0:,} each | |", "",
        f"Frames of variable size (`dynamic`, every one bounded by gcc): "
        f"{', '.join(f'`{f.function}`' for f in dynamic) or 'none'}. A call's worst stack is the sum "
        "of the frames along its call chain; the call graph has no cycle (docs/firmware.md, "
        "Footprint). bss holds the path pool and the core's path (100,000 points each) and the "
        "timing record (65,536 tasks); data the three generated OSQP workspaces.",
    ]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    """Write the report; 0, or 1 with one ``error:`` line (no build, no ``.su`` files)."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--exe", type=Path, default=Path("build/firmware/ecu"))
    parser.add_argument("--su", type=Path, action="append", default=None,
                        help="folder of .su files (repeatable; default build/firmware/obj-ecu, build/firmware/obj)")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(argv)
    folders = args.su or [Path("build/firmware/obj-ecu"), Path("build/firmware/obj")]
    try:
        text = report(args.exe, section_sizes(args.exe), read_frames(folders))
    except FootprintError as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    if not args.out.parent.is_dir():
        print(f"error: --out {args.out}: folder {args.out.parent} does not exist", file=sys.stderr)
        return 1
    args.out.write_text(text)
    print(text, end="")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
