"""Adam descent of the grasp energy (:class:`d3grasp.kernels.grasp_energy.GraspEnergy`) from many
starts at once: each row of parameters is one start, and all rows take their steps together.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from d3grasp.kernels.grasp_energy import GraspEnergy
from d3grasp.kernels.grasp_energy_inputs import POSE_PARAMS, EnergyWeights, HandLayout, ObjectShape

__all__ = ["DescentResult", "descend"]


@dataclass
class DescentResult:
    """Final parameters (n, 7 + J) with unit quaternions, their terms, and the energy per step."""

    params: np.ndarray
    terms: dict[str, np.ndarray]
    history: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))  # (steps + 1, n)


def descend(
    layout: HandLayout,
    params0: np.ndarray,
    obj: ObjectShape,
    contact_weight: Any,
    weights: EnergyWeights | None = None,
    steps: int = 200,
    lr_position: float = 2.0e-3,
    lr_rotation: float = 2.0e-2,
    lr_joint: float = 3.0e-2,
    lr_final: float = 0.1,
    clamp_joints: bool = True,
    device: Any = None,
) -> DescentResult:
    """Adam (Kingma & Ba 2015, beta 0.9/0.999) on every row of ``params0`` at once.

    Learning rates are per group because the parameters have different units (m, quaternion
    components, rad): Adam's step is about ``lr`` per parameter, so ``lr_position`` 2 mm and
    ``lr_joint`` 0.03 rad move the hand by a few mm per step; the rates decay exponentially to
    ``lr_final`` times these by the last step, so the end is not an Adam jitter of that size (a pad
    gap of a few mm at a constant rate). After each step the quaternions are
    renormalised and, with ``clamp_joints``, the joint angles projected into their limits (then the
    limit term only matters for starts outside them)."""
    energy_fn = GraspEnergy(layout, obj, len(params0), contact_weight, weights, device)
    x = np.array(params0, dtype=np.float64)
    lr = np.full(layout.num_params, lr_joint)
    lr[:3] = lr_position
    lr[3:POSE_PARAMS] = lr_rotation
    m = np.zeros_like(x)
    v = np.zeros_like(x)
    beta1, beta2, eps = 0.9, 0.999, 1.0e-12
    history = []
    for step in range(1, steps + 1):
        e, g = energy_fn.evaluate(x, grad=True)
        history.append(e)
        g = np.nan_to_num(g)
        m = beta1 * m + (1.0 - beta1) * g
        v = beta2 * v + (1.0 - beta2) * g * g
        m_hat = m / (1.0 - beta1**step)
        v_hat = v / (1.0 - beta2**step)
        decay = lr_final ** ((step - 1) / max(steps - 1, 1))
        x -= (decay * lr) * m_hat / (np.sqrt(v_hat) + eps)
        x[:, 3:POSE_PARAMS] /= np.linalg.norm(x[:, 3:POSE_PARAMS], axis=1, keepdims=True)
        if clamp_joints:
            x[:, POSE_PARAMS:] = np.clip(x[:, POSE_PARAMS:], layout.joint_lower, layout.joint_upper)
    e, _ = energy_fn.evaluate(x)
    history.append(e)
    return DescentResult(params=x, terms=energy_fn.terms(), history=np.array(history))
