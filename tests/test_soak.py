"""The soak command: counts add up across segments, a resumed soak continues its state file."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from d3grasp.soak import run_soak


def test_soak_counts_segments_and_resumes(tmp_path: Path) -> None:
    state = tmp_path / "soak.json"
    kw = {"num_envs": 2, "rebuild_every": 4, "soft_fraction": 0.5, "state": state, "progress": False}
    first = run_soak(8, **kw)
    # 8 env-steps at 2 worlds, rebuilt every 4: two builds of two control steps each.
    assert (first.env_steps, first.segments, len(first.peak_rss_mb)) == (8, 2, 2)
    assert len(first.rss_after_close_mb) == 2 and "RSS after closing: first" in first.summary()
    assert first.crashes == [] and first.nonfinite_returned == 0
    saved = json.loads(state.read_text())
    assert saved["env_steps"] == 8 and saved["soft_fraction"] == 0.5
    resumed = run_soak(12, resume=True, **kw)
    assert (resumed.env_steps, resumed.segments) == (12, 3)
    assert "env-steps 12  segments 3" in resumed.summary()
    with pytest.raises(ValueError, match="num_envs=2"):
        run_soak(16, resume=True, **{**kw, "num_envs": 4})
    with pytest.raises(ValueError, match="--resume needs an existing --state"):
        run_soak(16, resume=True, **{**kw, "state": tmp_path / "missing.json"})
