"""The closed-form tet elasticity kernel against float64 finite differences of the energy, against
SolverVBD's own kernel on the same inputs, and in a whole SolverVBD step."""

from __future__ import annotations

import newton
import numpy as np
import pytest
import warp as wp
from d3grasp.kernels.fem_elasticity import (
    solve_elasticity_tets,
    tet_vertex_force_hessian,
    use_closed_form_tets,
)
from d3grasp.kernels.particle_iteration import use_fused_particle_iteration
from d3grasp.kernels.strain_numpy import grid_tet_mesh
from newton._src.solvers.vbd import solver_vbd
from newton._src.solvers.vbd.particle_vbd_kernels import solve_elasticity as newton_solve_elasticity

wp.config.log_level = wp.LOG_WARNING

MU, LMBD, DAMP, DT = 3.0e4, 5.0e4, 40.0, 1.0 / 600.0


def edge_matrix(points: np.ndarray) -> np.ndarray:
    """[x1 - x0, x2 - x0, x3 - x0] of a tet's four points."""
    return np.column_stack([points[1] - points[0], points[2] - points[0], points[3] - points[0]])


def rest_volume(rest: np.ndarray) -> float:
    return abs(np.linalg.det(edge_matrix(rest))) / 6.0


def deformation_gradient(x: np.ndarray, rest: np.ndarray) -> np.ndarray:
    return edge_matrix(x) @ np.linalg.inv(edge_matrix(rest))


def ref_energy(x: np.ndarray, rest: np.ndarray) -> float:
    """Rest volume x the stable Neo-Hookean energy density (Newton's form, without the log term)."""
    F = deformation_gradient(x, rest)
    lmbd_nh = LMBD + MU
    alpha = 1.0 + MU / lmbd_nh
    psi = 0.5 * MU * (np.trace(F.T @ F) - 3.0) + 0.5 * lmbd_nh * (np.linalg.det(F) - alpha) ** 2
    return rest_volume(rest) * psi


def ref_cauchy_green(x: np.ndarray, rest: np.ndarray) -> np.ndarray:
    F = deformation_gradient(x, rest)
    return F.T @ F


def ref_dissipation(x: np.ndarray, x_prev: np.ndarray, rest: np.ndarray) -> float:
    """V k / (2 dt) sum_ij (C_ij - C_prev_ij)^2: its gradient in x is the damping force's negative."""
    dC = ref_cauchy_green(x, rest) - ref_cauchy_green(x_prev, rest)
    return rest_volume(rest) * DAMP / (2.0 * DT) * float(np.sum(dC * dC))


def central_gradient(fun, x: np.ndarray, corner: int, h: float) -> np.ndarray:
    g = np.zeros(3)
    for a in range(3):
        xp, xm = x.copy(), x.copy()
        xp[corner, a] += h
        xm[corner, a] -= h
        g[a] = (fun(xp) - fun(xm)) / (2.0 * h)
    return g


@wp.kernel
def _corner_kernel(
    pos: wp.array(dtype=wp.vec3),
    tet_indices: wp.array2d(dtype=wp.int32),
    dm_inv: wp.mat33,
    volume: float,
    cauchy_green_prev: wp.mat33,
    damping: float,
    forces: wp.array(dtype=wp.vec3),
    hessians: wp.array(dtype=wp.mat33),
):
    corner = wp.tid()
    f, h = tet_vertex_force_hessian(
        0, corner, pos, tet_indices, dm_inv, volume, cauchy_green_prev, MU, LMBD, damping, DT
    )
    forces[corner] = f
    hessians[corner] = h


def corner_terms(x: np.ndarray, x_prev: np.ndarray, rest: np.ndarray, damping: float):
    forces = wp.zeros(4, dtype=wp.vec3)
    hessians = wp.zeros(4, dtype=wp.mat33)
    wp.launch(
        _corner_kernel,
        dim=4,
        inputs=[
            wp.array(x, dtype=wp.vec3),
            wp.array([[0, 1, 2, 3]], dtype=wp.int32),
            wp.mat33(np.linalg.inv(edge_matrix(rest)).astype(np.float32)),
            rest_volume(rest),
            wp.mat33(ref_cauchy_green(x_prev, rest).astype(np.float32)),
            damping,
        ],
        outputs=[forces, hessians],
    )
    return forces.numpy().astype(np.float64), hessians.numpy().astype(np.float64)


def random_tet(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A 1 cm tet and a current pose up to ~30% strained, rotated and moved."""
    corners = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], float)
    rest = 0.01 * corners + 0.002 * rng.normal(size=(4, 3))
    A = np.eye(3) + 0.3 * rng.normal(size=(3, 3)) / 3.0
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    x = rest @ A.T @ (q * np.sign(np.linalg.det(q))).T + rng.normal(size=3) * 0.05
    return rest, x


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_elastic_force_and_hessian_are_the_energy_derivatives(seed: int) -> None:
    rng = np.random.default_rng(seed)
    rest, x = random_tet(rng)
    forces, hessians = corner_terms(x, x, rest, damping=0.0)

    def energy(y: np.ndarray) -> float:
        return ref_energy(y, rest)

    for corner in range(4):
        grad = central_gradient(energy, x, corner, 1e-7)
        np.testing.assert_allclose(forces[corner], -grad, rtol=2e-3, atol=1e-3 * np.abs(grad).max())
        # The block is the exact second derivative: J is linear in any one corner.
        hess = np.column_stack(
            [
                central_gradient(
                    lambda y, a=a, c=corner: central_gradient(energy, y, c, 1e-7)[a], x, corner, 1e-6
                )
                for a in range(3)
            ]
        )
        np.testing.assert_allclose(hessians[corner], hess, rtol=2e-2, atol=2e-2 * np.abs(hess).max())


def test_damping_force_is_the_dissipation_gradient_with_a_gauss_newton_hessian() -> None:
    rng = np.random.default_rng(3)
    rest, x = random_tet(rng)
    x_prev = x + 2e-4 * rng.normal(size=x.shape)
    f_all, h_all = corner_terms(x, x_prev, rest, damping=DAMP)
    f_el, h_el = corner_terms(x, x_prev, rest, damping=0.0)
    volume = rest_volume(rest)
    for corner in range(4):
        grad = central_gradient(lambda y: ref_dissipation(y, x_prev, rest), x, corner, 1e-8)
        damping_force = f_all[corner] - f_el[corner]
        np.testing.assert_allclose(damping_force, -grad, rtol=5e-3, atol=5e-3 * np.abs(grad).max())
        # Gauss-Newton: V k / dt sum_ij (dC_ij/dx)(dC_ij/dx)^T, dC/dx by finite differences.
        dC = np.stack(
            [
                central_gradient(lambda y, i=i, j=j: ref_cauchy_green(y, rest)[i, j], x, corner, 1e-7)
                for i in range(3)
                for j in range(3)
            ]
        )
        ref = volume * DAMP / DT * dC.T @ dC
        damping_hessian = h_all[corner] - h_el[corner]
        np.testing.assert_allclose(damping_hessian, ref, rtol=1e-2, atol=1e-2 * np.abs(ref).max())


def soft_grid_model(tri_ke: float = 0.0, box_on_top: bool = False) -> newton.Model:
    points, tets = grid_tet_mesh(4, 3, 3, spacing=0.01)
    # Positive orientation for every tet (half of the grid's come inverted): swap two corners.
    e = points[tets[:, 1:]] - points[tets[:, :1]]
    inverted = np.linalg.det(e.transpose(0, 2, 1)) < 0.0
    tets[inverted] = tets[inverted][:, [0, 2, 1, 3]]
    builder = newton.ModelBuilder()
    builder.add_soft_mesh(
        pos=(0.0, 0.0, 0.05),
        rot=wp.quat_identity(),
        scale=1.0,
        vel=(0.0, 0.0, 0.0),
        vertices=[tuple(p) for p in points],
        indices=tets.ravel().tolist(),
        density=200.0,
        k_mu=MU,
        k_lambda=LMBD,
        k_damp=DAMP,
        tri_ke=tri_ke,
        particle_radius=0.003,
    )
    if box_on_top:
        # A 40 g box dropped onto the block: contacts of nodes against a moving body as well.
        body = builder.add_body(xform=wp.transform((0.015, 0.01, 0.085), wp.quat_identity()))
        builder.add_shape_box(
            body, hx=0.01, hy=0.01, hz=0.01, cfg=newton.ModelBuilder.ShapeConfig(density=5000.0)
        )
    builder.color()
    builder.add_ground_plane()
    return builder.finalize(device="cpu")


def test_displacements_match_solver_vbds_own_kernel() -> None:
    """The same launch inputs through Newton's kernel and the closed form: the same Newton steps."""
    model = soft_grid_model()
    solver = newton.solvers.SolverVBD(model, iterations=1)
    rng = np.random.default_rng(4)
    rest = model.particle_q.numpy().astype(np.float64)
    x = rest @ (np.eye(3) + 0.1 * rng.normal(size=(3, 3))).T
    x_prev = x - 1e-4 * rng.normal(size=x.shape)
    # The closed form reads each tet's rest volume and C = F^T F at the previous positions (NumPy
    # here) where Newton's signature has the triangles' areas and poses, which a tet model leaves unread.
    tets = model.tet_indices.numpy()
    rest_tets = [rest[t] for t in tets]
    closed_form_slots = {
        "tri_poses": wp.array(
            [ref_cauchy_green(x_prev[t], r) for t, r in zip(tets, rest_tets, strict=True)], dtype=wp.mat33
        ),
        "tri_areas": wp.array([rest_volume(r) for r in rest_tets], dtype=float),
    }
    inputs_common = [
        wp.array(x_prev, dtype=wp.vec3),  # previous positions
        wp.array(x, dtype=wp.vec3),
        model.particle_mass,
        wp.array(x + 1e-5 * rng.normal(size=x.shape), dtype=wp.vec3),  # inertia targets
        model.particle_flags,
        model.tri_indices,
        model.tri_poses,
        model.tri_materials,
        model.tri_areas,
        model.edge_indices,
        model.edge_rest_angle,
        model.edge_rest_length,
        model.edge_bending_properties,
        model.tet_indices,
        model.tet_poses,
        model.tet_materials,
        solver.particle_adjacency,
        wp.array(1e-3 * rng.normal(size=x.shape), dtype=wp.vec3),  # contact forces
        wp.zeros(len(x), dtype=wp.mat33),
    ]
    out = {}
    for name, kernel in (("newton", newton_solve_elasticity), ("closed_form", solve_elasticity_tets)):
        inputs = list(inputs_common)
        if name == "closed_form":
            inputs[6], inputs[8] = closed_form_slots["tri_poses"], closed_form_slots["tri_areas"]
        displacement = wp.zeros(len(x), dtype=wp.vec3)
        for group in model.particle_color_groups:
            wp.launch(kernel, dim=group.size, inputs=[DT, group, *inputs], outputs=[displacement])
        out[name] = displacement.numpy()
    scale = np.abs(out["newton"]).max()
    assert scale > 1e-6
    np.testing.assert_allclose(out["closed_form"], out["newton"], atol=1e-4 * scale)


def drop(model: newton.Model, steps: int, solve: str) -> tuple[np.ndarray, np.ndarray, int]:
    """``steps`` substeps of 10 iterations with Newton's solve ("newton"), the closed form in
    Newton's iteration ("closed_form") or the fused iteration ("fused"): final node and body
    positions and the most soft contacts seen."""
    solver = newton.solvers.SolverVBD(model, iterations=10, particle_enable_self_contact=False)
    if solve != "newton":
        tets = use_closed_form_tets(solver)
        assert tets is not None
        if solve == "fused":
            assert use_fused_particle_iteration(solver, tets, point_contacts_only=True)
    state_0, state_1, control = model.state(), model.state(), model.control()
    pipeline = newton.CollisionPipeline(model, soft_contact_gap=0.005)
    contacts = pipeline.contacts()
    most_contacts = 0
    for _ in range(steps):
        state_0.clear_forces()
        pipeline.collide(state_0, contacts)
        most_contacts = max(most_contacts, int(contacts.soft_contact_count.numpy()[0]))
        solver.step(state_0, state_1, control, contacts, DT)
        state_0, state_1 = state_1, state_0
    bodies = state_0.body_q.numpy() if model.body_count else np.zeros((0, 7))
    return state_0.particle_q.numpy(), bodies, most_contacts


def test_solver_steps_with_the_closed_form_follow_newtons() -> None:
    """A soft block dropped onto the ground, 60 substeps of 10 iterations each way: same trajectory."""
    finals = {solve: drop(soft_grid_model(), 60, solve)[0] for solve in ("newton", "closed_form")}
    # It fell 0.1 s (~5 cm) onto the ground; the two solves agree to well under the particle radius.
    assert finals["newton"][:, 2].min() < 0.005
    np.testing.assert_allclose(finals["closed_form"], finals["newton"], atol=2e-5)
    # The swap lasts only through the closed-form solver's own iterations.
    assert solver_vbd.solve_elasticity is newton_solve_elasticity


def test_only_tet_only_models_get_the_closed_form() -> None:
    assert use_closed_form_tets(newton.solvers.SolverVBD(soft_grid_model(), iterations=1))
    membrane = soft_grid_model(tri_ke=100.0)
    assert not use_closed_form_tets(newton.solvers.SolverVBD(membrane, iterations=1))


def test_fused_iteration_follows_newtons_iteration() -> None:
    """The block on the ground with a box dropped onto it, 120 substeps: the fused iteration (contacts
    once an iteration, nodes placed by the solve) against the closed form in Newton's iteration. The
    same arithmetic in the same order: the trajectories agree far below any physical scale (they were
    bit-identical where measured)."""
    runs = {solve: drop(soft_grid_model(box_on_top=True), 120, solve) for solve in ("closed_form", "fused")}
    nodes, bodies, most_contacts = runs["closed_form"]
    assert most_contacts > 20  # the block's bottom on the ground and its top under the box
    assert nodes[:, 2].min() < 0.005  # landed
    assert bodies[0, 2] < 0.08  # the box fell onto the block (it started at 8.5 cm)
    np.testing.assert_allclose(runs["fused"][0], nodes, rtol=0.0, atol=1e-6)
    np.testing.assert_allclose(runs["fused"][1], bodies, rtol=0.0, atol=1e-6)


def test_fused_iteration_only_where_it_is_the_same_iteration() -> None:
    model = soft_grid_model()
    solver = newton.solvers.SolverVBD(model, iterations=1, particle_enable_self_contact=False)
    tets = use_closed_form_tets(solver)
    assert not use_fused_particle_iteration(solver, tets, point_contacts_only=False)
    self_contact = newton.solvers.SolverVBD(
        soft_grid_model(), iterations=1, particle_enable_self_contact=True
    )
    assert not use_fused_particle_iteration(
        self_contact, use_closed_form_tets(self_contact), point_contacts_only=True
    )
    assert use_fused_particle_iteration(solver, tets, point_contacts_only=True)
