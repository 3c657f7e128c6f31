"""Warp kernels: tactile forces, FEM strain, deformable pose and reward terms for all worlds.

Submodules (import them directly; nothing here imports Warp):

- :mod:`d3grasp.kernels.tactile`  -- pad forces from Newton contact rows, pad frames, noise, contact flags.
- :mod:`d3grasp.kernels.strain`   -- Green-Lagrange max principal strain per tet/node/object, sigma.
- :mod:`d3grasp.kernels.strain_numpy` -- one-off NumPy calls of the strain kernels, a tet grid mesh.
- :mod:`d3grasp.kernels.rotation` -- adaptive (sigma-selected) object rotation, CoM velocity.
- :mod:`d3grasp.kernels.rewards`  -- every reward term of the paper for all worlds.
- :mod:`d3grasp.kernels.scoring`  -- the success metrics, failure causes and terminations per world.
- :mod:`d3grasp.kernels.observations` -- the policy's and the critic's observation groups.
- :mod:`d3grasp.kernels.world_state` -- per-world reads of the state, the reward inputs' gather.
- :mod:`d3grasp.kernels.fem_elasticity` -- the soft objects' tet solve in closed form.
- :mod:`d3grasp.kernels.particle_iteration` -- SolverVBD's soft iteration without its repeated passes.
- :mod:`d3grasp.kernels.chebyshev` -- Chebyshev acceleration of the soft sweeps (off by default).
- :mod:`d3grasp.kernels.grasp_energy` -- a differentiable force-closure grasp energy over the hand's
  kinematics, many grasps at once (grasp synthesis by gradient descent).
- :mod:`d3grasp.kernels.grasp_energy_inputs` -- the hand layout, object shape and weights it reads.
- :mod:`d3grasp.kernels.grasp_energy_reference` -- its float64 NumPy twin (tests).
- :mod:`d3grasp.kernels.grasp_descent` -- Adam descent of the energy from many starts at once.
"""

__all__ = [
    "chebyshev",
    "fem_elasticity",
    "grasp_descent",
    "grasp_energy",
    "grasp_energy_inputs",
    "grasp_energy_reference",
    "observations",
    "particle_iteration",
    "rewards",
    "rotation",
    "scoring",
    "strain",
    "strain_numpy",
    "tactile",
    "world_state",
]
