"""The soft objects' FEM elasticity solve, per vertex, in closed form (a faster SolverVBD kernel).

SolverVBD (Newton 1.8) solves a soft body vertex by vertex: per vertex it sums the inertia, the
contacts and, over the tets that hold the vertex, the force and 3x3 Hessian block of the stable
Neo-Hookean energy (Smith et al. 2018, without the log term, as Newton writes it)::

    psi(F) = mu/2 (tr(F^T F) - 3) + lambda_nh/2 (J - alpha)^2,   lambda_nh = lambda + mu,
    alpha = 1 + mu / lambda_nh,   J = det F,   F = Ds Dm^-1

and takes the step ``H^-1 f``. Newton builds the 9x9 Hessian in F (``mu I9 + lambda_nh c c^T``, c = vec
cof F) and contracts it with the vertex's gradient row ``m`` of ``Dm^-1``. The contraction has a closed
form, since ``d vec(F) / d x = m (x) I3``::

    f = -V (mu F m + lambda_nh (J - alpha) cof(F) m)
    H = V (mu |m|^2 I3 + lambda_nh (cof(F) m)(cof(F) m)^T)

(exact: J is linear in any one vertex, so the block has no d2J term). The damping term is Newton's as
well: a dissipation ``V k / (2 dt) sum_ij (C_ij - C_prev_ij)^2`` of the right Cauchy-Green tensor
``C = F^T F`` with its Gauss-Newton Hessian, whose six per-entry sums collapse to
``f_d = -2 V k F (dC/dt) m`` and ``H_d = (2 V k / dt) (|m|^2 F F^T + (F m)(F m)^T)``.
On the 4 soft test objects Newton's kernel was ~85% of a soft control step (20 iterations x 10
substeps x 7 colours of launches); the closed form takes 112 against 199 us a launch and the step
214 against 376 ms; the damping's closed form took a launch from 0.55 to 0.47 of Newton's time (98
against 210 us, one later session) and the soft benchmark from 19-22 to 21-23 env-steps/s
(docs/design.md, Where a soft step's time goes; compare with ``python -m d3grasp.bench env --kinds
soft --set sim.closed_form_tets=false``).

What stays fixed through a substep's iterations is made outside the per-corner loop: each tet's rest
volume once (:data:`tet_rest_volumes`) and its ``C_prev`` once a substep (:data:`tet_cauchy_green`),
by the same operations the loop ran, so the results are the same bits. Each corner's evaluation read
its tet's four start positions and formed ``F_prev^T F_prev`` 20 x 4 times a substep: 40 against 49 us
a colour launch at 8 soft worlds, the soft benchmark at 8 worlds 98-100 against 88-89 env-steps/s.

Only the tets are handled: :func:`use_closed_form_tets` installs the kernel on a solver whose model has
no membrane or bending elements (the soft objects are tet meshes whose surface triangles and edges
carry zero material), and leaves any other solver on Newton's own kernel.
"""

from __future__ import annotations

from dataclasses import dataclass

import warp as wp
from newton._src.geometry import ParticleFlags
from newton._src.solvers.vbd import solver_vbd
from newton._src.utils.mesh import (
    MeshAdjacencyData,
    get_vertex_adjacent_tet_id_order,
    get_vertex_num_adjacent_tets,
)

__all__ = [
    "TetStartState",
    "solve_elasticity_tets",
    "tet_cauchy_green",
    "tet_rest_volumes",
    "tet_vertex_force_hessian",
    "use_closed_form_tets",
    "vertex_newton_step",
]


@wp.kernel
def tet_rest_volumes(tet_poses: wp.array(dtype=wp.mat33), volumes: wp.array(dtype=float)):
    """Each tet's rest volume from its ``Dm^-1`` (made once: the rest shape does not change)."""
    tet = wp.tid()
    volumes[tet] = 1.0 / (6.0 * wp.determinant(tet_poses[tet]))


@wp.kernel
def tet_cauchy_green(
    pos: wp.array(dtype=wp.vec3),
    tet_indices: wp.array2d(dtype=wp.int32),
    tet_poses: wp.array(dtype=wp.mat33),
    cauchy_green: wp.array(dtype=wp.mat33),
):
    """Each tet's right Cauchy-Green tensor ``C = F^T F`` at ``pos``. The damping reads it at the
    substep's start positions, which stay fixed through the substep's iterations: made once a substep
    here instead of once per corner and iteration (20 x 4 times) in the solve."""
    tet = wp.tid()
    x0 = pos[tet_indices[tet, 0]]
    F = (
        wp.matrix_from_cols(
            pos[tet_indices[tet, 1]] - x0, pos[tet_indices[tet, 2]] - x0, pos[tet_indices[tet, 3]] - x0
        )
        * tet_poses[tet]
    )
    cauchy_green[tet] = wp.transpose(F) * F


@wp.func
def tet_vertex_force_hessian(
    tet: int,
    corner: int,
    pos: wp.array(dtype=wp.vec3),
    tet_indices: wp.array2d(dtype=wp.int32),
    dm_inv: wp.mat33,
    volume: float,
    cauchy_green_prev: wp.mat33,
    mu: float,
    lmbd: float,
    damping: float,
    dt: float,
):
    """Force on and Hessian block of corner ``corner`` (0-3) of tet ``tet`` (formulas: module doc);
    ``volume`` is the tet's rest volume, ``cauchy_green_prev`` its ``C`` at the substep's start."""
    i0 = tet_indices[tet, 0]
    x0 = pos[i0]
    F = (
        wp.matrix_from_cols(
            pos[tet_indices[tet, 1]] - x0, pos[tet_indices[tet, 2]] - x0, pos[tet_indices[tet, 3]] - x0
        )
        * dm_inv
    )
    # The corner's gradient row: d F / d x_corner = m^T per row of F (corner 0 moves all three edges).
    if corner == 0:  # noqa: SIM108 (a Warp function: a statement per branch)
        m = -(dm_inv[0] + dm_inv[1] + dm_inv[2])
    else:
        m = dm_inv[corner - 1]
    lmbd_nh = lmbd + mu
    lmbd_safe = wp.sign(lmbd_nh) * wp.max(wp.abs(lmbd_nh), 1.0e-6)
    alpha = 1.0 + mu / lmbd_safe
    cols = wp.transpose(F)  # cols[j]: column j of F
    c0 = wp.cross(cols[1], cols[2])  # cof(F) = [c0 c1 c2]: its columns are crosses of F's columns
    c1 = wp.cross(cols[2], cols[0])
    c2 = wp.cross(cols[0], cols[1])
    J = wp.dot(cols[0], c0)
    cof_m = c0 * m[0] + c1 * m[1] + c2 * m[2]
    f_m = F * m
    force = -volume * (mu * f_m + lmbd_nh * (J - alpha) * cof_m)
    m2 = wp.dot(m, m)
    eye = wp.identity(n=3, dtype=float)
    hessian = volume * (mu * m2 * eye + lmbd_nh * wp.outer(cof_m, cof_m))
    if damping > 0.0:
        # Newton sums the six (i <= j) entries of the rate of C = F^T F, each with the gradient
        # g_ij = m_i F_j + m_j F_i (F_j: column j of F) and weight 2 off the diagonal. Summed over
        # all ordered pairs instead, that is 2 F (dC/dt) m for the force and
        # 2 (|m|^2 F F^T + (F m)(F m)^T) for the Gauss-Newton Hessian.
        rate = (cols * F - cauchy_green_prev) / dt
        force -= (2.0 * volume * damping) * (F * (rate * m))
        hessian += (2.0 * volume * damping / dt) * (m2 * (F * cols) + wp.outer(f_m, f_m))
    return force, hessian


@wp.func
def vertex_newton_step(
    particle: int,
    dt: float,
    pos: wp.array(dtype=wp.vec3),
    mass: wp.array(dtype=float),
    inertia: wp.array(dtype=wp.vec3),
    particle_flags: wp.array(dtype=wp.int32),
    tet_indices: wp.array2d(dtype=wp.int32),
    tet_poses: wp.array(dtype=wp.mat33),
    tet_materials: wp.array2d(dtype=float),
    tet_volumes: wp.array(dtype=float),
    tet_cauchy_green_prev: wp.array(dtype=wp.mat33),
    particle_adjacency: MeshAdjacencyData,
    particle_forces: wp.array(dtype=wp.vec3),
    particle_hessians: wp.array(dtype=wp.mat33),
    particle_displacements: wp.array(dtype=wp.vec3),
):
    """The vertex's accumulated displacement after its Newton step: inertia + contacts (already in
    ``particle_forces`` / ``particle_hessians``) + its tets; zero for an inactive or massless vertex,
    unchanged where the Hessian is singular (SolverVBD's rules)."""
    if (particle_flags[particle] & ParticleFlags.ACTIVE) == 0 or mass[particle] == 0.0:
        return wp.vec3(0.0)
    inv_dt2 = 1.0 / (dt * dt)
    f = mass[particle] * inv_dt2 * (inertia[particle] - pos[particle]) + particle_forces[particle]
    h = mass[particle] * inv_dt2 * wp.identity(n=3, dtype=float) + particle_hessians[particle]
    for k in range(get_vertex_num_adjacent_tets(particle_adjacency, particle)):
        tet, corner = get_vertex_adjacent_tet_id_order(particle_adjacency, particle, k)
        mu = tet_materials[tet, 0]
        lmbd = tet_materials[tet, 1]
        if mu > 0.0 or lmbd > 0.0:
            f_t, h_t = tet_vertex_force_hessian(
                tet,
                corner,
                pos,
                tet_indices,
                tet_poses[tet],
                tet_volumes[tet],
                tet_cauchy_green_prev[tet],
                mu,
                lmbd,
                tet_materials[tet, 2],
                dt,
            )
            f += f_t
            h += h_t
    displacement = particle_displacements[particle]
    if wp.abs(wp.determinant(h)) > 1.0e-8:
        displacement = displacement + wp.inverse(h) * f
    return displacement


@wp.kernel
def solve_elasticity_tets(
    dt: float,
    particle_ids_in_color: wp.array(dtype=wp.int32),
    pos_prev: wp.array(dtype=wp.vec3),
    pos: wp.array(dtype=wp.vec3),
    mass: wp.array(dtype=float),
    inertia: wp.array(dtype=wp.vec3),
    particle_flags: wp.array(dtype=wp.int32),
    tri_indices: wp.array2d(dtype=wp.int32),
    tet_cauchy_green_prev: wp.array(dtype=wp.mat33),  # in the triangles' poses' slot: use_closed_form_tets
    tri_materials: wp.array2d(dtype=float),
    tet_volumes: wp.array(dtype=float),  # in the triangles' areas' slot
    edge_indices: wp.array2d(dtype=wp.int32),
    edge_rest_angles: wp.array(dtype=float),
    edge_rest_length: wp.array(dtype=float),
    edge_bending_properties: wp.array2d(dtype=float),
    tet_indices: wp.array2d(dtype=wp.int32),
    tet_poses: wp.array(dtype=wp.mat33),
    tet_materials: wp.array2d(dtype=float),
    particle_adjacency: MeshAdjacencyData,
    particle_forces: wp.array(dtype=wp.vec3),
    particle_hessians: wp.array(dtype=wp.mat33),
    particle_displacements: wp.array(dtype=wp.vec3),
):
    # SolverVBD's ``solve_elasticity`` launch signature (the other triangle and edge inputs go unread:
    # the kernel serves tet-only models). One thread per vertex of the colour.
    particle = particle_ids_in_color[wp.tid()]
    particle_displacements[particle] = vertex_newton_step(
        particle,
        dt,
        pos,
        mass,
        inertia,
        particle_flags,
        tet_indices,
        tet_poses,
        tet_materials,
        tet_volumes,
        tet_cauchy_green_prev,
        particle_adjacency,
        particle_forces,
        particle_hessians,
        particle_displacements,
    )


@dataclass(frozen=True)
class TetStartState:
    """What the closed form reads besides the model: each tet's rest volume (made once) and its
    ``C = F^T F`` at the substep's start positions (remade each substep)."""

    volumes: wp.array
    cauchy_green_prev: wp.array


def use_closed_form_tets(solver) -> TetStartState | None:
    """Make ``solver`` (a SolverVBD) solve its tets with :data:`solve_elasticity_tets`; return the
    arrays it reads, or None where it does not qualify (only a model with tets and no other elastic
    elements, on the non-tiled path, does; any other keeps Newton's kernel).

    SolverVBD launches the kernel its module names ``solve_elasticity`` when a particle iteration runs,
    with the model's arrays as inputs. During this solver's iterations the module's name points to the
    closed form, and the model's triangle poses and areas, which a tet-only model's elasticity never
    reads, to the tets' Cauchy-Green tensors at the substep's start and their rest volumes (remade
    after each substep's particle initialisation, which sets those start positions). A captured graph
    keeps the kernel and arrays it recorded."""
    # Newton's own test for a model whose elements carry tet material only (springs are accumulated
    # by a kernel of their own, so they do not matter here).
    model = solver.model
    if (
        model.tet_count == 0
        or getattr(solver, "use_particle_tile_solve", False)
        or not solver_vbd._is_tet_only_elasticity_model(model)
    ):
        return None
    device = model.device
    tets = TetStartState(
        volumes=wp.empty(model.tet_count, dtype=float, device=device),
        cauchy_green_prev=wp.empty(model.tet_count, dtype=wp.mat33, device=device),
    )
    wp.launch(
        tet_rest_volumes, dim=model.tet_count, inputs=[model.tet_poses], outputs=[tets.volumes], device=device
    )
    initialize = solver._initialize_particles
    iterate = solver._solve_particle_iteration

    def initialize_and_strain(*args, **kwargs):
        initialize(*args, **kwargs)
        wp.launch(
            tet_cauchy_green,
            dim=model.tet_count,
            inputs=[solver.particle_q_prev, model.tet_indices, model.tet_poses],
            outputs=[tets.cauchy_green_prev],
            device=device,
        )

    def iterate_closed_form(*args, **kwargs):
        newton_kernel, tri_poses, tri_areas = solver_vbd.solve_elasticity, model.tri_poses, model.tri_areas
        solver_vbd.solve_elasticity = solve_elasticity_tets
        model.tri_poses, model.tri_areas = tets.cauchy_green_prev, tets.volumes
        try:
            return iterate(*args, **kwargs)
        finally:
            solver_vbd.solve_elasticity = newton_kernel
            model.tri_poses, model.tri_areas = tri_poses, tri_areas

    solver._initialize_particles = initialize_and_strain
    solver._solve_particle_iteration = iterate_closed_form
    return tets
