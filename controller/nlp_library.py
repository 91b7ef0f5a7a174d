"""An NLP's functions compiled to machine code once, for NMPC in real time (issue 37 item 5).

CasADi evaluates an expanded (SX) NLP on its own virtual machine. For NMPC's multiple
shooting NLP the exact Hessian of the Lagrangian alone takes about 0.85 ms per IPOPT
iteration there. `compiled_solver` has CasADi generate C for the NLP's functions
(objective, constraints, their derivatives, the Hessian), compiles it with the system's C
compiler into a shared library and hands IPOPT that library instead: the same operations
in the same order, so the same iterates to the last bit (tests/test_nlp_library.py), in
about half the time per step (``make bench``'s NMPC step against this module's).

The library is cached by the SHA-256 of the generated C source, the compiler and its
flags, so it is built once per NLP and machine (about 25 s at -O1 for NMPC) and loaded in
a fraction of a second afterwards. Compiling is atomic (a temporary file renamed into
place), so two processes that build the same library at once do not see half a file.
``-ffp-contract=off`` keeps the compiler from fusing a multiply and an add into one
rounding, which would change the last bits on CPUs with FMA.

Nothing here is needed for correctness: without a C compiler, or when a build fails, the
caller gets `NlpLibraryError` and keeps the virtual machine.
"""
from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
import tempfile
from pathlib import Path
from typing import Any

import casadi as ca

#: Where the libraries are kept (an ignored build folder); ``NLP_LIBRARY_DIR`` overrides it.
DEFAULT_CACHE_DIR = Path(__file__).resolve().parents[1] / "build" / "nlp"
#: -O1: NMPC's step 1.2x faster than at -O0 (7.0 against 8.5 ms), and a build 2.4x shorter
#: than -O2's (26 s against 62 s); -O2's step time was not measured. -ffp-contract=off keeps
#: the iterates those of CasADi's virtual machine, to the last bit (no fused multiply-add).
COMPILER_FLAGS = ("-O1", "-ffp-contract=off", "-fPIC", "-shared")
#: Longest build allowed, s.
BUILD_TIMEOUT_S = 600.0


class NlpLibraryError(RuntimeError):
    """The NLP's library could not be generated, built or loaded (the message says which)."""


def cache_dir() -> Path:
    """The folder of the compiled libraries: ``NLP_LIBRARY_DIR`` if set, else build/nlp."""
    configured = os.environ.get("NLP_LIBRARY_DIR")
    return Path(configured) if configured else DEFAULT_CACHE_DIR


def compiler() -> str:
    """The C compiler: ``CC`` if set, else gcc."""
    return os.environ.get("CC") or "gcc"


def compiled_solver(name: str, problem: dict[str, Any], options: dict[str, Any],
                    solver: str = "ipopt") -> Any:
    """``ca.nlpsol(name, solver, ...)`` on ``problem`` ({"x", "p", "f", "g"} SX expressions)
    with its functions from a compiled library (built on first use, see the module doc).

    ``options`` are nlpsol's, without "expand" (the library is the expanded NLP).

    Raises:
        NlpLibraryError: no C compiler, the build failed or timed out, or the library does
            not load.
    """
    cc = shutil.which(compiler())
    if cc is None:
        raise NlpLibraryError(f"no C compiler {compiler()!r} on PATH (set CC)")
    folder = cache_dir()
    try:
        folder.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryDirectory(dir=folder, prefix=".generate-") as scratch:
            source_name = f"{name}_nlp.c"
            expanded = ca.nlpsol(name, solver, problem, {"expand": True})
            # What Function.generate_dependencies writes, into the scratch folder (it
            # writes into the working folder only, and the ECU's threads share that).
            generator = ca.CodeGenerator(source_name, {"with_header": False})
            generator.add(expanded.oracle())
            for function in expanded.get_function():
                generator.add(expanded.get_function(function))
            generator.generate(f"{scratch}{os.sep}")
            source = Path(scratch) / source_name
            digest = hashlib.sha256(source.read_bytes())
            digest.update(f"{cc}\0{' '.join(COMPILER_FLAGS)}\0{ca.__version__}".encode())
            library = folder / f"{name}_{digest.hexdigest()[:20]}.so"
            return _load(name, solver, options, cc, source, library)
    except OSError as error:
        raise NlpLibraryError(f"cannot generate the NLP's C code in {folder}: {error}") from error


def _load(name: str, solver: str, options: dict[str, Any], cc: str, source: Path, library: Path) -> Any:
    """The solver on ``library``, built first if missing; a cached library that does not
    load (a damaged file) is built again once."""
    for attempt in (1, 2):
        if not library.is_file():
            _build(cc, source, library)
        try:
            return ca.nlpsol(name, solver, str(library), options)
        except RuntimeError as error:
            library.unlink(missing_ok=True)
            if attempt == 2:
                raise NlpLibraryError(f"the compiled NLP {library} does not load: {error}") from error
    raise AssertionError("unreachable")


def _build(cc: str, source: Path, library: Path) -> None:
    """Compile ``source`` into ``library`` atomically."""
    partial = library.with_name(f".{library.name}.{os.getpid()}.partial")
    try:
        result = subprocess.run([cc, *COMPILER_FLAGS, str(source), "-o", str(partial), "-lm"],
                                capture_output=True, text=True, timeout=BUILD_TIMEOUT_S)
    except subprocess.TimeoutExpired as error:
        partial.unlink(missing_ok=True)
        raise NlpLibraryError(f"{cc} took over {BUILD_TIMEOUT_S:.0f} s on {source.name}") from error
    if result.returncode != 0:
        partial.unlink(missing_ok=True)
        raise NlpLibraryError(f"{cc} failed on {source.name} (exit {result.returncode}): "
                              f"{result.stderr.strip()[-500:]}")
    os.replace(partial, library)
