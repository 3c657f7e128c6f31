"""Training on several processes: one per core on CPU (gloo), one per GPU on CUDA (NCCL).

rsl-rl 5.5.1 initialises NCCL and requires ``cuda:<local_rank>``. PPO's gradient all-reduce,
parameter broadcast and normaliser statistics already go through ``torch.distributed`` and work
unchanged on gloo, so what d3grasp adds is the process group for CPU ranks, gradients weighed by
each rank's share of the worlds, the world count over ranks and a stop all ranks agree on.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Any

import torch

__all__ = ["Ranks", "agree_to_stop", "init_ranks", "pool_rank_gradients", "sum_over_ranks"]


@dataclass(frozen=True)
class Ranks:
    """This process's place among torchrun's: world size, local and global rank."""

    world_size: int
    local_rank: int
    global_rank: int

    @property
    def distributed(self) -> bool:
        return self.world_size > 1


def init_ranks(device: str) -> Ranks:
    """The ranks from torchrun's environment (``WORLD_SIZE``, ``LOCAL_RANK``, ``RANK``); with more than
    one, the process group: gloo for CPU ranks, NCCL for ``cuda:<local_rank>`` ranks."""
    world_size = int(os.getenv("WORLD_SIZE", "1"))
    if world_size <= 1:
        return Ranks(1, 0, 0)
    ranks = Ranks(world_size, int(os.getenv("LOCAL_RANK", "0")), int(os.getenv("RANK", "0")))
    if not 0 <= ranks.global_rank < world_size:
        raise ValueError(f"RANK {ranks.global_rank} is outside WORLD_SIZE {world_size}")
    dev = torch.device(device)
    if dev.type == "cuda":
        expected = f"cuda:{ranks.local_rank}"
        if str(dev) != expected:
            raise ValueError(
                f"device '{device}' does not match local rank {ranks.local_rank}: use '{expected}'"
            )
        torch.cuda.set_device(ranks.local_rank)
        backend = "nccl"
    elif dev.type == "cpu":
        backend = "gloo"
    else:
        raise ValueError(f"distributed training supports cpu and cuda devices, not '{device}'")
    if not torch.distributed.is_initialized():
        torch.distributed.init_process_group(backend=backend, rank=ranks.global_rank, world_size=world_size)
    return ranks


def pool_rank_gradients(alg: Any, weight: float) -> None:
    """Weigh this rank's gradients by ``weight`` (its share of the worlds x the number of ranks)
    before rsl-rl averages them, so the update is the one of all ranks' samples pooled in one batch.

    rsl-rl averages the ranks' mini-batch gradients with equal weights, and each rank normalises
    its advantages over its own batch: a rank of 4 soft worlds beside one of 96 rigid worlds then
    steered half of every update with 1/25 of the samples. Measured over iterations 20-60 of two
    such runs: training s_lift 0.20-0.26 with equal weights, 0.30-0.39 pooled (docs/design.md,
    Fine-tuning the residual; both below the rule). With equal worlds on every rank the weight
    is 1 and nothing changes.
    """
    if weight == 1.0:
        return
    reduce = alg.reduce_parameters
    modules = [alg.actor, alg.critic] + ([alg.rnd] if alg.rnd else [])

    def weighted_reduce() -> None:
        for module in modules:
            for param in module.parameters():
                if param.grad is not None:
                    param.grad.mul_(weight)
        reduce()

    alg.reduce_parameters = weighted_reduce


def sum_over_ranks(value: float, ranks: Ranks, device: str) -> float:
    """``value`` summed over all ranks (itself on one)."""
    if not ranks.distributed:
        return value
    total = torch.tensor([float(value)], device=device)
    torch.distributed.all_reduce(total, op=torch.distributed.ReduceOp.SUM)
    return float(total.item())


def agree_to_stop(local: bool, ranks: Ranks, device: str) -> bool:
    """All ranks stop together (a rank leaving early would hang the others' all-reduce)."""
    if not ranks.distributed:
        return local
    flag = torch.tensor([1.0 if local else 0.0], device=device)
    torch.distributed.all_reduce(flag, op=torch.distributed.ReduceOp.MAX)
    return bool(flag.item() > 0)
