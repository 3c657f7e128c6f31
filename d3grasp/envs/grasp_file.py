"""The grasp file: the planner's measured grasps per object, ``grasps.json`` next to a manifest.

Schema::

    {
      "format": "d3grasp-grasps",
      "version": 1,
      "planner": {...},                      # the settings the grasps were planned with
      "objects": {
        "<asset id>": {
          "asset_sha256": "...",             # the asset file the grasps were measured on
          "grasps": {"<type>": {ObjectGrasp.to_json(), "score": float, "trials": {...}}, ...}
        }, ...
      }
    }

A grasp is stored in the object's frame (``d3grasp.envs.grasps.ObjectGrasp``) and placed with the
object's pose at run time. An entry whose asset file has changed since it was planned is ignored
(the object falls back to the geometric rule) rather than used for a shape it was not measured on.
"""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

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
            plan[oid] = StoredGrasps(grasps, scores, np.asarray(e.extents, dtype=np.float64))
    return plan
