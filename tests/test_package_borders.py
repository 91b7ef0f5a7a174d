"""Package borders: imports never run back up the layers (docs/interfaces.md).

    can_defs <- models <- controller <- firmware_sim <- hil <- studies

Each package may import only itself and the packages to its left; torch only in the
training modules ``models/koopman_train*.py``. The one exception: a CLI entry point under
``hil/commands/`` may import a study lazily, inside the function that runs it
(``python -m hil faults --campaign``). Every import statement counts, also those inside
functions; the modules are parsed (ast), never imported.
"""
from __future__ import annotations

import ast
import fnmatch
from pathlib import Path

import pytest

from studies.provenance import module_sources

ROOT = Path(__file__).resolve().parent.parent
LAYERS = ("can_defs", "models", "controller", "firmware_sim", "hil", "studies")
TORCH_ALLOWED = "models/koopman_train*.py"
LAZY_STUDY_IMPORTS_ALLOWED = "hil/commands/*.py"
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
            if (package == "studies" and in_function
                    and fnmatch.fnmatch(relative, LAZY_STUDY_IMPORTS_ALLOWED)):
                continue
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
    ("hil/x.py", "def f():\n    import studies.run_all\n", "hil imports studies"),
    ("controller/x.py", "import torch.nn\n", "imports torch"),
])
def test_the_check_finds_an_import_up_the_layers(tmp_path: Path, relative: str, source: str,
                                                  expected: str) -> None:
    problems = _violations(_write(tmp_path, relative, source), tmp_path)
    assert len(problems) == 1 and expected in problems[0], problems


@pytest.mark.parametrize(("relative", "source"), [
    ("hil/commands/x.py", "def main():\n    from studies import fault_campaign\n"),
    ("models/koopman_train_x.py", "import torch\n"),
    ("studies/x.py", "import can_defs, models, controller, firmware_sim, hil\n"),
    ("hil/x.py", "from . import bus\nimport numpy\n"),
])
def test_the_check_allows_what_the_layers_allow(tmp_path: Path, relative: str, source: str) -> None:
    assert _violations(_write(tmp_path, relative, source), tmp_path) == []


def _write(root: Path, relative: str, source: str) -> Path:
    module = root / relative
    module.parent.mkdir(parents=True, exist_ok=True)
    module.write_text(source)
    return module
