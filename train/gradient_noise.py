"""How many episodes an update needs before its policy gradient agrees with itself, measured.

    python -m d3grasp.train.gradient_noise --checkpoint RUN/model_50.pt --rollouts 5 \\
        [the d3grasp-train flags the run was trained with: --task, --set, --rank_num_envs ...]

The training diagnostic ``Diagnostics/grad_cosine_split_half`` is the cosine between the policy-loss
gradients of two halves of an update's worlds. It answers "is there a signal?" for one batch size.
This command answers "how large a batch would show it?": it loads a checkpoint, collects
``--rollouts`` whole-episode rollouts at its parameters (sampled actions, as in training; nothing is
updated, not even the normalisers), takes every world's own policy-loss gradient
(``D3GraspPPO.world_gradients``) and reads, from their Gram matrix, the figures below. A row is one
world's rollout of one episode length: about one episode (episodes that end early make it a little
more; the recipe's 52 worlds finish 52-66 episodes a rollout). "Episodes" in the report count rows.
Rows of one world in consecutive rollouts, and rows of one rollout (advantages normalised together),
are not quite independent, so the statistics below are close to, not exactly, unbiased.

- the per-episode signal-to-noise ratio ``r = |mu|^2 / sigma^2``: ``mu`` the mean of the per-episode
  gradients (``|mu|^2`` estimated without bias: ``(|sum g|^2 - sum |g|^2) / (N (N - 1))``) and
  ``sigma^2`` their summed variance over all parameters;
- the split-half cosine it predicts for two halves of ``n`` episodes each: the sums' inner product
  over their norms has expectation ``n^2 |mu|^2`` over ``n^2 |mu|^2 + n sigma^2``, i.e. about
  ``n r / (1 + n r)``; and the episodes per update a target cosine ``c`` needs, ``2 c / ((1 - c) r)``;
- the cosine measured on random disjoint halves of ``n`` of the collected episodes, for the same ``n``
  (the prediction checked against the data it came from);
- the same ratio for each of the actor's parameter tensors alone (the LSTM's weights, the output
  layer's bias = the action mean's offset, the action std, ...): where a signal is, if anywhere. The
  whole gradient's ratio is a noise-weighted mix of these, so a signal in a few parameters is diluted
  by the noise of all the others.

An interval on ``r`` comes from resampling the episodes (bootstrap). With several ranks every rank
collects its own worlds and the rows are pooled. Rank 0 prints the tables and writes ``--out`` (JSON)
and the Gram matrices beside it (``<out>.grams.pt``), to read other splits without collecting again.
"""

from __future__ import annotations

import json
import math
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch

__all__ = [
    "episodes_for_cosine",
    "expected_split_cosine",
    "gram_statistics",
    "main",
    "split_cosines",
]


def gram_statistics(gram: torch.Tensor, weights: torch.Tensor | None = None) -> dict[str, float]:
    """Signal and noise of N per-episode gradients from their Gram matrix ``gram[i, j] = g_i . g_j``.

    ``weights`` (N,) counts how often each episode is drawn (a bootstrap resample); None: once each.
    Returns ``episodes`` (N), ``mean_sq`` (|mu|^2 from the products of different episodes: unbiased for
    independent rows), ``noise`` (their summed variance sigma^2, unbiased without weights) and ``snr``
    (mean_sq / noise; may be negative when |mu|^2 is below its own estimation noise).
    """
    gram = gram.to(torch.float64)
    w = torch.ones(gram.shape[0], dtype=torch.float64) if weights is None else weights.to(torch.float64)
    n = float(w.sum())
    diag = torch.diagonal(gram)
    pairs = n * n - float((w * w).sum())  # ordered pairs of two different episodes
    if pairs <= 0:
        raise ValueError("need at least 2 different episodes")
    sum_sq = float(w @ gram @ w)  # |sum g|^2
    # An episode's product with itself (or a bootstrap copy of itself) is no evidence of agreement:
    # |mu|^2 from the products of different episodes only.
    mean_sq = (sum_sq - float((w * w * diag).sum())) / pairs
    noise = (float((w * diag).sum()) - sum_sq / n) / (n - 1.0)
    return {
        "episodes": n,
        "mean_sq": mean_sq,
        "noise": noise,
        "snr": mean_sq / noise if noise > 0 else math.nan,
    }


def expected_split_cosine(snr: float, n: float) -> float:
    """The split-half cosine of two halves of ``n`` episodes each at a per-episode signal-to-noise
    ratio ``snr``: ``n r / (1 + n r)`` (module docstring; 0 when r <= 0)."""
    nr = n * max(snr, 0.0)
    return nr / (1.0 + nr)


def episodes_for_cosine(snr: float, cosine: float) -> float:
    """Episodes per update (both halves) whose expected split-half cosine is ``cosine``:
    ``2 c / ((1 - c) r)``; infinite when r <= 0."""
    if not 0.0 < cosine < 1.0:
        raise ValueError(f"cosine must be in (0, 1), got {cosine}")
    if snr <= 0.0:
        return math.inf
    return 2.0 * cosine / ((1.0 - cosine) * snr)


def split_cosines(gram: torch.Tensor, n: int, draws: int, generator: torch.Generator) -> torch.Tensor:
    """Cosines between the summed gradients of two random disjoint sets of ``n`` episodes, ``draws``
    times: ``1_A' G 1_B / sqrt(1_A' G 1_A 1_B' G 1_B)``."""
    total = gram.shape[0]
    if 2 * n > total:
        raise ValueError(f"two halves of {n} need {2 * n} episodes, have {total}")
    gram = gram.to(torch.float64)
    out = torch.empty(draws, dtype=torch.float64)
    for k in range(draws):
        order = torch.randperm(total, generator=generator)
        a = torch.zeros(total, dtype=torch.float64)
        b = torch.zeros(total, dtype=torch.float64)
        a[order[:n]] = 1.0
        b[order[n : 2 * n]] = 1.0
        out[k] = (a @ gram @ b) / torch.sqrt((a @ gram @ a) * (b @ gram @ b))
    return out


def snr_interval(gram: torch.Tensor, boot: int, generator: torch.Generator) -> tuple[float, float]:
    """95% interval of the signal-to-noise ratio over ``boot`` resamples of the episodes."""
    total = gram.shape[0]
    values = []
    for _ in range(boot):
        counts = torch.bincount(torch.randint(total, (total,), generator=generator), minlength=total)
        if int((counts > 0).sum()) < 2:  # one episode drawn N times: no pair to compare
            values.append(math.nan)
            continue
        values.append(gram_statistics(gram, counts)["snr"])
    q = torch.tensor([0.025, 0.975], dtype=torch.float64)
    lo, hi = torch.tensor(values, dtype=torch.float64).nanquantile(q).tolist()
    return lo, hi


def report(
    gram: torch.Tensor,
    sizes: Sequence[int],
    draws: int = 200,
    boot: int = 1000,
    seed: int = 0,
    tensor_grams: dict[str, torch.Tensor] | None = None,
) -> dict:
    """Everything the command prints, from the Gram matrix: the signal-to-noise ratio with a 95%
    bootstrap interval, the episodes per update for cosines 0.1 and 0.3, and for each half size the
    predicted and measured split-half cosine (median and quartiles of ``draws`` random splits).
    ``tensor_grams``: the Gram matrices of single parameter tensors, each reported the same way
    (its ratio, interval and the episodes cosines of 0.1 and 0.3 need): where a signal is, if anywhere."""
    g = torch.Generator().manual_seed(seed)
    stats = gram_statistics(gram)
    whole = _ratio_summary(gram, stats["snr"], boot, g)  # before the splits: the generator's order
    total = gram.shape[0]
    rows = []
    for n in sizes:
        if 2 * n > total:
            continue
        cos = split_cosines(gram, n, draws, g)
        q1, med, q3 = cos.quantile(torch.tensor([0.25, 0.5, 0.75], dtype=torch.float64)).tolist()
        rows.append(
            {
                "half": n,
                "predicted": expected_split_cosine(stats["snr"], n),
                "measured_median": med,
                "measured_q1": q1,
                "measured_q3": q3,
            }
        )
    by_tensor = {}
    for name, tg in (tensor_grams or {}).items():
        snr = gram_statistics(tg)["snr"]
        by_tensor[name] = {"snr": snr, **_ratio_summary(tg, snr, boot, g)}
    return {**stats, **whole, "splits": rows, "by_tensor": by_tensor}


def _ratio_summary(gram: torch.Tensor, snr: float, boot: int, g: torch.Generator) -> dict[str, Any]:
    """The bootstrap interval of ``snr`` (the ratio of ``gram``'s rows) and the episodes per update
    cosines of 0.1 and 0.3 need, with the interval's bounds."""
    lo, hi = snr_interval(gram, boot, g)
    return {
        "snr_interval": [lo, hi],
        "episodes_for_cosine": {
            str(c): {
                "estimate": episodes_for_cosine(snr, c),
                # a higher r needs fewer episodes: the interval's ends swap
                "interval": [episodes_for_cosine(hi, c), episodes_for_cosine(lo, c)],
            }
            for c in (0.1, 0.3)
        },
    }


def format_report(rep: dict) -> str:
    lo, hi = rep["snr_interval"]
    lines = [
        f"episodes {int(rep['episodes'])}  |mu|^2 {rep['mean_sq']:.3e}  sigma^2 {rep['noise']:.3e}",
        f"per-episode signal-to-noise r {rep['snr']:+.2e} (95% bootstrap [{lo:+.2e}, {hi:+.2e}])",
    ]
    for c, e in rep["episodes_for_cosine"].items():
        a, b = e["interval"]
        lines.append(
            f"episodes per update for a split-half cosine of {c}: {e['estimate']:.0f} [{a:.0f}, {b:.0f}]"
        )
    lines.append("| episodes a half | predicted cosine | measured median [quartiles] |")
    lines.append("|---|---|---|")
    for r in rep["splits"]:
        lines.append(
            f"| {r['half']} | {r['predicted']:+.3f} | {r['measured_median']:+.3f} "
            f"[{r['measured_q1']:+.3f}, {r['measured_q3']:+.3f}] |"
        )
    if rep.get("by_tensor"):
        lines.append("| parameter tensor | r | 95% interval | episodes per update for 0.3 |")
        lines.append("|---|---|---|---|")
        for name, t in rep["by_tensor"].items():
            a, b = t["snr_interval"]
            need = t["episodes_for_cosine"]["0.3"]["estimate"]
            lines.append(f"| {name} | {t['snr']:+.2e} | [{a:+.2e}, {b:+.2e}] | {need:.0f} |")
    return "\n".join(lines)


def _finite(value: Any) -> Any:
    """``value`` with infinite or NaN floats as None (strict JSON has neither)."""
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_finite(v) for v in value]
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def _gather_rows(rows: torch.Tensor, distributed: bool) -> torch.Tensor:
    """Every rank's per-world gradient rows, pooled (ranks may hold different numbers of worlds)."""
    if not distributed:
        return rows.cpu()  # the statistics run on the CPU, whatever device the rollouts ran on
    parts: list[Any] = [None] * torch.distributed.get_world_size()
    torch.distributed.all_gather_object(parts, rows.cpu())
    return torch.cat(parts)


def main(argv: Sequence[str] | None = None) -> int:
    from d3grasp.train.cli_args import make_train_parser
    from d3grasp.train.train import run_training

    from d3grasp.cli.args import positive_int, run_command

    argv = list(sys.argv[1:] if argv is None else argv)
    parser = make_train_parser()
    parser.prog = "python -m d3grasp.train.gradient_noise"
    parser.add_argument(
        "--rollouts", type=positive_int, default=5, help="whole-episode rollouts to collect (default 5)"
    )
    parser.add_argument(
        "--halves",
        type=positive_int,
        nargs="+",
        default=[8, 16, 32, 64, 128],
        help="episodes a half to split into",
    )
    parser.add_argument("--out", type=Path, default=None, help="write the report here (JSON)")
    args = parser.parse_args(argv)
    if not args.checkpoint:
        parser.error("--checkpoint is required: the parameters to measure the gradient at")
    args.resume = True

    def probe(runner: Any) -> None:
        rank0 = runner.gpu_global_rank == 0  # 0 without distribution too

        def progress(k: int) -> None:
            if rank0:
                print(f"[gradient_noise] rollout {k}/{args.rollouts}", flush=True)

        runner.episode_stats.clear()
        rows = _gather_rows(runner.probe_world_gradients(args.rollouts, progress), runner.is_distributed)
        runner.episode_stats.all_reduce()  # every rank takes part
        if not rank0:
            return
        # What the sampled actions achieved (exploration on, the task's randomisation).
        outcomes = {
            k.removeprefix("Success/").removesuffix("/all"): v
            for k, v in runner.episode_stats.rates().items()
            if k.endswith("/all") or k == "Success/episodes"
        }
        rows = rows.to(torch.float64)
        tensor_grams, start = {}, 0
        for name, param in runner.alg.actor.named_parameters():  # the rows' order (world_gradients)
            part = rows[:, start : start + param.numel()]
            tensor_grams[name] = part @ part.T
            start += param.numel()
        gram = sum(tensor_grams.values())  # the whole rows' products are the tensors' summed
        rep = report(gram, args.halves, tensor_grams=tensor_grams)
        rep["checkpoint"] = str(args.checkpoint)
        rep["rollouts"] = args.rollouts
        rep["parameters"] = int(rows.shape[1])
        rep["outcomes"] = outcomes
        print(" ".join(f"{k} {v:.3g}" for k, v in outcomes.items()))
        print(format_report(rep))
        if args.out is not None:
            args.out.parent.mkdir(parents=True, exist_ok=True)
            args.out.write_text(json.dumps(_finite(rep), indent=1), encoding="utf-8")
            # The Gram matrices, to read other splits later without collecting again.
            torch.save({"all": gram, **tensor_grams}, args.out.with_suffix(".grams.pt"))
            print(f"[gradient_noise] wrote {args.out}")

    def body() -> None:
        run_training(args, ["gradient_noise", *argv], work=probe)

    return run_command("gradient_noise", body)


if __name__ == "__main__":
    raise SystemExit(main())
