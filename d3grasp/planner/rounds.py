"""The rounds that score one unit of objects' candidates (d3grasp.planner.plan's module docstring
says what each schedule does): round 1, every candidate once; then the legacy schedule's displaced
finalists or the evaluation schedule's successive halving; the unit's grasp records."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace
from typing import TYPE_CHECKING, Any

import numpy as np

from d3grasp.planner.candidates import candidates, perturbed
from d3grasp.planner.score import Trial, run_trials, trial_environment, trial_score

if TYPE_CHECKING:
    from d3grasp.planner.plan import PlannerConfig

# Object displaced by (dx, dy) m and turned by dyaw rad from where the planner thinks it is: the
# camera's localisation error class (5.6 mm mean, 11 mm p95 with noise; docs/evaluation.md, Perception).
PERTURBATIONS: tuple[tuple[float, float, float], ...] = ((0.004, -0.003, 0.08), (-0.004, 0.003, -0.08))


def candidates_of(row: dict[str, Any], cfg: PlannerConfig) -> list[Any]:
    """The candidates of a unit's object row (id, kind, extents, pieces) under ``cfg``."""
    pieces = [(np.asarray(c), np.asarray(x)) for c, x in row.get("pieces", ())]
    soft = row["kind"] == "deformable"
    hull = (np.asarray(row["hull"][0]), np.asarray(row["hull"][1])) if row.get("hull") else None
    return candidates(row["id"], np.asarray(row["extents"]), cfg.seed, cfg.candidates, soft, pieces, hull)


ByType = dict[tuple[str, str], list[tuple[float, Trial, dict[str, Any]]]]
"""Round 1's trials by (object, grasp type), in candidate order: (score, trial, record)."""


def _finalists(entries: Sequence[dict[str, Any]], cfg: PlannerConfig, by_type: ByType) -> list[Any]:
    """The best ``cfg.finalists`` of each object and type by round 1's score, those that lifted."""
    finalists: list[tuple[float, Trial, dict[str, Any]]] = []
    for e in entries:
        for grasp_type in cfg.candidates.types:
            mine = sorted(by_type.get((e["id"], grasp_type), []), key=lambda x: -x[0])
            finalists += [x for x in mine[: cfg.finalists] if x[2]["s_lift"]]
    return finalists


def plan_unit(
    manifest: str, entries: Sequence[dict[str, Any]], cfg: PlannerConfig
) -> dict[str, dict[str, Any]]:
    """Plan a group of objects (``entries``: id, kind, extents); the grasp file records by id."""
    trials: list[Trial] = []
    for e in entries:
        trials += [Trial(e["id"], g) for g in candidates_of(e, cfg)]
    records = run_trials(trials, manifest, cfg.scoring)
    by_type: ByType = {}
    for t, r in zip(trials, records, strict=True):
        by_type.setdefault((t.object_id, t.grasp.grasp), []).append((trial_score(r), t, r))
    if cfg.schedule == "evaluation":
        out = _halving_rounds(manifest, entries, cfg, by_type)
    else:
        out = _legacy_rounds(manifest, entries, cfg, by_type)
    _describe_unit(out, entries, cfg, by_type)
    return out


def _halving_rounds(
    manifest: str, entries: Sequence[dict[str, Any]], cfg: PlannerConfig, by_type: ByType
) -> dict[str, dict[str, Any]]:
    """Rounds 2 and 3 of the evaluation schedule (module docstring): the kept grasp of each type."""
    from d3grasp.eval.metrics import wilson_interval

    views = cfg.perceptions
    finalists = _finalists(entries, cfg, by_type)
    screen = [
        Trial(t.object_id, t.grasp, views[k % len(views)])
        for _, t, _ in finalists
        for k in range(cfg.screen_trials)
    ]
    screened = run_trials(screen, manifest, cfg.scoring, stream=1) if screen else []
    # Each finalist's trials so far; the best of each object and type by its mean trial score.
    best: dict[tuple[str, str], tuple[float, Trial, list[dict[str, Any]]]] = {}
    n = cfg.screen_trials
    for k, (_, t, r0) in enumerate(finalists):
        rs = [r0, *screened[k * n : (k + 1) * n]]
        mean = float(np.mean([trial_score(r) for r in rs]))
        key = (t.object_id, t.grasp.grasp)
        if key not in best or mean > best[key][0]:
            best[key] = (mean, t, rs)
    kept = list(best.values())
    final = [
        Trial(t.object_id, t.grasp, views[k % len(views)])
        for _, t, _ in kept
        for k in range(cfg.final_trials)
    ]
    full = replace(cfg.scoring, push_seconds=cfg.final_push_seconds)
    finals = run_trials(final, manifest, full, stream=2) if final else []
    out: dict[str, dict[str, Any]] = {e["id"]: {"grasps": {}} for e in entries}
    m = cfg.final_trials
    for k, (_, t, rs) in enumerate(kept):
        mine = finals[k * m : (k + 1) * m]
        mine_views = final[k * m : (k + 1) * m]
        held = sum(int(r["s_disturb"]) for r in mine)
        lo, hi = wilson_interval(held, m)
        firmness = float(np.mean([trial_score(r) for r in mine]))
        by_view = {
            view: _counts([r for r, f in zip(mine, mine_views, strict=True) if f.perception == view])
            for view in views
        }
        out[t.object_id]["grasps"][t.grasp.grasp] = {
            **t.grasp.to_json(),
            "score": round(lo + 0.01 * firmness, 4),
            "rate": round(held / m, 4),
            "rate_interval": [round(lo, 4), round(hi, 4)],
            "trials": {**_counts([*rs, *mine]), "final": {"push_seconds": cfg.final_push_seconds, **by_view}},
        }
    return out


def _counts(records: Sequence[dict[str, Any]]) -> dict[str, int]:
    """Lifts and holds of some trials' records, and how many there were."""
    return {
        "lift": sum(int(r["s_lift"]) for r in records),
        "disturb": sum(int(r["s_disturb"]) for r in records),
        "of": len(records),
    }


def _legacy_rounds(
    manifest: str, entries: Sequence[dict[str, Any]], cfg: PlannerConfig, by_type: ByType
) -> dict[str, dict[str, Any]]:
    """Round 2 of the legacy schedule: each finalist at the two ``PERTURBATIONS``, ranked by the mean."""
    finalists = _finalists(entries, cfg, by_type)
    retries = [
        Trial(t.object_id, perturbed(t.grasp, (dx, dy), dyaw))
        for _, t, _ in finalists
        for dx, dy, dyaw in PERTURBATIONS
    ]
    retry_records = run_trials(retries, manifest, cfg.scoring) if retries else []
    out: dict[str, dict[str, Any]] = {e["id"]: {"grasps": {}} for e in entries}
    n = len(PERTURBATIONS)
    for k, (_, t, r0) in enumerate(finalists):
        rs = [r0, *retry_records[k * n : (k + 1) * n]]
        score = float(np.mean([trial_score(r) for r in rs]))
        best = out[t.object_id]["grasps"].get(t.grasp.grasp)
        if best is None or score > best["score"]:
            out[t.object_id]["grasps"][t.grasp.grasp] = {
                **t.grasp.to_json(),
                "score": round(score, 4),
                "trials": _counts(rs),
            }
    return out


def _describe_unit(
    out: dict[str, dict[str, Any]], entries: Sequence[dict[str, Any]], cfg: PlannerConfig, by_type: ByType
) -> None:
    """Round 1's counts, the fallback of an object none of whose candidates lifted, and the settings
    its trials ran under, into each object's record."""
    environment = trial_environment(cfg.scoring)  # the same for every object of the unit
    for e in entries:
        oid = e["id"]
        mine_all = [x for g in cfg.candidates.types for x in by_type.get((oid, g), [])]
        out[oid]["candidates"] = len(mine_all)
        out[oid]["lifted_nominal"] = sum(1 for _, _, r in mine_all if r["s_lift"])
        if not out[oid]["grasps"]:
            # Nothing lifted: keep each type's best nominal candidate (by score, then by how far the
            # object rose), so the object still gets the most promising grasp, marked with score 0.
            for grasp_type in cfg.candidates.types:
                mine = by_type.get((oid, grasp_type), [])
                if mine:
                    s, t, r = max(mine, key=lambda x: (x[0], x[2]["max_rise"]))
                    out[oid]["grasps"][grasp_type] = {
                        **t.grasp.to_json(),
                        "score": round(s, 4),
                        "trials": {"lift": 0, "disturb": 0, "of": 1},
                    }
        out[oid]["environment"] = environment
