"""Soak test: many environment steps of random actions on mixed rigid and soft worlds.

``python -m d3grasp.bench soak --steps 1000000 --state soak.json`` steps the default task with
uniform random actions in [-1, 1] (the policy's whole action box, at the widest residual
authority, ``SOAK_ACTION_AUTHORITY``, so the fingers do far more than the rule-based grasp would),
resets worlds as their episodes end, and every ``--rebuild_every``
env-steps builds the worlds anew with another draw of objects from the whole library (both
splits), the way training resamples them. A quarter of the worlds hold soft objects by default,
the share the training runs use (``--soft_fraction``; a soft world costs ~8x a rigid one). It
counts:

- env-steps (one world advanced by one control step) and episodes ended, by how they ended;
- non-finite worlds: the environment resets a world whose state stops being finite and counts it
  (``GraspEnv.nonfinite_resets``); the soak adds those up;
- non-finite observations or rewards returned to the caller (after the reset: should be 0);
- crashes: exceptions out of ``step``; the soak records the error, rebuilds and goes on;
- the process's peak resident memory after each build, and its resident memory after each
  segment's environment is closed: a leak across rebuilds climbs in the second, while the first, a
  lifetime maximum, also climbs with every draw that needs more memory than any before it.

Progress is saved to ``--state`` (JSON, written atomically) after every build segment, and
``--resume`` continues from it, so a soak of 10^6 env-steps can span several sessions. Segment
``k`` draws its objects and actions from seed ``seed + k``: a resumed soak runs the same segments
as an uninterrupted one.
"""

from __future__ import annotations

import json
import math
import os
import resource
import time
import traceback
from collections import Counter
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from d3grasp.files import atomic_write_text

__all__ = ["SoakReport", "run_soak"]


@dataclass
class SoakReport:
    """What a soak did so far; also the content of its state file."""

    task: str
    num_envs: int
    seed: int
    rebuild_every: int
    soft_fraction: float
    overrides: dict[str, Any] = field(default_factory=dict)
    env_steps: int = 0
    segments: int = 0  # build segments completed
    episodes: int = 0
    endings: dict[str, int] = field(default_factory=dict)  # failure reason or "held through the pushes"
    nonfinite_worlds: int = 0
    nonfinite_objects: dict[str, int] = field(default_factory=dict)  # object id -> non-finite episodes
    nonfinite_returned: int = 0  # env-steps whose observation or reward reached the caller non-finite
    crashes: list[str] = field(default_factory=list)  # "segment k, step s: <error>"
    peak_rss_mb: list[float] = field(default_factory=list)  # after each build
    rss_after_close_mb: list[float] = field(default_factory=list)  # after each segment's env is closed
    wall_s: float = 0.0

    def summary(self) -> str:
        rate = self.env_steps / self.wall_s if self.wall_s > 0 else math.nan
        endings = ", ".join(f"{k} {v}" for k, v in sorted(self.endings.items(), key=lambda kv: -kv[1]))
        rss, closed = self.peak_rss_mb, self.rss_after_close_mb
        return "\n".join(
            [
                f"soak: {self.task}, {self.num_envs} worlds ({self.soft_fraction:.0%} soft), seed "
                f"{self.seed}, rebuilt every {self.rebuild_every} env-steps"
                + (f", overrides {self.overrides}" if self.overrides else ""),
                f"env-steps {self.env_steps}  segments {self.segments}  wall {self.wall_s:.0f} s "
                f"({rate:.1f} env-steps/s)",
                f"episodes ended {self.episodes}: {endings or '-'}",
                f"non-finite worlds reset {self.nonfinite_worlds}  non-finite returned "
                f"{self.nonfinite_returned}  crashes {len(self.crashes)}",
                "non-finite by object: "
                + (", ".join(f"{k} {v}" for k, v in sorted(self.nonfinite_objects.items())) or "-"),
                f"peak RSS after builds: first {rss[0]:.0f} MB, last {rss[-1]:.0f} MB" if rss else "",
                f"RSS after closing: first {closed[0]:.0f} MB, largest {max(closed):.0f} MB, last "
                f"{closed[-1]:.0f} MB"
                if closed
                else "",
                *(f"crash: {c}" for c in self.crashes[:10]),
            ]
        ).rstrip()


def _save(report: SoakReport, path: Path) -> None:
    atomic_write_text(path, json.dumps(asdict(report), indent=1) + "\n")


def _load(path: Path, expect: dict[str, Any]) -> SoakReport:
    try:
        doc = json.loads(path.read_text())
        report = SoakReport(**doc)
    except (OSError, ValueError, TypeError) as exc:
        raise ValueError(f"{path}: not a soak state file ({exc})") from None
    for key, value in expect.items():
        if getattr(report, key) != value:
            raise ValueError(
                f"{path}: soak state has {key}={getattr(report, key)!r}, this run {value!r}: resume "
                "with the same settings or start a new state file"
            )
    return report


def _peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux reports KiB


def _rss_mb() -> float:
    """The process's resident memory now (MB; NaN where /proc is absent)."""
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20
    except (OSError, ValueError, IndexError):
        return math.nan


# The widest finger authority the residual action modes offer (0.4 rad, integrated, from t = 0), not the
# task's default (0.1 rad, low-pass, from the grasp on): random actions should stress the contacts as
# far as any policy could, as they did when the soak figures in docs/performance.md were measured.
SOAK_ACTION_AUTHORITY: dict[str, Any] = {
    "residual_scale": 0.4,
    "residual_rate": 0.08,
    "residual_start": "approach",
}


def _settings(
    steps: int,
    task: str,
    num_envs: int,
    seed: int,
    rebuild_every: int,
    soft_fraction: float,
    overrides: dict[str, Any] | None,
) -> dict[str, Any]:
    """Check the soak's arguments; the settings a report records (a resumed soak must match them)."""
    if steps < 1 or num_envs < 1 or rebuild_every < num_envs:
        raise ValueError("--steps and --num_envs must be positive and --rebuild_every >= --num_envs")
    if not 0.0 <= soft_fraction <= 1.0:
        raise ValueError(f"--soft_fraction must be in [0, 1], got {soft_fraction}")
    return {
        "task": task,
        "num_envs": num_envs,
        "seed": seed,
        "rebuild_every": rebuild_every,
        "soft_fraction": soft_fraction,
        "overrides": {**SOAK_ACTION_AUTHORITY, **(overrides or {})},
    }


def _initial_report(settings: dict[str, Any], state_path: Path | None, resume: bool) -> SoakReport:
    """The report a soak starts from: the state file's when resuming, else a fresh one."""
    if resume:
        if state_path is None or not state_path.exists():
            raise ValueError("--resume needs an existing --state file")
        return _load(state_path, settings)
    return SoakReport(**settings)


def run_soak(
    steps: int,
    *,
    task: str | None = None,
    num_envs: int = 16,
    seed: int = 0,
    rebuild_every: int = 20_000,
    soft_fraction: float = 0.25,
    overrides: dict[str, Any] | None = None,
    state: str | os.PathLike[str] | None = None,
    resume: bool = False,
    device: str = "cpu",
    progress: bool = True,
) -> SoakReport:
    """Step ``steps`` env-steps of random actions (see the module docstring) and report."""
    import numpy as np
    import torch

    from d3grasp.console import quiet_warp
    from d3grasp.envs import DEFAULT_TASK, close_env, make_env
    from d3grasp.envs.mdp.terminations import episode_ending

    quiet_warp()

    task = task or DEFAULT_TASK
    settings = _settings(steps, task, num_envs, seed, rebuild_every, soft_fraction, overrides)
    state_path = Path(state) if state else None
    report = _initial_report(settings, state_path, resume)
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=steps, initial=min(report.env_steps, steps), unit="env-step", desc="soak")
    endings = Counter(report.endings)
    blown = Counter(report.nonfinite_objects)
    control_steps = rebuild_every // num_envs
    while report.env_steps < steps:
        k = report.segments
        t0 = time.perf_counter()
        env = make_env(
            task,
            num_envs=num_envs,
            device=device,
            seed=seed + k,
            objects={"split": "all", "soft_fraction": soft_fraction},
            **settings["overrides"],
        )
        report.peak_rss_mb.append(round(_peak_rss_mb(), 1))
        rng = np.random.default_rng(seed + k)
        done_steps = 0
        try:
            for s in range(min(control_steps, -(-(steps - report.env_steps) // num_envs))):
                action = torch.as_tensor(
                    rng.uniform(-1.0, 1.0, (num_envs, env.num_actions)), dtype=torch.float32
                )
                try:
                    obs, rew, _, extras = env.step(action)
                except Exception as exc:  # a crash is a finding: record it, rebuild, go on
                    report.crashes.append(f"segment {k}, step {s}: {type(exc).__name__}: {exc}")
                    traceback.print_exc()
                    break
                done_steps += 1
                finite = torch.isfinite(rew) & torch.stack(
                    [torch.isfinite(v.reshape(num_envs, -1)).all(-1) for v in obs.values()]
                ).all(0)
                report.nonfinite_returned += int((~finite).sum())
                for ep in extras.get("episodes", ()):
                    endings[episode_ending(ep)] += 1
                    if ep.get("failure") == "non-finite state":
                        blown[ep["object"]] += 1
                if bar is not None:
                    bar.update(num_envs)
        finally:
            report.nonfinite_worlds += env.nonfinite_resets  # a fresh env counts from 0
            close_env(env)  # frees the worlds at once (GraspEnv.close)
            report.rss_after_close_mb.append(round(_rss_mb(), 1))
        report.env_steps += done_steps * num_envs
        report.episodes = sum(endings.values())
        report.endings = dict(endings)
        report.nonfinite_objects = dict(blown)
        report.segments += 1
        report.wall_s += time.perf_counter() - t0
        if state_path is not None:
            _save(report, state_path)
    if bar is not None:
        bar.close()
    return report
