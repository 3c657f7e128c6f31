"""d3grasp: the D3Grasp dexterous-grasping tasks on NVIDIA Newton and Warp."""

from d3grasp.paths import assets_root, default_manifest, hand_usd


def make_env(*args, **kwargs):  # noqa: ANN002, ANN003 - forwards to d3grasp.envs.make_env
    """Make a registered task's environment (see :func:`d3grasp.envs.make_env`)."""
    from d3grasp.envs import make_env as _make_env

    return _make_env(*args, **kwargs)


__version__ = "0.1.0"

__all__ = ["__version__", "make_env", "assets_root", "default_manifest", "hand_usd"]
