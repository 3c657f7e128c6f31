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
import signal
import threading
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from typing import Any

__all__ = ["default_workers", "run_units"]


def default_workers() -> int:
    """The cores this process may run on (the affinity mask where the OS has one)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # macOS, Windows
        return max(1, os.cpu_count() or 1)


def _exit_with_parent() -> None:
    """Block until the parent process has gone, then end this one at once.

    A worker that outlives its parent (killed, or stopped by a signal no handler saw) would finish
    its unit for nobody and then wait on the task queue for ever, holding a core: the queue's
    write end lives in the workers too, so they never see it close.
    """
    import multiprocessing as mp

    parent = mp.parent_process()
    if parent is not None:
        parent.join()  # returns when the parent's sentinel closes, i.e. the parent has exited
        os._exit(1)


def _init_worker() -> None:
    # One torch thread per process: the processes already fill the cores. Warp quiet: one banner per
    # process would bury the parent's progress bar.
    import torch

    from d3grasp.console import quiet_warp

    threading.Thread(target=_exit_with_parent, name="exit-with-parent", daemon=True).start()
    torch.set_num_threads(1)
    quiet_warp()


@contextmanager
def _sigterm_as_interrupt() -> Iterator[None]:
    """SIGTERM raises KeyboardInterrupt here, as Ctrl-C does, so the caller's clean-up runs.

    Python's default for SIGTERM ends the process without unwinding, so the pool's workers were
    left behind. Signal handlers can only be set from the main thread; elsewhere this does nothing.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def interrupt(signum: int, frame: Any) -> None:
        raise KeyboardInterrupt(signal.Signals(signum).name)

    previous = signal.signal(signal.SIGTERM, interrupt)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


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

    with (
        _sigterm_as_interrupt(),
        ProcessPoolExecutor(
            max_workers=min(workers, len(units)), mp_context=mp.get_context("spawn"), initializer=_init_worker
        ) as pool,
    ):
        futures = {pool.submit(fn, *args): k for k, args in enumerate(units)}
        try:
            for fut in as_completed(futures):
                on_result(futures[fut], fut.result())
        except BaseException:
            # Ctrl-C, SIGTERM or a failed unit: stop the rest now. Leaving the block would otherwise
            # wait for every running unit to finish (minutes of simulation). Python 3.11's executor
            # has no public way to stop its workers (3.14 adds terminate_workers()).
            procs = list((getattr(pool, "_processes", None) or {}).values())  # shutdown() drops the map
            pool.shutdown(wait=False, cancel_futures=True)
            for proc in procs:
                proc.terminate()
            raise
