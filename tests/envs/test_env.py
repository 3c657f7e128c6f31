"""The grasp environment: observation groups, stability, determinism, resets, baseline, disturbance."""

from __future__ import annotations

import pathlib
import re

import numpy as np
import pytest
import torch
import warp as wp
from d3grasp.kernels import strain as strain_k
from d3grasp.kernels.rewards import TERM_NAMES

from d3grasp.dexhand13 import NUM_PADS
from d3grasp.envs import make_env
from d3grasp.envs.baseline import RuleBasedController
from d3grasp.envs.mdp import rewards
from d3grasp.envs.registry import UnknownTaskError
from d3grasp.vocabulary import PHASES

RIGID_MEDIUM_BOX = "box_01"  # 9.5 x 3.4 x 6.6 cm, 140 g
SOFT_SPONGE = "sponge_block_m"


def _env(ids: tuple[str, ...], **kw):
    return make_env("D3Grasp-DexHand13-Mixed-v0", num_envs=len(ids), objects={"ids": ids}, **kw)


def _box_env(**kw):
    """One world with the medium box, seed 0, no randomisation (the deterministic single-object case)."""
    return _env((RIGID_MEDIUM_BOX,), seed=0, randomization__enabled=False, **kw)


@pytest.fixture(scope="module")
def mixed_env():
    return _env((RIGID_MEDIUM_BOX, SOFT_SPONGE), seed=3)


def test_unknown_task_lists_known_ones():
    with pytest.raises(UnknownTaskError, match="D3Grasp-DexHand13-Mixed-v0"):
        make_env("D3Grasp-Nope-v0")


def test_observation_groups_shapes_and_dtypes(mixed_env):
    env = mixed_env
    obs = env.get_observations()
    assert set(obs.keys()) == {"policy", "privileged"}
    k = env.cfg.obs.action_history
    # tactile 33 + contacts 11 + q 16 + qd 16 + history 16k + step 3 + grasp 3 + phase 6 + root cmd 7
    # touch 33 + 11, q, qd, k actions, clock 3, grasp type 3, phase, root command 7, the rule's targets 16
    # and the residual now applied 16 (residual and synergy modes; the default has 4 synergy actions)
    a = env.num_actions
    assert obs["policy"].shape == (2, 33 + 11 + 16 + 16 + a * k + 3 + 3 + len(PHASES) + 7 + 16 + 16)
    # object pos 3, quat 4, lin 3, ang 3, 17 link distances, eps, sigma, mass, friction, log E, 33 forces
    # object pose and velocities, 17 link distances, strain, sigma, mass, friction, log E, true pad
    # forces 33, the episode's draw 4, the push ahead 3
    assert obs["privileged"].shape == (2, 3 + 4 + 3 + 3 + 17 + 5 + 33 + 4 + 3)
    assert obs["policy"].dtype == torch.float32 and obs["privileged"].dtype == torch.float32
    assert env.num_actions == 4 and env.episode_length_buf.shape == (2,)


def test_random_actions_stay_finite(mixed_env):
    env = mixed_env
    gen = torch.Generator().manual_seed(0)
    for _ in range(env.max_episode_length + 10):
        obs, rew, done, extras = env.step(torch.rand(2, env.num_actions, generator=gen) * 2 - 1)
        assert torch.isfinite(obs["policy"]).all() and torch.isfinite(obs["privileged"]).all()
        assert torch.isfinite(rew).all()
        assert set(extras) >= {"time_outs", "log"}
    assert env.nonfinite_resets == 0
    # The steps span a whole training episode, so both worlds were reset once at least.


def test_same_seed_same_rollout():
    def rollout() -> torch.Tensor:
        env = _env((RIGID_MEDIUM_BOX,), seed=11)
        gen = torch.Generator().manual_seed(5)
        out = []
        for _ in range(40):
            obs, *_ = env.step(torch.rand(1, env.num_actions, generator=gen) * 2 - 1)
            out.append(obs["privileged"].clone())
        return torch.stack(out)

    a, b = rollout(), rollout()
    assert torch.equal(a, b)


def test_reset_restores_soft_body_to_rest(mixed_env):
    env = mixed_env
    soft_world = 1
    # Squeeze for a while, then reset only the soft world.
    for _ in range(80):
        env.step(torch.ones(2, env.num_actions))
    env.reset_worlds(torch.tensor([soft_world]))
    sensors = env.sensors
    strain_k.compute_strain(sensors.strain_layout, env.state_0.particle_q, sensors.strain_buf)
    eps = sensors.strain_buf.object_eps.numpy()
    assert abs(eps[sensors.world_soft_slot[soft_world]]) < 1e-4


def _run_baseline_episode(env, pushes: list | None = None) -> list[dict]:
    ctl = RuleBasedController(env)
    obs = env.get_observations()
    episodes = []
    for _ in range(env.max_episode_length):
        obs, _, _, extras = env.step(ctl.act(obs))
        episodes += extras.get("episodes", [])
        if pushes is not None:
            pushes.append(env.view.object_force.clone())
    return episodes


def _push_magnitudes(env, pushes: list) -> torch.Tensor:
    """|push| of world 0 over the disturbance phase (the step applying it is the one before)."""
    d0, d1 = env.script.phase_start["disturb"], env.script.phase_start["release"]
    return torch.stack(pushes)[d0 : d1 - 1, 0].norm(dim=-1)


def test_an_env_with_a_soft_object_runs_the_soft_iterations(mixed_env):
    assert mixed_env.physics.solver.iterations == mixed_env.cfg.sim.soft_iterations == 20
    rigid = _box_env()
    assert rigid.physics.solver.iterations == rigid.cfg.sim.iterations == 5


def test_baseline_lifts_a_medium_box_and_holds_it_under_disturbance():
    env = _box_env()
    pushes: list = []
    (ep,) = _run_baseline_episode(env, pushes)
    assert ep["object"] == RIGID_MEDIUM_BOX
    assert ep["s_lift"], ep
    assert ep["s_disturb"], ep
    # Held: pushed with the paper's 2.5 N throughout the six pushes.
    assert torch.allclose(_push_magnitudes(env, pushes), torch.tensor(2.5))


def test_open_hand_never_counts_as_a_lift():
    # Absolute actions: the open pose is then the hand's target throughout (in residual mode the rule
    # inside the env would close it).
    env = _box_env(action_mode="absolute")
    episodes, pushes = [], []
    for _ in range(env.max_episode_length):
        _, _, _, extras = env.step(env.act.open_action.expand(1, -1))
        episodes += extras.get("episodes", [])
        pushes.append(env.view.object_force.clone())
    assert len(episodes) == 1
    assert not episodes[0]["s_lift"] and not episodes[0]["s_disturb"]
    # Never lifted: nothing to test under a push, so no push (a free object pushed for 12 s flies off).
    assert float(_push_magnitudes(env, pushes).max()) == 0.0


def test_zero_residual_reproduces_the_rule_based_controller():
    """Residual and synergy modes with zero actions drive the joints like the baseline in absolute mode,
    and lift.

    Compared up to the first touch (step 40 on this box): from there on float round-off in the
    targets (the absolute path normalises and de-normalises them) is enough for contact onsets to
    differ by a step, so the trajectories are compared by outcome instead.
    """
    closing_steps = 40
    targets = []
    for mode in ("absolute", "residual", "synergy"):
        env = _box_env(action_mode=mode)
        ctl = RuleBasedController(env)
        obs = env.get_observations()
        trace = []
        for _ in range(closing_steps):
            act = ctl.act(obs) if mode == "absolute" else torch.zeros(1, env.num_actions)
            obs, *_ = env.step(act)
            trace.append(env.act.finger_target.clone())
        targets.append(torch.stack(trace))
    assert (targets[0][-1] - targets[0][0]).abs().max() > 0.1  # the rule is closing the hand
    torch.testing.assert_close(targets[1], targets[0], atol=1e-5, rtol=0)
    torch.testing.assert_close(targets[2], targets[0], atol=1e-5, rtol=0)
    episodes = []
    while not episodes:  # the synergy env runs on to the end of its episode
        _, _, _, extras = env.step(torch.zeros(1, 4))
        episodes += extras.get("episodes", [])
    assert episodes[0]["s_lift"], episodes[0]


def test_residual_is_low_pass_filtered():
    """A constant residual action a reaches the joints as the geometric series a (1 - (1 - b)^k), on top
    of the rule's target and through the outer target smoothing (recomputed here step by step)."""
    b = 0.25
    env = _box_env(
        action_mode="residual",
        residual_rate=0.0,
        residual_smoothing=b,
        residual_start="approach",
        decision_steps=1,
    )
    action = torch.linspace(-1.0, 1.0, 16)[None]
    rest = env.residual_base.target.clone()  # the rule holds its rest pose through the approach
    a_s, target = env.cfg.action_smoothing, env.act.finger_target.clone()
    for k in range(1, 9):
        env.step(action)
        residual = action * (1.0 - (1.0 - b) ** k)
        torch.testing.assert_close(env.act.residual, residual, atol=1e-6, rtol=0)
        torch.testing.assert_close(env.get_observations()["policy"][:, -16:], residual, atol=1e-6, rtol=0)
        desired = torch.clamp(rest + env.cfg.residual_scale * residual, env.joints.lower, env.joints.upper)
        target = a_s * desired + (1.0 - a_s) * target
        torch.testing.assert_close(env.act.finger_target, target, atol=1e-5, rtol=0)
    with pytest.raises(ValueError, match="residual_smoothing"):
        _env((RIGID_MEDIUM_BOX,), residual_smoothing=0.0)


def test_synergy_action_squeezes_each_fingers_flexion_joints():
    """Synergy mode: 4 actions, action f offsets finger f's three flexion joints (4f+1..4f+3) equally and
    no abduction joint; the offset is filtered like the residual mode's."""
    b = 0.25
    env = _box_env(
        action_mode="synergy",
        residual_rate=0.0,
        residual_smoothing=b,
        residual_start="approach",
        decision_steps=1,
    )
    assert env.num_actions == 4
    action = torch.tensor([[0.5, -1.0, 0.2, 1.0]])
    expected = torch.zeros(1, 16)
    for f in range(4):
        expected[0, 4 * f + 1 : 4 * f + 4] = action[0, f]
    for k in range(1, 6):
        env.step(action)
        torch.testing.assert_close(env.act.residual, expected * (1.0 - (1.0 - b) ** k), atol=1e-6, rtol=0)
    assert torch.all(env.act.residual[0, ::4] == 0.0)
    with pytest.raises(ValueError, match="shape"):
        env.step(torch.zeros(1, 16))


def test_residual_integrator_holds_and_saturates():
    """residual_rate > 0: the residual is the clipped running sum of rate * action (zero holds it)."""
    rate = 0.3
    env = _box_env(action_mode="synergy", residual_rate=rate, residual_start="approach", decision_steps=1)
    expected = np.zeros(4)
    for action in ([1.0, -0.5, 0.2, 0.0], [0.0] * 4) + ([1.0, -1.0, 0.5, -0.1],) * 3:
        env.step(torch.tensor([action]))
        expected = np.clip(expected + rate * np.array(action), -1.0, 1.0)
        flexion = env.act.residual[0].reshape(4, 4)[:, 1:].numpy()
        np.testing.assert_allclose(flexion, np.repeat(expected[:, None], 3, axis=1), atol=1e-6)
    assert expected[0] == 1.0 and expected[1] == -1.0  # saturated at the clip
    with pytest.raises(ValueError, match="residual_rate"):
        _env((RIGID_MEDIUM_BOX,), residual_rate=-0.1)


def test_residual_waits_for_its_start_phase():
    """residual_start="grasp": through the scripted approach the residual stays 0 whatever the actions;
    from the first grasp step on it integrates them from 0."""
    rate = 0.1
    env = _box_env(action_mode="synergy", residual_rate=rate, residual_start="grasp", decision_steps=1)
    grasp = PHASES.index("grasp")
    action = torch.tensor([[1.0, -0.5, 0.2, 0.0]])
    steps_in_grasp = 0
    while steps_in_grasp < 4:
        in_grasp = int(env.phase_of(env.episode_length_buf)[0]) >= grasp  # the phase this step acts in
        env.step(action)
        flexion = env.act.residual[0].reshape(4, 4)[:, 1:]
        if not in_grasp:
            assert torch.all(flexion == 0.0)
            continue
        steps_in_grasp += 1
        want = torch.clamp(rate * steps_in_grasp * action[0], -1.0, 1.0)
        torch.testing.assert_close(flexion, want[:, None].expand(4, 3), atol=1e-6, rtol=0)
    with pytest.raises(ValueError, match="residual_start"):
        _env((RIGID_MEDIUM_BOX,), residual_start="squeeze")


def test_decisions_are_held_for_decision_steps():
    """decision_steps k: from the first step the actions act (residual_start), the action of every k-th
    step is taken and held for k steps; the others change nothing, and action_takes_effect() marks
    exactly the steps whose action is taken."""
    k = 3
    env = _box_env(action_mode="synergy", residual_start="grasp", decision_steps=k)
    grasp = PHASES.index("grasp")
    gen = torch.Generator().manual_seed(0)
    taken, held = [], []
    steps_in_grasp = 0
    while steps_in_grasp < 3 * k + 1:
        in_grasp = int(env.phase_of(env.episode_length_buf)[0]) >= grasp
        action = torch.rand(1, 4, generator=gen) * 2.0 - 1.0
        takes = bool(env.action_takes_effect()[0])
        env.step(action)
        if not in_grasp:
            assert not takes and torch.all(env.act.actions == 0.0) and torch.all(env.act.residual == 0.0)
            continue
        assert takes == (steps_in_grasp % k == 0), steps_in_grasp
        if takes:
            taken.append(action[0])
        held.append(env.act.actions[0].clone())
        steps_in_grasp += 1
    for n, a in enumerate(held):
        torch.testing.assert_close(a, taken[n // k], atol=0, rtol=0)
    with pytest.raises(ValueError, match="decision_steps"):
        _env((RIGID_MEDIUM_BOX,), decision_steps=0)


def test_a_still_wrist_is_the_scripted_palm_path():
    """With a wrist but the zero action, the palm follows the script exactly: same palm poses and finger
    targets as the env without one, step for step, through the approach and the grasp."""
    plain, wrist = _box_env(), _box_env(palm_offset_limit=0.015, palm_yaw_limit=0.3)
    assert wrist.num_actions == plain.num_actions + 4
    for _ in range(60):
        plain.step(torch.zeros(1, plain.num_actions))
        wrist.step(torch.zeros(1, wrist.num_actions))
        palms = wrist.view.body_q[wrist.index.palm], plain.view.body_q[plain.index.palm]
        torch.testing.assert_close(*palms, atol=0, rtol=0)
        torch.testing.assert_close(wrist.act.finger_target, plain.act.finger_target, atol=0, rtol=0)


def test_the_wrist_offsets_the_palm_at_its_rate_up_to_its_limit():
    """A constant wrist action a: the palm offset moves towards a x limit at the configured rate per axis
    (one decision held, the limit reached), the palm turns about the vertical by the yaw offset, and the
    offset is held from the hold on."""
    limit, yaw_limit, rate, yaw_rate = 0.01, 0.2, 0.03, 0.6
    env = _box_env(
        palm_offset_limit=limit, palm_yaw_limit=yaw_limit, palm_offset_rate=rate, palm_yaw_rate=yaw_rate
    )
    a = torch.tensor([[0.0, 0.0, 0.0, 0.0, 1.0, -0.5, 0.2, 0.5]])
    dt = env.dt
    for n in range(1, 31):
        plan = env.script.palm_command(env.episode_length_buf + 1, env.grasp.palm_pos, env.grasp.approach_dir)
        env.step(a)
        want = np.clip(a[0, 4:7].numpy() * limit, -n * rate * dt, n * rate * dt)
        np.testing.assert_allclose(env.act.palm_offset[0].numpy(), want, atol=1e-7)
        np.testing.assert_allclose(env.palm.cmd_pos[0].numpy(), plan[0].numpy() + want, atol=1e-6)
        yaw = float(np.clip(0.5 * yaw_limit, -n * yaw_rate * dt, n * yaw_rate * dt))
        assert float(env.act.palm_yaw[0]) == pytest.approx(yaw, abs=1e-6)
    # The palm body's orientation: the grasp orientation turned by the yaw about the vertical.
    q = env.view.body_q[env.index.palm][0, 3:].numpy()
    g = env.grasp.palm_quat[0].numpy()
    turn = np.array([0.0, 0.0, np.sin(0.5 * yaw), np.cos(0.5 * yaw)])
    expected = _quat_mul(turn, g)
    assert min(np.abs(q - expected).max(), np.abs(q + expected).max()) < 1e-5
    # Held from the hold on: a 2 mm rise of the palm keeps the rule's grasp, so the episode goes on.
    env = _box_env(palm_offset_limit=limit)
    up = torch.tensor([[0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.2, 0.0]])
    hold, ended = PHASES.index("hold"), []
    while int(env.phase_of(env.episode_length_buf)[0]) < hold:
        ended += env.step(up)[3].get("episodes", [])
    held = env.act.palm_offset.clone()
    torch.testing.assert_close(held[0], torch.tensor([0.0, 0.0, 0.2 * limit]), atol=1e-7, rtol=0)
    for _ in range(5):
        ended += env.step(-up)[3].get("episodes", [])
    assert not ended
    torch.testing.assert_close(env.act.palm_offset, held, atol=0, rtol=0)
    with pytest.raises(ValueError, match="wrist"):
        _env((RIGID_MEDIUM_BOX,), palm_offset_limit=0.01, action_mode="absolute")


def _quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product of xyzw quaternions (NumPy reference)."""
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return np.array(
        [
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
            aw * bw - ax * bx - ay * by - az * bz,
        ]
    )


def test_disturbance_force_pushes_a_free_object():
    # The hand waits in its pre-grasp pose; push the free box along +x with 2.5 N for 0.5 s.
    env = _box_env(sim__use_graph=False)
    start = env.object_state()[0].clone()
    mass = float(env.draw.object_mass[0])
    for _ in range(30):
        env.view.object_force[:] = torch.tensor([[2.5, 0.0, 0.0]])
        env.launch_step()
    moved = env.object_state()[0][0] - start[0]
    # Pushing force 2.5 N beats the friction limit mu*m*g (~1.4 N at mu = 1): the box slides along +x.
    assert 1.0 * mass * 9.81 < 2.5
    assert moved[0] > 0.02, moved
    assert abs(float(moved[1])) < 0.3 * float(moved[0])


def test_held_object_contact_forces_carry_its_weight():
    """The exported contact forces on a held box, summed over every contact row (rigid rows: the force
    on shape0's body), carry its weight. SolverVBD's hard AVBD contacts export their multipliers, whose
    sum on a held object converges to the weight with the solver's iterations but not at the task's 5
    (box_01 in its planned top grasp of 2026-12-08, vertical / horizontal sum against its 1.37 N
    weight: 5.5 / 2.2 N at 5 iterations, 2.5 / 0.55 N at 10, 1.7 / 0.9 N at 20; resting on the table
    the sum is exact). Measured at 20 iterations, the bounds hold that residual and fail on a broken
    export (a sign, a frame, a missing row: zero, negative or many times the weight)."""
    with pytest.warns(UserWarning, match="sim.iterations"):  # the grasp was planned at 5 iterations
        env = _box_env(sim__iterations=20)
    ctl = RuleBasedController(env)
    obs = env.get_observations()
    for _ in range(env.script.phase_start["hold"] + 5):
        obs, *_ = env.step(ctl.act(obs))
    body = env.model.shape_body.numpy()
    obj = env.layout.object_body[0]
    nets = []
    for _ in range(10):  # averaged over a sixth of a second of the hold
        obs, *_ = env.step(ctl.act(obs))
        contacts = env.contacts
        n = int(contacts.rigid_contact_count.numpy()[0])
        s0 = contacts.rigid_contact_shape0.numpy()[:n]
        s1 = contacts.rigid_contact_shape1.numpy()[:n]
        f = env.observables.contact_f.numpy()[:n, :3]
        nets.append(f[body[s0] == obj].sum(0) - f[body[s1] == obj].sum(0))
    net = np.mean(nets, axis=0)
    weight = float(env.model.body_mass.numpy()[obj]) * 9.81
    lifted = env.object_state()[0][0, 2] - env.draw.object_start[0, 2]
    assert lifted > 0.08
    assert 0.8 * weight < net[2] < 2.0 * weight, (net, weight)
    assert np.hypot(net[0], net[1]) < weight, (net, weight)


def test_the_environment_runs_warp_on_the_cpu():
    """``device="cpu"`` puts the model, the state and the sensors' arrays on Warp's CPU device."""
    env = _box_env()
    assert env.wp_device.is_cpu
    assert env.model.body_q.device.is_cpu and env.state_0.body_q.device.is_cpu
    assert env.sensors.pad_force.device.is_cpu


def test_contact_reward_counts_the_pads_touch_of_the_object_only():
    """r_contact (paper: contact "between the fingertips and the object surface") from hand-set pad
    forces: pads pressing the table earn nothing; pads on the object earn k_f f, the excess over f_m
    costs k_p per newton."""
    env = _box_env()
    rcfg = env.cfg.rewards
    table = torch.zeros(1, NUM_PADS, 3)
    table[0, [0, 3, 6], 2] = 15.0  # three fingertip pads pressing the table at 15 N each
    on_object = torch.zeros(1, NUM_PADS, 3)
    on_object[0, 9, 2] = 4.0  # a thumb pad at 4 N
    on_object[0, 2, 0] = rcfg.max_force + 5.0  # an index pad 5 N over the permitted maximum
    contact = TERM_NAMES.index("contact")

    def set_pads(force_buf: wp.array, contact_buf: wp.array, force: torch.Tensor) -> None:
        wp.to_torch(force_buf)[:] = force
        wp.to_torch(contact_buf)[:] = (torch.linalg.norm(force, dim=-1) > 0).float()

    for object_force, expected in (
        (torch.zeros(1, NUM_PADS, 3), 0.0),
        (on_object, rcfg.contact_gain * (4.0 + rcfg.max_force + 5.0) - rcfg.contact_penalty * 5.0),
    ):
        set_pads(env.sensors.pad_force_true, env.sensors.pad_contact_true, table + object_force)
        set_pads(env.sensors.pad_force_object, env.sensors.pad_contact_object, object_force)
        rewards.compute_rewards(env)
        assert float(env.reward.terms[0, contact]) == pytest.approx(expected, rel=1e-5, abs=1e-6)


def test_the_rule_squeezes_soft_worlds_with_the_soft_squeeze(mixed_env, monkeypatch):
    """The rule-based controller hands rule_step which worlds hold a soft object (world 0 the box,
    world 1 the sponge), so the sponge closes with rule.squeeze_deformable: a controller that lost the
    flag closed soft objects with the rigid squeeze and the evaluation's soft holds fell (2026-12-08)."""
    import d3grasp.envs.baseline as baseline

    seen = []

    def spy(*args, **kwargs):
        seen.append(args[8])
        return real(*args, **kwargs)

    real = baseline.rule_step
    monkeypatch.setattr(baseline, "rule_step", spy)
    env = mixed_env
    # In the residual modes the environment runs the rule; the controller runs it itself without one.
    residual_base, env.residual_base = env.residual_base, None
    try:
        RuleBasedController(env).act(env.get_observations())
    finally:
        env.residual_base = residual_base
    assert [bool(x) for x in seen[0]] == [False, True]
    squeeze = baseline.squeeze_per_world(env.cfg.rule, seen[0]).flatten().tolist()
    assert squeeze == pytest.approx([env.cfg.rule.squeeze, env.cfg.rule.squeeze_deformable])


def test_the_environment_is_its_named_parts(mixed_env):
    """The environment's state lives in named parts (d3grasp/envs/parts.py and the mdp modules'
    states): GraspEnv itself holds at most 30 attributes, and nothing in the package sets one on an
    env by a computed name (``setattr``), which neither grep nor an IDE can follow."""
    mdp_parts = {"observation", "reward", "scoring"}
    own = set(vars(mixed_env)) - mdp_parts
    assert mdp_parts <= set(vars(mixed_env))
    assert len(own) <= 30, sorted(own)
    root = pathlib.Path(__file__).resolve().parents[2]
    offenders = [
        str(p.relative_to(root))
        for folder in ("d3grasp", "kernels", "train")
        for p in (root / folder).rglob("*.py")
        if re.search(r"setattr\((self\.)?env\b", p.read_text(encoding="utf-8"))
    ]
    assert not offenders
