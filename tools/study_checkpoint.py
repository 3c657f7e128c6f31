"""Study tool: a checkpoint moved off the point its training left it at.

Where a policy sits at (or near) the best its action space offers, the policy gradient has little
mean to find, and the split-half cosine stays near 0 at any practical batch size. To check that the
estimator and its diagnostics do see a delayed outcome when there is one to see, move the policy off
that point: this adds ``--shift`` to the bias of the actor's output layer (the action mean, in the
environment's [-1, 1] units, for every action or the ``--actions`` listed), keeping everything else
(critic, normalisers, optimiser, iteration). In the synergy mode a negative shift opens every finger
by ``shift x residual_scale`` rad from the rule's touch-stopped targets, so the grasp squeezes less.
The checkpoint records the shift (``infos["shifted_action_mean"]``).

``--interface KEY=VALUE`` rewrites what the checkpoint says its actions mean (its policy interface,
e.g. ``decision_steps=60``), so the same weights can be measured or trained in a changed action space
(evaluation and training refuse a checkpoint whose interface differs from the environment's).

    python tools/study_checkpoint.py RUN/model_50.pt /tmp/shifted.pt --shift -0.6
    python tools/study_checkpoint.py RUN/model_50.pt /tmp/d60.pt --interface decision_steps=60

Then measure (python -m d3grasp.train.gradient_noise --checkpoint /tmp/shifted.pt ...) or train from it
(d3grasp-train --resume --checkpoint /tmp/shifted.pt ...). docs/studies/gradient_noise.md reports the
measurements.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

from d3grasp.cli.args import add_trust_arg, parse_override
from d3grasp.policies.checkpoint import atomic_torch_save, read_checkpoint


def output_bias_key(actor_state: dict[str, torch.Tensor], num_actions: int) -> str:
    """The state-dict key of the actor's action-mean bias: the last ``mlp.<i>.bias`` of size
    ``num_actions``."""
    keys = [
        k
        for k, v in actor_state.items()
        if k.startswith("mlp.") and k.endswith(".bias") and v.shape == (num_actions,)
    ]
    if not keys:
        raise ValueError(f"no output bias of {num_actions} actions in the actor")
    return max(keys, key=lambda k: int(k.split(".")[1]))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("checkpoint", type=Path)
    p.add_argument("out", type=Path)
    p.add_argument("--shift", type=float, default=0.0, help="added to the action mean ([-1, 1] units)")
    p.add_argument("--actions", type=int, nargs="*", default=None, help="action indices (default: all)")
    p.add_argument(
        "--interface",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="rewrite a policy-interface entry",
    )
    add_trust_arg(p)
    args = p.parse_args(argv)
    ckpt = read_checkpoint(args.checkpoint, trust=args.trust_checkpoint)
    actor = ckpt["actor_state_dict"]
    n = int(ckpt["infos"]["num_actions"])
    key = output_bias_key(actor, n)
    idx = list(range(n)) if args.actions is None else args.actions
    bad = [i for i in idx if not 0 <= i < n]
    if bad:
        p.error(f"--actions {bad} outside 0..{n - 1}")
    if args.shift:
        actor[key][idx] += args.shift
        ckpt["infos"]["shifted_action_mean"] = {
            "shift": args.shift,
            "actions": idx,
            "from": str(args.checkpoint),
        }
    interface = ckpt["infos"].get("policy_interface") or {}
    for item in args.interface:
        name, value = parse_override(item)  # the value read as --set reads it (JSON, else text)
        if name not in interface or isinstance(interface[name], dict):
            p.error(f"--interface {item}: not an entry of {sorted(interface)}")
        interface[name] = value
        ckpt["infos"].setdefault("rewritten_interface", {})[name] = interface[name]
    atomic_torch_save(ckpt, args.out)
    print(f"{args.out}: {key} {actor[key].tolist()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
