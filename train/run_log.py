"""What a training run records besides rsl-rl's scalars: each iteration's timing, the run's cumulative
env-steps and wall-clock (carried in checkpoints), grasp outcomes by group, and the console line of an
update's diagnostics."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch

from d3grasp.vocabulary import GRASP_TYPES, KINDS, METRICS, SIZE_BINS

__all__ = ["EpisodeStats", "IterationTiming", "TrainingProgress", "format_diagnostics"]

# Group keys come from the fixed vocabulary, so every rank's outcome counts line up in one
# all-reduced tensor.


@dataclass
class IterationTiming:
    """Wall time of one training iteration, in seconds, and the env-steps it collected (all ranks)."""

    iteration: int
    sim_s: float  # inside env.step
    rollout_s: float  # whole rollout: policy inference + env.step + storage
    update_s: float  # returns + PPO update (incl. gradient all-reduce)
    env_steps: int

    @property
    def total_s(self) -> float:
        return self.rollout_s + self.update_s


@dataclass
class TrainingProgress:
    """What a run has consumed since its first iteration, resumed runs included: env-steps of all
    ranks and wall-clock seconds (checkpoint saves and object redraws counted). Stored in every
    checkpoint, so a resumed run's curves continue where the first one stopped."""

    env_steps: int = 0
    wall_clock_s: float = 0.0


class EpisodeStats:
    """Counts of grasp outcomes over finished episodes, grouped by kind, size bin and grasp type."""

    groups: tuple[str, ...] = (
        ("all",)
        + tuple(f"kind/{k}" for k in KINDS)
        + tuple(f"size/{s}" for s in SIZE_BINS)
        + tuple(f"grasp/{g}" for g in GRASP_TYPES)
    )

    def __init__(self) -> None:
        self.counts = torch.zeros(len(self.groups), 1 + len(METRICS), dtype=torch.float64)
        self._index = {g: i for i, g in enumerate(self.groups)}

    def add(self, episodes: list[dict[str, Any]]) -> None:
        for ep in episodes:
            row = torch.tensor([1.0] + [float(bool(ep.get(m, False))) for m in METRICS], dtype=torch.float64)
            keys = [
                "all",
                f"kind/{ep.get('kind')}",
                f"size/{ep.get('size_bin')}",
                f"grasp/{ep.get('grasp_type')}",
            ]
            for key in keys:
                i = self._index.get(key)
                if i is not None:
                    self.counts[i] += row

    def all_reduce(self) -> None:
        if torch.distributed.is_available() and torch.distributed.is_initialized():
            torch.distributed.all_reduce(self.counts, op=torch.distributed.ReduceOp.SUM)

    def rates(self) -> dict[str, float]:
        """``{"Success/<metric>/<group>": rate}`` for groups with at least one episode."""
        out: dict[str, float] = {}
        for i, group in enumerate(self.groups):
            n = float(self.counts[i, 0])
            if n > 0:
                for j, m in enumerate(METRICS):
                    out[f"Success/{m}/{group}"] = float(self.counts[i, 1 + j]) / n
        out["Success/episodes"] = float(self.counts[0, 0])
        return out

    def clear(self) -> None:
        self.counts.zero_()


def format_diagnostics(diagnostics: dict[str, float]) -> str:
    """The console line of an update's diagnostics (D3GraspPPO.diagnose)."""
    d = diagnostics
    phases = " ".join(
        f"{k.removeprefix('explained_variance_')} {v:.2f}"
        for k, v in d.items()
        if k.startswith("explained_variance_")
    )
    return (
        f"{'Diagnostics:':>35} episodes {d.get('episodes_per_update', float('nan')):.0f} | "
        f"grad cosine (split half) {d.get('grad_cosine_split_half', float('nan')):+.3f} | "
        f"explained variance {d.get('explained_variance', float('nan')):.2f} ({phases})"
    )
