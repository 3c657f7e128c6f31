"""Where the shipped assets live, for source checkouts and installed wheels alike."""

from __future__ import annotations

from pathlib import Path


def assets_root() -> Path:
    """Directory of the shipped USD library (``assets_usd/`` in the repository)."""
    import d3grasp.assets_usd

    return Path(d3grasp.assets_usd.__file__).resolve().parent


def default_manifest() -> Path:
    """The shipped library's manifest."""
    return assets_root() / "manifest.json"


def hand_usd() -> Path:
    """The DexHand13 USD file."""
    return assets_root() / "hands" / "dexhand13.usda"
