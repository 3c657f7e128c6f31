"""The package's import structure: no cycles among module-level imports, the kernels import
nothing of the package, and the environment, the controllers and the evaluation import nothing of
the training side (not even inside functions)."""

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
    mods = _modules()
    for name, path in mods.items():
        if not name.startswith(("d3grasp.envs", "d3grasp.eval", "d3grasp.controllers", "d3grasp.policies")):
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module:
                assert not node.module.startswith("d3grasp.train"), (name, node.module)
            elif isinstance(node, ast.Import):
                assert not any(a.name.startswith("d3grasp.train") for a in node.names), name


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


def test_the_checkout_itself_resolves_the_mapped_packages() -> None:
    """`python -m d3grasp...` in the repository root imports the source folder ahead of any installed
    copy: the folders pyproject maps under d3grasp must resolve from there too. Checked in a bare
    interpreter (no site-packages, so no editable-install finder) with only the checkout on the path."""
    import subprocess
    import sys

    code = (
        "import importlib.util, sys; sys.path.insert(0, sys.argv[1]); "
        "print(*(importlib.util.find_spec(n).origin for n in sys.argv[2:]), sep='\\n')"
    )
    names = [package for folder, package in ROOTS.items() if folder != "d3grasp"] + ["d3grasp.assets_usd"]
    out = subprocess.run(
        [sys.executable, "-S", "-c", code, str(REPO), *names], capture_output=True, text=True, check=True
    ).stdout.split()
    folders = [Path(o).parent.name for o in out]
    assert folders == ["kernels", "train", "assets_usd"]
