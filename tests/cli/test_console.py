"""Console output: quiet by default (no Warp banner, module loads or no-CUDA line); all with --verbose."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

SCRIPT = textwrap.dedent(
    """
    import sys
    from d3grasp.console import library_output, set_verbosity

    set_verbosity(sys.argv[1] == "verbose")
    import warp as wp

    @wp.kernel
    def double_it(a: wp.array(dtype=float)):
        i = wp.tid()
        a[i] = 2.0 * a[i]

    a = wp.ones(4, dtype=float, device="cpu")
    wp.launch(double_it, dim=4, inputs=[a], device="cpu")
    with library_output("a library"):
        print("Actor Model: MLP(...)")
    print("result", a.numpy().sum())
    """
)


def _run(script: Path, mode: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, str(script), mode], capture_output=True, text=True, timeout=600, check=True
    )


def test_quiet_by_default_and_everything_when_verbose(tmp_path: Path) -> None:
    script = tmp_path / "command.py"  # a file: Warp reads a kernel's source from it
    script.write_text(SCRIPT)
    quiet = _run(script, "quiet")
    assert quiet.stdout == "result 8.0\n"
    assert quiet.stderr == ""
    loud = _run(script, "verbose")
    assert "result 8.0" in loud.stdout
    assert "Warp 1.19" in loud.stdout and "Module " in loud.stdout  # banner and module-load line
    assert "a library:\nActor Model: MLP(...)" in loud.stderr  # the library's print, as a debug record
