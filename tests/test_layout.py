"""The package's import structure: no cycles among module-level imports, the kernels import
nothing of the package, the environment, the controllers and the evaluation import nothing of the
training side, and vision nothing of the environment (these two anywhere in a file, inside
functions too), and the package finds its mapped folders through the install, not by changing its
own ``__path__``."""

from __future__ import annotations

import ast
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
# Source folder -> installed package name (pyproject's package-dir mapping).
ROOTS = {"d3grasp": "d3grasp", "kernels": "d3grasp.kernels", "train": "d3grasp.train"}


def _modules() -> dict[str, Path]:
    mods = {}
    for folder, package in ROOTS.items():
        for path in (REPO / folder).rglob("*.py"):
            parts = path.relative_to(REPO / folder).with_suffix("").parts
            name = ".".join((package, *parts))
            mods[name.removesuffix(".__init__")] = path
    return mods


def _module_level_imports(path: Path, known: set[str]) -> set[str]:
    """Project modules imported at module level (not inside functions or ``if TYPE_CHECKING``)."""
    out: set[str] = set()
    for node in ast.parse(path.read_text()).body:
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
        else:
            continue
        out |= {n for n in names if n in known}
    return out


def _run_time_imports(path: Path) -> set[str]:
    """Every module a file imports when it runs: at module level and inside functions, but not under
    ``if TYPE_CHECKING:`` (annotations only)."""
    out: set[str] = set()
    tree = ast.parse(path.read_text())
    typing_only = {
        id(n)
        for node in ast.walk(tree)
        if isinstance(node, ast.If) and getattr(node.test, "id", None) == "TYPE_CHECKING"
        for stmt in node.body
        for n in ast.walk(stmt)
    }
    for node in ast.walk(tree):
        if id(node) in typing_only:
            continue
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            out |= {node.module} | {f"{node.module}.{a.name}" for a in node.names}
    return out


def test_no_import_cycles() -> None:
    mods = _modules()
    graph = {m: _module_level_imports(p, set(mods)) - {m} for m, p in mods.items()}
    state: dict[str, int] = {}  # 1 visiting, 2 done

    def visit(m: str, stack: list[str]) -> None:
        state[m] = 1
        for n in sorted(graph[m]):
            assert state.get(n) != 1, "import cycle: " + " -> ".join([*stack, m, n])
            if n not in state:
                visit(n, [*stack, m])
        state[m] = 2

    for m in sorted(graph):
        if m not in state:
            visit(m, [])


def test_arrows_point_one_way() -> None:
    mods = _modules()
    for name, path in mods.items():
        imported = _module_level_imports(path, set(mods))
        if name.startswith("d3grasp.kernels"):
            assert all(i.startswith("d3grasp.kernels") for i in imported), (name, imported)
        if name.startswith("d3grasp.envs"):
            assert not any(i.startswith("d3grasp.train") for i in imported), (name, imported)


def test_geometry_is_a_leaf() -> None:
    """d3grasp.geometry (rotations, quaternions) imports only the standard library and NumPy, nowhere
    in the file, so every layer may import it."""
    import sys

    path = REPO / "d3grasp" / "geometry.py"
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            assert node.level == 0 and node.module, ("relative import", node.module)
            names = [node.module]
        elif isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        else:
            continue
        for n in names:
            top = n.split(".")[0]
            assert top in sys.stdlib_module_names or top == "numpy", n


def test_evaluation_needs_nothing_of_training() -> None:
    for name, path in _modules().items():
        if name.startswith(("d3grasp.envs", "d3grasp.eval", "d3grasp.controllers", "d3grasp.policies")):
            assert not any(i.startswith("d3grasp.train") for i in _run_time_imports(path)), name


def test_vision_needs_nothing_of_the_environment() -> None:
    """envs uses vision (the camera, the footprint registration), never the reverse: vision reads
    the environment's config through annotations only."""
    for name, path in _modules().items():
        if name.startswith("d3grasp.vision"):
            imported = _run_time_imports(path)
            assert not any(i.startswith("d3grasp.envs") for i in imported), (name, imported)


def test_the_walk_sees_imports_inside_functions(tmp_path: Path) -> None:
    src = tmp_path / "m.py"
    src.write_text(
        "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    import d3grasp.envs.config\n"
        "def f():\n    from d3grasp.envs.grasps import rest_height\n"
    )
    assert "d3grasp.envs.grasps" in _run_time_imports(src)
    assert "d3grasp.envs.config" not in _run_time_imports(src)


def test_every_package_is_installed() -> None:
    """pyproject lists the packages explicitly: a new sub-package missing there would be absent
    from a (non-editable) pip install."""
    import tomllib

    listed = set(tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"])
    found = set()
    for folder, package in ROOTS.items():
        for init in (REPO / folder).rglob("__init__.py"):
            parts = init.parent.relative_to(REPO / folder).parts
            found.add(".".join((package, *parts)))
    assert found <= listed, f"packages missing from pyproject.toml: {sorted(found - listed)}"


def test_the_mapped_folders_resolve_through_the_install() -> None:
    """kernels/, train/ and assets_usd/ import as d3grasp.* through pyproject's package-dir (the
    editable install maps them to the checkout's folders), and the package does not append anything
    to its own ``__path__`` (which made every folder of the checkout importable as d3grasp.*)."""
    import importlib.util

    init = ast.parse((REPO / "d3grasp" / "__init__.py").read_text())
    assert not any(isinstance(n, ast.Name) and n.id == "__path__" for n in ast.walk(init))
    names = [package for folder, package in ROOTS.items() if folder != "d3grasp"] + ["d3grasp.assets_usd"]
    origins = [importlib.util.find_spec(n).origin for n in names]
    assert [Path(o).parent for o in origins] == [REPO / "kernels", REPO / "train", REPO / "assets_usd"]
    assert importlib.util.find_spec("d3grasp.tools") is None  # a root folder not mapped stays outside


def test_the_checkout_without_the_mapping_says_what_to_run() -> None:
    """The checkout's d3grasp/ imported with no install's mapping (a bare interpreter with only the
    checkout on its path: `python -m d3grasp...` in the checkout after a non-editable install) stops
    in one line naming the editable install, not at the first kernel import."""
    import subprocess
    import sys

    code = "import sys; sys.path.insert(0, sys.argv[1]); import d3grasp"
    res = subprocess.run([sys.executable, "-S", "-c", code, str(REPO)], capture_output=True, text=True)
    assert res.returncode != 0
    assert res.stderr.strip().splitlines()[-1].startswith("ImportError: ")
    assert "pip install -e ." in res.stderr


# What a reader can take in at once: a module of one role, a function of one step.
MAX_MODULE_LINES = 450
MAX_FUNCTION_LINES = 100


def test_modules_and_functions_stay_readable() -> None:
    long_files, long_functions = [], []
    for path in _modules().values():
        text = path.read_text(encoding="utf-8")
        name = str(path.relative_to(REPO))
        if text.count("\n") > MAX_MODULE_LINES:
            long_files.append(f"{name} ({text.count(chr(10))} lines)")
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                length = node.end_lineno - node.lineno + 1
                if length > MAX_FUNCTION_LINES:
                    long_functions.append(f"{name}:{node.lineno} {node.name} ({length} lines)")
    assert not long_files, long_files
    assert not long_functions, long_functions
