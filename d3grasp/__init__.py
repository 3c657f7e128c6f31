"""d3grasp: the D3Grasp dexterous-grasping tasks on NVIDIA Newton and Warp."""

from pathlib import Path as _Path

# A source checkout keeps kernels/, train/ and assets_usd/ beside this folder, and installing maps
# them under d3grasp (pyproject.toml's package-dir). Run from the checkout's root, `python -m
# d3grasp...` imports this folder ahead of any installed copy, so the package looks beside it too.
_checkout = _Path(__file__).resolve().parent.parent
if (_checkout / "pyproject.toml").is_file() and not (_Path(__file__).parent / "kernels").is_dir():
    __path__.append(str(_checkout))

from d3grasp.paths import assets_root, default_manifest, hand_usd  # noqa: E402


def make_env(*args, **kwargs):  # noqa: ANN002, ANN003 - forwards to d3grasp.envs.make_env
    """Make a registered task's environment (see :func:`d3grasp.envs.make_env`)."""
    from d3grasp.envs import make_env as _make_env

    return _make_env(*args, **kwargs)


__version__ = "0.1.0"

__all__ = ["__version__", "make_env", "assets_root", "default_manifest", "hand_usd"]
