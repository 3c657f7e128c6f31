"""Finished evaluation batches kept on disk, so that a stopped ``d3grasp-eval`` resumes where it was.

Each batch's episodes go to ``<out>/.batches/<key hash>.json`` (atomically) as the batch finishes.
``d3grasp-eval --resume`` reuses a stored batch only when everything its episodes depend on is the
same: the settings, the controller and its checkpoint file's bytes, the objects, seed and grasp
types of the batch, the bytes of the manifest, the grasp file, the objects' and the hand's USD files,
the package's source (kernels included) and the Warp and Newton versions. Anything else
runs again. The folder is removed once the outputs are written.
"""

from __future__ import annotations

import hashlib
import json
import shutil
from collections.abc import Sequence
from dataclasses import asdict
from functools import cache
from pathlib import Path
from typing import Any

from d3grasp.files import atomic_write_text

__all__ = ["BATCH_DIR_NAME", "BatchStore", "batch_keys"]

BATCH_DIR_NAME = ".batches"


def _file_sha256(path: str | Path) -> str | None:
    """SHA-256 of a file's bytes, None when there is no such file."""
    from d3grasp.envs.grasp_file import asset_sha256

    return asset_sha256(path) if Path(path).is_file() else None


@cache
def _code_fingerprint() -> dict[str, str]:
    """What the episodes' numbers come from besides the inputs: the package's Python source (hashed),
    the hand's USD file and the simulator's versions. Computed once per process."""
    import newton
    import warp

    import d3grasp
    import d3grasp.kernels
    from d3grasp.paths import hand_usd

    # kernels/ installs under d3grasp but lives beside it in an editable install. The training code is
    # not part of an evaluation (tests/test_layout.py): beside it, its edits do not count.
    roots = [Path(d3grasp.__file__).parent, *map(Path, d3grasp.kernels.__path__)]
    files = sorted({path.resolve() for root in roots for path in root.rglob("*.py")})
    h = hashlib.sha256()
    for path in files:
        h.update(path.name.encode())
        h.update(path.read_bytes())
    return {
        "d3grasp_source": h.hexdigest(),
        "hand_sha256": _file_sha256(hand_usd()) or "",
        "warp": warp.__version__,
        "newton": newton.__version__,
    }


def batch_keys(
    settings: Any,
    batches: Sequence[tuple[Any, str, Sequence[str], int]],
    manifest: str | None,
    grasp_types: Sequence[str],
) -> list[dict[str, Any]]:
    """Everything each batch ``(spec, perception, object ids, repeat)``'s episodes depend on, as
    JSON-able values (the files by their SHA-256). What the batches share is read and hashed once."""
    from d3grasp.authoring.manifest import read_manifest, resolve_asset_path
    from d3grasp.envs.grasp_file import grasp_file_path
    from d3grasp.paths import default_manifest

    manifest_path = Path(manifest) if manifest is not None else default_manifest()
    shared = {
        # Whether code-carrying checkpoints may be read changes no episode: not part of the key.
        "settings": {k: v for k, v in asdict(settings).items() if k != "trust_checkpoint"},
        "grasp_types": list(grasp_types),
        "manifest": str(manifest_path),
        "manifest_sha256": _file_sha256(manifest_path),
        "grasps_sha256": _file_sha256(grasp_file_path(manifest_path)),
        **_code_fingerprint(),
    }
    entries = {e.id: e for e in read_manifest(manifest_path)}
    ids = {i for _, _, chunk, _ in batches for i in chunk if i in entries}
    asset_sha = {i: _file_sha256(resolve_asset_path(manifest_path, entries[i])) for i in ids}
    checkpoints = {spec.checkpoint for spec, *_ in batches}
    checkpoint_sha = {c: _file_sha256(c) if Path(c).suffix == ".pt" else None for c in checkpoints}
    return [
        {
            **shared,
            "spec": asdict(spec),
            "checkpoint_sha256": checkpoint_sha[spec.checkpoint],
            "perception": perception,
            "objects": list(chunk),
            "repeat": repeat,
            "assets_sha256": {i: asset_sha[i] for i in chunk if i in asset_sha},  # the objects' USD files
        }
        for spec, perception, chunk, repeat in batches
    ]


def _key_hash(key: dict[str, Any]) -> str:
    return hashlib.sha256(json.dumps(key, sort_keys=True, default=str).encode()).hexdigest()[:24]


class BatchStore:
    """The finished batches of one output folder."""

    def __init__(self, out_dir: str | Path):
        self.dir = Path(out_dir) / BATCH_DIR_NAME

    def _path(self, key: dict[str, Any]) -> Path:
        return self.dir / f"{_key_hash(key)}.json"

    def load(self, key: dict[str, Any]) -> list[dict[str, Any]] | None:
        """The stored episodes of the batch with this key; None if none or if stored for other inputs."""
        path = self._path(key)
        try:
            doc = json.loads(path.read_text())
        except (FileNotFoundError, json.JSONDecodeError, UnicodeDecodeError):
            return None
        # The hash names the file; the full key inside guards against a collision or a hand-edited file.
        if not isinstance(doc, dict) or doc.get("key") != json.loads(json.dumps(key, default=str)):
            return None
        episodes = doc.get("episodes")
        return episodes if isinstance(episodes, list) else None

    def save(self, key: dict[str, Any], episodes: list[dict[str, Any]]) -> None:
        # NaN stays NaN here (Python's JSON reads it back); results.json writes it as null.
        atomic_write_text(self._path(key), json.dumps({"key": key, "episodes": episodes}, default=str))

    def clear(self) -> None:
        shutil.rmtree(self.dir, ignore_errors=True)
