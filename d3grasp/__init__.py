"""d3grasp: the D3Grasp dexterous-grasping tasks on NVIDIA Newton and Warp."""

from importlib.util import find_spec as _find_spec
from pathlib import Path as _Path

# kernels/, train/ and assets_usd/ sit beside this folder in a checkout and import as
# d3grasp.kernels, d3grasp.train and d3grasp.assets_usd through the install's mapping
# (pyproject.toml's package-dir; an editable install, `pip install -e .`, maps them to the
# checkout's folders), not through any change to this package's __path__. A checkout's folder
# imported without that mapping (`python -m d3grasp...` in the checkout after `pip install .`) says so.
_checkout = _Path(__file__).resolve().parent.parent
if (_checkout / "pyproject.toml").is_file() and _find_spec("d3grasp.kernels") is None:
    raise ImportError(
        f"{_Path(__file__).parent}: a source checkout's d3grasp without the install's mapping of kernels/ "
        "and train/: run `pip install -e .` in the checkout, or run from another folder"
    )

from d3grasp.paths import assets_root, default_manifest, hand_usd  # noqa: E402


def make_env(*args, **kwargs):  # noqa: ANN002, ANN003 - forwards to d3grasp.envs.make_env
    """Make a registered task's environment (see :func:`d3grasp.envs.make_env`)."""
    from d3grasp.envs import make_env as _make_env

    return _make_env(*args, **kwargs)


__version__ = "0.1.0"

__all__ = ["__version__", "make_env", "assets_root", "default_manifest", "hand_usd"]
