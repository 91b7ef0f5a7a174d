"""A real SocketCAN ``vcan0`` where the host kernel has no CAN: user-mode Linux (UML).

UML is a Linux kernel that runs as an ordinary process. Booted with the host's own
directory tree as its root file system (hostfs), it sees the checkout and its ``.venv``
unchanged; its own kernel has CAN as modules, so inside it ``vcan0`` is a real SocketCAN
device. `run_in_uml` writes an init script, boots ``linux.uml``, loads ``can.ko``,
``can-raw.ko``, ``can-dev.ko`` and ``vcan.ko`` with insmod (modprobe does not look in
``/usr/lib/uml/modules``), creates ``vcan0``, runs one shell command as root in the
checkout, records its exit status and output in files on the host (hostfs writes go
straight through) and powers off. UML's own exit status is 0 whatever happened, so the
recorded status is the result. Use it for correctness of the SocketCAN path, never for
timing figures (system calls are slow in UML).

Hosts with large XSAVE state (AVX-512 / AMX, e.g. Sapphire Rapids): the UML kernel of
Debian bookworm (6.1) saves the user FPU state with PTRACE_SETREGSET(NT_X86_XSTATE) into
a buffer of fixed size; a host whose XSAVE area is larger answers EFAULT and UML panics
("ptrace set fp regs failed, errno = 14"; fixed upstream in Linux 6.13 by "um: switch to
regset API and depend on XSTATE"). We start UML under a seccomp filter that answers EIO
to exactly those two ptrace requests, so UML falls back to PTRACE_GETFPREGS/SETFPREGS
(the 512-byte FXSAVE area, which every x86-64 host supports). The price: UML then saves
and restores only the x87/SSE registers of its processes across its own context
switches, so processes inside must not use AVX registers. `UML_SAFE_ENV` makes glibc,
numpy and OpenBLAS pick their SSE code paths; use the same environment for any
reference run whose numbers are compared bit for bit with a run inside UML.
"""
from __future__ import annotations

import argparse
import ctypes
import os
import shlex
import shutil
import signal
import socket
import struct
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

from hil.errors import HilError

#: Debian packages the UML path needs (the top Makefile's ``apt-deps`` installs them).
APT_PACKAGES = ("user-mode-linux", "kmod", "iproute2", "can-utils")
UML_KERNEL = "linux.uml"
UML_MODULE_ROOT = Path("/usr/lib/uml/modules")
#: Kernel modules for vcan, in load order (vcan needs can-dev's symbols).
CAN_MODULES = ("net/can/can.ko", "net/can/can-raw.ko", "drivers/net/can/dev/can-dev.ko",
               "drivers/net/can/vcan.ko")
#: Status recorded when the set-up inside UML (modules, vcan0) failed.
SETUP_FAILED_STATUS = 125
REPO_ROOT = Path(__file__).resolve().parent.parent

#: Environment for processes inside UML: SSE code paths only (see the module docstring).
UML_SAFE_ENV = {
    "GLIBC_TUNABLES": "glibc.cpu.hwcaps=-AVX,-AVX2,-AVX512F,-AVX512VL,-AVX512BW,-AVX512DQ,"
                      "-AVX512CD,-FMA,-AVX_Fast_Unaligned_Load,-AVX2_Usable,-AVX512F_Usable",
    "NPY_DISABLE_CPU_FEATURES": "X86_V3 X86_V4 AVX512_ICL AVX512_SPR",
    "OPENBLAS_CORETYPE": "Nehalem",
    "OPENBLAS_NUM_THREADS": "1",
    "OMP_NUM_THREADS": "1",
    "PYTHONDONTWRITEBYTECODE": "1",
}


class VcanError(HilError):
    """User-mode Linux could not be started or did not record a result."""


@dataclass(frozen=True)
class UmlResult:
    """Outcome of a command run inside UML: its exit status and output, UML's console
    log (kernel messages, for diagnosis) and the wall time of the whole boot-run-halt."""

    returncode: int
    output: str
    console: str
    wall_s: float


def host_vcan_available(channel: str = "vcan0") -> bool:
    """True when this kernel speaks SocketCAN and ``channel`` exists (a user's
    workstation after ``ip link add dev vcan0 type vcan``)."""
    try:
        with socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW):
            pass
    except (OSError, AttributeError):
        return False
    return Path("/sys/class/net", channel).exists()


def uml_module_dir() -> Path | None:
    """``/usr/lib/uml/modules/<version>/kernel``: the one version installed, else None."""
    if not UML_MODULE_ROOT.is_dir():
        return None
    versions = sorted(p for p in UML_MODULE_ROOT.iterdir() if (p / "kernel").is_dir())
    return versions[-1] / "kernel" if versions else None


def uml_unavailable_reason() -> str | None:
    """Why UML cannot provide vcan0 here (None when it can): missing packages or modules."""
    missing = [tool for tool, package in ((UML_KERNEL, "user-mode-linux"), ("insmod", "kmod"),
                                           ("ip", "iproute2"), ("candump", "can-utils"))
               if shutil.which(tool) is None and not Path("/sbin", tool).exists()
               and not Path("/usr/sbin", tool).exists()]
    if missing:
        return (f"missing {', '.join(missing)}: install with `sudo apt-get install "
                f"{' '.join(APT_PACKAGES)}` (or `sudo make apt-deps`)")
    modules = uml_module_dir()
    if modules is None:
        return f"no UML kernel modules under {UML_MODULE_ROOT} (package user-mode-linux)"
    absent = [m for m in CAN_MODULES if not (modules / m).exists()]
    if absent:
        return f"UML kernel modules missing under {modules}: {', '.join(absent)}"
    return None


# --- seccomp: make UML fall back to FXSAVE (see the module docstring) -------------------

_PTRACE_GETREGSET, _PTRACE_SETREGSET, _NT_X86_XSTATE = 0x4204, 0x4205, 0x202
_AUDIT_ARCH_X86_64 = 0xC000003E
_NR_PTRACE_X86_64 = 101
_EIO = 5


def _bpf(code: int, jump_true: int, jump_false: int, k: int) -> bytes:
    return struct.pack("HBBI", code, jump_true, jump_false, k)


def _xstate_filter_program() -> bytes:
    """Classic BPF: ptrace(PTRACE_{GET,SET}REGSET, *, NT_X86_XSTATE, *) -> EIO; allow all
    else. Offsets in struct seccomp_data: nr 0, arch 4, args[i] 16 + 8 i (low word)."""
    load, jeq, ret = 0x20, 0x15, 0x06  # BPF_LD|BPF_W|BPF_ABS, BPF_JMP|BPF_JEQ|BPF_K, BPF_RET|BPF_K
    allow, fail = 0x7FFF0000, 0x00050000 | _EIO  # SECCOMP_RET_ALLOW, SECCOMP_RET_ERRNO | EIO
    return b"".join([
        _bpf(load, 0, 0, 4), _bpf(jeq, 0, 7, _AUDIT_ARCH_X86_64),          # other ABI -> allow
        _bpf(load, 0, 0, 0), _bpf(jeq, 0, 5, _NR_PTRACE_X86_64),           # not ptrace -> allow
        _bpf(load, 0, 0, 16), _bpf(jeq, 1, 0, _PTRACE_GETREGSET),
        _bpf(jeq, 0, 2, _PTRACE_SETREGSET),                                # other request -> allow
        _bpf(load, 0, 0, 32), _bpf(jeq, 1, 0, _NT_X86_XSTATE),
        _bpf(ret, 0, 0, allow), _bpf(ret, 0, 0, fail),
    ])


class _SockFprog(ctypes.Structure):
    _fields_ = [("len", ctypes.c_ushort), ("filter", ctypes.c_void_p)]


def _install_xstate_filter() -> None:
    """Runs in the child between fork and exec (``preexec_fn``): no Python objects are
    created that could need the parent's locks beyond ctypes calls."""
    libc = ctypes.CDLL(None, use_errno=True)
    program = _xstate_filter_program()
    buffer = ctypes.create_string_buffer(program)
    fprog = _SockFprog(len(program) // 8, ctypes.addressof(buffer))
    pr_set_no_new_privs, pr_set_seccomp, seccomp_mode_filter = 38, 22, 2
    if libc.prctl(pr_set_no_new_privs, 1, 0, 0, 0) != 0 or \
            libc.prctl(pr_set_seccomp, seccomp_mode_filter, ctypes.byref(fprog), 0, 0) != 0:
        os.write(2, b"hil.vcan: cannot install the seccomp filter for UML\n")
        os._exit(126)


# --- running a command inside UML --------------------------------------------------------


def _init_script(command: str, workdir: Path, result_dir: Path, channel: str,
                 modules: Path, env: dict[str, str]) -> str:
    exports = "\n".join(f"export {name}={shlex.quote(value)}" for name, value in env.items())
    insmods = "\n".join(f"insmod {shlex.quote(str(modules / m))}" for m in CAN_MODULES)
    status = shlex.quote(str(result_dir / "status"))
    return f"""#!/bin/sh
# Written by hil/vcan.py: PID 1 of user-mode Linux.
export PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin
export HOME={shlex.quote(os.environ.get("HOME", "/root"))}
export LANG=C.UTF-8
{exports}
mount -t proc proc /proc
mount -t sysfs sysfs /sys
if ! ( set -e
{insmods}
ip link add dev {shlex.quote(channel)} type vcan
ip link set up {shlex.quote(channel)}
) > {shlex.quote(str(result_dir / "setup.txt"))} 2>&1; then
    echo {SETUP_FAILED_STATUS} > {status}.tmp && mv {status}.tmp {status}
    poweroff -f
fi
cd {shlex.quote(str(workdir))}
/bin/sh -c {shlex.quote(command)} > {shlex.quote(str(result_dir / "output.txt"))} 2>&1
echo $? > {status}.tmp && mv {status}.tmp {status}
sync
poweroff -f
"""


def run_in_uml(command: str, *, workdir: Path = REPO_ROOT, channel: str = "vcan0",
               timeout_s: float = 180.0, memory: str = "1G",
               env: dict[str, str] | None = None) -> UmlResult:
    """Run the shell ``command`` as root inside UML with a SocketCAN ``channel`` up.

    Args:
        command: ``/bin/sh -c`` command line, run in ``workdir`` (a host path).
        channel: the vcan device to create.
        timeout_s: wall-clock limit for boot + command + halt; UML is killed after it.
        memory: UML's RAM (``mem=``).
        env: extra environment (added to :data:`UML_SAFE_ENV`).

    Raises:
        VcanError: UML or its modules are missing, UML timed out, or it halted without
            recording a status (the message carries the end of its console).
    """
    reason = uml_unavailable_reason()
    if reason is not None:
        raise VcanError(f"user-mode Linux cannot provide {channel}: {reason}")
    modules = uml_module_dir()
    assert modules is not None  # checked by uml_unavailable_reason
    result_dir = Path(tempfile.mkdtemp(prefix="hil-uml-"))
    init = result_dir / "init.sh"
    init.write_text(_init_script(command, Path(workdir).resolve(), result_dir, channel, modules,
                                 {**UML_SAFE_ENV, **(env or {})}), encoding="utf-8")
    init.chmod(0o755)
    console_path = result_dir / "console.txt"
    kernel = shutil.which(UML_KERNEL)
    argv = [kernel or UML_KERNEL, f"mem={memory}", "rootfstype=hostfs", "rootflags=/", "rw",
            f"init={init}", "con=null", "con0=fd:0,fd:1"]
    started = time.monotonic()
    with console_path.open("wb") as console:
        process = subprocess.Popen(argv, stdin=subprocess.DEVNULL, stdout=console,
                                   stderr=subprocess.STDOUT, start_new_session=True,
                                   preexec_fn=_install_xstate_filter, cwd=result_dir)
        try:
            process.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            # UML runs as a group of host processes; end exactly the group we started.
            os.killpg(process.pid, signal.SIGKILL)
            process.wait()
            raise VcanError(f"user-mode Linux did not finish within {timeout_s:.0f} s; "
                            f"console: {console_path}, output: {result_dir / 'output.txt'}")
    wall = time.monotonic() - started
    console_text = console_path.read_text(errors="replace")
    status_file = result_dir / "status"
    if not status_file.exists():
        raise VcanError(f"user-mode Linux halted without recording a status (exit "
                        f"{process.returncode}); end of its console:\n{console_text[-2000:]}")
    returncode = int(status_file.read_text().strip() or "-1")
    output_file = result_dir / ("setup.txt" if returncode == SETUP_FAILED_STATUS
                                and not (result_dir / "output.txt").exists() else "output.txt")
    output = output_file.read_text(errors="replace") if output_file.exists() else ""
    shutil.rmtree(result_dir, ignore_errors=True)
    return UmlResult(returncode, output, console_text, wall)


def main(argv: list[str] | None = None) -> int:
    """``python -m hil.vcan [--channel vcan0] -- COMMAND ...``: run a command inside UML
    with a real SocketCAN vcan; prints its output and exits with its status."""
    parser = argparse.ArgumentParser(prog="python -m hil.vcan", description=main.__doc__)
    parser.add_argument("--channel", default="vcan0")
    parser.add_argument("--timeout", type=float, default=180.0, help="seconds (default 180)")
    parser.add_argument("command", nargs=argparse.REMAINDER, help="command to run inside")
    args = parser.parse_args(argv)
    words = args.command[1:] if args.command[:1] == ["--"] else args.command
    if not words:
        parser.error("no command given")
    try:
        result = run_in_uml(shlex.join(words), channel=args.channel, timeout_s=args.timeout)
    except VcanError as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    sys.stdout.write(result.output)
    print(f"[user-mode Linux: status {result.returncode}, {result.wall_s:.1f} s]", file=sys.stderr)
    return result.returncode


if __name__ == "__main__":
    sys.exit(main())
