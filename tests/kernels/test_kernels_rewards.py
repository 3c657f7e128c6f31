"""Reward terms against a NumPy transcription of the equations, on random batches, plus gradients."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp
from d3grasp.kernels.rewards import (
    TERM_NAMES,
    RewardBuffers,
    RewardConfig,
    compute_rewards,
    compute_rewards_numpy,
    make_inputs,
)

wp.config.log_level = wp.LOG_WARNING

W, J, L, P, K = 7, 16, 16, 11, 12


def random_batch(rng: np.random.Generator) -> dict[str, np.ndarray]:
    pad_force = rng.normal(size=(W, P, 3)) * rng.uniform(0.0, 8.0, size=(W, P, 1))
    pad_force[0] = 0.0  # a world without contact
    pad_force[1, 2] = [0.0, 0.0, 30.0]  # beyond the permitted maximum
    pad_force[2, 8:] = 0.0  # thumb off (either thumb_pads choice below): maximal imbalance
    env = rng.uniform(-0.002, 0.03, size=(W, K))
    env[3, 0] = 1e-6  # below the floor
    return dict(
        alive=rng.integers(0, 2, W).astype(float),
        joint_q=rng.uniform(0, 1.5, (W, J)),
        joint_q_ref=rng.uniform(0, 1.5, (W, J)),
        joint_qd=rng.normal(size=(W, J)) * 3,
        link_pos=rng.normal(size=(W, L, 3)) * 0.1,
        object_com=rng.normal(size=(W, 3)) * 0.1,
        pad_force=pad_force,
        pad_contact=(np.linalg.norm(pad_force, axis=-1) > 0.5).astype(float),
        obj_lin_vel=rng.normal(size=(W, 3)),
        obj_ang_vel=rng.normal(size=(W, 3)),
        env_dist=env,
        eps_bar=rng.uniform(0, 0.3, W),
        node_count=rng.integers(50, 600, W).astype(float),
        is_deformable=np.array([1, 0, 1, 1, 0, 1, 0]),
        object_rise=np.array([-0.01, 0.0, 0.03, 0.1, 0.25, 0.07, 0.0]),
    )


def ref_terms(c: RewardConfig, b: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The module docstring's equations, term by term, in float64."""
    kw = np.full(L, c.distance) if c.distance_link_weights is None else np.asarray(c.distance_link_weights)
    f = np.linalg.norm(b["pad_force"], axis=-1)
    thumb = np.zeros(P, bool)
    thumb[list(c.thumb_pads)] = True
    ft, fo = f[:, thumb].sum(1), f[:, ~thumb].sum(1)
    tot = ft + fo
    sym = np.where(tot > c.symmetry_min_force, -c.symmetry * np.abs(ft - fo) / np.where(tot > 0, tot, 1), 0.0)
    d = np.clip(b["env_dist"], None, c.safe_distance)
    d = np.maximum(d, c.distance_floor)
    out = {
        "generic": c.alive * b["alive"]
        - c.joint_pos * np.sum((b["joint_q"] - b["joint_q_ref"]) ** 2, 1)
        - c.joint_vel * np.sum(b["joint_qd"] ** 2, 1),
        "distance": -np.sum(kw * np.sum((b["link_pos"] - b["object_com"][:, None]) ** 2, -1), 1),
        "contact": np.sum(
            b["pad_contact"] * c.contact_gain * f - c.contact_penalty * np.maximum(f - c.max_force, 0), 1
        ),
        "symmetry": sym,
        "stability": -c.stability_lin * np.sum(b["obj_lin_vel"] ** 2, 1)
        - c.stability_ang * np.sum(b["obj_ang_vel"] ** 2, 1),
        "collision": c.collision * np.sum(np.log(d / c.safe_distance), 1),
        "deform": np.where(b["is_deformable"] != 0, -c.deform * b["node_count"] * b["eps_bar"], 0.0),
        "lift": c.lift * np.minimum(np.maximum(b["object_rise"] / c.lift_height, 0.0), 1.0),
    }
    out["total"] = sum(out[n] for n in TERM_NAMES)
    return out


@pytest.mark.parametrize(
    "cfg",
    [
        RewardConfig(),
        RewardConfig(
            alive=0.5,
            joint_pos=0.2,
            joint_vel=0.01,
            distance_link_weights=tuple(np.linspace(0.5, 2.0, L)),
            contact_gain=0.3,
            contact_penalty=1.0,
            max_force=4.0,
            symmetry=2.0,
            thumb_pads=(8, 9, 10),
            stability_lin=3.0,
            stability_ang=0.2,
            collision=0.7,
            safe_distance=0.02,
            distance_floor=1e-3,
            deform=0.01,
            lift=2.0,
            lift_height=0.05,
        ),
    ],
)
def test_every_term_matches_numpy(cfg: RewardConfig) -> None:
    rng = np.random.default_rng(30)
    for _ in range(3):
        batch = random_batch(rng)
        got = compute_rewards_numpy(cfg, **batch)
        ref = ref_terms(cfg, batch)
        for name in (*TERM_NAMES, "total"):
            np.testing.assert_allclose(got[name], ref[name], rtol=2e-5, atol=2e-5, err_msg=name)
        assert got["symmetry"][0] == 0.0 and got["symmetry"][2] == pytest.approx(-cfg.symmetry)
        assert np.all(got["deform"][batch["is_deformable"] == 0] == 0.0)
        assert np.all(got["collision"] <= 0.0)
        # Lift saturates at the lift height and is 0 for a sunk object (world 0).
        assert got["lift"][0] == 0.0 and got["lift"][4] == pytest.approx(cfg.lift)


def test_reward_gradients_with_tape() -> None:
    """d total / d q = -2 k_j (q - q_ref) exactly; d total / d pad forces vs central differences."""
    cfg = RewardConfig()
    rng = np.random.default_rng(31)
    batch = random_batch(rng)
    batch["pad_force"][0] = rng.normal(size=(P, 3))  # keep every pad away from |f| = 0 (a kink)
    inp = make_inputs(requires_grad=True, **batch)
    out = RewardBuffers.allocate(cfg, W, L, P, requires_grad=True)
    tape = wp.Tape()
    with tape:
        compute_rewards(inp, out)
    tape.backward(grads={out.total: wp.ones(W, dtype=float)})
    np.testing.assert_allclose(
        inp.joint_q.grad.numpy(),
        -2 * cfg.joint_pos * (batch["joint_q"] - batch["joint_q_ref"]),
        rtol=1e-4,
        atol=1e-6,
    )
    np.testing.assert_allclose(
        inp.joint_qd.grad.numpy(), -2 * cfg.joint_vel * batch["joint_qd"], rtol=1e-4, atol=1e-7
    )

    grad = inp.pad_force.grad.numpy()
    h = 1e-5
    fd = np.zeros_like(batch["pad_force"])
    for w in range(W):
        for k in range(P):
            if np.linalg.norm(batch["pad_force"][w, k]) < 1e-3:
                continue
            for a in range(3):
                plus = {**batch, "pad_force": batch["pad_force"].copy()}
                minus = {**batch, "pad_force": batch["pad_force"].copy()}
                plus["pad_force"][w, k, a] += h
                minus["pad_force"][w, k, a] -= h
                fd[w, k, a] = (ref_terms(cfg, plus)["total"][w] - ref_terms(cfg, minus)["total"][w]) / (2 * h)
    assert np.abs(fd).max() > 0.1
    np.testing.assert_allclose(grad, fd, atol=2e-4, rtol=1e-3)


def test_config_validation() -> None:
    with pytest.raises(ValueError, match="contact_gain"):
        RewardConfig(contact_gain=-1.0)
    with pytest.raises(ValueError, match="distance_link_weights"):
        RewardConfig(distance_link_weights=(1.0, 2.0)).link_weights(L)
    with pytest.raises(ValueError, match="missing reward inputs"):
        make_inputs(alive=np.ones(2))


def test_each_coefficient_is_declared_once_and_reaches_the_kernels() -> None:
    """RewardConfig's float fields are the coefficients: each is refused below zero and carried to the
    kernels' parameter struct under its own name (the distance weight per link instead)."""
    import dataclasses

    from d3grasp.kernels import rewards as rk

    floats = [f.name for f in dataclasses.fields(RewardConfig) if f.type in (float, "float")]
    assert "alive" in floats and "lift_height" in floats and "thumb_pads" not in floats
    cfg = RewardConfig(**{name: 0.5 + k for k, name in enumerate(floats) if name != "distance_floor"})
    prm = rk._params(cfg)
    for name in floats:
        if name != "distance":
            assert getattr(prm, name) == pytest.approx(getattr(cfg, name)), name
        with pytest.raises(ValueError, match=name):
            RewardConfig(**{name: -1.0})
    np.testing.assert_allclose(cfg.link_weights(3), [cfg.distance] * 3)
