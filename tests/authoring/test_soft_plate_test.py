"""tools/soft_plate_test.py against linear elasticity: a block under a plate's weight shortens by
F / (E A) of its height (Hooke's law in one axis), which a structured tet mesh of a block
represents exactly (a uniform strain is linear in every tet)."""

from __future__ import annotations

import importlib.util
import itertools
import sys
from pathlib import Path

import numpy as np
import pytest

from d3grasp.authoring.manifest import AssetEntry
from d3grasp.authoring.usd_soft import write_soft_usd
from d3grasp.envs.config import SimConfig

REPO = Path(__file__).resolve().parents[2]


def _tool():
    spec = importlib.util.spec_from_file_location("soft_plate_test", REPO / "tools" / "soft_plate_test.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules.setdefault("soft_plate_test", mod)
    spec.loader.exec_module(mod)
    return mod


def _block(side: float, cells: int) -> tuple[np.ndarray, np.ndarray]:
    """A cube of ``side`` m centred at the origin: cells^3 hexahedra of six tets each (Kuhn's split
    along the main diagonal), every tet positively oriented."""
    n = cells + 1
    g = np.linspace(-side / 2, side / 2, n)
    points = np.array([(x, y, z) for x in g for y in g for z in g])

    def node(i: int, j: int, k: int) -> int:
        return (i * n + j) * n + k

    tets = []
    for i, j, k in itertools.product(range(cells), repeat=3):
        corner = np.array([i, j, k])
        for perm in itertools.permutations(range(3)):
            path = [corner.copy()]
            for axis in perm:
                step = path[-1].copy()
                step[axis] += 1
                path.append(step)
            tets.append([node(*p) for p in path])
    tets = np.array(tets, dtype=np.int32)
    a, b, c, d = (points[tets[:, m]] for m in range(4))
    flip = np.linalg.det(np.stack([b - a, c - a, d - a], axis=-1)) < 0
    tets[flip, 2], tets[flip, 3] = tets[flip, 3].copy(), tets[flip, 2].copy()
    return points, tets


@pytest.mark.parametrize(
    ("cells", "seconds"),
    [
        (2, 0.5),  # the quick version: 27 nodes, half a second under the plate
        pytest.param(4, 1.0, marks=pytest.mark.slow),
    ],
)
def test_block_under_plate_follows_hookes_law(tmp_path, cells: int, seconds: float):
    side, young, nu = 0.04, 2.0e4, 0.15
    material = {
        "class": "sponge",
        "youngs_modulus": young,
        "poissons_ratio": nu,
        "density": 60.0,
        "damping": young * 2e-3,
        "friction": 1.0,
    }
    points, tets = _block(side, cells)
    path = tmp_path / "block.usda"
    write_soft_usd(path, points, tets, material, name="block")
    entry = AssetEntry(
        id="block",
        path="block.usda",
        kind="deformable",
        family="sponge",
        size_bin="small",
        extents=[side, side, side],
        mass=60.0 * side**3,
        volume=side**3,
        material=material,
        stats={"particle_radius": 0.003},
    )
    tool = _tool()
    strain = 0.05
    # Solved to convergence (80 SolverVBD iterations a substep; the environment's 20 leave a mesh of
    # this many nodes stiffer than its modulus: the tool's docstring).
    got = tool.plate_test(entry, path, strain, seconds, SimConfig(), iterations=80)
    assert got["finite"]
    assert got["load_n"] == pytest.approx(strain * young * side**2)
    # Hooke: 5% shorter. The plate's and table's friction hold the block's ends from spreading
    # sideways (stiffer by a few % at nu = 0.15) and its own weight adds 0.3% of the load.
    assert got["compression"] == pytest.approx(strain, rel=0.08)
    # The largest principal Green strain is the sideways stretch, about nu times the shortening.
    assert 0.3 * nu * strain < got["eps_bar"] < 2.0 * nu * strain
