"""The planner's ranking with scripted trial records (no simulation): which finalists go on, which
grasp is kept, how many trials it has, under which conditions they ran, and its rate, interval and
score, checked against counts worked out by hand."""

from __future__ import annotations

import json
import math
from dataclasses import replace
from typing import Any

import pytest

from d3grasp.planner import rounds as rounds_mod
from d3grasp.planner.candidates import perturbed
from d3grasp.planner.plan import PlannerConfig, config_of_record, evaluation_planner
from d3grasp.planner.rounds import PERTURBATIONS, candidates_of, plan_unit
from d3grasp.planner.score import Trial

ENTRY = {"id": "cube", "kind": "rigid", "extents": [0.06, 0.06, 0.06], "pieces": []}


def _key(trial: Trial) -> str:
    return json.dumps(trial.grasp.to_json(), sort_keys=True)


def _record(lift: bool, hold: bool, motion: float | None = None) -> dict[str, Any]:
    """A trial's record; by default a held object stayed put and a lost one moved past the 2 cm."""
    motion = (0.0 if hold else 0.03) if motion is None else motion
    return {"s_lift": lift, "s_disturb": lift and hold, "max_push_motion": motion, "max_rise": 0.1 * lift}


def _scripted(cfg: PlannerConfig, outcome: Any, calls: list[tuple[int, float, list[Trial]]]) -> Any:
    """A ``run_trials`` whose record of a trial is ``outcome(candidate index, trial, stream, n)``,
    ``n`` counting that candidate's trials in the stream; ``calls`` logs (stream, push, trials)."""
    cands = candidates_of(ENTRY, cfg)
    index = {json.dumps(g.to_json(), sort_keys=True): k for k, g in enumerate(cands)}
    for k, g in enumerate(cands):  # the legacy schedule's displaced retries of each candidate
        for dx, dy, dyaw in PERTURBATIONS:
            index[json.dumps(perturbed(g, (dx, dy), dyaw).to_json(), sort_keys=True)] = k

    def run(trials: list[Trial], manifest: Any, scoring: Any, on_batch: Any = None, stream: int = 0) -> list:
        calls.append((stream, scoring.push_seconds, list(trials)))
        seen: dict[int, int] = {}
        out = []
        for t in trials:
            k = index[_key(t)]
            seen[k] = seen.get(k, -1) + 1
            out.append(outcome(k, t, stream, seen[k]))
        return out

    return run


def test_evaluation_schedule_keeps_the_grasp_that_holds_most(monkeypatch: pytest.MonkeyPatch) -> None:
    cfg = evaluation_planner(candidates=replace(PlannerConfig().candidates, per_type=3, types=("top",)))
    assert [c.grasp for c in candidates_of(ENTRY, cfg)] == ["top"] * 3

    # Candidate 0 lifts in round 1 but never holds afterwards; 1 does not lift in round 1 (out);
    # 2 lifts and holds round 1 and 2 of its 3 screening trials, then 9 of its 12 final ones, the
    # last three lost.
    def outcome(k: int, t: Trial, stream: int, n: int) -> dict[str, Any]:
        if stream == 0:
            return _record(lift=k != 1, hold=True)
        if k == 0:
            return _record(lift=True, hold=False, motion=0.03)
        if stream == 1:
            return _record(lift=True, hold=n < 2, motion=0.004)
        return _record(lift=True, hold=n < 9, motion=0.004 if n < 9 else 0.03)  # lost: moved > 2 cm

    calls: list[tuple[int, float, list[Trial]]] = []
    monkeypatch.setattr(rounds_mod, "run_trials", _scripted(cfg, outcome, calls))
    out = plan_unit("unused.json", [ENTRY], cfg)["cube"]

    streams = [(s, push, len(ts)) for s, push, ts in calls]
    # Round 1: 3 candidates; round 2: the 2 that lifted x 3; round 3: the kept one x 12 at 2 s.
    assert streams == [(0, 0.3, 3), (1, 0.3, 6), (2, 2.0, 12)]
    assert all(t.perception == "oracle" for t in calls[0][2])
    assert [t.perception for t in calls[1][2][:3]] == ["camera", "oracle", "camera"]
    final = calls[2][2]
    assert (
        sum(t.perception == "camera" for t in final) == 6
        and sum(t.perception == "oracle" for t in final) == 6
    )
    kept = out["grasps"]["top"]
    candidates = candidates_of(ENTRY, cfg)
    assert {k: v for k, v in kept.items() if k in candidates[2].to_json()} == candidates[2].to_json()
    # Its trials: 1 + 3 + 12 = 16; held: 1 (round 1) + 2 (round 2) + 9 (round 3) = 12.
    assert kept["trials"]["of"] == 16 and kept["trials"]["lift"] == 16 and kept["trials"]["disturb"] == 12
    # The rate is the final round's alone: 9 of 12, with its Wilson interval worked out by hand.
    z = 1.959963984540054
    p, n = 9 / 12, 12
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    assert kept["rate"] == pytest.approx(0.75)
    assert kept["rate_interval"] == pytest.approx([centre - half, centre + half], abs=1e-4)
    # Score: the lower bound plus a hundredth of the final trials' mean trial score
    # (9 held at 2 + 0.5 * (1 - 0.004 / 0.02) = 2.4, 3 lifted and lost, moved past 2 cm, at 1).
    firmness = (9 * 2.4 + 3 * 1.0) / 12
    assert kept["score"] == pytest.approx(centre - half + 0.01 * firmness, abs=1e-4)
    by_view = kept["trials"]["final"]
    assert by_view["push_seconds"] == 2.0
    assert by_view["camera"]["of"] == by_view["oracle"]["of"] == 6
    assert by_view["camera"]["disturb"] + by_view["oracle"]["disturb"] == 9
    assert out["candidates"] == 3 and out["lifted_nominal"] == 2


def test_a_type_whose_candidates_never_lift_keeps_its_best_attempt_at_score_zero(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    cfg = evaluation_planner(candidates=replace(PlannerConfig().candidates, per_type=2, types=("pinch",)))
    calls: list[tuple[int, float, list[Trial]]] = []
    monkeypatch.setattr(
        rounds_mod, "run_trials", _scripted(cfg, lambda k, t, s, n: _record(False, False), calls)
    )
    out = plan_unit("unused.json", [ENTRY], cfg)["cube"]
    assert [s for s, _, _ in calls] == [0]  # nothing lifted: no further round
    assert out["grasps"]["pinch"]["score"] == 0.0 and out["grasps"]["pinch"]["trials"]["of"] == 1


def test_legacy_schedule_ranks_finalists_by_the_mean_of_three(monkeypatch: pytest.MonkeyPatch) -> None:
    cfg = PlannerConfig(candidates=replace(PlannerConfig().candidates, per_type=3, types=("side",)))

    # Round 1: candidate 0 held (2.5), 2 lifted only (1.0), 1 dropped. Displaced: 0 drops both times
    # (mean 2.5 / 3), 2 holds both (mean (1 + 2.5 + 2.5) / 3 = 2): 2 is kept.
    def outcome(k: int, t: Trial, stream: int, n: int) -> dict[str, Any]:
        if k == 1:
            return _record(False, False)
        first = not getattr(outcome, "done", set()) >= {k}
        outcome.done = getattr(outcome, "done", set()) | {k}  # type: ignore[attr-defined]
        if first:
            return _record(True, k == 0)
        return _record(k == 2, k == 2)

    calls: list[tuple[int, float, list[Trial]]] = []
    monkeypatch.setattr(rounds_mod, "run_trials", _scripted(cfg, outcome, calls))
    kept = plan_unit("unused.json", [ENTRY], cfg)["cube"]["grasps"]["side"]
    assert [len(ts) for _, _, ts in calls] == [3, 4]  # the two finalists x the two displacements
    assert kept["trials"] == {"lift": 3, "disturb": 2, "of": 3}
    assert kept["score"] == pytest.approx(2.0)
    assert "rate" not in kept


def test_schedules_round_trip_through_the_grasp_file_record() -> None:
    legacy = PlannerConfig()
    assert "schedule" not in legacy.record() and "randomise" not in legacy.record()["scoring"]
    assert config_of_record(legacy.record()) == replace(legacy, objects_per_unit=4)
    ev = evaluation_planner(seed=3, final_trials=8)
    back = config_of_record(ev.record())
    assert back is not None and back.schedule == "evaluation" and back.final_trials == 8
    assert back.scoring.randomise and back.perceptions == ("camera", "oracle")
    with pytest.raises(ValueError, match="schedule"):
        PlannerConfig(schedule="other")
    with pytest.raises(ValueError, match="randomise"):
        PlannerConfig(schedule="evaluation")


def test_the_shipped_plan_records_the_schedules_it_was_made_with() -> None:
    """The shipped grasp file: its rigid objects planned under the evaluation schedule (the
    command line's default, seed 0), its soft objects kept from the legacy plan, each recording
    the legacy planner's settings, which the default ``PlannerConfig`` still writes as before the
    schedules existed."""
    from d3grasp.authoring.manifest import read_manifest
    from d3grasp.envs.grasp_file import grasp_file_path, read_grasp_file
    from d3grasp.paths import default_manifest

    data = read_grasp_file(grasp_file_path(default_manifest()))
    assert data["planner"] == evaluation_planner(seed=0).record()
    kinds = {e.id: e.kind for e in read_manifest(default_manifest())}
    own = {oid: rec.get("planner") for oid, rec in data["objects"].items()}
    assert {oid for oid, p in own.items() if p is not None} == {
        i for i, k in kinds.items() if k == "deformable"
    }
    assert all(p == PlannerConfig().record() for p in own.values() if p is not None)
