"""Trained policies shipped with the package, one folder per policy.

``--checkpoint shipped`` on ``d3grasp-play`` and ``d3grasp-eval`` resolves to the checkpoint of the
task being run (``resolve_checkpoint``); ``d3grasp-eval --ablation shipped`` to the three checkpoints
of the paper's ablation table (``shipped_ablation``). Each folder holds the rsl-rl checkpoint
(``model.pt``), its training curves and a model card (``MODEL_CARD.md``) with the exact command,
iterations, env-steps, wall-clock and hardware; the task's default policy also its TorchScript and
ONNX exports.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

__all__ = [
    "ABLATIONS",
    "ABLATION_NAMES",
    "BASELINE",
    "SHIPPED",
    "SHIPPED_ABLATION",
    "Ablation",
    "SHIPPED_POLICIES",
    "resolve_checkpoint",
    "shipped_ablation",
    "shipped_checkpoint",
]

SHIPPED = "shipped"
"""The ``--checkpoint`` value that selects the shipped policy of the task."""

BASELINE = "baseline"
"""The ``--checkpoint`` value that runs the rule-based controller (d3grasp.envs.baseline) instead."""

# task -> folder under d3grasp/policies/
SHIPPED_POLICIES: dict[str, str] = {"D3Grasp-DexHand13-Mixed-v0": "mixed_v0"}


@dataclass(frozen=True)
class Ablation:
    """One column of the paper's ablation table: the task it trains on, its name in the tables and
    the folder of its shipped checkpoint under d3grasp/policies/."""

    task: str
    name: str
    folder: str


# The paper's ablation table under the camera, one recipe and budget each (their model cards):
# ``d3grasp-eval --ablation shipped``, in the table's order. The one declaration of the ablations.
ABLATIONS: tuple[Ablation, ...] = (
    Ablation("D3Grasp-DexHand13-Base-v0", "Base", "ablation_base"),
    Ablation("D3Grasp-DexHand13-BaseTactile-v0", "Base+Tactile", "ablation_basetactile"),
    Ablation("D3Grasp-DexHand13-Mixed-v0", "Asymmetric", "ablation_asymmetric"),
)
SHIPPED_ABLATION: dict[str, str] = {a.task: a.folder for a in ABLATIONS}
"""Task -> folder of its shipped ablation checkpoint."""
ABLATION_NAMES: dict[str, str] = {a.task: a.name for a in ABLATIONS}
"""Task -> its column's name in the tables (other tasks are named after their variant)."""

_ROOT = Path(__file__).resolve().parent


def shipped_checkpoint(task: str) -> Path:
    """Path of the shipped ``model.pt`` of ``task``; ``FileNotFoundError`` names the tasks that have one."""
    folder = SHIPPED_POLICIES.get(task)
    path = _ROOT / folder / "model.pt" if folder else None
    if path is None or not path.is_file():
        have = ", ".join(t for t, f in SHIPPED_POLICIES.items() if (_ROOT / f / "model.pt").is_file())
        raise FileNotFoundError(
            f"no shipped policy for task '{task}' (shipped: {have or 'none'}); pass a checkpoint path instead"
        )
    return path


def resolve_checkpoint(checkpoint: str, task: str) -> str:
    """``"shipped"`` -> the task's shipped checkpoint path; anything else unchanged."""
    return str(shipped_checkpoint(task)) if checkpoint == SHIPPED else checkpoint


def shipped_ablation() -> tuple[str, ...]:
    """The shipped ablation checkpoints as ``--ablation`` entries (``"TASK=PATH"``);
    ``FileNotFoundError`` if the package lacks one."""
    missing = [f for f in SHIPPED_ABLATION.values() if not (_ROOT / f / "model.pt").is_file()]
    if missing:
        raise FileNotFoundError(f"the package lacks the shipped ablation checkpoints {missing}")
    return tuple(f"{task}={_ROOT / folder / 'model.pt'}" for task, folder in SHIPPED_ABLATION.items())
