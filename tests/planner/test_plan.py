"""The planner end to end on a one-object library: candidates scored in simulation, the grasp file
written, a rerun resumes instead of replanning, and the stored grasp is one that lifted."""

from __future__ import annotations

import json
import shutil
from dataclasses import asdict, replace
from pathlib import Path

import pytest

from d3grasp.authoring.manifest import read_manifest
from d3grasp.envs.baseline import BaselineConfig
from d3grasp.envs.config import SimConfig
from d3grasp.envs.grasp_file import grasp_file_path, load_grasp_plan, read_grasp_file
from d3grasp.paths import default_manifest
from d3grasp.planner.plan import (
    PlannerConfig,
    _differing,
    adopt_plans,
    config_of_record,
    evaluation_planner,
    plan_grasps,
    same_trials,
)
from d3grasp.planner.score import trial_score

BOX = "box_01"  # 9.5 x 3.4 x 6.6 cm, 138 g: the top hook and the side wrap both lift it (measured)


def _library(tmp_path: Path) -> Path:
    entry = next(e for e in read_manifest(default_manifest()) if e.id == BOX)
    (tmp_path / Path(entry.path).parent).mkdir(parents=True)
    shutil.copy(default_manifest().parent / entry.path, tmp_path / entry.path)
    manifest = json.loads(default_manifest().read_text())
    manifest["assets"] = [a for a in manifest["assets"] if a["id"] == BOX]
    (tmp_path / "manifest.json").write_text(json.dumps(manifest))
    return tmp_path / "manifest.json"


def test_trial_score_orders_outcomes() -> None:
    dropped = {"s_lift": False, "s_disturb": False, "max_push_motion": 0.0}
    lifted = {"s_lift": True, "s_disturb": False, "max_push_motion": 0.05}
    held_loose = {"s_lift": True, "s_disturb": True, "max_push_motion": 0.015}
    held_firm = {"s_lift": True, "s_disturb": True, "max_push_motion": 0.001}
    scores = [trial_score(r) for r in (dropped, lifted, held_loose, held_firm)]
    assert scores == sorted(scores) and scores[0] == 0.0 and scores[1] == 1.0
    assert scores[3] == 2.0 + 0.5 * (1 - 0.001 / 0.02)


def test_plan_a_box_in_simulation_and_resume(tmp_path: Path) -> None:
    manifest = _library(tmp_path)
    cfg = PlannerConfig()
    cfg = replace(cfg, candidates=replace(cfg.candidates, per_type=1))  # the three rule placements
    logs: list[str] = []
    path = plan_grasps(manifest, cfg=cfg, progress=False, log=logs.append)
    assert path == grasp_file_path(manifest)
    data = read_grasp_file(path)
    rec = data["objects"][BOX]
    assert rec["candidates"] == 3 and rec["lifted_nominal"] >= 1
    # The settings the trials ran under: the task's simulation settings and the rule's.
    assert rec["environment"]["sim"] == json.loads(json.dumps(asdict(SimConfig())))
    assert rec["environment"]["rule"] == json.loads(json.dumps(asdict(BaselineConfig())))
    lifted = {g: v for g, v in rec["grasps"].items() if v["trials"]["lift"] >= 1}
    assert lifted, rec  # a grasp validated in simulation: it lifted the box
    for v in lifted.values():
        assert v["trials"]["of"] == 3  # the nominal trial and the two displaced ones
        assert 1.0 <= v["score"] <= 2.5
    plan = load_grasp_plan(manifest)
    assert plan is not None and plan[BOX].best(("top", "side", "pinch")) in lifted
    # A rerun with the same settings finds the object planned and runs nothing.
    before = path.read_bytes()
    plan_grasps(manifest, cfg=cfg, progress=False, log=logs.append)
    assert path.read_bytes() == before
    assert any("planned already" in line for line in logs)
    # A plan of other settings keeps the groups whose trials those settings ran as these would: the
    # box is one convex piece, so a planner without the pieces' candidates planned it the same way.
    data = json.loads(before)
    del data["planner"]["candidates"]["max_pieces"]
    path.write_text(json.dumps(data))
    plan_grasps(manifest, cfg=cfg, progress=False, log=logs.append)
    assert json.loads(path.read_bytes())["objects"] == json.loads(before)["objects"]
    assert any("kept from the plan of other settings" in line for line in logs)
    # A plan measured under other simulation settings is planned again, under these.
    data = json.loads(before)
    data["objects"][BOX]["environment"]["sim"]["substeps"] = 4
    path.write_text(json.dumps(data))
    logs.clear()
    plan_grasps(manifest, cfg=cfg, progress=False, log=logs.append)
    assert not any("planned already" in line for line in logs)
    assert json.loads(path.read_bytes())["objects"][BOX]["environment"] == rec["environment"]


def test_a_composite_is_replanned_when_its_candidates_change() -> None:
    cfg = PlannerConfig()
    before = config_of_record(cfg.record() | {"candidates": {**cfg.record()["candidates"], "max_pieces": 0}})
    assert before is not None and before.candidates.max_pieces == 0
    bar = ([0.0, -0.03, 0.0], [0.08, 0.02, 0.02])
    post = ([0.03, 0.01, 0.0], [0.02, 0.06, 0.02])
    ell = {"id": "ell", "kind": "rigid", "extents": [0.08, 0.08, 0.02], "pieces": [bar, post]}
    lone = {**ell, "pieces": [bar]}
    assert not same_trials(before, cfg, [ell])
    assert same_trials(before, cfg, [lone])
    assert config_of_record({"seed": 0}) is None  # not a record this planner can read back


def test_planning_some_objects_under_new_settings_refuses_to_drop_the_others(tmp_path: Path) -> None:
    # A library of two objects whose grasp file was planned with seed 1: replanning one of them with
    # seed 0 would write a file of seed 0 holding that one only.
    ids = [BOX, "box_02"]
    manifest = json.loads(default_manifest().read_text())
    manifest["assets"] = [a for a in manifest["assets"] if a["id"] in ids]
    path = tmp_path / "manifest.json"
    path.write_text(json.dumps(manifest))
    shipped = read_grasp_file(grasp_file_path(default_manifest()))
    old = {**shipped, "planner": PlannerConfig(seed=1).record()}
    old["objects"] = {i: shipped["objects"][i] for i in ids}
    grasps = grasp_file_path(path)
    grasps.write_text(json.dumps(old))
    before = grasps.read_bytes()
    with pytest.raises(ValueError, match=r"\(seed\).*the 1 others \(box_02\)"):
        plan_grasps(path, [BOX], PlannerConfig(seed=0), progress=False)
    assert grasps.read_bytes() == before  # refused before anything ran or was written


def test_differing_names_the_changed_settings() -> None:
    old = {"seed": 1, "candidates": {"per_type": 10, "types": ["top"]}, "finalists": 2}
    new = {"seed": 1, "candidates": {"per_type": 5, "types": ["top"]}, "finalists": 2, "extra": 0}
    assert _differing(old, new) == ["candidates.per_type", "extra"]
    assert _differing(None, new) == ["the planner record"]
    assert _differing(new, new) == []


def test_adopted_plans_keep_their_settings_and_are_replanned_under_the_files(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # A library of two objects planned with seed 1; box_02's plan taken from a file of seed 0.
    ids = [BOX, "box_02"]
    manifest = json.loads(default_manifest().read_text())
    manifest["assets"] = [a for a in manifest["assets"] if a["id"] in ids]
    path = tmp_path / "manifest.json"
    path.write_text(json.dumps(manifest))
    for a in manifest["assets"]:
        (tmp_path / a["path"]).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(default_manifest().parent / a["path"], tmp_path / a["path"])
    shipped = read_grasp_file(grasp_file_path(default_manifest()))
    mine = {**shipped, "planner": evaluation_planner(seed=1).record()}
    mine["objects"] = {i: shipped["objects"][i] for i in ids}
    grasps = grasp_file_path(path)
    grasps.write_text(json.dumps(mine))
    other = tmp_path / "other.json"
    other.write_text(json.dumps({**shipped, "planner": PlannerConfig(seed=0).record()}))
    adopt_plans(path, other, ["box_02"])
    data = read_grasp_file(grasps)
    assert data["planner"] == evaluation_planner(seed=1).record()
    assert data["objects"]["box_02"]["planner"] == PlannerConfig(seed=0).record()
    assert "planner" not in data["objects"][BOX]
    assert load_grasp_plan(path) is not None and set(load_grasp_plan(path) or {}) == set(ids)
    # Planning the library under the file's settings runs box_02 only (its record is of seed 0;
    # the evaluation schedule plans each object in a group of its own).
    asked: list[str] = []
    monkeypatch.setattr(
        "d3grasp.planner.plan.run_units",
        lambda fn, args, workers, done: asked.extend(e["id"] for _, unit, _ in args for e in unit),
    )
    plan_grasps(path, None, evaluation_planner(seed=1), progress=False, log=lambda _: None)
    assert asked == ["box_02"]
    # A plan measured on another asset file is refused, nothing written.
    before = grasps.read_bytes()
    other.write_text(
        json.dumps({**shipped, "objects": {"box_02": {**shipped["objects"]["box_02"], "asset_sha256": "0"}}})
    )
    with pytest.raises(ValueError, match="another asset file"):
        adopt_plans(path, other, ["box_02"])
    assert grasps.read_bytes() == before
