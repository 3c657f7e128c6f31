"""Training curves and milestones from TensorBoard event files, checked against hand-worked values."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("tensorboard")

from d3grasp.train import curves  # noqa: E402


def _write_run(run: Path, lift: list[float], episodes: list[int], with_progress: bool = True) -> None:
    from torch.utils.tensorboard import SummaryWriter

    writer = SummaryWriter(str(run))
    for it, (rate, n) in enumerate(zip(lift, episodes, strict=True)):
        writer.add_scalar("Success/s_lift/all", rate, it)
        writer.add_scalar("Success/episodes", n, it)
        writer.add_scalar("Train/mean_reward", 10.0 * it, it)
        writer.add_scalar("Reward/lift", rate, it)
        if with_progress:
            writer.add_scalar("Progress/env_steps", 2400 * (it + 1), it)
            writer.add_scalar("Progress/wall_clock_s", 30.0 * (it + 1), it)
    writer.close()


def test_milestones_from_the_episode_weighted_average(tmp_path: Path) -> None:
    # Window 2: the average of the last two batches weighted by their episodes.
    # it 0: 0.25 (4 ep) -> 0.25; it 1: 0.75 (1 ep) -> (1.0 + 0.75) / 5 = 0.35;
    # it 2: 0.5 (4 ep) -> (0.75 + 2.0) / 5 = 0.55; it 3: 0.875 (6 ep) -> (2.0 + 5.25) / 10 = 0.725;
    # it 4: 1.0 (10 ep) -> (5.25 + 10) / 16 = 0.953125. (An unweighted average would pass 0.5 at it 1.)
    _write_run(tmp_path / "run", [0.25, 0.75, 0.5, 0.875, 1.0], [4, 1, 4, 6, 10])
    s = curves.load_scalars(tmp_path / "run")
    it, v = curves.smoothed_success(s, "s_lift", window=2)
    np.testing.assert_allclose(v, [0.25, 0.35, 0.55, 0.725, 0.953125], rtol=1e-6)

    rows = curves.milestones(s, rates=(0.5, 0.7, 0.99), baselines={"s_lift": 0.6}, window=2)
    lift = {m.label: m for m in rows if m.metric == "s_lift"}
    assert [lift[k].iteration for k in ("above the baseline's 60.0%", "50%", "70%", "99%")] == [3, 2, 3, None]
    assert lift["50%"].env_steps == 7200 and lift["50%"].wall_clock_s == pytest.approx(90.0)
    assert lift["70%"].env_steps == 9600
    # Metrics that were never logged are reported as not reached.
    assert all(m.iteration is None for m in rows if m.metric != "s_lift")
    table = curves.milestones_markdown(rows)
    assert "| s_lift | 70% | 3 | 9,600 | 2.0 |" in table and "| s_lift | 99% | not reached | | |" in table


def test_cli_writes_the_figure_and_prints_the_milestones(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    _write_run(tmp_path / "old", [0.6, 0.7], [2, 2], with_progress=False)
    out = tmp_path / "curves.png"
    assert curves.main([str(tmp_path / "old"), "--out", str(out), "--baseline", "s_lift=0.5"]) == 0
    printed = capsys.readouterr().out
    assert out.is_file() and out.stat().st_size > 10_000
    # A run from before the progress scalars: iterations, and env-steps and wall-clock not logged.
    assert "| s_lift | above the baseline's 50.0% | 0 | not logged | not logged |" in printed
    assert curves.main([str(tmp_path / "missing")]) == 2
    with pytest.raises(SystemExit):
        curves.main([str(tmp_path / "old"), "--baseline", "s_hold=0.5"])
