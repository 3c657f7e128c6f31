"""The console commands' shared argument types and error contract (``d3grasp-eval``,
``d3grasp-play``, ``d3grasp-train``, ``python -m d3grasp.bench``)."""

from __future__ import annotations

import argparse
import json
import os
import sys
from collections.abc import Callable
from typing import Any

__all__ = [
    "add_env_override_arg",
    "non_negative_int",
    "parse_override",
    "positive_float",
    "positive_int",
    "resolve_torch_threads",
    "run_command",
]


def positive_int(value: str) -> int:
    """argparse type: an integer >= 1."""
    n = int(value)
    if n < 1:
        raise argparse.ArgumentTypeError(f"must be a positive integer, got {value}")
    return n


def non_negative_int(value: str) -> int:
    """argparse type: an integer >= 0."""
    n = int(value)
    if n < 0:
        raise argparse.ArgumentTypeError(f"must be a non-negative integer, got {value}")
    return n


def positive_float(value: str) -> float:
    """argparse type: a number > 0."""
    x = float(value)
    if not x > 0.0:
        raise argparse.ArgumentTypeError(f"must be > 0, got {value}")
    return x


def parse_override(text: str) -> tuple[str, Any]:
    """``"phases.disturb_per_direction=0.1"`` -> ``("phases__disturb_per_direction", 0.1)``.

    The value is read as JSON when it parses (numbers, true/false, lists), else kept as a string.
    """
    key, sep, raw = text.partition("=")
    if not sep or not key.strip():
        raise argparse.ArgumentTypeError(f"--set expects KEY=VALUE, got '{text}'")
    try:
        value: Any = json.loads(raw)
    except json.JSONDecodeError:
        value = raw
    if isinstance(value, list):
        value = tuple(value)  # config sequences are tuples
    return key.strip().replace(".", "__"), value


def add_env_override_arg(parser: argparse.ArgumentParser, help_text: str) -> None:
    """``--set KEY=VALUE`` (repeatable): environment config overrides, collected in ``args.overrides``."""
    parser.add_argument(
        "--set",
        dest="overrides",
        action="append",
        type=parse_override,
        default=[],
        metavar="KEY=VALUE",
        help=help_text,
    )


def add_trust_arg(parser: argparse.ArgumentParser) -> None:
    """``--trust-checkpoint``: read checkpoints that name code (``d3grasp.policies.checkpoint``)."""
    from d3grasp.policies.checkpoint import TRUST_FLAG

    parser.add_argument(
        TRUST_FLAG,
        dest="trust_checkpoint",
        action="store_true",
        help="read a checkpoint that pickles objects other than tensors and plain values (older "
        "files); unpickling them can run any code the file names: only for a file you trust",
    )


def resolve_torch_threads(requested: int | None) -> int:
    """Threads for this process: explicit, else 1.

    One thread per process is the default because the simulation of a rank is one CPU thread and
    the PPO update of these small networks gains little from more: measured on the 2-core machine
    with another job running, one process with 2 torch threads took 8.5 s per update at 32 worlds
    (OpenMP threads spinning against the busy core) against 0.5 s with 1 thread per rank.
    """
    return 1 if requested is None else requested


def run_command(prog: str, body: Callable[[], int | None], *, one_line: bool = False) -> int:
    """Run a command's body with the commands' shared error contract.

    A bad task, a checkpoint that does not fit, bad input or a missing file print
    ``<prog>: error: <reason>`` and exit 2 (``one_line`` folds a multi-line reason onto one line);
    Ctrl-C prints ``<prog>: aborted`` and exits 130 (SIGTERM during a multi-process run: ``aborted by
    SIGTERM``, its workers stopped); ``D3GRASP_DEBUG=1`` re-raises for a traceback.
    """
    from d3grasp.envs.registry import UnknownTaskError
    from d3grasp.policies.checkpoint import CheckpointError

    try:
        code = body()
    except (UnknownTaskError, CheckpointError, ValueError, FileNotFoundError) as exc:
        if os.getenv("D3GRASP_DEBUG"):
            raise
        reason = " ".join(str(exc).split()) if one_line else str(exc)
        print(f"{prog}: error: {reason}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as exc:  # Ctrl-C, or SIGTERM while workers run (d3grasp.parallel says which)
        print(f"{prog}: aborted" + (f" by {exc}" if str(exc) else ""), file=sys.stderr)
        return 130
    return 0 if code is None else code
