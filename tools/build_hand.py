"""Author the DexHand13 USD from the kinematic spec: ``python tools/build_hand.py [--out PATH]``.

Writes ``assets_usd/hands/dexhand13.usda`` by default. The output is deterministic, so re-running
it on an unchanged spec leaves the committed file unchanged. ``build`` is also what
``d3grasp-assets build`` calls.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from d3grasp.authoring.hand_spec import HandPhysics, load_spec
from d3grasp.authoring.hand_usd import write_hand_usd

REPO = Path(__file__).resolve().parents[1]
DEFAULT_OUT = REPO / "assets_usd" / "hands" / "dexhand13.usda"
DEFAULT_SPEC = REPO / "tools" / "specs" / "dexhand13_kinematics.json"


def build(out_path: Path = DEFAULT_OUT, spec_path: Path = DEFAULT_SPEC) -> Path:
    """Write the hand USD to ``out_path`` from the spec at ``spec_path``; returns the written path."""
    return write_hand_usd(Path(out_path), load_spec(spec_path), HandPhysics())


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT, help="output .usda path")
    parser.add_argument("--spec", type=Path, default=DEFAULT_SPEC, help="kinematic spec JSON")
    args = parser.parse_args(argv)
    try:
        path = build(args.out, args.spec)
    except (FileNotFoundError, ValueError) as exc:
        print(f"build_hand: {exc}", file=sys.stderr)
        return 1
    physics = HandPhysics()
    print(f"wrote {path} (hand mass {physics.total_mass():.3f} kg, 16 finger joints, 11 pads, 6-DoF root)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
