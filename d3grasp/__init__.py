"""d3grasp: the D3Grasp dexterous-grasping tasks on NVIDIA Newton and Warp."""

from d3grasp.paths import assets_root, default_manifest, hand_usd

__version__ = "0.1.0"

__all__ = ["__version__", "assets_root", "default_manifest", "hand_usd"]
