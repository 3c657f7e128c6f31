"""The asset manifest: one JSON file listing every asset of a library.

Schema (``manifest.json``)::

    {
      "format": "d3grasp-manifest",
      "version": 1,
      "size_bins": {"small": [0.03, 0.06], "medium": [0.06, 0.12], "large": [0.12, 0.20]},
      "assets": [AssetEntry, ...]
    }

Paths inside entries are relative to the manifest's directory, so a library can be moved or
installed as package data.
"""

from __future__ import annotations

import json
import shutil
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Literal

from d3grasp.authoring.precision import stable_json
from d3grasp.files import atomic_write_text
from d3grasp.vocabulary import SIZE_BINS

MANIFEST_FORMAT = "d3grasp-manifest"
MANIFEST_VERSION = 1

AssetKind = Literal["rigid", "deformable"]


def size_bin_of(longest_side: float) -> str:
    """Size bin name for an object whose longest side is ``longest_side`` metres.

    Raises ``ValueError`` outside every bin (too small or too large for the hand).
    """
    names = list(SIZE_BINS)
    for i, name in enumerate(names):
        lo, hi = SIZE_BINS[name]
        last = i == len(names) - 1
        if lo <= longest_side < hi or (last and longest_side == hi):
            return name
    lo = SIZE_BINS[names[0]][0]
    hi = SIZE_BINS[names[-1]][1]
    raise ValueError(
        f"longest side {longest_side * 100:.1f} cm is outside the graspable range "
        f"{lo * 100:.0f}-{hi * 100:.0f} cm"
    )


@dataclass
class AssetEntry:
    """One asset of a library.

    ``material`` keys: rigid: ``density`` (kg/m^3), ``friction``; deformable additionally
    ``youngs_modulus`` (Pa), ``poissons_ratio``, ``damping`` (Newton does not read damping from
    USD: the environment applies it after loading), ``class`` (sponge/bread/plush/rubber).
    ``stats``: rigid: ``num_hulls``, ``num_hull_vertices``; deformable: ``num_tets``,
    ``num_nodes``, ``num_surface_triangles``.
    """

    id: str
    path: str  # relative to the manifest directory
    kind: AssetKind
    family: str
    size_bin: str
    extents: list[float]  # bounding-box side lengths in the rest frame, metres
    mass: float  # kg
    volume: float  # m^3
    material: dict[str, Any]
    split: Literal["train", "test"] = "train"
    stats: dict[str, Any] = field(default_factory=dict)
    source: str = ""  # how it was made, e.g. "procedural:box" or "import:mug.obj"


def write_manifest(path: str | Path, entries: list[AssetEntry]) -> None:
    """Write a manifest atomically (temp file + rename), sorted by kind then id."""
    path = Path(path)
    entries = sorted(entries, key=lambda e: (e.kind, e.id))
    ids = [e.id for e in entries]
    dup = {i for i in ids if ids.count(i) > 1}
    if dup:
        raise ValueError(f"duplicate asset ids in manifest: {sorted(dup)}")
    doc = {
        "format": MANIFEST_FORMAT,
        "version": MANIFEST_VERSION,
        "size_bins": {k: list(v) for k, v in SIZE_BINS.items()},
        "assets": [stable_json(asdict(e)) for e in entries],
    }
    atomic_write_text(path, json.dumps(doc, indent=1) + "\n")


def read_manifest(path: str | Path) -> list[AssetEntry]:
    """Read a manifest; raises ``ValueError`` with the file name on any malformed content."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: manifest not found")
    try:
        doc = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ValueError(f"{path}: not a JSON manifest ({exc})") from None
    if not isinstance(doc, dict) or doc.get("format") != MANIFEST_FORMAT:
        raise ValueError(f"{path}: not a d3grasp manifest (missing format '{MANIFEST_FORMAT}')")
    if doc.get("version") != MANIFEST_VERSION:
        raise ValueError(f"{path}: unsupported manifest version {doc.get('version')!r}")
    entries = []
    for i, raw in enumerate(doc.get("assets", [])):
        try:
            entries.append(AssetEntry(**raw))
        except TypeError as exc:
            raise ValueError(f"{path}: asset #{i} is malformed ({exc})") from None
    return entries


def resolve_asset_path(manifest_path: str | Path, entry: AssetEntry) -> Path:
    """Absolute path of an entry's USD file."""
    return (Path(manifest_path).resolve().parent / entry.path).resolve()


def merge_into_manifest(path: str | Path, entries: list[AssetEntry], kind: AssetKind) -> None:
    """Replace every entry of ``kind`` in the manifest at ``path`` by ``entries``.

    Lets the rigid and the soft builders run separately (and be re-run alone) while sharing one
    manifest. Creates the manifest if it does not exist.
    """
    path = Path(path)
    kept = [e for e in read_manifest(path) if e.kind != kind] if path.exists() else []
    write_manifest(path, kept + list(entries))


def install_built_assets(
    staging: str | Path, out_root: str | Path, subdir: str, entries: list[AssetEntry], kind: AssetKind
) -> None:
    """Move a builder's finished USD files from ``staging`` into ``out_root/subdir`` and merge their entries.

    The folder's previous USD files are removed first, so a rebuild leaves no stale assets; the
    builders write everything to ``staging`` and call this only after every asset succeeded.
    """
    staging, out_root = Path(staging), Path(out_root)
    dst = out_root / subdir
    dst.mkdir(parents=True, exist_ok=True)
    for old in dst.glob("*.usd*"):
        old.unlink()
    for e in entries:
        shutil.move(str(staging / e.path), str(out_root / e.path))
    merge_into_manifest(out_root / "manifest.json", entries, kind=kind)
