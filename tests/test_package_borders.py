"""Package borders: imports never run back up the layers (docs/interfaces.md).

    can_defs <- models <- controller <- firmware_sim <- hil <- studies

Each package may import only itself and the packages to its left; torch only in the
training modules ``models/koopman_train*.py``; no exception (``python -m hil faults
--campaign`` runs the study's command as a process). Every import statement counts, also those inside functions; the modules are parsed (ast),
never imported.

Besides the layers: no module imports a command line (``cli.py``, another package's
``__main__.py``), and no files import each other round a circle, in Python or (by
``#include``) in the C ECU's sources.
"""
from __future__ import annotations

import ast
import fnmatch
import re
from pathlib import Path

import pytest

from studies.provenance import module_sources

ROOT = Path(__file__).resolve().parent.parent
LAYERS = ("can_defs", "models", "controller", "firmware_sim", "hil", "studies")
TORCH_ALLOWED = "models/koopman_train*.py"
#: What runs in the ECU process and the lockstep loop around it.
RUN_TIME_ENTRY_POINTS = ("firmware_sim.ecu", "hil.session")


def _modules() -> list[Path]:
    return sorted(path for layer in LAYERS for path in (ROOT / layer).rglob("*.py"))


def _imports(tree: ast.Module) -> list[tuple[str, int, bool]]:
    """(top-level package, line, inside a function) of every absolute import."""
    found: list[tuple[str, int, bool]] = []

    def visit(node: ast.AST, in_function: bool) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.Import):
                found.extend((alias.name.split(".")[0], child.lineno, in_function) for alias in child.names)
            elif isinstance(child, ast.ImportFrom) and child.level == 0 and child.module:
                found.append((child.module.split(".")[0], child.lineno, in_function))
            visit(child, in_function or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef)))

    visit(tree, False)
    return found


def _violations(path: Path, root: Path = ROOT) -> list[str]:
    """What in ``path`` (a module under ``root``) imports against the layers."""
    relative = path.relative_to(root).as_posix()
    layer = LAYERS.index(relative.split("/")[0])
    allowed = set(LAYERS[:layer + 1])
    problems = []
    for package, line, in_function in _imports(ast.parse(path.read_text(), filename=relative)):
        where = f"{relative}:{line}"
        if package == "torch" and not fnmatch.fnmatch(relative, TORCH_ALLOWED):
            problems.append(f"{where} imports torch (only {TORCH_ALLOWED} may)")
        elif package in LAYERS and package not in allowed:
            problems.append(f"{where}: {LAYERS[layer]} imports {package} (may import "
                            f"{', '.join(sorted(allowed))})")
    return problems


def test_every_package_is_scanned() -> None:
    for layer in LAYERS:
        assert (ROOT / layer / "__init__.py").is_file(), f"{layer}/ is not a package"
    assert len(_modules()) > 50


def test_imports_never_run_back_up_the_layers() -> None:
    problems = [problem for path in _modules() for problem in _violations(path)]
    assert not problems, "imports against the package order:\n" + "\n".join(problems)


def test_the_ecu_run_time_reaches_no_training_code() -> None:
    """The ECU and the HIL session import no training module, not even lazily inside a
    function: the provenance stamps of every closed-loop result follow those imports, so a
    change to the training code would otherwise mark all of them stale (the DMDc artefact's
    loader is in models/dmdc_model.py, apart from its builder, for this reason)."""
    reached = [path.relative_to(ROOT).as_posix() for path in module_sources(RUN_TIME_ENTRY_POINTS)]
    assert any(name.endswith("models/koopman.py") for name in reached)  # the tracer follows models
    assert any(name.endswith("controller/dmdc_eso.py") for name in reached)
    training = [name for name in reached if fnmatch.fnmatch(name, TORCH_ALLOWED)]
    assert not training, f"the ECU's run time reaches training code: {training}"


@pytest.mark.parametrize(("relative", "source", "expected"), [
    ("models/x.py", "import hil.scenario\n", "models imports hil"),
    ("controller/x.py", "def f():\n    from firmware_sim import ecu\n", "controller imports firmware_sim"),
    ("hil/x.py", "from studies import closed_loop\n", "hil imports studies"),
    ("hil/commands/x.py", "from studies import run_all\n", "hil imports studies"),
    ("hil/commands/x.py", "def main():\n    from studies import fault_campaign\n", "hil imports studies"),
    ("hil/commands/faults.py", "from studies import fault_campaign\n", "hil imports studies"),
    ("hil/commands/faults.py", "def main():\n    from studies import fault_campaign\n", "hil imports studies"),
    ("hil/x.py", "def f():\n    import studies.run_all\n", "hil imports studies"),
    ("controller/x.py", "import torch.nn\n", "imports torch"),
])
def test_the_check_finds_an_import_up_the_layers(tmp_path: Path, relative: str, source: str,
                                                  expected: str) -> None:
    problems = _violations(_write(tmp_path, relative, source), tmp_path)
    assert len(problems) == 1 and expected in problems[0], problems


@pytest.mark.parametrize(("relative", "source"), [
    ("models/koopman_train_x.py", "import torch\n"),
    ("studies/x.py", "import can_defs, models, controller, firmware_sim, hil\n"),
    ("hil/x.py", "from . import bus\nimport numpy\n"),
])
def test_the_check_allows_what_the_layers_allow(tmp_path: Path, relative: str, source: str) -> None:
    assert _violations(_write(tmp_path, relative, source), tmp_path) == []


# ---------------------------------------------------------------------------- command lines

def _module_name(path: Path, root: Path) -> str:
    """Dotted name of the module in ``path`` (a package's ``__init__.py``: the package)."""
    parts = list(path.relative_to(root).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _module_file(name: str, root: Path) -> Path | None:
    """The source file of module ``name`` under ``root``; None outside the packages."""
    if name.split(".")[0] not in LAYERS:
        return None
    base = root.joinpath(*name.split("."))
    for candidate in (base.with_suffix(".py"), base / "__init__.py"):
        if candidate.is_file():
            return candidate
    return None


def _is_main_guard(node: ast.AST) -> bool:
    """``if __name__ == "__main__":``: what runs only when the file is the script."""
    test = getattr(node, "test", None)
    return (isinstance(node, ast.If) and isinstance(test, ast.Compare)
            and isinstance(test.left, ast.Name) and test.left.id == "__name__"
            and any(isinstance(c, ast.Constant) and c.value == "__main__" for c in test.comparators))


def _imported_files(path: Path, root: Path = ROOT, *, script_part: bool = True) -> list[tuple[Path, int]]:
    """(file, line) of every project module ``path`` imports: ``import a.b``, ``from a.b
    import c`` (the submodule ``a/b/c.py`` where there is one, else ``a/b``) and relative
    imports, also inside functions; without ``script_part`` not those under
    ``if __name__ == "__main__":``."""
    name = _module_name(path, root)
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found: list[tuple[Path, int]] = []

    def visit(node: ast.AST) -> None:
        for child in ast.iter_child_nodes(node):
            if not script_part and _is_main_guard(child):
                continue
            if isinstance(child, ast.Import):
                found.extend((file, child.lineno) for alias in child.names
                             if (file := _module_file(alias.name, root)) is not None)
            elif isinstance(child, ast.ImportFrom):
                if child.level:
                    parts = package.split(".")[:len(package.split(".")) - child.level + 1]
                    base = ".".join(parts + ([child.module] if child.module else []))
                else:
                    base = child.module or ""
                for alias in child.names:
                    file = _module_file(f"{base}.{alias.name}", root) or _module_file(base, root)
                    if file is not None:
                        found.append((file, child.lineno))
            visit(child)

    visit(ast.parse(path.read_text(), filename=str(path)))
    return found


def _command_line_imports(path: Path, root: Path = ROOT) -> list[str]:
    """Imports in ``path`` of a command-line module (``cli.py``, ``*_cli.py``,
    ``__main__.py``); only a package's ``__main__.py`` may import its own package's
    ``cli.py``."""
    relative = path.relative_to(root).as_posix()
    problems = []
    # a module's script part (`python -m models.koopman_train` runs models/koopman_cli.py's
    # main) is a command line itself: only what the module gives its importers counts
    for file, line in _imported_files(path, root, script_part=False):
        own_entry = path.name == "__main__.py" and file.parent == path.parent
        command_line = file.name in ("cli.py", "__main__.py") or file.name.endswith("_cli.py")
        if command_line and file != path and not own_entry:
            problems.append(f"{relative}:{line} imports the command line "
                            f"{file.relative_to(root).as_posix()}")
    return problems


def test_no_module_imports_a_command_line() -> None:
    """Command-line modules stay thin and nothing builds on them: what a CLI and a library
    share lives in a library module (issue 36)."""
    problems = [problem for path in _modules() for problem in _command_line_imports(path)]
    assert not problems, "imports of command-line modules:\n" + "\n".join(problems)


@pytest.mark.parametrize(("relative", "source", "expected"), [
    ("hil/session.py", "def f():\n    from firmware_sim.cli import parse_paths\n",
     "imports the command line firmware_sim/cli.py"),
    ("hil/x.py", "import firmware_sim.cli\n", "firmware_sim/cli.py"),
    ("studies/x.py", "def f():\n    from models import koopman_cli\n", "models/koopman_cli.py"),
    ("hil/commands/x.py", "from firmware_sim import cli\n", "firmware_sim/cli.py"),
    ("studies/x.py", "from hil.__main__ import main\n", "hil/__main__.py"),
    ("hil/__main__.py", "from firmware_sim.cli import main\n", "firmware_sim/cli.py"),
    ("firmware_sim/x.py", "from .cli import main\n", "firmware_sim/cli.py"),
])
def test_the_check_finds_an_import_of_a_command_line(tmp_path: Path, relative: str, source: str,
                                                     expected: str) -> None:
    for module in ("firmware_sim/cli.py", "firmware_sim/__main__.py", "hil/__main__.py", "models/koopman_cli.py"):
        _write(tmp_path, module, "")
    problems = _command_line_imports(_write(tmp_path, relative, source), tmp_path)
    assert len(problems) == 1 and expected in problems[0], problems


def test_the_check_lets_a_package_run_its_own_command_line(tmp_path: Path) -> None:
    _write(tmp_path, "firmware_sim/cli.py", "")
    _write(tmp_path, "firmware_sim/path_arguments.py", "")
    entry = _write(tmp_path, "firmware_sim/__main__.py", "from firmware_sim.cli import main\n")
    library = _write(tmp_path, "hil/x.py", "from firmware_sim.path_arguments import parse_paths\n")
    assert _command_line_imports(entry, tmp_path) == [] and _command_line_imports(library, tmp_path) == []


# ---------------------------------------------------------------------------- circles

def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """One circle per strongly connected component of ``graph`` (node -> the nodes it
    depends on) with more than one node, as a chain ``[a, b, ..., a]`` (Tarjan's algorithm,
    iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    components: list[list[str]] = []
    for start in sorted(graph):
        if start in index:
            continue
        work = [(start, iter(sorted(graph.get(start, ()))))]
        index[start] = low[start] = len(index)
        stack.append(start)
        on_stack.add(start)
        while work:
            node, successors = work[-1]
            for successor in successors:
                if successor not in index:
                    index[successor] = low[successor] = len(index)
                    stack.append(successor)
                    on_stack.add(successor)
                    work.append((successor, iter(sorted(graph.get(successor, ())))))
                    break
                if successor in on_stack:
                    low[node] = min(low[node], index[successor])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[node])
                if low[node] == index[node]:
                    component = []
                    while True:
                        member = stack.pop()
                        on_stack.discard(member)
                        component.append(member)
                        if member == node:
                            break
                    if len(component) > 1:
                        components.append(sorted(component))
    return [_chain(graph, set(component)) for component in sorted(components)]


def _chain(graph: dict[str, set[str]], component: set[str]) -> list[str]:
    """A shortest circle through the first node of ``component`` (breadth first)."""
    first = min(component)
    came_from: dict[str, str] = {}
    frontier = [first]
    while frontier:
        following = []
        for node in frontier:
            for successor in sorted(graph.get(node, ())):
                if successor == first:
                    chain = [node]
                    while chain[-1] != first:
                        chain.append(came_from[chain[-1]])
                    return [first, *reversed(chain[:-1]), first] if node != first else [first, first]
                if successor in component and successor not in came_from:
                    came_from[successor] = node
                    following.append(successor)
        frontier = following
    return sorted(component)


def _python_import_graph(paths: list[Path], root: Path = ROOT) -> dict[str, set[str]]:
    """File -> the files it imports (lazily or not; the script part under
    ``if __name__ == "__main__":`` left out, as it never runs on import)."""
    return {path.relative_to(root).as_posix():
            {file.relative_to(root).as_posix() for file, _ in _imported_files(path, root, script_part=False)
             if file != path}
            for path in paths}


def _described(cycles: list[list[str]]) -> str:
    return "\n".join(" -> ".join(chain) for chain in cycles)


def test_no_python_module_imports_itself_in_a_circle() -> None:
    """No two files import each other, directly or round a circle, not even lazily: a
    circle makes two modules one (neither can be read, tested or moved alone)."""
    cycles = _cycles(_python_import_graph(_modules()))
    assert not cycles, "import circles between files:\n" + _described(cycles)


#: Where the C ECU's sources are; ``#include "x.h"`` makes the including file depend on module x.
C_SOURCES = ROOT / "firmware" / "src"
_C_INCLUDE = re.compile(r'^\s*#\s*include\s+"([^"]+)\.h"', re.MULTILINE)


def _c_module_graph(source_folder: Path) -> dict[str, set[str]]:
    """Module -> the modules it includes, over ``*.c`` / ``*.h`` in ``source_folder``: a
    module is a stem (``ecu_core`` for ecu_core.c and ecu_core.h); file A depends on module
    B when A includes B.h and A is not B.c (nor B.h); headers that are not in the folder
    (generated, third-party) are left out."""
    files = sorted([*source_folder.glob("*.c"), *source_folder.glob("*.h")])
    local = {file.stem for file in files}
    graph: dict[str, set[str]] = {stem: set() for stem in local}
    for file in files:
        for included in _C_INCLUDE.findall(file.read_text(errors="replace")):
            if included in local and included != file.stem:
                graph[file.stem].add(included)
    return graph


def test_no_c_module_includes_itself_in_a_circle() -> None:
    """The C ECU's modules form no include circle either (firmware/src)."""
    cycles = _cycles(_c_module_graph(C_SOURCES))
    assert not cycles, "include circles between C modules:\n" + _described(cycles)


@pytest.mark.parametrize(("files", "expected"), [
    ({"studies/a.py": "import studies.b\n", "studies/b.py": "from studies.a import f\n"},
     ["studies/a.py", "studies/b.py", "studies/a.py"]),
    ({"studies/a.py": "def f():\n    import studies.b.c\n", "studies/b/__init__.py": "",
      "studies/b/c.py": "from ..a import x\n"},
     ["studies/a.py", "studies/b/c.py", "studies/a.py"]),
    ({"hil/x.py": "from . import y\n", "hil/y.py": "from hil import z\n", "hil/z.py": "import hil.x\n"},
     ["hil/x.py", "hil/y.py", "hil/z.py", "hil/x.py"]),
])
def test_the_check_finds_an_import_circle(tmp_path: Path, files: dict[str, str],
                                          expected: list[str]) -> None:
    paths = [_write(tmp_path, relative, source) for relative, source in files.items()]
    cycles = _cycles(_python_import_graph(paths, tmp_path))
    print(_described(cycles))
    assert cycles == [expected], cycles


def test_the_check_allows_a_script_part_and_a_chain(tmp_path: Path) -> None:
    paths = [_write(tmp_path, "studies/a.py", "import studies.b\n"),
             _write(tmp_path, "studies/b.py", "import studies.c\n"),
             _write(tmp_path, "studies/c.py", "if __name__ == '__main__':\n    import studies.a\n")]
    assert _cycles(_python_import_graph(paths, tmp_path)) == []


def test_the_check_finds_an_include_circle(tmp_path: Path) -> None:
    _write(tmp_path, "core.h", '#include "types.h"\n')
    _write(tmp_path, "core.c", '#include "core.h"\n#include "path.h"\n#include <stdio.h>\n')
    _write(tmp_path, "path.h", '#include "types.h"\n')
    _write(tmp_path, "path.c", '#include "path.h"\n#include "core.h"\n#include "osqp.h"\n')
    _write(tmp_path, "types.h", "")
    assert _cycles(_c_module_graph(tmp_path)) == [["core", "path", "core"]]
    _write(tmp_path, "path.c", '#include "path.h"\n#include "types.h"\n')
    assert _cycles(_c_module_graph(tmp_path)) == []


def _write(root: Path, relative: str, source: str) -> Path:
    module = root / relative
    module.parent.mkdir(parents=True, exist_ok=True)
    module.write_text(source)
    return module


#: The most lines a module of the product packages, the studies or the C ECU may have
#: (about 400 is typical); a longer one does several jobs and is split by them.
MODULE_MAX_LINES = 600


def test_no_module_is_over_600_lines() -> None:
    sources = [*_modules(), *sorted((ROOT / "firmware" / "src").glob("*.[ch]")),
               *sorted((ROOT / "firmware" / "tools").glob("*.py"))]
    long = {path.relative_to(ROOT).as_posix(): n for path in sources
            if (n := path.read_text(errors="replace").count("\n")) > MODULE_MAX_LINES}
    assert not long, f"modules over {MODULE_MAX_LINES} lines (split them by their jobs): {long}"
