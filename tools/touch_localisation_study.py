"""Study: does what the hand senses when the rule's lift starts tell where the camera was wrong?

Under camera perception (the paper's protocol) the rule closes the hand on a grasp placed at the
camera's estimate of the object. A student that corrects the palm from touch can only do so if its
observation at that time carries the estimate's error. This study measures that directly, without
training anything: for every rigid object of a split, at ``--rounds`` object placements each, it
records at the step the lift starts (the rule's own timeline, touch-timed) what a student sees of
the grasp (the finger joints, the three-axis force of each pad from the object, the step each pad
first felt the object, the grasp type) and the camera's centre error (true centre minus estimate)
in the planned palm's frame. A ridge regression fitted on the train split's objects then predicts
the error of the test split's objects; its R^2 per palm axis (1 = touch locates the object, 0 = no
better than the mean) bounds what any policy reading these signals at the lift can correct. A second
fit reads the deviation of the same signals from the oracle's at the same placement (the rule on the
true pose): what a grasp whose planned contact signature is stored could compare against.

    python tools/touch_localisation_study.py --out /tmp/touch_loc --rounds 4   # ~10 min on 2 cores

Records already in ``--out`` are kept (a second call only fits).

Writes ``OUT/<split>_<perception>.npz`` (the records) and prints the table;
docs/studies/touch_localisation.md reports a run.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np


def collect(
    split: str, rounds: int, seed: int, batch: int, limit: int | None = None, perception: str = "camera"
) -> dict[str, np.ndarray]:
    """Records of every rigid object of ``split`` (its first ``limit``), ``rounds`` placements each, the
    rule under ``perception``. The placements do not depend on it (the camera draws from its own
    stream), so a camera record and an oracle record of the same row share the object's pose."""
    import torch

    from d3grasp.envs import make_env
    from d3grasp.envs.config import BaselineConfig
    from d3grasp.eval.evaluate import select_objects
    from d3grasp.geometry import quat_xyzw_to_matrix

    # A pad "first felt the object" above the force at which the rule stops a joint on it.
    touch_force = BaselineConfig().force_threshold

    _, entries = select_objects("diverse", split)
    ids = [e.id for e in entries][:limit]
    rows: dict[str, list[np.ndarray]] = {k: [] for k in ("q", "force", "first", "grasp", "error", "obj")}
    start = time.time()
    for b0 in range(0, len(ids), batch):
        chunk = tuple(ids[b0 : b0 + batch])
        env = make_env(
            num_envs=len(chunk), seed=seed + b0, eval_mode=True, objects={"ids": chunk}, perception=perception
        )
        W = env.num_envs
        zero = torch.zeros(W, env.num_actions)
        g0 = env.script.phase_start["grasp"]
        for r in range(rounds):
            if r:
                env.reset_worlds(torch.arange(W))
            error = env.grasp.centre_correction.double().numpy().copy()
            rot = np.stack([quat_xyzw_to_matrix(q) for q in env.grasp.palm_quat.double().numpy()])
            error_palm = np.einsum("wji,wj->wi", rot, error)  # R^T e: the error in the palm's frame
            first = np.full((W, env.view.pad_force_object.shape[1]), -1.0)
            done = np.zeros(W, dtype=bool)
            rec = {k: np.zeros((W,) + s) for k, s in (("q", (16,)), ("force", (11, 3)))}
            grasp = env.grasp.type_id.numpy().copy()
            for _ in range(env.script.phase_start["lift"] + 2):
                env.step(zero)
                t = env.episode_length_buf.numpy()
                force = env.view.pad_force_object.double().numpy()
                touching = np.linalg.norm(force, axis=-1) > touch_force
                newly = touching & (first < 0) & (t[:, None] > g0)
                first[newly] = np.broadcast_to(((t - g0) / 60.0)[:, None], first.shape)[newly]
                now = ~done & (t >= env.scoring.now.lift_start.numpy())
                if now.any():
                    q = env.view.joint_q[env.index.finger_q].view(W, -1).double().numpy()
                    rec["q"][now], rec["force"][now] = q[now], force[now]
                    done |= now
                if done.all():
                    break
            rows["q"].append(rec["q"])
            rows["force"].append(rec["force"])
            rows["first"].append(first)
            rows["grasp"].append(grasp)
            rows["error"].append(error_palm)
            rows["obj"].append(np.array(chunk))
        env.close()
        n = min(b0 + batch, len(ids))
        print(f"  {split}, {perception}: {n}/{len(ids)} objects, {time.time() - start:.0f} s", flush=True)
    return {k: np.concatenate(v) for k, v in rows.items()}


def features(d: dict[str, np.ndarray], reference: dict[str, np.ndarray] | None = None) -> np.ndarray:
    """What a student reads at the lift: joints, pad forces, first-touch times (never: 1.5 s), grasp
    type; with ``reference`` (the oracle's records of the same placements) the touch's deviation from
    the reference's, i.e. from the signature the grasp leaves when it is placed right."""

    def touch(r: dict[str, np.ndarray]) -> np.ndarray:
        first = np.where(r["first"] < 0, 1.5, r["first"])
        return np.concatenate([r["q"], r["force"].reshape(len(r["q"]), -1), first], axis=1)

    x = touch(d) if reference is None else touch(d) - touch(reference)
    return np.concatenate([x, np.eye(3)[d["grasp"].astype(int)]], axis=1)


def ridge_r2(
    xa: np.ndarray,
    ya: np.ndarray,
    objects: np.ndarray,
    xb: np.ndarray,
    yb: np.ndarray,
    alphas: tuple[float, ...] = (0.1, 1, 10, 100, 1000),
) -> list[tuple[float, float, float]]:
    """Per column of ``ya``: the ridge alpha chosen by 5-fold cross-validation over the train rows'
    ``objects`` (an object's rows in one fold), its cross-validated R^2 and the R^2 on the test rows
    ``xb``, ``yb`` (against the train mean: a model that knows nothing scores <= 0)."""
    mu, sd = xa.mean(0), xa.std(0) + 1e-9
    xa1 = np.c_[(xa - mu) / sd, np.ones(len(xa))]
    xb1 = np.c_[(xb - mu) / sd, np.ones(len(xb))]
    names = np.unique(objects)
    fold_of = {o: i % 5 for i, o in enumerate(np.random.default_rng(0).permutation(names))}
    folds = np.array([fold_of[o] for o in objects])

    def fit(x: np.ndarray, y: np.ndarray, a: float) -> np.ndarray:
        reg = a * np.eye(x.shape[1])
        reg[-1, -1] = 0.0  # no penalty on the intercept
        return np.linalg.solve(x.T @ x + reg, x.T @ y)

    out = []
    for axis in range(ya.shape[1]):
        y, yt = ya[:, axis], yb[:, axis]
        cv = []
        for a in alphas:
            sse = 0.0
            for k in range(5):
                m = folds == k
                sse += float(((xa1[m] @ fit(xa1[~m], y[~m], a) - y[m]) ** 2).sum())
            cv.append(sse)
        best = int(np.argmin(cv))
        pred = xb1 @ fit(xa1, y, alphas[best])
        r2 = 1.0 - ((pred - yt) ** 2).sum() / ((yt - y.mean()) ** 2).sum()
        out.append((alphas[best], 1.0 - cv[best] / ((y - y.mean()) ** 2).sum(), float(r2)))
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", required=True)
    p.add_argument("--rounds", type=int, default=2, help="placements per object (default 2)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--batch", type=int, default=16, help="worlds per environment (default 16)")
    p.add_argument("--limit", type=int, default=None, help="the first N objects of each split (a quick look)")
    args = p.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    data = {}
    for split in ("train", "test"):
        for perception in ("camera", "oracle"):
            path = out / f"{split}_{perception}.npz"
            if not path.is_file():  # what a stopped study already wrote is kept
                rec = collect(split, args.rounds, args.seed, args.batch, args.limit, perception)
                np.savez(path, **rec)
            data[split, perception] = dict(np.load(path))
    train, test = data["train", "camera"], data["test", "camera"]
    print(f"episodes: train {len(train['q'])}, test {len(test['q'])} (rigid objects, camera)")
    print(
        "centre error in the palm frame, std train / test (mm): "
        + ", ".join(
            f"{ax} {1e3 * train['error'][:, i].std():.1f} / {1e3 * test['error'][:, i].std():.1f}"
            for i, ax in enumerate("xyz")
        )
    )
    print(
        "| the model reads at the lift | R^2 x / y / z, CV on train objects | R^2 x / y / z, test objects |"
    )
    print("|---|---|---|")
    for label, ref_a, ref_b in (
        ("touch and joints", None, None),
        (
            "their deviation from the oracle's at the same placement",
            data["train", "oracle"],
            data["test", "oracle"],
        ),
    ):
        fits = ridge_r2(
            features(train, ref_a), train["error"], train["obj"], features(test, ref_b), test["error"]
        )
        cv = " / ".join(f"{f[1]:+.2f}" for f in fits)
        r2 = " / ".join(f"{f[2]:+.2f}" for f in fits)
        print(f"| {label} | {cv} | {r2} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
