"""SolverVBD's particle iteration for tet-only soft bodies with point contacts, on the CPU, with two
passes of every colour taken out (the same arithmetic in the same order, so the same bits).

A SolverVBD particle iteration (Newton 1.8) runs, for each colour of the soft nodes: a pass over all
body-particle contacts that adds those of the colour's nodes, the colour's elasticity solve, and a
"penetration-free truncation" pass over all nodes that sets each node's position to its substep-start
position plus its accumulated displacement. With 7 colours, 20 iterations and 10 substeps that is
1,400 launches of each a control step. For the soft objects here two of them repeat work:

- A point contact (a node against a rigid shape) reads only its node's position, the node's start
  position and the bodies' poses. The bodies do not move during a particle iteration, and a node
  moves only in its own colour's solve, so its contacts read the same values at the iteration's start
  as just before that solve. :data:`accumulate_point_contacts` adds them all once an iteration, in the
  contacts' order, as the per-colour pass (run by one worker on the CPU, d3grasp.envs.physics) adds
  each colour's share.
- Without self-contact or rigid-soft DAT the truncation's factor is 1 and its clamp infinite, so the
  pass only rewrites every position from its displacement; those of the other colours come out as they
  were. :data:`solve_elasticity_tets_in_place` writes the colour's own positions as it solves them.

On 8 soft worlds the two passes were ~15% of a control step (10.4% and 4.6% by a per-launch profile
at the grasp, docs/design.md, Work a soft iteration repeated). Edge and face contacts, which Newton
makes only with ``enable_rigid_soft_full_surface_contact``, read several nodes' positions and keep the
per-colour pass: the iteration is installed only for point contacts, and only where the solver has
no self-contact, DAT, springs or particle-body attachments (each adds launches this iteration lacks).
"""

from __future__ import annotations

import warp as wp
from d3grasp.kernels.fem_elasticity import TetStartState, vertex_newton_step
from newton._src.geometry.soft_contacts_mesh import (
    _make_soft_contact_filter_data,
    _soft_contact_force_enabled,
    _SoftContactFilterData,
)
from newton._src.solvers.vbd.rigid_vbd_kernels import _eval_body_particle_contact
from newton._src.utils.mesh import MeshAdjacencyData

__all__ = ["accumulate_point_contacts", "solve_elasticity_tets_in_place", "use_fused_particle_iteration"]


@wp.kernel
def accumulate_point_contacts(
    dt: float,
    pos_anchor: wp.array(dtype=wp.vec3),
    pos: wp.array(dtype=wp.vec3),
    friction_epsilon: float,
    use_log_barrier: bool,
    particle_radius: wp.array(dtype=float),
    contact_indices: wp.array(dtype=wp.vec3i),
    contact_count: wp.array(dtype=int),
    contact_filter: _SoftContactFilterData,
    contact_max: int,
    contact_ke: wp.array(dtype=float),
    contact_kd: wp.array(dtype=float),
    contact_mu: wp.array(dtype=float),
    shape_body: wp.array(dtype=int),
    body_q: wp.array(dtype=wp.transform),
    body_q_prev: wp.array(dtype=wp.transform),
    body_qd: wp.array(dtype=wp.spatial_vector),
    body_com: wp.array(dtype=wp.vec3),
    contact_shape: wp.array(dtype=int),
    contact_body_pos: wp.array(dtype=wp.vec3),
    contact_body_vel: wp.array(dtype=wp.vec3),
    contact_normal: wp.array(dtype=wp.vec3),
    shape_margin: wp.array(dtype=float),
    particle_forces: wp.array(dtype=wp.vec3),
    particle_hessians: wp.array(dtype=wp.mat33),
):
    # One thread, the contacts in their order: a node's sum comes out as the per-colour pass's.
    for contact in range(wp.min(contact_max, contact_count[0])):
        corners = contact_indices[contact]
        if corners[1] < 0 and _soft_contact_force_enabled(contact, contact_filter):
            particle = corners[0]
            force, hessian = _eval_body_particle_contact(
                particle,
                pos[particle],
                pos_anchor[particle],
                contact,
                contact_ke[contact],
                contact_kd[contact],
                contact_mu[contact],
                friction_epsilon,
                particle_radius,
                shape_body,
                body_q,
                body_q_prev,
                body_qd,
                body_com,
                contact_shape,
                contact_body_pos,
                contact_body_vel,
                contact_normal,
                shape_margin,
                dt,
                use_log_barrier,
            )
            particle_forces[particle] = particle_forces[particle] + force
            particle_hessians[particle] = particle_hessians[particle] + hessian


@wp.kernel
def solve_elasticity_tets_in_place(
    dt: float,
    particle_ids_in_color: wp.array(dtype=wp.int32),
    pos_start: wp.array(dtype=wp.vec3),
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
    # The closed-form solve of one colour's vertices, each then placed at its start position plus
    # its displacement, as the truncation pass (factor 1, no clamp) would place it.
    particle = particle_ids_in_color[wp.tid()]
    displacement = vertex_newton_step(
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
    particle_displacements[particle] = displacement
    pos[particle] = pos_start[particle] + displacement


def use_fused_particle_iteration(solver, tets: TetStartState, point_contacts_only: bool) -> bool:
    """Give ``solver`` (a SolverVBD on which :func:`use_closed_form_tets` returned ``tets``) the
    iteration of this module; return whether it qualifies. ``point_contacts_only``: the collision
    pipeline makes no edge or face soft contacts (``enable_rigid_soft_full_surface_contact`` off)."""
    model = solver.model
    if (
        not point_contacts_only
        or model.device.is_cuda
        or solver.particle_enable_self_contact
        or solver.rigid_soft_enable_dat
        or model.spring_count
        or model.attachment_particle_body_count
    ):
        return False

    def iterate(state_in, state_out, contacts, dt):
        # SolverVBD._solve_particle_iteration with the two passes taken out (module doc).
        if model.particle_count == 0:
            return
        if solver.integrate_with_external_rigid_solver:
            body_q, body_q_prev, body_qd = state_out.body_q, state_in.body_q, state_out.body_qd
        else:
            body_q, body_qd = state_in.body_q, state_in.body_qd
            body_q_prev = solver.body_q_prev if model.body_count > 0 else None
        solver.particle_forces.zero_()
        solver.particle_hessians.zero_()
        if contacts is not None and contacts.soft_contact_max > 0:
            wp.launch(
                accumulate_point_contacts,
                dim=1,
                inputs=[
                    dt,
                    solver.particle_q_prev,
                    state_in.particle_q,
                    solver.friction_epsilon,
                    solver.rigid_soft_contact_use_log_barrier,
                    model.particle_radius,
                    contacts.soft_contact_indices,
                    contacts.soft_contact_count,
                    _make_soft_contact_filter_data(model, contacts, state_in.particle_q, body_q),
                    contacts.soft_contact_max,
                    solver.body_particle_contact_penalty_k,
                    solver.body_particle_contact_material_kd,
                    solver.body_particle_contact_material_mu,
                    model.shape_body,
                    body_q,
                    body_q_prev,
                    body_qd,
                    model.body_com,
                    contacts.soft_contact_shape,
                    contacts.soft_contact_body_pos,
                    contacts.soft_contact_body_vel,
                    contacts.soft_contact_normal,
                    model.shape_margin,
                ],
                outputs=[solver.particle_forces, solver.particle_hessians],
                device=model.device,
            )
        for group in model.particle_color_groups:
            wp.launch(
                solve_elasticity_tets_in_place,
                dim=group.size,
                inputs=[
                    dt,
                    group,
                    solver.pos_prev_collision_detection,
                    state_in.particle_q,
                    model.particle_mass,
                    solver.inertia,
                    model.particle_flags,
                    model.tet_indices,
                    model.tet_poses,
                    model.tet_materials,
                    tets.volumes,
                    tets.cauchy_green_prev,
                    solver.particle_adjacency,
                    solver.particle_forces,
                    solver.particle_hessians,
                ],
                outputs=[solver.particle_displacements],
                device=model.device,
            )
        wp.copy(state_out.particle_q, state_in.particle_q)

    solver._solve_particle_iteration = iterate
    return True
