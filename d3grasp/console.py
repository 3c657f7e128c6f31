"""What the console commands print: progress, results and errors by default; library chatter
(Warp's start-up banner and per-module load times, rsl-rl's model printout) behind ``--verbose``.

Warp 1.19 decides what it prints by ``wp.config.log_level`` (its old ``wp.config.quiet`` flag is
gone: setting it does nothing); rsl-rl prints its networks with ``print`` while a runner is built,
which :func:`library_output` turns into debug records of the ``d3grasp`` logger.
"""

from __future__ import annotations

import contextlib
import io
import logging
import os
import sys
from collections.abc import Iterator

LOGGER = logging.getLogger("d3grasp")

__all__ = ["LOGGER", "library_output", "quiet_warp", "set_verbosity"]

# Warp's native library prints this (to the process's stderr, from C) at start-up on every machine
# without a CUDA driver: on a CPU run it says nothing a user needs.
_NO_CUDA_DRIVER_LINE = "Warp CUDA warning: Could not find or load the NVIDIA CUDA driver"


def quiet_warp() -> None:
    """Warp prints warnings and errors only (no banner, no module-load lines, no 'no CUDA driver'
    line on a machine without one); call it before Warp's first use."""
    import warp as wp

    wp.config.log_level = max(wp.config.log_level, wp.LOG_WARNING)
    _init_warp_without_driver_line()


def _init_warp_without_driver_line() -> None:
    """``wp.init()`` with the native stderr caught, passed on less the no-CUDA-driver line."""
    import tempfile

    import warp as wp

    sys.stderr.flush()
    saved = os.dup(2)
    with tempfile.TemporaryFile(mode="w+b") as caught:
        os.dup2(caught.fileno(), 2)
        try:
            wp.init()
        finally:
            os.dup2(saved, 2)
            os.close(saved)
        caught.seek(0)
        text = caught.read().decode(errors="replace")
    kept = [ln for ln in text.splitlines() if not ln.startswith(_NO_CUDA_DRIVER_LINE)]
    if kept:
        print("\n".join(kept), file=sys.stderr)


def set_verbosity(verbose: bool) -> None:
    """Set up a console command's output: ``verbose`` shows what Warp and rsl-rl report."""
    import warp as wp

    if verbose:
        wp.config.log_level = min(wp.config.log_level, wp.LOG_INFO)
    else:
        quiet_warp()
    if not LOGGER.handlers:
        handler = logging.StreamHandler()
        handler.setFormatter(logging.Formatter("%(message)s"))
        LOGGER.addHandler(handler)
    LOGGER.setLevel(logging.DEBUG if verbose else logging.INFO)


@contextlib.contextmanager
def library_output(what: str) -> Iterator[None]:
    """Catch what a library prints to stdout inside the block and log it at debug level."""
    buf = io.StringIO()
    try:
        with contextlib.redirect_stdout(buf):
            yield
    finally:
        text = buf.getvalue().rstrip()
        if text:
            LOGGER.debug("%s:\n%s", what, text)
