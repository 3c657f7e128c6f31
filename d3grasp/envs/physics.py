"""The physics of all worlds: SolverVBD, the collision pipeline, the substeps of one control step,
and clearing a reset world's solver history.

One control step (60 Hz) is ``substeps x (clear forces, move the kinematic palm, apply the
disturbance, collide, SolverVBD step)``; the environment captures it together with the sensors
as one Warp graph (:meth:`Physics.capture`).
"""

from __future__ import annotations

from collections.abc import Callable

import newton
import numpy as np
import warp as wp

from d3grasp.envs.config import SimConfig
from d3grasp.envs.scene import SceneLayout
from d3grasp.kernels.chebyshev import use_chebyshev
from d3grasp.kernels.fem_elasticity import use_closed_form_tets
from d3grasp.kernels.particle_iteration import use_fused_particle_iteration


@wp.kernel
def _apply_object_force_kernel(
    force: wp.array(dtype=wp.vec3),
    object_body: wp.array(dtype=wp.int32),
    particle_start: wp.array(dtype=wp.int32),
    particle_count: wp.array(dtype=wp.int32),
    particle_mass: wp.array(dtype=float),
    body_f: wp.array(dtype=wp.spatial_vector),
    particle_f: wp.array(dtype=wp.vec3),
):
    # One thread per world: the disturbance acts at the rigid body's frame origin (its bounding-box
    # centre, within millimetres of the centre of mass) or on a soft object's nodes in proportion to
    # their mass (a body force: every node accelerates alike and the push strains nothing). An equal
    # share per node gave a 0.44 mg surface node of sponge_cube_s 5e4 m/s^2 under the 2.5 N push.
    w = wp.tid()
    f = force[w]
    b = object_body[w]
    if b >= 0:
        body_f[b] = body_f[b] + wp.spatial_vector(f, wp.vec3(0.0, 0.0, 0.0))
    n = particle_count[w]
    if n > 0:
        p0 = particle_start[w]
        total = float(0.0)  # noqa: UP018 (Warp: a typed, mutable local)
        for i in range(n):
            total += particle_mass[p0 + i]
        if total > 0.0:
            for i in range(n):
                particle_f[p0 + i] = particle_f[p0 + i] + f * (particle_mass[p0 + i] / total)


@wp.kernel
def _set_palm_pose_kernel(
    palm_body: wp.array(dtype=wp.int32),
    pos_start: wp.array(dtype=wp.vec3),
    pos_end: wp.array(dtype=wp.vec3),
    quat: wp.array(dtype=wp.quat),
    yaw_start: wp.array(dtype=float),
    yaw_end: wp.array(dtype=float),
    alpha: float,
    body_q: wp.array(dtype=wp.transform),
):
    # One thread per world: the kinematic palm at fraction ``alpha`` of the control step, on the
    # straight line from where it was to the commanded position, turned about the vertical by the
    # wrist's yaw offset (0: exactly ``quat``). SolverVBD takes its velocity from the change against
    # its previous pose, so contacts see the true palm motion.
    w = wp.tid()
    p = pos_start[w] + alpha * (pos_end[w] - pos_start[w])
    yaw = yaw_start[w] + alpha * (yaw_end[w] - yaw_start[w])
    turn = wp.quat_from_axis_angle(wp.vec3(0.0, 0.0, 1.0), yaw)
    body_q[palm_body[w]] = wp.transform(p, turn * quat[w])


def rigid_iterations_run(n: int, iterations: int) -> list[bool]:
    """Which of ``iterations`` solver iterations solve the rigid bodies when ``n`` of them do: evenly
    spaced, the last one included (its result is the substep's)."""
    if not 1 <= n <= iterations:
        raise ValueError(f"sim.soft_rigid_iterations must be in [1, {iterations}] (0: all), got {n}")
    return [(i + 1) * n // iterations > i * n // iterations for i in range(iterations)]


def thin_rigid_iterations(solver: newton.solvers.SolverVBD, runs: list[bool]) -> None:
    """Make ``solver`` solve its rigid bodies only on the iterations ``runs`` marks (its particles on
    all; :func:`rigid_iterations_run`)."""
    step, solve_rigid = solver.step, solver._solve_rigid_body_iteration
    sweep = [0]

    def step_counting(*args, **kwargs):
        sweep[0] = 0
        return step(*args, **kwargs)

    def solve_rigid_some(*args, **kwargs):
        k = sweep[0]
        sweep[0] += 1
        if runs[k % len(runs)]:
            return solve_rigid(*args, **kwargs)
        # An iteration without the rigid solve takes SolverVBD's own path for a solver that does not
        # integrate bodies: the body-particle contacts' penalties still ramp as on every iteration.
        solver._integrates_rigid_bodies = False
        try:
            return solve_rigid(*args, **kwargs)
        finally:
            solver._integrates_rigid_bodies = True

    solver.step = step_counting
    solver._solve_rigid_body_iteration = solve_rigid_some


def use_soft_solve_kernels(
    solver: newton.solvers.SolverVBD, pipeline: newton.CollisionPipeline, sim: SimConfig
) -> None:
    """The soft solve's kernels of d3grasp.kernels where ``sim`` asks for them and the model qualifies:
    the closed-form tets (``sim.closed_form_tets``) and, on the CPU, the particle iteration without its
    repeated passes (``sim.fused_particle_iteration``). Both give SolverVBD's results."""
    tets = use_closed_form_tets(solver) if sim.closed_form_tets else None
    if tets is not None and sim.fused_particle_iteration:
        use_fused_particle_iteration(
            solver, tets, point_contacts_only=not pipeline.enable_rigid_soft_full_surface_contact
        )


def capture_graph(launches: Callable[[], None], device: wp.context.Device) -> wp.Graph:
    """``launches`` captured as a Warp graph on ``device`` (run it once before: a capture records
    launches, it does not load modules or size lazy buffers)."""
    with wp.ScopedDevice(device), wp.ScopedCapture() as capture:
        launches()
    return capture.graph


class Replayed:
    """Kernel launches on fixed buffers, replayed as a captured graph when ``use_graph`` (a graph
    launch costs ~0.5 us on the CPU, a ``wp.launch`` with a dozen arguments ~7 us), else called.
    ``modules``: the Python modules of the kernels, loaded before the capture (which records
    launches; it does not load modules)."""

    def __init__(
        self, launches: Callable[[], None], modules: list, device: wp.context.Device, use_graph: bool
    ):
        self.launches = launches
        self.graph = None
        if use_graph:
            for m in modules:
                wp.load_module(m, device=device)
            self.graph = capture_graph(launches, device)

    def __call__(self) -> None:
        if self.graph is not None:
            wp.capture_launch(self.graph)
        else:
            self.launches()


class Physics:
    """States, solver and collision pipeline of the multi-world model, and the per-world inputs the
    substeps read: the disturbance force on each object and the kinematic palm's path."""

    def __init__(self, model: newton.Model, layout: SceneLayout, sim: SimConfig, device: wp.context.Device):
        self.model, self.layout, self.sim, self.device = model, layout, sim, device
        W = layout.num_worlds
        self.num_worlds = W
        self.sim_dt = 1.0 / sim.control_hz / sim.substeps
        with wp.ScopedDevice(device):
            self.state_0 = model.state()
            self.state_1 = model.state()
            self.control = model.control()
            # The default capacity (~1300 per world here) sizes several per-substep kernels that run
            # over the whole buffer; grasps use < 100 contacts per world.
            self.pipeline = newton.CollisionPipeline(
                model,
                contact_matching="sticky",
                soft_contact_gap=sim.soft_contact_gap,
                rigid_contact_max=sim.rigid_contacts_per_world * W,
            )
            self.contacts = self.pipeline.contacts()
            self.solver = newton.solvers.SolverVBD(
                model,
                iterations=sim.soft_iterations if (layout.particle_count > 0).any() else sim.iterations,
                friction_epsilon=sim.friction_epsilon,
                rigid_contact_history=True,
                particle_enable_self_contact=False,
                rigid_body_contact_buffer_size=sim.body_contact_buffer,
            )
            use_soft_solve_kernels(self.solver, self.pipeline, sim)
            use_chebyshev(self.solver, sim.soft_chebyshev_rho)
            if sim.soft_rigid_iterations:
                # A bad value is refused on any model, soft or not.
                runs = rigid_iterations_run(sim.soft_rigid_iterations, sim.soft_iterations)
                if (layout.particle_count > 0).any():
                    thin_rigid_iterations(self.solver, runs)
            if not device.is_cuda:
                # The body-particle contact kernel runs this many workers per colour and iteration,
                # each striding over the active contacts (Newton sizes it to fill a GPU: one per
                # particle). On the CPU backend a worker is a loop iteration with a call's overhead
                # and the atomics are plain adds, so one worker does the same sums with no idle
                # calls: 7% of a soft control step on the 4 soft test objects (797 contacts).
                self.solver._particle_contact_worker_count = 1
            self.observables = self.solver.observables(kinds={"contact_f"}, contacts=self.contacts)
        self.object_force = wp.zeros(W, dtype=wp.vec3, device=device)
        self.object_body = wp.array(layout.object_body, dtype=wp.int32, device=device)
        self.particle_start = wp.array(layout.particle_start, dtype=wp.int32, device=device)
        self.particle_count = wp.array(layout.particle_count, dtype=wp.int32, device=device)
        # Kinematic palm: position at the start and end of the control step, fixed orientation.
        self.palm_body = wp.array(layout.palm_body, dtype=wp.int32, device=device)
        self.palm_pos_start = wp.zeros(W, dtype=wp.vec3, device=device)
        self.palm_pos_end = wp.zeros(W, dtype=wp.vec3, device=device)
        self.palm_quat = wp.zeros(W, dtype=wp.quat, device=device)
        self.palm_yaw_start = wp.zeros(W, dtype=float, device=device)  # the wrist's yaw offset (rad)
        self.palm_yaw_end = wp.zeros(W, dtype=float, device=device)
        self.graph = None

    def substeps(self) -> None:
        """The physics of one control step (Warp launches only: capturable)."""
        sim = self.sim
        for i in range(sim.substeps):
            self.state_0.clear_forces()
            if self.layout.kinematic_palm:
                wp.launch(
                    _set_palm_pose_kernel,
                    dim=self.num_worlds,
                    inputs=[
                        self.palm_body,
                        self.palm_pos_start,
                        self.palm_pos_end,
                        self.palm_quat,
                        self.palm_yaw_start,
                        self.palm_yaw_end,
                        float(i + 1) / float(sim.substeps),
                    ],
                    outputs=[self.state_0.body_q],
                    device=self.device,
                )
            wp.launch(
                _apply_object_force_kernel,
                dim=self.num_worlds,
                inputs=[
                    self.object_force,
                    self.object_body,
                    self.particle_start,
                    self.particle_count,
                    self.model.particle_mass,
                ],
                outputs=[self.state_0.body_f, self.state_0.particle_f],
                device=self.device,
            )
            # Contacts are stored in body frames and re-evaluated every solver iteration, so detecting
            # every other substep loses little (the gap covers the motion in between).
            if i % max(1, sim.collide_every) == 0:
                self.pipeline.collide(self.state_0, self.contacts)
            self.solver.step(
                self.state_0,
                self.state_1,
                self.control,
                self.contacts,
                self.sim_dt,
                observables=self.observables,
            )
            self.state_0, self.state_1 = self.state_1, self.state_0

    def capture(self, control_step: Callable[[], None]) -> None:
        """Run ``control_step`` once (it sizes the solver's lazy buffers), then capture it as a graph."""
        if self.sim.substeps % 2:
            raise ValueError("sim.substeps must be even: the captured step swaps two states")
        control_step()
        self.graph = capture_graph(control_step, self.device) if self.sim.use_graph else None

    def launch(self, control_step: Callable[[], None]) -> None:
        """One control step: the captured graph, or ``control_step`` itself when not captured."""
        if self.graph is not None:
            wp.capture_launch(self.graph)
        else:
            control_step()

    def forget_history(self, worlds: np.ndarray) -> None:
        """Clear the solver's rigid history (previous poses, joint winding, contact warm starts) and
        the pipeline's sticky contacts of ``worlds``: without it a body teleported by a reset looks
        as if it moved that far in one substep."""
        world_mask = np.zeros(self.model.world_count + 1, dtype=bool)
        world_mask[worlds] = True
        wmask = wp.array(world_mask, dtype=wp.bool, device=self.device)
        self.solver.reset(self.state_0, wmask, flags=0)
        self.pipeline.reset_contact_matching(wmask)
