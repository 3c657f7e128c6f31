"""Build the procedural rigid object library: ``assets_usd/objects/rigid/*.usda`` + manifest entries.

13 shape families x 10 instances = 130 objects, made with trimesh from a seeded RNG (seed =
CRC32 of "<family>:<index>"), so a rebuild gives the same shapes. Each instance gets a size bin
by ``(index + family number) % 3`` and a longest side drawn inside that bin (10% margins), so
every family spans all three bins and the bins hold 43-44 objects each. Every 5th instance of a
family (index 4 and 9) is held out as ``test`` (20% of each family).

Materials (density kg/m^3, friction) are per family and realistic for the material named in
:data:`FAMILIES`. Hollow objects (mug, bowl) are modelled as shells, so their solid volume is
small. The hand (~1 kg, finger drives of a few N*m) cannot lift more than about half a
kilogram, so the density of large solid shapes is lowered until the object weighs at most
:data:`MAX_MASS` -- physically, a hollow or foam-cored version of the same object; the manifest
records the effective density actually used.

Convex decomposition: nearly convex shapes (volume >= 97% of their hull) get one hull; the rest
run coacd (threshold 0.08, at most 16 hulls of at most 64 vertices). coacd is seeded; its
output for this library is committed, so users never run it.

Run: ``python tools/build_rigid_objects.py [--out assets_usd]`` (a few minutes on 2 cores).
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
import zlib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:  # run as a script from a checkout without installing
    sys.path.insert(0, str(REPO))

from d3grasp.authoring.importer import RIGID_DIR, author_rigid  # noqa: E402
from d3grasp.authoring.manifest import SIZE_BINS, AssetEntry, install_built_assets  # noqa: E402

INSTANCES_PER_FAMILY = 10
TEST_EVERY = 5  # instance i is held out when i % TEST_EVERY == TEST_EVERY - 1
MAX_MASS = 0.5  # kg; see the module docstring
BIN_NAMES = list(SIZE_BINS)


# --------------------------------------------------------------------------------------------
# Geometry helpers (all return closed, outward-wound meshes in arbitrary units)


def _revolve(profile: list[tuple[float, float]], sections: int = 28) -> trimesh.Trimesh:
    """Solid of revolution about z of a closed (r, z) profile starting and ending on the axis."""
    m = trimesh.creation.revolve(np.asarray(profile, dtype=np.float64), sections=sections)
    trimesh.repair.fix_normals(m)
    return m


def _ear_clip(poly: np.ndarray) -> np.ndarray:
    """Triangles of a simple counter-clockwise polygon by ear clipping (small polygons only)."""

    def cross(o: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
        return float((a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0]))

    idx = list(range(len(poly)))
    tris = []
    while len(idx) > 3:
        for k in range(len(idx)):
            i0, i1, i2 = idx[k - 1], idx[k], idx[(k + 1) % len(idx)]
            a, b, c = poly[i0], poly[i1], poly[i2]
            if cross(a, b, c) <= 1e-12:  # reflex or collinear corner: not an ear
                continue
            inside = False
            for j in idx:
                if j in (i0, i1, i2):
                    continue
                p = poly[j]
                if cross(a, b, p) >= 0 and cross(b, c, p) >= 0 and cross(c, a, p) >= 0:
                    inside = True
                    break
            if not inside:
                tris.append((i0, i1, i2))
                idx.pop(k)
                break
        else:
            raise ValueError("polygon is not simple")
    tris.append(tuple(idx))
    return np.asarray(tris, dtype=np.int64)


def _extrude(poly: list[tuple[float, float]], height: float) -> trimesh.Trimesh:
    p = np.asarray(poly, dtype=np.float64)
    m = trimesh.creation.extrude_triangulation(p, _ear_clip(p), height)
    trimesh.repair.fix_normals(m)
    return m


def _tube_arc(
    center: np.ndarray,
    arc_radius: float,
    tube_radius: float,
    phi0: float,
    phi1: float,
    n: int = 12,
    m: int = 10,
) -> trimesh.Trimesh:
    """A capped circular tube swept along an arc in the xz-plane (a mug handle)."""
    phis = np.linspace(phi0, phi1, n)
    thetas = np.linspace(0.0, 2.0 * np.pi, m, endpoint=False)
    verts = []
    for phi in phis:
        radial = np.array([np.cos(phi), 0.0, np.sin(phi)])
        c = center + arc_radius * radial
        for th in thetas:
            verts.append(c + tube_radius * (np.cos(th) * radial + np.sin(th) * np.array([0.0, 1.0, 0.0])))
    verts.append(center + arc_radius * np.array([np.cos(phi0), 0.0, np.sin(phi0)]))
    verts.append(center + arc_radius * np.array([np.cos(phi1), 0.0, np.sin(phi1)]))
    faces = []
    for i in range(n - 1):
        for j in range(m):
            a, b = i * m + j, i * m + (j + 1) % m
            c, d = a + m, b + m
            faces += [(a, b, d), (a, d, c)]
    s0, s1 = n * m, n * m + 1
    for j in range(m):
        faces.append((s0, (j + 1) % m, j))
        faces.append((s1, (n - 1) * m + j, (n - 1) * m + (j + 1) % m))
    mesh = trimesh.Trimesh(np.asarray(verts), np.asarray(faces), process=True)
    trimesh.repair.fix_normals(mesh)
    return mesh


# --------------------------------------------------------------------------------------------
# Families: each maker takes an RNG and returns a closed mesh; the builder scales it to size.


def make_box(rng: np.random.Generator) -> trimesh.Trimesh:
    return trimesh.creation.box(extents=[1.0, rng.uniform(0.35, 1.0), rng.uniform(0.35, 1.0)])


def make_cylinder(rng: np.random.Generator) -> trimesh.Trimesh:
    return trimesh.creation.cylinder(radius=0.5, height=rng.uniform(0.4, 2.5), sections=24)


def make_ellipsoid(rng: np.random.Generator) -> trimesh.Trimesh:
    m = trimesh.creation.icosphere(subdivisions=2)
    m.apply_scale([1.0, rng.uniform(0.5, 1.0), rng.uniform(0.5, 1.0)])
    return m


def make_capsule(rng: np.random.Generator) -> trimesh.Trimesh:
    return trimesh.creation.capsule(height=rng.uniform(0.5, 3.0), radius=0.5, count=[16, 8])


def make_frustum(rng: np.random.Generator) -> trimesh.Trimesh:
    r0, r1, h = 0.5, 0.5 * rng.uniform(0.0, 0.7), rng.uniform(0.5, 1.6)
    prof = [(0.0, 0.0), (r0, 0.0), (r1, h), (0.0, h)] if r1 > 0.02 else [(0.0, 0.0), (r0, 0.0), (0.0, h)]
    return _revolve(prof, sections=28)


def make_superquadric(rng: np.random.Generator) -> trimesh.Trimesh:
    """Rounded box |x|^p + |y|^p + |z|^p = 1 (p 2.5-5), by projecting an icosphere radially."""
    p = rng.uniform(2.5, 5.0)
    m = trimesh.creation.icosphere(subdivisions=3)
    d = np.asarray(m.vertices)
    t = np.sum(np.abs(d) ** p, axis=1) ** (-1.0 / p)
    m = trimesh.Trimesh(d * t[:, None], m.faces, process=True)
    m.apply_scale([1.0, rng.uniform(0.45, 1.0), rng.uniform(0.45, 1.0)])
    return m


def make_torus(rng: np.random.Generator) -> trimesh.Trimesh:
    return trimesh.creation.torus(
        major_radius=1.0, minor_radius=rng.uniform(0.22, 0.45), major_sections=28, minor_sections=10
    )


def make_mug(rng: np.random.Generator) -> trimesh.Trimesh:
    """Hollow cup (revolved wall + bottom) with a tube handle touching the outer wall."""
    ro, h = 0.5, rng.uniform(0.9, 1.6)
    t, tb = ro * rng.uniform(0.08, 0.12), h * rng.uniform(0.06, 0.1)
    cup = _revolve([(0.0, 0.0), (ro, 0.0), (ro, h), (ro - t, h), (ro - t, tb), (0.0, tb)], sections=28)
    arc = h * rng.uniform(0.25, 0.35)
    handle = _tube_arc(np.array([ro, 0.0, 0.5 * h]), arc, 0.05 + 0.03 * rng.uniform(), -np.pi / 2, np.pi / 2)
    return trimesh.util.concatenate([cup, handle])


def make_bowl(rng: np.random.Generator) -> trimesh.Trimesh:
    ro, h = 0.5, rng.uniform(0.3, 0.55)
    rf, t, tb = ro * rng.uniform(0.35, 0.55), ro * rng.uniform(0.06, 0.1), h * rng.uniform(0.1, 0.15)
    n = 8
    s = np.linspace(0.0, 1.0, n)
    outer = [(rf + (ro - rf) * np.sin(si * np.pi / 2), h * (1 - np.cos(si * np.pi / 2))) for si in s]
    ri = ro - t
    inner = [(ri * np.sin(si * np.pi / 2), tb + (h - tb) * (1 - np.cos(si * np.pi / 2))) for si in s[::-1]]
    prof = [(0.0, 0.0), *outer, *inner[:-1], (0.0, tb)]
    return _revolve(prof, sections=28)


def make_bottle(rng: np.random.Generator) -> trimesh.Trimesh:
    r, h = 0.5, rng.uniform(1.8, 3.5)
    rn, hb, hn = r * rng.uniform(0.3, 0.45), h * rng.uniform(0.5, 0.65), h * rng.uniform(0.15, 0.25)
    hs = h - hn
    shoulder = [(rn + (r - rn) * np.cos(a), hb + (hs - hb) * np.sin(a)) for a in np.linspace(0, np.pi / 2, 6)]
    prof = [(0.0, 0.0), (r, 0.0), *shoulder, (rn, h), (0.0, h)]
    return _revolve(prof, sections=24)


def make_blob(rng: np.random.Generator) -> trimesh.Trimesh:
    """Icosphere displaced radially by a few random smooth waves (a pebble or potato)."""
    m = trimesh.creation.icosphere(subdivisions=3)
    d = np.asarray(m.vertices)
    r = np.ones(len(d))
    for _ in range(6):
        w = rng.normal(size=3)
        w *= rng.uniform(2.0, 4.0) / np.linalg.norm(w)
        r += rng.uniform(0.06, 0.14) * np.sin(d @ w + rng.uniform(0, 2 * np.pi))
    m = trimesh.Trimesh(d * r[:, None], m.faces, process=True)
    m.apply_scale([1.0, rng.uniform(0.6, 1.0), rng.uniform(0.5, 0.9)])
    return m


def make_lshape(rng: np.random.Generator) -> trimesh.Trimesh:
    a, b = 1.0, rng.uniform(0.5, 1.0)
    w = rng.uniform(0.25, 0.4) * b
    return _extrude([(0, 0), (a, 0), (a, w), (w, w), (w, b), (0, b)], rng.uniform(0.15, 0.35))


def make_cross(rng: np.random.Generator) -> trimesh.Trimesh:
    """A T or a plus sign, extruded (toy building pieces)."""
    w = rng.uniform(0.22, 0.34)
    h = w * rng.uniform(0.8, 1.4)
    lo, hi = 0.5 - w / 2, 0.5 + w / 2
    if rng.uniform() < 0.5:  # T
        poly = [(0, 1 - w), (0, 1), (1, 1), (1, 1 - w), (hi, 1 - w), (hi, 0), (lo, 0), (lo, 1 - w)]
    else:  # plus
        poly = [
            (lo, 0),
            (hi, 0),
            (hi, lo),
            (1, lo),
            (1, hi),
            (hi, hi),
            (hi, 1),
            (lo, 1),
            (lo, hi),
            (0, hi),
            (0, lo),
            (lo, lo),
        ]
    poly = poly[::-1] if _signed_area(poly) < 0 else poly
    return _extrude(poly, h)


def _signed_area(poly: list[tuple[float, float]]) -> float:
    p = np.asarray(poly, dtype=np.float64)
    return 0.5 * float(np.sum(p[:, 0] * np.roll(p[:, 1], -1) - np.roll(p[:, 0], -1) * p[:, 1]))


@dataclass(frozen=True)
class Family:
    make: Callable[[np.random.Generator], trimesh.Trimesh]
    material: str
    density: float  # kg/m^3 of the solid material
    friction: float
    color: tuple[float, float, float]


FAMILIES: dict[str, Family] = {
    "box": Family(make_box, "wood", 650.0, 0.6, (0.72, 0.55, 0.35)),
    "cylinder": Family(make_cylinder, "hdpe", 950.0, 0.5, (0.2, 0.45, 0.8)),
    "ellipsoid": Family(make_ellipsoid, "hard_rubber", 1100.0, 0.9, (0.8, 0.3, 0.25)),
    "capsule": Family(make_capsule, "hdpe", 950.0, 0.5, (0.3, 0.7, 0.4)),
    "frustum": Family(make_frustum, "wood", 600.0, 0.6, (0.65, 0.5, 0.3)),
    "superquadric": Family(make_superquadric, "abs", 1050.0, 0.5, (0.9, 0.75, 0.2)),
    "torus": Family(make_torus, "rubber", 1150.0, 0.9, (0.15, 0.15, 0.15)),
    "mug": Family(make_mug, "ceramic", 2300.0, 0.6, (0.92, 0.92, 0.88)),
    "bowl": Family(make_bowl, "melamine", 1500.0, 0.55, (0.85, 0.4, 0.3)),
    "bottle": Family(make_bottle, "filled_bottle", 1000.0, 0.5, (0.4, 0.75, 0.85)),
    "blob": Family(make_blob, "dense_foam", 800.0, 0.8, (0.55, 0.5, 0.45)),
    "lshape": Family(make_lshape, "wood", 650.0, 0.6, (0.6, 0.45, 0.3)),
    "cross": Family(make_cross, "abs", 1050.0, 0.5, (0.3, 0.35, 0.9)),
}


@dataclass(frozen=True)
class Spec:
    """One planned instance: everything needed to author it (pure data, deterministic)."""

    asset_id: str
    family: str
    index: int
    size_bin: str
    longest_side: float
    split: str
    seed: int


def plan() -> list[Spec]:
    """The list of instances to build, in a fixed order."""
    specs = []
    for f, name in enumerate(FAMILIES):
        for i in range(INSTANCES_PER_FAMILY):
            seed = zlib.crc32(f"{name}:{i}".encode())
            rng = np.random.default_rng(seed)
            bin_name = BIN_NAMES[(i + f) % len(BIN_NAMES)]
            lo, hi = SIZE_BINS[bin_name]
            longest = lo + (hi - lo) * rng.uniform(0.1, 0.9)
            split = "test" if i % TEST_EVERY == TEST_EVERY - 1 else "train"
            specs.append(Spec(f"{name}_{i:02d}", name, i, bin_name, float(longest), split, seed))
    return specs


def make_mesh(spec: Spec) -> trimesh.Trimesh:
    """The closed mesh of one instance, scaled so its longest side is ``spec.longest_side``."""
    # The size was drawn from the seed's first numbers; shapes use a separate stream.
    rng = np.random.default_rng([spec.seed, 1])
    m = FAMILIES[spec.family].make(rng)
    m.apply_scale(spec.longest_side / float(m.extents.max()))
    m.apply_translation(-0.5 * (m.bounds[0] + m.bounds[1]))
    if not m.is_watertight or m.volume <= 0:
        raise RuntimeError(f"{spec.asset_id}: generator made an open or inverted mesh")
    return m


def build_one(spec: Spec, root: Path) -> AssetEntry:
    fam = FAMILIES[spec.family]
    mesh = make_mesh(spec)
    density = min(fam.density, MAX_MASS / float(mesh.volume))
    return author_rigid(
        mesh,
        root,
        spec.asset_id,
        family=spec.family,
        density=density,
        friction=fam.friction,
        split=spec.split,
        source=f"procedural:{spec.family} seed={spec.seed}",
        seed=0,
        color=fam.color,
        extra_material={"name": fam.material, "nominal_density": fam.density},
    )


def build(out_root: Path, *, progress: bool = True) -> list[AssetEntry]:
    """Regenerate ``out_root/objects/rigid/`` and the rigid entries of ``out_root/manifest.json``.

    Authoring happens in a temporary directory; the old rigid files are replaced only after
    every object was built.
    """
    out_root = Path(out_root)
    specs = plan()
    out_root.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=".rigid-build-", dir=out_root))
    try:
        it = specs
        if progress:
            from tqdm import tqdm

            it = tqdm(specs, desc="rigid objects", unit="obj")
        entries = [build_one(s, tmp) for s in it]
        install_built_assets(tmp, out_root, RIGID_DIR, entries, kind="rigid")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return entries


def summary(entries: list[AssetEntry]) -> str:
    lines = []
    for name in FAMILIES:
        es = [e for e in entries if e.family == name]
        bins = {b: sum(e.size_bin == b for e in es) for b in BIN_NAMES}
        hulls = [e.stats["num_hulls"] for e in es]
        lines.append(
            f"{name:13s} n={len(es):3d} bins={bins} test={sum(e.split == 'test' for e in es)} "
            f"hulls {min(hulls)}-{max(hulls)} mass {min(e.mass for e in es) * 1e3:.0f}-"
            f"{max(e.mass for e in es) * 1e3:.0f} g"
        )
    bins = {b: sum(e.size_bin == b for e in entries) for b in BIN_NAMES}
    lines.append(
        f"total {len(entries)} objects, bins {bins}, hulls {sum(e.stats['num_hulls'] for e in entries)}"
    )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--out", type=Path, default=REPO / "assets_usd", help="library root (default: assets_usd/)"
    )
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    entries = build(args.out)
    print(summary(entries))
    size = sum(p.stat().st_size for p in (args.out / RIGID_DIR).glob("*.usda"))
    print(f"built in {time.perf_counter() - t0:.1f} s; {size / 1e6:.2f} MB on disk")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
