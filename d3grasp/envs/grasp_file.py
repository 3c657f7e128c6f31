"""The grasp file: the planner's measured grasps per object, ``grasps.json`` next to a manifest.

Schema::

    {
      "format": "d3grasp-grasps",
      "version": 1,
      "planner": {...},                      # the settings the grasps were planned with
      "objects": {
        "<asset id>": {
          "asset_sha256": "...",             # the asset file the grasps were measured on
          "environment": {"sim": {...}, "rule": {...}},  # the settings its trials ran under
          "grasps": {"<type>": {ObjectGrasp.to_json(), "score": float, "trials": {...}}, ...},
          "planner": {...}                   # only on a record planned under other settings than
        }, ...                               # the file's (adopted, d3grasp.planner.plan.adopt_plans)
      }
    }

A grasp is stored in the object's frame (``d3grasp.envs.grasps.ObjectGrasp``) and placed with the
object's pose at run time. An entry whose asset file has changed since it was planned is ignored
(the object falls back to the geometric rule) rather than used for a shape it was not measured on.
An entry measured under other simulation or rule settings than an environment's is used, with a
warning (:func:`changed_settings`), and planned again by the next ``plan-grasps``; entries planned
before the file recorded the settings (no ``environment``) are taken as current.
"""

from __future__ import annotations

import hashlib
import json
import math
import warnings
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from d3grasp.envs.config import PRIOR_SETTINGS
from d3grasp.envs.grasps import ObjectGrasp

GRASP_FILE_NAME = "grasps.json"
GRASP_FILE_FORMAT = "d3grasp-grasps"
GRASP_FILE_VERSION = 1


class GraspFileError(ValueError):
    """A grasp file that cannot be read (one line: the file and what is wrong)."""


def grasp_file_path(manifest: str | Path) -> Path:
    """Where a library's grasp file lives: next to its manifest."""
    return Path(manifest).parent / GRASP_FILE_NAME


def asset_sha256(path: str | Path) -> str:
    """SHA-256 of an asset file's bytes (what a stored grasp was measured on)."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


@dataclass
class StoredGrasps:
    """One object's stored grasps by type, each with its measured score (higher is better)."""

    grasps: dict[str, ObjectGrasp]
    scores: dict[str, float]
    extents: np.ndarray = field(default_factory=lambda: np.ones(3))  # the object's manifest extents
    environment: dict[str, Any] | None = None  # the settings its trials ran under (None: not recorded)

    def best(self, allowed: tuple[str, ...]) -> str | None:
        types = [g for g in allowed if g in self.grasps]
        return max(types, key=lambda g: self.scores[g]) if types else None

    def align_yaw(self, est_yaw: float, est_extents: np.ndarray) -> float:
        """The object-frame yaw of a camera estimate: the estimate's footprint sides are unordered,
        so of the quarter turns of ``est_yaw`` the one whose sides match the object's own extents
        (x, y) is taken, the smaller angle of the two half-turn twins (a box fit cannot tell the two
        ends of an object apart: grasps of objects that look the same from both ends are unaffected)."""
        e = np.asarray(est_extents, dtype=np.float64)
        best: tuple[float, float, float] | None = None
        for k in range(4):
            yaw = math.atan2(math.sin(est_yaw + 0.5 * math.pi * k), math.cos(est_yaw + 0.5 * math.pi * k))
            sides = (e[0], e[1]) if k % 2 == 0 else (e[1], e[0])
            err = abs(sides[0] - self.extents[0]) + abs(sides[1] - self.extents[1])
            key = (round(err, 6), abs(yaw), yaw)
            if best is None or key < best:
                best = key
        assert best is not None
        return best[2]


def environment_record(sim: Any, rule: Any) -> dict[str, Any]:
    """What a grasp's trials depend on besides the planner's own settings and the asset: the
    simulation settings (``SimConfig``) and the rule's (``BaselineConfig``: the environment's own,
    ``GraspEnvConfig.rule``), as JSON values."""
    return json.loads(json.dumps({"sim": asdict(sim), "rule": asdict(rule)}))


def without_prior(record: dict[str, Any]) -> dict[str, Any]:
    """An :func:`environment_record` without the rule's ``PRIOR_SETTINGS``: every task runs on the
    library's grasps, planned under the touch rule, so an environment on the Base task's stall prior
    uses them as planned (its prior is the ablation's point, not a changed setting)."""
    rule = {k: v for k, v in record.get("rule", {}).items() if k not in PRIOR_SETTINGS}
    return {**record, "rule": rule}


def changed_settings(recorded: dict[str, Any] | None, current: dict[str, Any]) -> list[str]:
    """The settings of ``current`` that ``recorded`` (an :func:`environment_record`) holds with
    another value, as ``"sim.soft_iterations 5 -> 20"``. A setting the record lacks is not
    compared (it did not exist when the grasps were planned); no record: none."""
    if recorded is None:
        return []
    out = []
    for section, values in current.items():
        old = recorded.get(section) or {}
        out += [f"{section}.{k} {old[k]} -> {v}" for k, v in values.items() if k in old and old[k] != v]
    return out


def read_grasp_file(path: str | Path) -> dict[str, Any]:
    """The parsed grasp file; ``GraspFileError`` for a file that is not one."""
    path = Path(path)
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError) as exc:
        raise GraspFileError(f"{path}: not a readable grasp file ({exc})") from exc
    if not isinstance(data, dict) or data.get("format") != GRASP_FILE_FORMAT:
        raise GraspFileError(f"{path}: not a grasp file (format is not '{GRASP_FILE_FORMAT}')")
    if data.get("version") != GRASP_FILE_VERSION:
        raise GraspFileError(f"{path}: grasp file version {data.get('version')} (this d3grasp reads 1)")
    if not isinstance(data.get("objects"), dict):
        raise GraspFileError(f"{path}: grasp file without an 'objects' table")
    return data


def load_grasp_plan(manifest: str | Path) -> dict[str, StoredGrasps] | None:
    """The stored grasps of a library by asset id, or None when it has no grasp file. Entries whose
    asset file changed since they were planned are left out."""
    from d3grasp.authoring.manifest import read_manifest, resolve_asset_path

    path = grasp_file_path(manifest)
    if not path.is_file():
        return None
    data = read_grasp_file(path)
    entries = {e.id: e for e in read_manifest(manifest)}
    plan: dict[str, StoredGrasps] = {}
    for oid, rec in data["objects"].items():
        e = entries.get(oid)
        if e is None:
            continue
        asset = resolve_asset_path(Path(manifest), e)
        if not asset.is_file() or rec.get("asset_sha256") != asset_sha256(asset):
            continue
        try:
            grasps = {g: ObjectGrasp.from_json(d) for g, d in rec.get("grasps", {}).items()}
            scores = {g: float(d["score"]) for g, d in rec.get("grasps", {}).items()}
        except (KeyError, TypeError, ValueError) as exc:
            raise GraspFileError(f"{path}: object '{oid}': {exc}") from exc
        if grasps:
            plan[oid] = StoredGrasps(
                grasps, scores, np.asarray(e.extents, dtype=np.float64), rec.get("environment")
            )
    return plan


def warn_changed_settings(plan: dict[str, Any], entries: list[Any], current: dict[str, Any]) -> None:
    """One warning when the worlds' stored grasps were measured under other simulation or rule
    settings than this environment's: they may not hold here."""
    changed: dict[str, list[str]] = {}
    for e in entries:
        stored = plan.get(e.id)
        for c in changed_settings(stored.environment if stored else None, current):
            changed.setdefault(c, []).append(e.id)
    if changed:
        ids = sorted({i for v in changed.values() for i in v})
        warnings.warn(
            f"the grasps of {len(ids)} object(s) ({', '.join(ids[:3])}{', ...' if len(ids) > 3 else ''}) "
            f"were planned under other settings ({'; '.join(changed)}): they may not hold under these; "
            "replan them with `d3grasp-assets plan-grasps DIR`, DIR their library's folder",
            stacklevel=4,
        )
