"""Worker processes of d3grasp.parallel end with their parent: SIGTERM to the parent stops them, and
a parent killed outright (no handler runs) leaves none behind."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from d3grasp.parallel import run_units

pytestmark = pytest.mark.skipif(sys.platform != "linux", reason="signals and /proc as on Linux")


def sleeping_unit(pid_dir: str, seconds: float) -> int:
    """A unit that says which process runs it, then outlasts any test."""
    Path(pid_dir, str(os.getpid())).touch()
    time.sleep(seconds)
    return os.getpid()


def double(x: int) -> int:
    return 2 * x


def alive(pid: int) -> bool:
    """True while ``pid`` runs (a zombie, dead but not yet reaped, counts as gone)."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (FileNotFoundError, IndexError):
        return False
    return state != "Z"


def kill_left(pids: list[int]) -> None:
    """A failed test leaves no sleeping workers behind."""
    for p in pids:
        if alive(p):
            os.kill(p, signal.SIGKILL)


def wait_until(cond, timeout: float) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if cond():
            return True
        time.sleep(0.2)
    return cond()


def start_parent(pid_dir: Path) -> subprocess.Popen:
    """A parent process running two sleeping units on two workers, and the workers' pids once both started."""
    script = textwrap.dedent(
        f"""
        import sys
        sys.path.insert(0, {str(Path(__file__).parent)!r})
        from test_parallel import sleeping_unit
        from d3grasp.parallel import run_units
        run_units(sleeping_unit, [({str(pid_dir)!r}, 600.0)] * 2, 2, lambda k, r: None)
        """
    )
    return subprocess.Popen([sys.executable, "-c", script], stderr=subprocess.PIPE, text=True)


def worker_pids(parent: subprocess.Popen, pid_dir: Path) -> list[int]:
    started = wait_until(lambda: len(list(pid_dir.iterdir())) == 2 or parent.poll() is not None, 120)
    assert started and parent.poll() is None, (
        f"workers did not start: {parent.stderr.read() if parent.stderr else ''}"
    )
    return [int(p.name) for p in pid_dir.iterdir()]


def test_results_in_process_and_in_workers_agree():
    got: dict[str, dict[int, int]] = {"one": {}, "two": {}}
    units = [(x,) for x in range(5)]
    run_units(double, units, 1, lambda k, r: got["one"].__setitem__(k, r))
    run_units(double, units, 2, lambda k, r: got["two"].__setitem__(k, r))
    assert got["one"] == got["two"] == {k: 2 * k for k in range(5)}


def test_sigterm_to_the_parent_stops_its_workers(tmp_path):
    parent = start_parent(tmp_path)
    pids = worker_pids(parent, tmp_path)
    parent.send_signal(signal.SIGTERM)
    parent.wait(timeout=30)
    try:
        assert parent.returncode != 0
        assert wait_until(lambda: not any(alive(p) for p in pids), 15), "workers outlived a SIGTERM'd parent"
    finally:
        kill_left(pids)


def test_workers_exit_when_the_parent_is_killed(tmp_path):
    parent = start_parent(tmp_path)
    pids = worker_pids(parent, tmp_path)
    parent.kill()  # SIGKILL: no handler in the parent runs
    parent.wait(timeout=30)
    try:
        assert wait_until(lambda: not any(alive(p) for p in pids), 15), "workers outlived a killed parent"
    finally:
        kill_left(pids)
