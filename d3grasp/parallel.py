"""Independent units of work over processes: the evaluation's batches and the grasp planner's object
groups.

Warp's CPU backend runs a process's kernels on one thread, so a long command uses a machine's cores
only through processes. Every unit builds its own environment from its own arguments, so a unit's
result does not depend on which process ran it or on how many ran: ``workers=N`` returns what
``workers=1`` returns. Processes are spawned (not forked: Warp and torch hold threads and device
state that a fork would copy half-made).
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from typing import Any

__all__ = ["default_workers", "run_units"]


def default_workers() -> int:
    """The cores this process may run on (the affinity mask where the OS has one)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # macOS, Windows
        return max(1, os.cpu_count() or 1)


def _init_worker() -> None:
    # One torch thread per process: the processes already fill the cores. Warp quiet: one banner per
    # process would bury the parent's progress bar.
    import torch

    from d3grasp.console import quiet_warp

    torch.set_num_threads(1)
    quiet_warp()


def run_units(
    fn: Callable[..., Any],
    units: Sequence[tuple[Any, ...]],
    workers: int,
    on_result: Callable[[int, Any], None],
) -> None:
    """Call ``fn(*units[k])`` for every k and ``on_result(k, result)`` in this process as each finishes.

    ``workers <= 1`` (or a single unit) runs them here, in order; otherwise in ``workers`` spawned
    processes, in the order they finish. ``fn`` must be a module-level function and the units
    picklable. An exception in a unit is raised here.
    """
    if workers <= 1 or len(units) <= 1:
        for k, args in enumerate(units):
            on_result(k, fn(*args))
        return
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor, as_completed

    with ProcessPoolExecutor(
        max_workers=min(workers, len(units)), mp_context=mp.get_context("spawn"), initializer=_init_worker
    ) as pool:
        futures = {pool.submit(fn, *args): k for k, args in enumerate(units)}
        for fut in as_completed(futures):
            on_result(futures[fut], fut.result())
