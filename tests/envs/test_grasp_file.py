"""The grasp file: stored grasps read back, stale entries left out, broken files refused in one line,
and an environment placing the stored grasp with the object's pose."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest

from d3grasp.authoring.manifest import read_manifest
from d3grasp.envs.config import BaselineConfig, SimConfig
from d3grasp.envs.grasp_file import (
    GraspFileError,
    StoredGrasps,
    asset_sha256,
    changed_settings,
    environment_record,
    grasp_file_path,
    load_grasp_plan,
    without_prior,
)
from d3grasp.envs.grasps import object_grasp, rest_height
from d3grasp.paths import default_manifest

BOX = "box_01"


def _library(tmp_path: Path) -> Path:
    """A one-object library: the shipped box's USD file and its manifest entry."""
    entry = next(e for e in read_manifest(default_manifest()) if e.id == BOX)
    src = default_manifest().parent / entry.path
    (tmp_path / Path(entry.path).parent).mkdir(parents=True)
    shutil.copy(src, tmp_path / entry.path)
    manifest = json.loads(default_manifest().read_text())
    manifest["assets"] = [a for a in manifest["assets"] if a["id"] == BOX]
    (tmp_path / "manifest.json").write_text(json.dumps(manifest))
    return tmp_path / "manifest.json"


def _write_grasps(manifest: Path, scores: dict[str, float]) -> dict:
    entry = read_manifest(manifest)[0]
    ex = np.asarray(entry.extents)
    grasps = {
        g: {**object_grasp(g, ex, rest_height(ex)).to_json(), "score": s, "trials": {}}
        for g, s in scores.items()
    }
    data = {
        "format": "d3grasp-grasps",
        "version": 1,
        "planner": {},
        "objects": {BOX: {"asset_sha256": asset_sha256(manifest.parent / entry.path), "grasps": grasps}},
    }
    grasp_file_path(manifest).write_text(json.dumps(data))
    return data


def test_stored_grasps_load_and_the_best_type_is_chosen(tmp_path: Path) -> None:
    manifest = _library(tmp_path)
    assert load_grasp_plan(manifest) is None  # no grasp file: the rule decides
    _write_grasps(manifest, {"top": 1.2, "pinch": 2.4})
    plan = load_grasp_plan(manifest)
    assert plan is not None and set(plan) == {BOX}
    assert plan[BOX].best(("top", "side", "pinch")) == "pinch"
    assert plan[BOX].best(("top", "side")) == "top"
    assert plan[BOX].best(("side",)) is None


def test_a_changed_asset_file_is_not_used(tmp_path: Path) -> None:
    manifest = _library(tmp_path)
    _write_grasps(manifest, {"top": 1.0})
    usd = manifest.parent / read_manifest(manifest)[0].path
    usd.write_text(usd.read_text() + "\n")  # the asset changed after it was planned
    assert load_grasp_plan(manifest) == {}


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("{not json", "not a readable grasp file"),
        ('{"format": "other"}', "not a grasp file"),
        ('{"format": "d3grasp-grasps", "version": 9, "objects": {}}', "version 9"),
    ],
)
def test_broken_grasp_files_are_refused_in_one_line(tmp_path: Path, text: str, message: str) -> None:
    manifest = _library(tmp_path)
    grasp_file_path(manifest).write_text(text)
    with pytest.raises(GraspFileError, match=message) as info:
        load_grasp_plan(manifest)
    assert "\n" not in str(info.value) and "grasps.json" in str(info.value)


def test_camera_yaw_is_aligned_with_the_object_frame() -> None:
    stored = StoredGrasps({}, {}, np.array([0.04, 0.09, 0.05]))
    # The camera's rectangle named the long side first: a quarter turn brings it to the object frame.
    yaw = stored.align_yaw(1.0, np.array([0.091, 0.041, 0.05]))
    assert math.cos(yaw - (1.0 + 0.5 * math.pi)) == pytest.approx(1.0) or math.cos(
        yaw - (1.0 - 0.5 * math.pi)
    ) == pytest.approx(1.0)
    assert abs(yaw) <= 0.5 * math.pi + 1e-9
    assert stored.align_yaw(0.2, np.array([0.041, 0.089, 0.05])) == pytest.approx(0.2)


def test_the_environment_places_the_stored_grasp(tmp_path: Path) -> None:
    from scipy.spatial.transform import Rotation

    from d3grasp.envs import make_env

    manifest = _library(tmp_path)
    entry = read_manifest(manifest)[0]
    ex = np.asarray(entry.extents)
    stored = object_grasp("top", ex, rest_height(ex), near_face_x=0.12, lateral_y=-0.03, top_z=0.04)
    data = _write_grasps(manifest, {"top": 2.0, "side": 1.0})
    data["objects"][BOX]["grasps"]["top"] |= stored.to_json()
    grasp_file_path(manifest).write_text(json.dumps(data))
    env = make_env(num_envs=1, objects={"manifest": str(manifest), "ids": (BOX,)}, eval_mode=True)
    try:
        assert env.grasp.type_id.tolist() == [0]  # top: the higher score
        obj = env.draw.object_start[0].double().numpy()
        r = Rotation.from_quat(env.grasp.palm_quat[0].double().numpy()).as_matrix()
        local = r.T @ (obj - env.grasp.palm_pos[0].double().numpy())  # object centre in the palm frame
        along = min(ex[0], ex[1])
        np.testing.assert_allclose(local, [0.12 + 0.5 * along, -0.03, 0.04 + 0.5 * ex[2]], atol=1e-5)
        # grasp_source="rule" ignores the file.
        env2 = make_env(num_envs=1, objects={"manifest": str(manifest), "ids": (BOX,)}, grasp_source="rule")
        assert env2.planning.plan is None
        env2.close()
    finally:
        env.close()


def test_changed_settings_name_what_differs() -> None:
    current = {"sim": {"iterations": 5, "soft_iterations": 20}, "rule": {"squeeze": 0.1}}
    assert changed_settings(None, current) == []  # planned before the file recorded settings
    assert changed_settings(current, current) == []
    old = {"sim": {"iterations": 5, "soft_iterations": 5}, "rule": {}}  # a rule setting not yet recorded
    assert changed_settings(old, current) == ["sim.soft_iterations 5 -> 20"]
    rec = environment_record(SimConfig(), BaselineConfig())
    assert rec["sim"]["substeps"] == SimConfig().substeps and "squeeze_deformable" in rec["rule"]
    # The record is the environment's own rule, not the default one: the Base task's trials run the
    # stall rule, and grasps planned under it would be replanned under the touch rule.
    from d3grasp.planner.score import ScoringConfig, trial_environment

    assert trial_environment(ScoringConfig())["rule"]["stop_on"] == "touch"
    base = trial_environment(ScoringConfig(task="D3Grasp-DexHand13-Base-v0"))
    assert base["rule"]["stop_on"] == "stall"
    assert changed_settings(base, rec) == ["rule.stop_on stall -> touch"]
    # An environment on the stall prior uses grasps planned under the touch rule without a warning:
    # the prior is the Base task's choice, the grasps are every task's.
    assert changed_settings(rec, without_prior(base)) == []
    base["rule"]["squeeze"] = 0.25
    assert changed_settings(rec, without_prior(base)) == ["rule.squeeze 0.1 -> 0.25"]


def test_grasps_planned_under_other_settings_are_used_with_a_warning(tmp_path: Path) -> None:
    from d3grasp.envs import make_env

    manifest = _library(tmp_path)
    data = _write_grasps(manifest, {"top": 2.0})
    planned = environment_record(SimConfig(), BaselineConfig())
    planned["sim"]["iterations"] += 3
    data["objects"][BOX]["environment"] = planned
    grasp_file_path(manifest).write_text(json.dumps(data))
    with pytest.warns(UserWarning, match=r"box_01\).*sim\.iterations 8 -> 5.*plan-grasps"):
        env = make_env(num_envs=1, objects={"manifest": str(manifest), "ids": (BOX,)}, eval_mode=True)
    try:
        assert env.planning.plan[BOX].environment == planned  # still used: the warning says why to replan
    finally:
        env.close()


def test_the_shipped_library_has_a_current_plan_for_every_object() -> None:
    """grasps.json was planned on the committed asset files, rigid and soft: a changed asset must be
    replanned (``d3grasp-assets plan-grasps``), not silently left to the rule."""
    plan = load_grasp_plan(default_manifest())
    assert plan is not None
    ids = [e.id for e in read_manifest(default_manifest())]
    assert sorted(set(ids) - set(plan)) == []
    # Objects whose plan records its settings (the soft ones since 2026-12-04) were planned under
    # today's: a change of SimConfig or BaselineConfig needs them replanned.
    current = environment_record(SimConfig(), BaselineConfig())
    stale = {i: changed_settings(s.environment, current) for i, s in plan.items()}
    assert {i: c for i, c in stale.items() if c} == {}
