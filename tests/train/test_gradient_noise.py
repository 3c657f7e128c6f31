"""The gradient-noise measurement (d3grasp.train.gradient_noise) against hand-worked cases and
draws of known signal and noise.

Signal and noise of two and three vectors worked by hand (a bootstrap copy of an episode adds no
agreement); the predicted split-half cosine and episodes per update from their formulas and each
other; on Gaussian "gradients" of known mean and variance the estimated signal-to-noise ratio and the
measured split-half cosines against n r / (1 + n r). The per-world gradient rows the command collects
are checked in test_ppo_diagnostics.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from d3grasp.train.gradient_noise import (
    _finite,
    episodes_for_cosine,
    expected_split_cosine,
    gram_statistics,
    report,
    split_cosines,
)


def _gram(rows: list[list[float]]) -> torch.Tensor:
    g = torch.tensor(rows, dtype=torch.float64)
    return g @ g.T


def test_signal_and_noise_of_two_vectors_by_hand() -> None:
    # g1 = (1, 0), g2 = (1, 2): mean (1, 1); |mu|^2 from the one cross product g1 . g2 = 1;
    # deviations (0, -1) and (0, 1): summed variance (1 + 1) / (2 - 1) = 2; r = 0.5.
    s = gram_statistics(_gram([[1.0, 0.0], [1.0, 2.0]]))
    assert s["episodes"] == 2
    assert s["mean_sq"] == pytest.approx(1.0)
    assert s["noise"] == pytest.approx(2.0)
    assert s["snr"] == pytest.approx(0.5)


def test_a_bootstrap_copy_adds_no_agreement() -> None:
    # Drawn (2, 1, 0) times: the pairs of different episodes are (1, 2) and (2, 1) twice each, so
    # |mu|^2 is g1 . g2 = 3 whatever g1 . g1 and g3 are.
    gram = _gram([[1.0, 1.0], [2.0, 1.0], [-5.0, 7.0]])
    s = gram_statistics(gram, torch.tensor([2.0, 1.0, 0.0]))
    assert s["mean_sq"] == pytest.approx(3.0)
    # Summed variance with weights: mean (4, 3) / 3; deviations (-1/3, 0) twice and (2/3, 0): 2/3 / 2
    assert s["noise"] == pytest.approx((2 * (1 / 9) + 4 / 9) / 2)
    with pytest.raises(ValueError):
        gram_statistics(gram, torch.tensor([3.0, 0.0, 0.0]))  # one episode drawn three times


def test_predicted_cosine_and_episodes_invert_each_other() -> None:
    assert expected_split_cosine(0.01, 100) == pytest.approx(0.5)  # n r = 1
    assert expected_split_cosine(-0.01, 100) == 0.0
    assert episodes_for_cosine(0.01, 0.3) == pytest.approx(2 * 0.3 / (0.7 * 0.01))
    assert expected_split_cosine(0.002, episodes_for_cosine(0.002, 0.3) / 2) == pytest.approx(0.3)
    assert math.isinf(episodes_for_cosine(0.0, 0.3))
    with pytest.raises(ValueError):
        episodes_for_cosine(0.01, 1.0)
    # The report is written as strict JSON: no Infinity or NaN.
    assert _finite({"a": [math.inf, 1.0], "b": math.nan, "c": "x"}) == {"a": [None, 1.0], "b": None, "c": "x"}


def test_known_signal_and_noise_are_recovered() -> None:
    """Gradients mu + noise in 400 dimensions, |mu|^2 = 4 and sigma^2 = 400 (r = 0.01): the
    estimate within 35% and the measured split cosines within 0.08 of n r / (1 + n r)."""
    rng = np.random.default_rng(7)
    d, n_ep = 400, 800
    mu = np.zeros(d)
    mu[:4] = 1.0
    g = torch.as_tensor(mu + rng.normal(size=(n_ep, d)))
    gram = g @ g.T
    s = gram_statistics(gram)
    assert s["noise"] == pytest.approx(400.0, rel=0.05)
    assert s["snr"] == pytest.approx(0.01, rel=0.35)
    gen = torch.Generator().manual_seed(0)
    for n in (50, 200, 400):
        median = float(split_cosines(gram, n, 100, gen).median())
        assert median == pytest.approx(expected_split_cosine(0.01, n), abs=0.08)
    # The signal lives in the first 4 dimensions: there r = 4 / 4 = 1; the other 396 are noise only.
    head, tail = g[:, :4], g[:, 4:]
    rep = report(
        gram, [50, 500], draws=20, boot=50, tensor_grams={"head": head @ head.T, "tail": tail @ tail.T}
    )
    assert [r["half"] for r in rep["splits"]] == [50]  # two halves of 500 need 1000 episodes
    lo, hi = rep["snr_interval"]
    assert lo < 0.01 < hi
    assert rep["by_tensor"]["head"]["snr"] == pytest.approx(1.0, rel=0.25)
    t_lo, t_hi = rep["by_tensor"]["tail"]["snr_interval"]
    assert t_lo < 0.0 < t_hi
