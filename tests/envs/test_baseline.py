"""The rule-based baseline as a function of tensors, on hand-made pad forces and joint positions.

Expected values are worked out by hand from the rule (close at ``close_speed`` from the grasp
phase on; a pad above the threshold stops the joints of its finger proximal to its link, each at
its current position plus ``squeeze``), not from the code's output.
"""

from __future__ import annotations

import pytest
import torch

from d3grasp.envs.baseline import (
    BaselineConfig,
    RuleState,
    RuleTables,
    grasp_closing_joints,
    rest_targets,
    rule_step,
    stop_matrix,
)
from d3grasp.vocabulary import GRASP_TYPES

LOWER = torch.tensor([-0.35, 0.0, 0.0, 0.0] * 3 + [0.0, 0.0, 0.0, 0.0])
UPPER = torch.tensor([0.35, 1.57, 1.57, 1.57] * 3 + [1.57, 1.57, 1.57, 1.57])
DT = 1.0 / 60.0
CFG = BaselineConfig(close_speed=1.5, force_threshold=0.5, squeeze=0.1, per_joint=True)
STEP = 1.5 / 60.0  # rad a closing joint advances per control step


def _rule(num_worlds: int, cfg: BaselineConfig = CFG) -> tuple[RuleState, RuleTables]:
    return RuleState.open(num_worlds, rest_targets(LOWER, UPPER)), RuleTables.make(cfg, UPPER)


def _pads(num_worlds: int, pressed: dict[tuple[int, int], float] | None = None) -> torch.Tensor:
    """(W, 11, 3) pad forces, zero but for {(world, pad): normal force in N}."""
    f = torch.zeros(num_worlds, 11, 3)
    for (w, p), n in (pressed or {}).items():
        f[w, p, 2] = -n
    return f


def test_stop_matrix_pads_stop_the_joints_proximal_to_their_link() -> None:
    s = stop_matrix(per_joint=True)
    stops = {j: sorted(torch.nonzero(s[j]).flatten().tolist()) for j in range(16)}
    for abduction in (0, 4, 8, 12):
        assert stops[abduction] == []
    assert (stops[1], stops[2], stops[3]) == ([0, 1, 2], [1, 2], [2])  # index: pads on links 1, 2, 3
    assert (stops[9], stops[10], stops[11]) == ([6, 7, 8], [7, 8], [8])  # ring
    assert (stops[13], stops[14], stops[15]) == ([9, 10], [9, 10], [10])  # thumb: pads on links 2, 3
    whole = stop_matrix(per_joint=False)
    assert sorted(torch.nonzero(whole[7]).flatten().tolist()) == [3, 4, 5]  # middle tip: all middle pads


def test_grasp_types_close_their_fingers_flexion_joints_only() -> None:
    uses = grasp_closing_joints()
    flexion = [j for j in range(16) if j % 4]
    top = GRASP_TYPES.index("top")
    pinch = GRASP_TYPES.index("pinch")
    assert torch.nonzero(uses[top]).flatten().tolist() == flexion
    assert torch.nonzero(uses[pinch]).flatten().tolist() == [1, 2, 3, 5, 6, 7, 13, 14, 15]  # no ring


def test_closes_at_constant_speed_only_once_closing() -> None:
    state, tables = _rule(2)
    rest = rest_targets(LOWER, UPPER)
    torch.testing.assert_close(rest[[0, 4, 8, 12]], torch.tensor([0.0, 0.0, 0.0, 0.785]))  # centred
    grasp = torch.tensor([GRASP_TYPES.index("top"), GRASP_TYPES.index("pinch")])
    closing = torch.tensor([True, False])
    q = LOWER.expand(2, -1).clone()
    for _ in range(3):
        target = rule_step(state, tables, CFG, _pads(2), q, closing, grasp, DT)
    flexion = [j for j in range(16) if j % 4]
    torch.testing.assert_close(target[0, flexion], torch.full((12,), 3 * STEP))
    assert torch.equal(target[0, [0, 4, 8, 12]], rest[[0, 4, 8, 12]])  # abduction never moves
    assert torch.equal(target[1], rest)  # not closing yet: the open hand


def test_a_touch_stops_the_joints_proximal_to_the_pad_with_a_squeeze() -> None:
    state, tables = _rule(1)
    grasp = torch.tensor([GRASP_TYPES.index("top")])
    closing = torch.tensor([True])
    q = torch.zeros(1, 16)
    q[0, 1:4] = torch.tensor([0.30, 0.20, 0.10])  # the index finger where the drives have taken it
    q[0, 5:8] = torch.tensor([0.40, 0.40, 0.40])
    rule_step(state, tables, CFG, _pads(1), q, closing, grasp, DT)  # one free step
    # The index tip pad (2, link 3) and the middle's proximal pad (3, link 1) press; 0.4 N on the
    # thumb's tip pad (10) is below the threshold.
    pressed = _pads(1, {(0, 2): 2.0, (0, 3): 0.8, (0, 10): 0.4})
    target = rule_step(state, tables, CFG, pressed, q, closing, grasp, DT)
    torch.testing.assert_close(target[0, 1:4], torch.tensor([0.40, 0.30, 0.20]))  # q + 0.1, all index joints
    assert target[0, 5].item() == pytest.approx(0.50)  # middle joint 1 stopped at q + 0.1 ...
    torch.testing.assert_close(target[0, 6:8], torch.full((2,), 2 * STEP))  # ... its distal joints go on
    torch.testing.assert_close(target[0, 13:16], torch.full((3,), 2 * STEP))  # the thumb goes on
    assert state.stopped[0].nonzero().flatten().tolist() == [1, 2, 3, 5]
    # Stopped joints hold, even when the touch is gone; a squeeze never passes the joint limit.
    q[0, 9] = 1.55
    after = rule_step(state, tables, CFG, _pads(1, {(0, 6): 5.0}), q, closing, grasp, DT)
    torch.testing.assert_close(after[0, 1:4], torch.tensor([0.40, 0.30, 0.20]))
    assert after[0, 9].item() == pytest.approx(1.57)  # min(1.55 + 0.1, upper)


def test_a_soft_object_is_squeezed_deeper_than_a_rigid_one() -> None:
    cfg = BaselineConfig(close_speed=1.5, force_threshold=0.5, squeeze=0.1, squeeze_deformable=0.25)
    state, tables = _rule(2, cfg)
    grasp = torch.full((2,), GRASP_TYPES.index("top"))
    closing = torch.tensor([True, True])
    q = torch.zeros(2, 16)
    q[:, 1:4] = torch.tensor([0.30, 0.20, 0.10])
    soft = torch.tensor([False, True])
    pressed = _pads(2, {(0, 2): 2.0, (1, 2): 2.0})  # both index tips press
    target = rule_step(state, tables, cfg, pressed, q, closing, grasp, DT, object_soft=soft)
    torch.testing.assert_close(target[0, 1:4], torch.tensor([0.40, 0.30, 0.20]))  # rigid: q + 0.1
    torch.testing.assert_close(target[1, 1:4], torch.tensor([0.55, 0.45, 0.35]))  # soft: q + 0.25
    # Without the soft flags every world is squeezed as a rigid object.
    state, tables = _rule(2, cfg)
    target = rule_step(state, tables, cfg, pressed, q, closing, grasp, DT)
    torch.testing.assert_close(target[:, 1:4], torch.tensor([[0.40, 0.30, 0.20]] * 2))


def test_the_stall_prior_stops_a_held_back_joint_and_reads_no_pad() -> None:
    """The Base ablation's prior: a joint whose drive lags its target by more than ``stall_lag`` stops
    (at its position plus the squeeze); the pads, pressed hard everywhere, stop nothing."""
    cfg = BaselineConfig(close_speed=1.5, squeeze=0.1, stop_on="stall", stall_lag=0.15)
    state, tables = _rule(1, cfg)
    grasp = torch.tensor([GRASP_TYPES.index("top")])
    closing = torch.tensor([True])
    every_pad = _pads(1, {(0, p): 5.0 for p in range(11)})
    for _ in range(8):  # free closing: the joints keep up with their targets
        rule_step(state, tables, cfg, every_pad, state.target.clone(), closing, grasp, DT)
    flexion = [j for j in range(16) if j % 4]
    torch.testing.assert_close(state.target[0, flexion], torch.full((12,), 8 * STEP))  # 0.2 rad
    assert not state.stopped.any()
    q = state.target.clone()
    q[0, 1] = 0.04  # held back: 0.16 rad behind its target
    q[0, 5] = 0.06  # 0.14 rad behind: still closing
    target = rule_step(state, tables, cfg, every_pad, q, closing, grasp, DT)
    assert target[0, 1].item() == pytest.approx(0.14)  # 0.04 + the squeeze
    assert target[0, 5].item() == pytest.approx(9 * STEP)
    assert state.stopped[0].nonzero().flatten().tolist() == [1]


def test_an_unknown_closing_prior_is_a_one_line_error() -> None:
    from d3grasp.envs.config import GraspEnvConfig
    from d3grasp.envs.grasp_env import _check_config

    with pytest.raises(ValueError, match="unknown rule.stop_on 'vision'; known: \\['touch', 'stall'\\]"):
        _check_config(GraspEnvConfig(rule=BaselineConfig(stop_on="vision")), num_envs=1)
