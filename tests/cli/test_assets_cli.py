"""The ``d3grasp-assets`` command: exit codes, one-line errors, tables, no partial output."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh

from d3grasp.authoring.manifest import AssetEntry, read_manifest, write_manifest
from d3grasp.cli.assets import main
from d3grasp.paths import default_manifest


def _run(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str, str]:
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def _error_lines(err: str) -> list[str]:
    """stderr lines that are not progress-bar redraws."""
    return [ln for ln in err.replace("\r", "\n").splitlines() if ln.startswith("error:")]


@pytest.fixture
def library(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> Path:
    """A small imported library: a box (convex) and a ring (coacd)."""
    trimesh.creation.box(extents=[0.08, 0.05, 0.04]).export(tmp_path / "brick.obj")
    trimesh.creation.torus(0.035, 0.01, major_sections=20, minor_sections=8).export(tmp_path / "ring.ply")
    out = tmp_path / "lib"
    code, stdout, err = _run(
        capsys,
        "import",
        "--no-plan-grasps",
        str(tmp_path / "brick.obj"),
        str(tmp_path / "ring.ply"),
        "--out",
        str(out),
        "--density",
        "800",
    )
    assert code == 0, err
    assert "brick: rigid, medium" in stdout and "ring: rigid" in stdout
    return out


def test_import_validate_list(library: Path, capsys: pytest.CaptureFixture[str]) -> None:
    entries = {e.id: e for e in read_manifest(library / "manifest.json")}
    assert set(entries) == {"brick", "ring"}
    assert entries["brick"].mass == pytest.approx(800 * 0.08 * 0.05 * 0.04, rel=1e-6)
    code, out, err = _run(capsys, "validate", str(library))
    assert code == 0, err
    assert "RESULT: PASS" in out and "rigid: mass read-back" in out
    row = next(ln for ln in out.splitlines() if ln.startswith("rigid "))
    assert row.split()[1:5] == ["0", "2", "0", "2"]  # small, medium, large, total
    code, out, _ = _run(capsys, "list", str(library / "manifest.json"))
    assert code == 0 and "rigid / medium" in out and "brick" in out and "ring" in out


def test_validate_malformed_usd_names_file(library: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bad = library / "objects" / "rigid" / "ring.usda"
    bad.write_text('#usda 1.0\n( defaultPrim = "ring" )\ndef Xform "ring" {\n  float mass = [oops\n')
    code, out, err = _run(capsys, "validate", str(library))
    assert code == 1
    assert "RESULT: FAIL" in out
    fails = [ln for ln in err.splitlines() if ln.startswith("FAIL")]
    assert any(str(bad) in ln and "malformed USD" in ln for ln in fails), fails


def test_validate_detects_wrong_mass(library: Path, capsys: pytest.CaptureFixture[str]) -> None:
    entries = read_manifest(library / "manifest.json")
    doctored = [AssetEntry(**{**e.__dict__, "mass": e.mass * 1.1}) if e.id == "brick" else e for e in entries]
    write_manifest(library / "manifest.json", doctored)
    code, out, err = _run(capsys, "validate", str(library))
    assert code == 1
    assert "rigid: mass read-back" in err and "brick" in err


def test_validate_missing_manifest_and_garbage_manifest(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    code, _, err = _run(capsys, "validate", str(tmp_path / "nowhere.json"))
    assert code == 2 and _error_lines(err) == [f"error: {tmp_path / 'nowhere.json'}: manifest not found"]
    (tmp_path / "manifest.json").write_text("{not json")
    code, _, err = _run(capsys, "list", str(tmp_path))
    assert code == 2 and len(_error_lines(err)) == 1 and "not a JSON manifest" in err


def test_plan_grasps_needs_a_library_folder(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """With no folder, plan-grasps would write grasps.json into the installed package (a system-wide
    install is not writable): refused in one line that names the argument to give, nothing written."""
    shipped = default_manifest().parent / "grasps.json"
    before = shipped.stat().st_mtime_ns if shipped.exists() else None
    code, out, err = _run(capsys, "plan-grasps")
    (line,) = _error_lines(err)
    assert code == 2 and out == ""
    assert "d3grasp-assets plan-grasps DIR" in line and "grasps.json" in line
    assert (shipped.stat().st_mtime_ns if shipped.exists() else None) == before
    # A named folder that cannot be written is refused before any trial runs (root writes anywhere,
    # so the permission is what the check reads).
    (tmp_path / "manifest.json").write_text("{}")
    monkeypatch.setattr("d3grasp.cli.assets.os.access", lambda path, mode: False)
    code, out, err = _run(capsys, "plan-grasps", str(tmp_path))
    (line,) = _error_lines(err)
    assert code == 2 and line == (
        f"error: {tmp_path}: not writable, and grasps.json is written there; copy the library to a "
        "folder you can write and plan that copy (d3grasp-assets plan-grasps COPY)"
    )


@pytest.mark.parametrize(
    ("name", "content", "reason"),
    [
        ("empty.stl", b"", "empty file"),
        ("noise.obj", bytes(range(256)) * 10, "unreadable"),
        (
            "nan.obj",
            b"v 0 0 0\nv 0.05 0 0\nv 0 nan 0\nv 0 0 0.05\nf 1 2 3\nf 1 3 4\nf 1 4 2\nf 2 4 3\n",
            "NaN",
        ),
    ],
)
def test_import_bad_file_one_line_error(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], name: str, content: bytes, reason: str
) -> None:
    (tmp_path / name).write_bytes(content)
    out = tmp_path / "lib"
    code, stdout, err = _run(capsys, "import", "--no-plan-grasps", str(tmp_path / name), "--out", str(out))
    lines = _error_lines(err)
    assert code == 2 and len(lines) == 1
    assert lines[0].startswith(f"error: {tmp_path / name}: ") and reason in lines[0]
    assert not out.exists() and stdout == ""


def test_import_absurd_size_and_open_soft(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    trimesh.creation.box(extents=[2.0, 0.5, 0.5]).export(tmp_path / "table.stl")
    code, _, err = _run(
        capsys, "import", "--no-plan-grasps", str(tmp_path / "table.stl"), "--out", str(tmp_path / "lib")
    )
    assert code == 2 and "200 cm" in err and "--scale 0.1" in err
    s = trimesh.creation.icosphere(subdivisions=2, radius=0.03)
    trimesh.Trimesh(s.vertices, s.faces[s.triangles_center[:, 2] > 0]).export(tmp_path / "cap.stl")
    code, _, err = _run(
        capsys,
        "import",
        "--no-plan-grasps",
        str(tmp_path / "cap.stl"),
        "--out",
        str(tmp_path / "lib"),
        "--deformable",
    )
    assert code == 2 and "non-watertight" in err
    assert not (tmp_path / "lib").exists()


def test_import_skip_invalid_writes_the_rest(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    trimesh.creation.box(extents=[0.06, 0.04, 0.03]).export(tmp_path / "brick.stl")
    trimesh.creation.box(extents=[0.5, 0.3, 0.3]).export(tmp_path / "crate.stl")  # 50 cm: too large
    trimesh.creation.icosphere(subdivisions=2, radius=0.03).export(tmp_path / "ball.stl")
    meshes = [str(tmp_path / n) for n in ("brick.stl", "crate.stl", "ball.stl")]
    out = tmp_path / "lib"
    # Default: one mesh out of range imports nothing.
    code, stdout, err = _run(capsys, "import", "--no-plan-grasps", *meshes, "--out", str(out))
    assert code == 2 and len(_error_lines(err)) == 1 and "crate.stl" in err and not out.exists()
    # --skip-invalid: the other two are written, the refused one is listed with its reason, exit 3.
    code, stdout, err = _run(
        capsys, "import", "--no-plan-grasps", *meshes, "--out", str(out), "--skip-invalid"
    )
    skipped = [ln for ln in err.replace("\r", "\n").splitlines() if ln.startswith("skipped ")]
    assert code == 3 and len(skipped) == 1
    assert skipped[0].startswith(f"skipped {tmp_path / 'crate.stl'}: ") and "50 cm" in skipped[0]
    assert {e.id for e in read_manifest(out / "manifest.json")} == {"brick", "ball"}
    assert "2 assets written" in stdout
    # --skip-invalid with nothing valid is still bad input: exit 2, nothing written.
    code, _, err = _run(
        capsys, "import", "--no-plan-grasps", meshes[1], "--out", str(tmp_path / "none"), "--skip-invalid"
    )
    assert code == 2 and "none of the 1 meshes" in err and not (tmp_path / "none").exists()


@pytest.mark.skipif(
    __import__("importlib").util.find_spec("pytetwild") is None, reason="tet meshing needs pytetwild"
)
def test_reimport_says_what_it_replaced(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    trimesh.creation.icosphere(subdivisions=2, radius=0.035).export(tmp_path / "pear.stl")
    out = tmp_path / "lib"
    code, _, err = _run(capsys, "import", "--no-plan-grasps", str(tmp_path / "pear.stl"), "--out", str(out))
    assert code == 0, err
    code, stdout, err = _run(
        capsys, "import", "--no-plan-grasps", str(tmp_path / "pear.stl"), "--out", str(out), "--deformable"
    )
    assert code == 0, err
    assert "replaced the rigid asset pear (objects/rigid/pear.usda, from import:pear.stl)" in stdout
    (entry,) = read_manifest(out / "manifest.json")
    assert entry.kind == "deformable"
    assert not (out / "objects/rigid/pear.usda").exists()  # the old kind's file went with its entry
    assert (out / entry.path).is_file()


def test_import_rejects_soft_options_for_rigid(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    trimesh.creation.box(extents=[0.05] * 3).export(tmp_path / "b.obj")
    code, _, err = _run(
        capsys,
        "import",
        "--no-plan-grasps",
        str(tmp_path / "b.obj"),
        "--out",
        str(tmp_path / "l"),
        "--poisson",
        "0.3",
    )
    assert code == 2 and "--deformable" in err


def test_build_outside_checkout_is_clear(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code, _, err = _run(capsys, "build", "--tools-dir", str(tmp_path))
    assert code == 2 and "not a d3grasp tools/ directory" in err


def test_list_shipped_library(capsys: pytest.CaptureFixture[str]) -> None:
    if not default_manifest().exists():
        pytest.skip("library not built")
    code, out, _ = _run(capsys, "list")
    assert code == 0
    doc = json.loads(default_manifest().read_text())
    assert f"({len(doc['assets'])} assets)" in out
    for b in ("small", "medium", "large"):
        assert f"rigid / {b}" in out


def test_console_script_installed() -> None:
    exe = shutil.which("d3grasp-assets") or str(Path(sys.executable).parent / "d3grasp-assets")
    res = subprocess.run([exe, "--help"], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0
    for cmd in ("build", "import", "validate", "list", "plan-grasps"):
        assert cmd in res.stdout


NEEDS_TETWILD = pytest.mark.skipif(
    __import__("importlib").util.find_spec("pytetwild") is None, reason="tet meshing needs pytetwild"
)
FLAT_BAR = (0.15, 0.045, 0.02)  # the 15 x 4.5 x 2 cm bar that took fTetWild (and the import) down


@NEEDS_TETWILD
def test_a_flat_bar_meshes_on_every_run() -> None:
    """fTetWild crashed on this bar in 5 of 6 runs (issue 45): it meshes on each of three, to its volume."""
    from d3grasp.authoring.tetmesh import tetrahedralize

    bar = trimesh.creation.box(extents=FLAT_BAR)
    for _ in range(3):
        points, tets = tetrahedralize(bar, 400)
        v = points[tets]
        volume = np.abs(
            np.einsum("ij,ij->i", v[:, 1] - v[:, 0], np.cross(v[:, 2] - v[:, 0], v[:, 3] - v[:, 0]))
        )
        assert float(volume.sum()) / 6.0 == pytest.approx(float(np.prod(FLAT_BAR)), rel=0.05)


@NEEDS_TETWILD
def test_a_soft_batch_with_the_flat_bar_imports_every_mesh(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The bar among other meshes, in worker processes: every mesh is written as a soft body."""
    trimesh.creation.box(extents=FLAT_BAR).export(tmp_path / "bar.stl")
    trimesh.creation.box(extents=[0.06, 0.05, 0.04]).export(tmp_path / "sponge.stl")
    trimesh.creation.icosphere(subdivisions=2, radius=0.03).export(tmp_path / "ball.stl")
    meshes = [str(tmp_path / n) for n in ("bar.stl", "sponge.stl", "ball.stl")]
    out = tmp_path / "lib"
    code, stdout, err = _run(
        capsys, "import", "--no-plan-grasps", "--deformable", *meshes, "--out", str(out), "--workers", "2"
    )
    assert code == 0, err
    entries = {e.id: e for e in read_manifest(out / "manifest.json")}
    assert set(entries) == {"bar", "sponge", "ball"} and all(e.kind == "deformable" for e in entries.values())
    assert entries["bar"].volume == pytest.approx(float(np.prod(FLAT_BAR)), rel=0.05)


@NEEDS_TETWILD
def test_a_mesher_that_always_crashes_is_a_one_line_error(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """fTetWild dying on one mesh at every setting: the import says which file and why in one line
    (exit 2, nothing written), or with --skip-invalid skips it and writes the others (exit 3)."""
    from d3grasp.authoring import tetmesh

    real = tetmesh._run_ftetwild

    def crash_on_the_bar(vertices: np.ndarray, *args: float) -> tuple[np.ndarray, np.ndarray]:
        if np.ptp(vertices, axis=0).max() > 0.14:  # the bar, 15 cm long; the ball is 6 cm
            raise tetmesh.MesherCrash("fTetWild crashed (signal SIGSEGV)")
        return real(vertices, *args)

    monkeypatch.setattr(tetmesh, "_run_ftetwild", crash_on_the_bar)
    trimesh.creation.box(extents=FLAT_BAR).export(tmp_path / "bar.stl")
    trimesh.creation.icosphere(subdivisions=2, radius=0.03).export(tmp_path / "ball.stl")
    meshes = [str(tmp_path / "bar.stl"), str(tmp_path / "ball.stl")]
    out = tmp_path / "lib"
    argv = ["import", "--no-plan-grasps", "--deformable", *meshes, "--out", str(out), "--workers", "1"]
    code, _, err = _run(capsys, *argv)
    lines = _error_lines(err)
    assert code == 2 and len(lines) == 1 and not out.exists()
    assert lines[0].startswith(f"error: {tmp_path / 'bar.stl'}: ") and "crashed" in lines[0]
    code, stdout, err = _run(capsys, *argv, "--skip-invalid")
    skipped = [ln for ln in err.replace("\r", "\n").splitlines() if ln.startswith("skipped ")]
    assert code == 3 and len(skipped) == 1 and skipped[0].startswith(f"skipped {tmp_path / 'bar.stl'}: ")
    assert [e.id for e in read_manifest(out / "manifest.json")] == ["ball"]
