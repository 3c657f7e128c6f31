"""Plan a library's grasps: candidates from each object's geometry, scored in simulation, the best of
each grasp type kept with its measured score in the library's grasp file (``grasps.json``).

Two schedules (``PlannerConfig.schedule``), in multi-world environments (``d3grasp.planner.score``).

``legacy`` (the shipped library's plan), two rounds without randomisation and with 0.3 s pushes:

1. every candidate (``d3grasp.planner.candidates``) once, at the nominal placement;
2. the best ``finalists`` of each type that lifted in round 1 again with the object displaced by a
   few millimetres and degrees (``PERTURBATIONS``); a finalist's score is the mean over its three
   trials, so a grasp that holds only at one exact placement loses to one that holds around it.

``evaluation``: successive halving under the evaluation's own conditions (its draws of pose and
sensor noise, the grasp placed by the true pose or by the camera, ``ScoringConfig.randomise``):

1. every candidate once (the true pose), 0.3 s pushes: the screen;
2. the best ``finalists`` of each type that lifted, ``screen_trials`` more (the camera first, then
   alternating with the true pose), 0.3 s pushes; the best of each type by its mean trial score
   goes on;
3. that grasp ``final_trials`` more times at the evaluation's 2 s pushes, half under the camera and
   half at the true pose. Its measured rate is the share of these final trials it held, stored with
   the 95% Wilson interval; its score, by which the environment picks among the types, is the
   interval's lower bound (plus a hundredth of its mean trial score to order equal bounds), so a
   grasp that held 12 of 12 outranks one that held 3 of 3. Every kept grasp that lifted has
   1 + ``screen_trials`` + ``final_trials`` trials (16 by default).

Objects are planned in fixed groups (``objects_per_unit`` in library order) whatever the number of
worker processes, so a plan is the same for a seed on any number of cores. The grasp file is
rewritten (atomically) after every group, and a rerun skips the objects it already holds for the
same asset file and planner settings: an interrupted run resumes where it stopped. Under other
settings, a group whose trials those settings ran as these would (its objects' candidates and the
scoring unchanged: e.g. no composite among them when only the pieces' candidates are new) keeps its
records, which a fresh plan would reproduce.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

from d3grasp.envs.grasp_file import (
    GRASP_FILE_FORMAT,
    GRASP_FILE_VERSION,
    asset_sha256,
    changed_settings,
    grasp_file_path,
    read_grasp_file,
)
from d3grasp.parallel import run_units
from d3grasp.planner.candidates import CandidateConfig, collision_pieces, convex_hull
from d3grasp.planner.rounds import PERTURBATIONS, candidates_of, plan_unit
from d3grasp.planner.score import ScoringConfig, trial_environment

SCHEDULES: tuple[str, ...] = ("legacy", "evaluation")
"""How candidates are tried and kept (module docstring)."""

# The settings only the evaluation schedule has (a legacy record carries none of them).
_EVALUATION_FIELDS = ("screen_trials", "final_trials", "final_push_seconds", "perceptions")


@dataclass(frozen=True)
class PlannerConfig:
    seed: int = 0
    candidates: CandidateConfig = field(default_factory=CandidateConfig)
    scoring: ScoringConfig = field(default_factory=ScoringConfig)
    finalists: int = 2  # per grasp type, re-tried under the perturbations (legacy) or screened again
    objects_per_unit: int = 4
    schedule: str = "legacy"  # see SCHEDULES; evaluation_planner() makes the other
    screen_trials: int = 3  # evaluation: round 2's trials per finalist
    final_trials: int = 12  # evaluation: round 3's trials of each type's best
    final_push_seconds: float = 2.0  # evaluation: round 3's pushes, the evaluation's (PhaseConfig)
    perceptions: tuple[str, ...] = ("camera", "oracle")  # evaluation: rounds 2-3 alternate these

    def __post_init__(self) -> None:
        if self.schedule not in SCHEDULES:
            raise ValueError(f"planner schedule must be one of {list(SCHEDULES)}, got '{self.schedule}'")
        if self.schedule == "evaluation" and not self.scoring.randomise:
            raise ValueError("the evaluation schedule scores with the evaluation's draws (scoring.randomise)")
        if min(self.screen_trials, self.final_trials) < 1 or self.finalists < 1:
            raise ValueError("finalists, screen_trials and final_trials must be >= 1")

    def record(self) -> dict[str, Any]:
        """What the grasp file records of the settings (a rerun with other settings replans)."""
        d = asdict(self)
        d["scoring"].pop("device", None)
        d.pop("objects_per_unit", None)
        d["candidates"]["types"] = list(d["candidates"]["types"])
        if not self.candidates.synthesised:  # recorded as before synthesis existed
            for key in ("synthesised", "synthesis_starts", "synthesis_steps"):
                d["candidates"].pop(key)
        if self.schedule == "legacy":  # recorded as before the schedules existed
            for key in ("schedule", *_EVALUATION_FIELDS):
                d.pop(key)
            d["scoring"].pop("randomise")
            d["perturbations"] = [list(p) for p in PERTURBATIONS]
        else:
            d["perceptions"] = list(d["perceptions"])
        return json.loads(json.dumps(d))


def evaluation_planner(seed: int = 0, **changes: Any) -> PlannerConfig:
    """The planner of the ``evaluation`` schedule (successive halving under the evaluation's draws)."""
    # One object a unit: every core works whatever the number of objects (units of four planned four
    # soft objects in one process), and an object's ~30 candidates still fill a multi-world batch.
    changes = {"objects_per_unit": 1, **changes}
    return PlannerConfig(seed=seed, schedule="evaluation", scoring=ScoringConfig(randomise=True), **changes)


# What a grasp file recorded before a candidate setting existed: the behaviour it was planned with.
CANDIDATES_BEFORE: dict[str, Any] = {"max_pieces": 0, "synthesised": 0}


def config_of_record(record: dict[str, Any]) -> PlannerConfig | None:
    """The settings a grasp file records (:meth:`PlannerConfig.record`), or None for a record this
    planner cannot read back (then nothing of that file is reused)."""
    try:
        cand = {**CANDIDATES_BEFORE, **record["candidates"]}
        cand = {k: tuple(v) if isinstance(v, list) else v for k, v in cand.items()}
        schedule = record.get("schedule", "legacy")
        if schedule == "legacy" and [tuple(p) for p in record["perturbations"]] != list(PERTURBATIONS):
            return None
        extra = {k: record[k] for k in _EVALUATION_FIELDS if schedule != "legacy"}
        if "perceptions" in extra:
            extra["perceptions"] = tuple(extra["perceptions"])
        return PlannerConfig(
            seed=record["seed"],
            candidates=CandidateConfig(**cand),
            scoring=ScoringConfig(**record["scoring"]),
            finalists=record["finalists"],
            schedule=schedule,
            **extra,
        )
    except (KeyError, TypeError, ValueError):
        return None


def same_trials(old: PlannerConfig, new: PlannerConfig, rows: Sequence[dict[str, Any]]) -> bool:
    """Whether planning the group ``rows`` under ``old`` and ``new`` runs the same trials (then it
    gives the same plan: a group's trials depend on nothing else)."""
    if replace(old, candidates=new.candidates, objects_per_unit=new.objects_per_unit) != new:
        return False  # any setting but the candidates' changes the trials
    for row in rows:
        a, b = candidates_of(row, old), candidates_of(row, new)
        if [g.to_json() for g in a] != [g.to_json() for g in b]:
            return False
    return True


def _differing(old: Any, new: Any, prefix: str = "") -> list[str]:
    """The dotted keys whose values differ between two planner records (``old`` may be anything)."""
    if not isinstance(old, dict) or not isinstance(new, dict):
        return [prefix or "the planner record"] if old != new else []
    keys = sorted(set(old) | set(new))
    return [d for k in keys for d in _differing(old.get(k), new.get(k), f"{prefix}.{k}" if prefix else k)]


def _units(
    manifest: Path, entries: Sequence[Any], order: dict[str, int], cfg: PlannerConfig
) -> list[list[dict[str, Any]]]:
    """The selection's objects in fixed groups of ``cfg.objects_per_unit``, in library ``order`` (asset
    id -> its place in the manifest), each object a row of what its trials need (id, kind, extents,
    collision pieces, hull)."""
    from d3grasp.authoring.manifest import resolve_asset_path
    from d3grasp.authoring.precision import stable_json

    # Fixed groups of the whole selection in library order (rigid objects first: a FEM step costs
    # ~20x a rigid one, d3grasp.eval.evaluate.SOFT_COST, and the two kinds never share a group, so a
    # group of rigid objects runs at 5 solver iterations), whatever is planned already and
    # however many workers run them: a group's objects share their batches, so the same groups give
    # the same plan for a seed on any number of cores and after any interruption. A group with an
    # object left to plan runs whole.
    units = []
    for kind in ("rigid", "deformable"):
        mine = sorted((e for e in entries if e.kind == kind), key=lambda e: order[e.id])
        rows = [
            {
                "id": e.id,
                "kind": e.kind,
                "extents": list(e.extents),
                # The collision pieces of a rigid object (composites get candidates on them), at the
                # authoring precision: the same candidates whichever process reads the file.
                "pieces": [
                    (stable_json(c.tolist()), stable_json(x.tolist()))
                    for c, x in collision_pieces(resolve_asset_path(manifest, e))
                ]
                if e.kind == "rigid"
                else [],
                # The convex hull the synthesised candidates are descended on (only when asked for).
                "hull": (
                    tuple(a.tolist() for a in convex_hull(resolve_asset_path(manifest, e)))
                    if e.kind == "rigid" and cfg.candidates.synthesised
                    else None
                ),
            }
            for e in mine
        ]
        units += [rows[k : k + cfg.objects_per_unit] for k in range(0, len(rows), cfg.objects_per_unit)]
    return units


def plan_grasps(
    manifest: str | Path,
    ids: Sequence[str] | None = None,
    cfg: PlannerConfig | None = None,
    workers: int = 1,
    progress: bool = True,
    log: Callable[[str], None] = print,
) -> Path:
    """Plan the grasps of a library's objects (all, or ``ids``) into its grasp file; returns its path."""
    from tqdm import tqdm

    from d3grasp.authoring.manifest import read_manifest, resolve_asset_path

    cfg = cfg or PlannerConfig()
    manifest = Path(manifest).resolve()
    entries = read_manifest(manifest)
    order = {e.id: k for k, e in enumerate(entries)}  # the library's order, whatever is selected
    if ids:
        known = {e.id for e in entries}
        missing = [i for i in ids if i not in known]
        if missing:
            raise ValueError(f"{manifest}: unknown asset ids {missing}")
        entries = [e for e in entries if e.id in set(ids)]
    path = grasp_file_path(manifest)
    settings = cfg.record()
    data: dict[str, Any] = {
        "format": GRASP_FILE_FORMAT,
        "version": GRASP_FILE_VERSION,
        "planner": settings,
        "objects": {},
    }
    earlier: tuple[PlannerConfig, dict[str, Any]] | None = None  # a plan of other settings
    if path.is_file():
        old = read_grasp_file(path)
        if old.get("planner") == settings:
            data["objects"] = old["objects"]
        elif others := sorted(set(old["objects"]) - {e.id for e in entries}):
            # The file records one planner setting for all its objects: written under these, it would
            # keep the selection only. Refused before any trial runs, nothing of the old plan lost.
            changed = ", ".join(_differing(old.get("planner"), settings))
            raise ValueError(
                f"{path}: planned under other planner settings ({changed}); "
                f"planning {len(entries)} of its objects under these would drop the plans of the "
                f"{len(others)} others ({', '.join(others[:3])}{', ...' if len(others) > 3 else ''}): "
                "plan the whole library (no --ids), or with the settings it records"
            )
        elif (old_cfg := config_of_record(old.get("planner") or {})) is not None:
            earlier = (old_cfg, old["objects"])
    sha = {e.id: asset_sha256(resolve_asset_path(manifest, e)) for e in entries}
    environment = trial_environment(cfg.scoring)

    def current(rec: dict[str, Any] | None, oid: str) -> bool:
        """A record measured on this asset under these simulation, rule and planner settings (a
        record adopted from another plan, :func:`adopt_plans`, carries its own planner settings)."""
        return (
            rec is not None
            and rec.get("asset_sha256") == sha[oid]
            and not changed_settings(rec.get("environment"), environment)
            and rec.get("planner", settings) == settings
        )

    units = _units(manifest, entries, order, cfg)
    if earlier is not None:
        # A plan of other settings: a group whose trials those settings ran as these would (e.g. no
        # composite among its objects when the settings differ by the pieces' candidates) is kept.
        old_cfg, old_objects = earlier
        kept = 0
        for unit in units:
            recs = {e["id"]: old_objects.get(e["id"]) for e in unit}
            if all(current(r, i) for i, r in recs.items()) and same_trials(old_cfg, cfg, unit):
                data["objects"].update(recs)
                kept += len(unit)
        if kept:
            log(f"[plan-grasps] {kept} objects kept from the plan of other settings: the same trials")
    done = {e.id for e in entries if current(data["objects"].get(e.id), e.id)}
    if done:
        log(f"[plan-grasps] {len(done)} of {len(entries)} planned already ({path.name})")
    units = [u for u in units if any(e["id"] not in done for e in u)]
    todo = [e for u in units for e in u]

    def save(result: dict[str, dict[str, Any]]) -> None:
        for oid, rec in result.items():
            data["objects"][oid] = {"asset_sha256": sha[oid], **rec}
        _write_plan(path, data, order)

    with tqdm(
        total=len(todo), unit="obj", disable=not progress, dynamic_ncols=True, desc="plan-grasps"
    ) as bar:

        def done_unit(k: int, result: dict[str, dict[str, Any]]) -> None:
            save(result)
            bar.update(len(units[k]))

        run_units(plan_unit, [(str(manifest), unit, cfg) for unit in units], workers, done_unit)
    return path


def adopt_plans(manifest: str | Path, source: str | Path, ids: Sequence[str]) -> Path:
    """Take the records of ``ids`` from another grasp file ``source`` (e.g. the plan of a slower
    schedule kept for the soft objects) into the library's grasp file, each carrying the planner
    settings it was measured under as its own ``planner`` (the file's ``planner`` stays the one the
    others were planned with, and a later ``plan_grasps`` under those replans these). Only records
    measured on the library's current asset files are taken; returns the grasp file's path."""
    from d3grasp.authoring.manifest import read_manifest, resolve_asset_path

    manifest = Path(manifest).resolve()
    path = grasp_file_path(manifest)
    if not path.is_file():
        raise ValueError(f"{path}: no grasp file to adopt plans into (plan the library first)")
    data = read_grasp_file(path)
    other = read_grasp_file(source)
    entries = {e.id: e for e in read_manifest(manifest)}
    for oid in ids:
        rec = other["objects"].get(oid)
        if oid not in entries or rec is None:
            raise ValueError(f"{source}: no plan of '{oid}' (or '{oid}' is not in {manifest.name})")
        if rec.get("asset_sha256") != asset_sha256(resolve_asset_path(manifest, entries[oid])):
            raise ValueError(f"{source}: the plan of '{oid}' was measured on another asset file")
        data["objects"][oid] = {**rec, "planner": rec.get("planner", other.get("planner"))}
    _write_plan(path, data, {oid: k for k, oid in enumerate(entries)})
    return path


def _write_plan(path: Path, data: dict[str, Any], order: dict[str, int]) -> None:
    """Write a grasp file atomically, its objects in library ``order`` (asset id -> place; others
    last) and its numbers at the authoring precision (9 digits): the same file on any machine for
    the same plan."""
    from d3grasp.authoring.precision import stable_json
    from d3grasp.files import atomic_write_text

    data["objects"] = dict(sorted(data["objects"].items(), key=lambda kv: order.get(kv[0], math.inf)))
    atomic_write_text(path, json.dumps(stable_json(data), indent=1) + "\n")
