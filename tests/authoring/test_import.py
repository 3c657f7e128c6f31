"""The import pipeline (meshes made here with trimesh) and every class of bad input.

References are analytic (box volume and inertia, torus volume) or read straight from the USD
file with pxr, independent of the authoring code's own numbers.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
import trimesh

from d3grasp.authoring import tetmesh, usd_soft  # noqa: F401 (usd_soft: the soft USD writer must import)
from d3grasp.authoring.importer import import_meshes
from d3grasp.authoring.manifest import read_manifest, resolve_asset_path
from d3grasp.authoring.meshcheck import MeshError, load_and_check

BOX = (0.05, 0.04, 0.03)  # metres


def _box_mesh() -> trimesh.Trimesh:
    return trimesh.creation.box(extents=BOX)


def _usd_mass_api(path: Path, prim_name: str) -> dict:
    from pxr import Usd, UsdGeom, UsdPhysics

    stage = Usd.Stage.Open(str(path))
    prim = stage.GetPrimAtPath(f"/{prim_name}")
    assert stage.GetDefaultPrim() == prim
    api = UsdPhysics.MassAPI(prim)
    hulls = [p for p in Usd.PrimRange(prim) if p.HasAPI(UsdPhysics.CollisionAPI)]
    return {
        "mass": api.GetMassAttr().Get(),
        "diag": np.array(api.GetDiagonalInertiaAttr().Get(), dtype=float),
        "com": np.array(api.GetCenterOfMassAttr().Get(), dtype=float),
        "rigid": prim.HasAPI(UsdPhysics.RigidBodyAPI),
        "hulls": [np.array(UsdGeom.Mesh(p).GetPointsAttr().Get(), dtype=float) for p in hulls],
    }


@pytest.mark.parametrize("suffix", [".obj", ".stl", ".ply", ".glb"])
def test_import_box_every_format(tmp_path: Path, suffix: str) -> None:
    src = tmp_path / f"my box{suffix}"
    _box_mesh().export(src)
    out = tmp_path / "lib"
    rho, mu = 700.0, 0.65
    entries = import_meshes([src], out, density=rho, friction=mu).entries
    assert [e.id for e in entries] == ["my_box"]
    (e,) = read_manifest(out / "manifest.json")
    a, b, c = BOX
    vol = a * b * c
    assert e.kind == "rigid" and e.size_bin == "small"  # longest side 5 cm
    assert sorted(e.extents) == pytest.approx(sorted(BOX), rel=1e-6)
    assert e.volume == pytest.approx(vol, rel=1e-6)
    assert e.mass == pytest.approx(rho * vol, rel=1e-6)
    assert e.stats["num_hulls"] == 1  # a box is convex: one hull
    usd = _usd_mass_api(resolve_asset_path(out / "manifest.json", e), e.id)
    assert usd["rigid"] and len(usd["hulls"]) == 1
    assert usd["mass"] == pytest.approx(rho * vol, rel=1e-5)
    # Solid box principal moments m/12 (b^2 + c^2) etc., in any order of axes.
    m = rho * vol
    ref = sorted([m / 12 * (b * b + c * c), m / 12 * (a * a + c * c), m / 12 * (a * a + b * b)])
    assert sorted(usd["diag"]) == pytest.approx(ref, rel=1e-4)
    assert np.allclose(usd["com"], 0.0, atol=1e-6)  # body origin = box centre = centre of mass
    assert not list(out.glob(".d3grasp-import-*")) and not list(tmp_path.glob(".d3grasp-import-*"))


def test_import_torus_gets_several_hulls(tmp_path: Path) -> None:
    R, r = 0.04, 0.012
    src = tmp_path / "ring.stl"
    trimesh.creation.torus(major_radius=R, minor_radius=r, major_sections=24, minor_sections=10).export(src)
    (e,) = import_meshes([src], tmp_path / "lib", density=1000.0).entries
    assert 2 <= e.stats["num_hulls"] <= 16
    assert all(4 <= n <= 64 for n in e.stats["num_hull_vertices"])
    # The faceted torus is a little smaller than the smooth one (2 pi^2 R r^2).
    assert e.volume == pytest.approx(2 * np.pi**2 * R * r * r, rel=0.08)
    usd = _usd_mass_api(resolve_asset_path(tmp_path / "lib" / "manifest.json", e), e.id)
    assert len(usd["hulls"]) == e.stats["num_hulls"]
    # Hulls must cover the ring without filling the hole: total hull volume near the ring's.
    hull_vol = sum(trimesh.convex.convex_hull(pts).volume for pts in usd["hulls"])
    assert 0.9 * e.volume < hull_vol < 1.5 * e.volume


def test_import_scale_and_reimport_replaces(tmp_path: Path) -> None:
    src = tmp_path / "mm_box.stl"
    trimesh.creation.box(extents=[s * 1000 for s in BOX]).export(src)  # authored in millimetres
    out = tmp_path / "lib"
    (e,) = import_meshes([src], out, scale=0.001).entries
    assert max(e.extents) == pytest.approx(0.05, rel=1e-6)
    other = tmp_path / "other.obj"
    _box_mesh().export(other)
    import_meshes([other], out)
    import_meshes([src], out, scale=0.002)  # same id: replaces, keeps "other"
    entries = {x.id: x for x in read_manifest(out / "manifest.json")}
    assert set(entries) == {"mm_box", "other"}
    assert max(entries["mm_box"].extents) == pytest.approx(0.10, rel=1e-6)
    assert entries["mm_box"].size_bin == "medium"


# ------------------------------------------------------------------------------ bad input


def _write(path: Path, data: bytes | str) -> Path:
    path.write_bytes(data if isinstance(data, bytes) else data.encode())
    return path


def _nan_obj(path: Path) -> Path:
    m = _box_mesh()
    lines = [f"v {x} {y} {z}" for x, y, z in m.vertices]
    lines[3] = "v nan 0.01 0.02"
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in m.faces]
    return _write(path, "\n".join(lines) + "\n")


def _flat_stl(path: Path) -> Path:
    v = [[0, 0, 0], [0.05, 0, 0], [0.05, 0.05, 0], [0, 0.05, 0]]
    trimesh.Trimesh(v, [[0, 1, 2], [0, 2, 3], [0, 3, 2], [0, 2, 1]], process=False).export(path)
    return path


def _hemisphere_stl(path: Path) -> Path:
    s = trimesh.creation.icosphere(subdivisions=2, radius=0.03)
    trimesh.Trimesh(s.vertices, s.faces[s.triangles_center[:, 2] > 0]).export(path)
    return path


BAD_CASES = {
    "empty": (lambda p: _write(p / "empty.obj", b""), "empty file"),
    "garbage_obj": (lambda p: _write(p / "junk.obj", os.urandom(3000)), "unreadable"),
    "garbage_stl": (lambda p: _write(p / "junk.stl", bytes(range(256)) * 8), "unreadable"),
    "garbage_glb": (lambda p: _write(p / "junk.glb", os.urandom(600)), "unreadable"),
    "text_obj": (lambda p: _write(p / "notes.obj", "hello\nnot a mesh\n"), "no triangles"),
    "nan_vertex": (lambda p: _nan_obj(p / "nan.obj"), "NaN"),
    "flat": (lambda p: _flat_stl(p / "flat.stl"), "degenerate"),
    "two_metres": (
        lambda p: trimesh.creation.box(extents=[2.0, 1.0, 1.0]).export(p / "crate.stl"),
        "--scale",
    ),
    "too_small": (lambda p: trimesh.creation.box(extents=[0.01] * 3).export(p / "bead.stl"), "graspable"),
    "wrong_type": (lambda p: _write(p / "mesh.xyz", "1 2 3\n"), "unsupported file type"),
}


@pytest.mark.parametrize("case", sorted(BAD_CASES))
def test_bad_input_is_refused_with_no_output(tmp_path: Path, case: str) -> None:
    make, reason = BAD_CASES[case]
    make(tmp_path)
    bad = next(p for p in tmp_path.iterdir() if p.is_file())
    good = _box_mesh().export(tmp_path / "good.obj") and tmp_path / "good.obj"
    out = tmp_path / "lib"
    with pytest.raises(MeshError) as info:
        import_meshes([good, bad], out)
    msg = str(info.value)
    assert msg.startswith(f"{bad}: ") and reason in msg and "\n" not in msg
    assert not out.exists()  # nothing written, not even the good mesh
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []


def test_open_mesh_refused_for_soft_but_repaired_when_sound(tmp_path: Path) -> None:
    hemi = _hemisphere_stl(tmp_path / "cap.stl")
    with pytest.raises(MeshError, match=r"cap\.stl: open \(non-watertight\)"):
        load_and_check(hemi, require_watertight=True)
    # A rigid object only needs hulls: the open cap is accepted (volume from its hull).
    rigid = load_and_check(hemi)
    assert not rigid.is_watertight
    # One missing triangle is a sound repair: the surface closes and keeps the box volume.
    b = _box_mesh()
    holed = tmp_path / "holed.stl"
    trimesh.Trimesh(b.vertices, b.faces[1:]).export(holed)
    fixed = load_and_check(holed, require_watertight=True)
    assert fixed.is_watertight and fixed.volume == pytest.approx(np.prod(BOX), rel=1e-6)  # STL: float32


def test_inverted_winding_is_fixed(tmp_path: Path) -> None:
    b = _box_mesh()
    inv = tmp_path / "inside_out.obj"
    trimesh.Trimesh(b.vertices, b.faces[:, ::-1], process=False).export(inv)
    m = load_and_check(inv)
    assert m.volume == pytest.approx(np.prod(BOX), rel=1e-9)  # positive: winding turned outward


def test_open_mesh_deformable_import_refused(tmp_path: Path) -> None:
    hemi = _hemisphere_stl(tmp_path / "cap.stl")
    with pytest.raises(MeshError, match="non-watertight"):
        import_meshes([hemi], tmp_path / "lib", deformable=True)
    assert not (tmp_path / "lib").exists()


def test_bad_material_parameters(tmp_path: Path) -> None:
    src = _box_mesh().export(tmp_path / "b.obj") and tmp_path / "b.obj"
    with pytest.raises(ValueError, match="Poisson"):
        import_meshes([src], tmp_path / "lib", deformable=True, poissons_ratio=0.5)
    with pytest.raises(ValueError, match="density"):
        import_meshes([src], tmp_path / "lib", density=-1.0)
    with pytest.raises(ValueError, match="scale"):
        import_meshes([src], tmp_path / "lib", scale=0.0)
    assert not (tmp_path / "lib").exists()


def test_import_deformable_sphere(tmp_path: Path) -> None:
    """End to end through the soft-body authoring functions. The mesher (pytetwild) is in the test
    extra: a missing or broken one fails here rather than skipping."""
    tetmesh._ftetwild()
    src = tmp_path / "sponge.stl"
    trimesh.creation.icosphere(subdivisions=2, radius=0.035).export(src)
    E, nu, rho = 8.0e4, 0.35, 250.0
    (e,) = import_meshes(
        [src], tmp_path / "lib", deformable=True, youngs_modulus=E, poissons_ratio=nu, density=rho
    ).entries
    assert e.kind == "deformable" and e.size_bin == "medium"
    # Tet volume within 5% of the sphere's (the mesher works on a faceted icosphere).
    assert e.volume == pytest.approx(4 / 3 * np.pi * 0.035**3, rel=0.08)
    assert e.mass == pytest.approx(rho * e.volume, rel=1e-9)
    assert e.material["youngs_modulus"] == E and e.material["poissons_ratio"] == nu
    from d3grasp.authoring.validate import validate_library

    report = validate_library(tmp_path / "lib", hand=False)
    assert report.ok, report.failures()
    k_mu = E / (2 * (1 + nu))
    assert report.assets[0].checks["material: k_mu"] and k_mu > 0


@pytest.mark.parametrize("extents", [(0.12, 0.02, 0.004), (0.12, 0.02, 0.001)], ids=["4mm", "1mm"])
def test_import_flat_soft_bar(tmp_path: Path, extents: tuple[float, float, float]) -> None:
    """A flat bar took the mesher down: fTetWild crashed the importing process (segmentation fault,
    or a double free) once its envelope grew past a quarter of the bar's thickness. The envelope is
    bounded by the thickness and the mesher runs in a child process: the bar is meshed."""
    tetmesh._ftetwild_library()
    src = tmp_path / "bar.stl"
    trimesh.creation.box(extents=extents).export(src)
    (e,) = import_meshes(
        [src], tmp_path / "lib", deformable=True, youngs_modulus=3e4, poissons_ratio=0.3, density=150.0
    ).entries
    assert e.kind == "deformable" and 200 <= e.stats["num_tets"] <= 2000
    assert e.volume == pytest.approx(float(np.prod(extents)), rel=0.05)
    assert sorted(e.extents) == pytest.approx(sorted(extents), rel=0.1)


def test_import_on_two_processes_writes_what_one_writes(tmp_path: Path) -> None:
    # Authoring runs one mesh per process (coacd takes minutes on a many-part shape); the files and
    # the manifest must not depend on how many processes wrote them.
    paths = []
    for name, ext in (("brick", (0.07, 0.05, 0.04)), ("bar", (0.11, 0.03, 0.02)), ("cube", (0.05,) * 3)):
        trimesh.creation.box(extents=ext).export(tmp_path / f"{name}.obj")
        paths.append(tmp_path / f"{name}.obj")
    one = import_meshes(paths, tmp_path / "one", workers=1).entries
    two = import_meshes(paths, tmp_path / "two", workers=2).entries
    assert [e.id for e in two] == [e.id for e in one] == ["brick", "bar", "cube"]  # input order kept
    for e in one:
        assert (tmp_path / "two" / e.path).read_bytes() == (tmp_path / "one" / e.path).read_bytes()
    assert (tmp_path / "two" / "manifest.json").read_bytes() == (
        tmp_path / "one" / "manifest.json"
    ).read_bytes()


def test_separate_convex_bodies_become_their_own_hulls() -> None:
    # A shape modelled as overlapping primitives (two crossing bars and a disc): each body's hull is
    # the exact decomposition, with each body's own volume; coacd is not needed (and took minutes).
    from d3grasp.authoring.convex import convex_bodies, convex_decompose

    bar_x = trimesh.creation.box(extents=(0.08, 0.02, 0.02))
    bar_y = trimesh.creation.box(extents=(0.02, 0.06, 0.02))
    disc = trimesh.creation.cylinder(radius=0.015, height=0.01, sections=24)
    disc.apply_translation((0.0, 0.0, 0.015))
    mesh = trimesh.util.concatenate([bar_x, bar_y, disc])
    hulls = convex_decompose(mesh)
    expected = sorted([0.08 * 0.02 * 0.02, 0.02 * 0.06 * 0.02, float(disc.volume)])
    assert sorted(h.volume for h in hulls) == pytest.approx(expected, rel=1e-9)
    # Not this path: one body, a non-convex body among them, or more bodies than hulls allowed.
    assert convex_bodies(bar_x) is None
    torus = trimesh.creation.torus(major_radius=0.03, minor_radius=0.008)
    assert convex_bodies(trimesh.util.concatenate([bar_x, torus])) is None
    assert convex_bodies(mesh, max_bodies=2) is None
