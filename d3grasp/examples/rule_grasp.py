"""The rule-based controller grasping test objects in four worlds, each world's pads printed.

    python -m d3grasp.examples.rule_grasp [--worlds 4] [--seed 0] [--every 60]

The environment runs the rule inside (the residual task): the policy's zero action is the rule, so
stepping with zeros plays the baseline. Every ``--every`` control steps (60 Hz) it prints each
world's phase, the object's height and the normal force each finger's pads read from the object;
at the end, every world's scored episode.
"""

from __future__ import annotations

import argparse
from typing import Any

import torch

import d3grasp
from d3grasp.console import quiet_warp
from d3grasp.dexhand13 import FINGERS, PAD_NAMES
from d3grasp.vocabulary import PHASES


def finger_forces(pad_force: torch.Tensor) -> dict[str, float]:
    """Normal force (N) on each finger's pads of one world, from its (11, 3) pad forces in the pads'
    frames (the pad's normal is its local z, kernels/tactile.py)."""
    normal = pad_force[:, 2].abs()
    return {f: float(sum(normal[i] for i, n in enumerate(PAD_NAMES) if f"_{f}_" in n)) for f in FINGERS}


def run(worlds: int = 4, seed: int = 0, every: int = 60, log: Any = print) -> list[dict[str, Any]]:
    """Play one episode in ``worlds`` worlds of the Diverse task's test objects; returns each
    world's episode as the environment scores it, with ``hold_rise_cm`` and ``hold_pad_n`` (the
    object's rise and the pads' summed normal force at the last step of the hold phase)."""
    quiet_warp()
    env = d3grasp.make_env(
        "D3Grasp-DexHand13-Diverse-v0", num_envs=worlds, seed=seed, objects={"split": "test"}
    )
    names = [e.id for e in env.world_entries]
    zero = torch.zeros(worlds, env.num_actions)
    episodes: list[dict[str, Any]] = []
    start_z = env.object_state()[0][:, 2].clone()
    hold: dict[int, tuple[float, float]] = {}
    try:
        for t in range(env.max_episode_length):
            _, _, _, extras = env.step(zero)
            episodes += extras.get("episodes", [])
            phase = env.phase_of(env.episode_length_buf)
            rise = (env.object_state()[0][:, 2] - start_z) * 100.0
            for w in torch.nonzero(phase == PHASES.index("hold")).flatten().tolist():
                hold[w] = (float(rise[w]), sum(finger_forces(env.view.pad_force_object[w]).values()))
            if t % every == 0:
                for w in range(worlds):
                    pads = finger_forces(env.view.pad_force_object[w])
                    forces = "  ".join(f"{f} {n:5.2f}" for f, n in pads.items())
                    log(
                        f"step {t:3d}  world {w} {names[w]:16s} {PHASES[int(phase[w])]:8s} "
                        f"rise {float(rise[w]):5.1f} cm  pads (N): {forces}"
                    )
            if len(episodes) >= worlds:
                break
    finally:
        env.close()
    for ep in episodes:
        ep["hold_rise_cm"], ep["hold_pad_n"] = hold.get(int(ep["env"]), (float("nan"), float("nan")))
        lifted, held = ep["s_lift"], ep["s_disturb"]
        log(f"{ep['object']:16s} {ep['grasp_type']:5s} lifted {lifted!s:5s} held {held!s:5s} {ep['failure']}")
    return episodes


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--worlds", type=int, default=4, help="worlds (objects) side by side")
    ap.add_argument("--seed", type=int, default=0, help="the environment's seed (objects, poses)")
    ap.add_argument("--every", type=int, default=60, help="print every N control steps")
    args = ap.parse_args(argv)
    run(args.worlds, args.seed, args.every)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
