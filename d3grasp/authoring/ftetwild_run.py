"""One fTetWild run in a process of its own: ``python ftetwild_run.py DIR`` reads ``DIR/in.npz`` and
writes ``DIR/out.npz`` (see :func:`d3grasp.authoring.tetmesh.tetrahedralize`).

fTetWild crashes outright on some inputs and settings: a segmentation fault or a glibc "double free"
abort on a 12 x 2 x 0.4 cm bar at an ideal edge of 0.03 bounding-box diagonals and an envelope of
0.01 (measured, pytetwild 0.4.2). In the importing process that would take the whole import down,
so each run happens here and a crash is one failed attempt. Run as a script (not ``-m``), it needs
NumPy and the compiled binding only, not d3grasp on the child's path, and starts in ~0.2 s.
"""

from __future__ import annotations

import importlib.machinery
import importlib.util
import sys
from pathlib import Path

import numpy as np


def run(scratch: Path) -> None:
    args = np.load(scratch / "in.npz")
    name = "pytetwild.PyfTetWildWrapper"
    loader = importlib.machinery.ExtensionFileLoader(name, str(args["library"]))
    spec = importlib.util.spec_from_loader(name, loader)
    assert spec is not None
    ftw = importlib.util.module_from_spec(spec)
    loader.exec_module(ftw)
    # fTetWild writes its working surface (``__tracked_surface.stl``) into the current directory: the
    # parent starts this process in ``scratch``, so an import leaves nothing in the user's folder.
    v, t = ftw.tetrahedralize_mesh(
        np.ascontiguousarray(args["vertices"], dtype=np.float64),
        np.ascontiguousarray(args["faces"], dtype=np.uint32),
        True,  # optimize: improve element quality
        False,  # skip_simplify: let fTetWild simplify within the envelope
        float(args["edge_length_r"]),
        0.0,  # edge_length_abs: use the relative length
        float(args["epsilon"]),
        10.0,  # stop_energy (AMIPS), fTetWild's default
        True,  # coarsen: fewest tets at the requested quality
        1,  # num_threads: the machines this runs on are shared
        80,  # num_opt_iter
        6,  # loglevel: quiet
        True,  # quiet
        False,  # vtk_ordering
        False,  # disable_filtering: drop the exterior of the background mesh
        np.empty((0, 3), dtype=np.float64),
        np.empty((0, 4), dtype=np.int32),
        np.empty(0, dtype=np.float64),
    )
    np.savez(scratch / "out.npz", points=np.asarray(v, dtype=np.float64), tets=np.asarray(t, dtype=np.int64))


if __name__ == "__main__":
    run(Path(sys.argv[1]))
