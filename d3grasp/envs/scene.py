"""The multi-world grasp scene: one ``newton.Model`` with a table, a DexHand13 and one object per world.

Worlds do not collide with each other in Newton, so every world sits at the same place: the
table is one global ground plane (world -1) at ``SimConfig.table_height``. Each hand's root chain
is anchored at the world origin, rotated so that zero root angles mean *palm facing down*
(:data:`HAND_ANCHOR_QUAT`): SolverVBD's angular drives wrap their error to ±π, so a target of
exactly π (palm down from a palm-up anchor) is unstable; from a palm-down anchor every grasp
type's orientation stays well inside ±π/2.

:class:`SceneLayout` holds every index the environment needs, one row per world, as NumPy arrays
(and Warp copies where kernels read them).
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import newton
import numpy as np
import warp as wp

from d3grasp.authoring.hand_newton import HandIndices, add_hand
from d3grasp.authoring.hand_spec import palm_pose_to_root_q
from d3grasp.authoring.manifest import AssetEntry, read_manifest
from d3grasp.dexhand13 import LINK_NAMES
from d3grasp.envs.config import ObjectSetConfig
from d3grasp.geometry import matrix_to_quat_xyzw_nonneg_w, quat_xyzw_to_matrix
from d3grasp.paths import default_manifest

HAND_ANCHOR_QUAT = (1.0, 0.0, 0.0, 0.0)
"""Rotation (x, y, z, w) of the root chain's anchor: π about world x, so the palm faces down."""

_ANCHOR_R = quat_xyzw_to_matrix(HAND_ANCHOR_QUAT)

OBJECT_RIGID = 0
OBJECT_SOFT = 1


def palm_world_pose_to_free_q(pos: np.ndarray, quat_xyzw: np.ndarray) -> np.ndarray:
    """Free-joint coordinates (7,) of a kinematic palm at a world pose: position, quaternion x, y, z, w."""
    return np.concatenate([np.asarray(pos, dtype=np.float64), np.asarray(quat_xyzw, dtype=np.float64)])


def palm_world_pose_to_root_q(pos: np.ndarray, quat_xyzw: np.ndarray) -> np.ndarray:
    """Root joint coordinates (6,) that put the palm at a world pose (the anchor sits at the origin)."""
    r_world = quat_xyzw_to_matrix(quat_xyzw)
    return palm_pose_to_root_q(
        _ANCHOR_R.T @ np.asarray(pos, dtype=np.float64), matrix_to_quat_xyzw_nonneg_w(_ANCHOR_R.T @ r_world)
    )


@dataclass
class SceneLayout:
    """Per-world indices into the finalized model. Arrays have the world as first axis."""

    num_worlds: int
    entries: list[AssetEntry]
    object_kind: np.ndarray  # (W,) OBJECT_RIGID / OBJECT_SOFT
    object_body: np.ndarray  # (W,) body index, -1 for soft objects
    object_joint_q: np.ndarray  # (W,) start of the free joint's 7 coordinates, -1 for soft
    object_joint_qd: np.ndarray  # (W,) start of the free joint's 6 velocities, -1 for soft
    particle_start: np.ndarray  # (W,) first particle of the soft object (0 for rigid)
    particle_count: np.ndarray  # (W,) 0 for rigid
    tet_start: np.ndarray  # (W,)
    tet_count: np.ndarray  # (W,)
    finger_q: np.ndarray  # (W, 16) joint_q indices of the finger joints
    finger_dof: np.ndarray  # (W, 16)
    root_q: np.ndarray  # (W, 6) root chain angles, or (W, 7) the kinematic palm's free joint
    root_dof: np.ndarray  # (W, 6)
    kinematic_palm: bool  # palm prescribed each substep (no root chain)
    palm_body: np.ndarray  # (W,)
    link_bodies: np.ndarray  # (W, 17) palm + finger links, dexhand13.LINK_NAMES order
    hand_shapes: list[np.ndarray]  # per world, every collision shape of the hand
    pad_shapes: np.ndarray  # (W, 11)
    object_shapes: list[np.ndarray]  # per world, a rigid object's shapes, visual mesh first (empty: soft)
    articulation_world: np.ndarray  # (A,) world of each articulation (for masked FK on reset)
    rest_particle_q: np.ndarray  # (P, 3) particle positions as loaded (objects centred at the origin)
    finger_lower: np.ndarray  # (16,) joint limits (same hand in every world)
    finger_upper: np.ndarray  # (16,)


def build_scene(
    entries: list[tuple[AssetEntry, Path]],
    *,
    shape_mu: float = 1.0,
    particle_radius: float = 0.003,
    table_height: float = 0.0,
    contact_gap: float = 0.005,
    kinematic_palm: bool = False,
    device: str | None = None,
) -> tuple[newton.Model, SceneLayout]:
    """Build and finalize one model with a world per (asset entry, USD path).

    Objects are loaded at the origin in their rest frame; the environment places them on reset.
    ``kinematic_palm`` loads the hand without its root chain (see :func:`add_hand`).

    The hand's USD and each distinct object's are parsed once, into a template builder, and copied
    into every world that holds them (``ModelBuilder.add_builder``): parsing the hand took 0.2 s a
    world, which made a 4,096-world GPU scene a quarter of an hour of parsing. The copies are the
    same model, array for array, as parsing in every world (tests/envs/test_scene.py).
    """

    def new_builder() -> newton.ModelBuilder:
        b = newton.ModelBuilder()
        b.default_shape_cfg.mu = shape_mu
        # Contacts are generated for shape pairs closer than the gap; Newton's 0.1 m default makes
        # hundreds of far-apart contacts per hand and overflows VBD's per-body contact lists.
        b.default_shape_cfg.gap = contact_gap
        b.default_particle_radius = particle_radius
        return b

    builder = new_builder()
    builder.add_ground_plane(height=table_height)
    anchor = (
        wp.transform_identity()
        if kinematic_palm
        else wp.transform(wp.vec3(0.0, 0.0, 0.0), wp.quat(*HAND_ANCHOR_QUAT))
    )
    hand_template = new_builder()
    hand = add_hand(hand_template, xform=anchor, kinematic_palm=kinematic_palm)
    object_templates: dict[Path, newton.ModelBuilder] = {}
    rows: dict[str, list] = defaultdict(list)  # one row per world of every SceneLayout array
    for w, (entry, usd_path) in enumerate(entries):
        if usd_path not in object_templates:
            object_templates[usd_path] = _object_template(new_builder(), entry, usd_path)
        builder.begin_world(label=f"world_{w}")
        _add_hand(builder, rows, hand_template, hand)
        _add_object(builder, rows, entry, object_templates[usd_path])
        builder.end_world()
    builder.color()
    model = builder.finalize(device=device)
    return model, _layout(model, rows, [e for e, _ in entries], kinematic_palm)


def _add_hand(
    builder: newton.ModelBuilder, rows: dict[str, list], template: newton.ModelBuilder, hand: HandIndices
) -> None:
    """Copy the hand ``template`` (indexed by ``hand``) into the current world; record its indices."""
    q0, d0 = builder.joint_coord_count, builder.joint_dof_count
    b0, s0 = builder.body_count, builder.shape_count
    builder.add_builder(template)
    rows["finger_q"].append(hand.finger_q + q0)
    rows["finger_dof"].append(hand.finger_dof + d0)
    rows["root_q"].append(hand.root_q + q0)
    rows["root_dof"].append(hand.root_dof + d0)
    rows["palm_body"].append(hand.palm_body + b0)
    rows["link_bodies"].append([hand.link_bodies[n] + b0 for n in LINK_NAMES])
    rows["pad_shapes"].append(hand.pad_shapes + s0)
    rows["hand_shapes"].append(np.arange(*hand.shape_range, dtype=np.int32) + s0)


def _object_template(template: newton.ModelBuilder, entry: AssetEntry, usd_path: Path) -> newton.ModelBuilder:
    """One object's USD loaded into the empty ``template``, checked to be what its kind says."""
    try:
        template.add_usd(str(usd_path), xform=wp.transform_identity())
    except Exception as exc:  # a broken asset must name itself
        raise ValueError(f"{usd_path}: cannot load object '{entry.id}' ({exc})") from exc
    bodies, joints = template.body_count, template.joint_count
    if entry.kind == "rigid" and (bodies != 1 or joints != 1):
        raise ValueError(
            f"{usd_path}: rigid object must add one body and one free joint, "
            f"added {bodies} bodies and {joints} joints"
        )
    if entry.kind != "rigid" and (not template.particle_count or not template.tet_count):
        raise ValueError(f"{usd_path}: soft object added no particles or tets")
    return template


def _add_object(
    builder: newton.ModelBuilder, rows: dict[str, list], entry: AssetEntry, template: newton.ModelBuilder
) -> None:
    """Copy one object's template into the current world and record where its body or particles went."""
    b0, s0 = builder.body_count, builder.shape_count
    q0, d0 = builder.joint_coord_count, builder.joint_dof_count
    n0, t0 = builder.particle_count, builder.tet_count
    builder.add_builder(template)
    if entry.kind == "rigid":
        rows["object_kind"].append(OBJECT_RIGID)
        rows["object_body"].append(b0)
        rows["object_joint_q"].append(q0 + template.joint_q_start[0])
        rows["object_joint_qd"].append(d0 + template.joint_qd_start[0])
        rows["object_shapes"].append(np.arange(s0, builder.shape_count, dtype=np.int32))
    else:
        rows["object_kind"].append(OBJECT_SOFT)
        rows["object_body"].append(-1)
        rows["object_joint_q"].append(-1)
        rows["object_joint_qd"].append(-1)
        rows["object_shapes"].append(np.zeros(0, dtype=np.int32))
    rows["particle_start"].append(n0)
    rows["particle_count"].append(template.particle_count)
    rows["tet_start"].append(t0)
    rows["tet_count"].append(template.tet_count)


def _layout(
    model: newton.Model, rows: dict[str, list], entries: list[AssetEntry], kinematic_palm: bool
) -> SceneLayout:
    art_world = model.articulation_world.numpy() if model.articulation_count else np.zeros(0, np.int32)
    f_dof0 = np.asarray(rows["finger_dof"][0])
    per_world = {
        k: np.array(v, dtype=np.int32) for k, v in rows.items() if k not in ("hand_shapes", "object_shapes")
    }
    return SceneLayout(
        num_worlds=len(entries),
        entries=entries,
        kinematic_palm=kinematic_palm,
        hand_shapes=rows["hand_shapes"],
        object_shapes=rows["object_shapes"],
        articulation_world=np.asarray(art_world, dtype=np.int32),
        rest_particle_q=model.particle_q.numpy().copy() if model.particle_count else np.zeros((0, 3)),
        finger_lower=model.joint_limit_lower.numpy()[f_dof0].astype(np.float64),
        finger_upper=model.joint_limit_upper.numpy()[f_dof0].astype(np.float64),
        **per_world,
    )


def select_world_objects(
    objects: ObjectSetConfig, num_worlds: int, rng: np.random.Generator
) -> tuple[Path, list[AssetEntry]]:
    """``(manifest, one entry per world)`` for an object set: explicit ids fill the worlds in the
    given order (cycled, e.g. for evaluation); otherwise the matching rigid and soft objects are
    shuffled and ``soft_fraction`` of the worlds (at least one each when both kinds are wanted and
    there are two or more worlds) get a soft one."""
    manifest = Path(objects.manifest) if objects.manifest else default_manifest()
    if not manifest.is_file():
        raise FileNotFoundError(f"object manifest not found: {manifest}")
    entries = read_manifest(manifest)
    if objects.ids:
        by_id = {e.id: e for e in entries}
        missing = [i for i in objects.ids if i not in by_id]
        if missing:
            raise ValueError(f"{manifest}: unknown asset ids {missing}")
        return manifest, [by_id[objects.ids[i % len(objects.ids)]] for i in range(num_worlds)]
    chosen = [
        e
        for e in entries
        if e.kind in objects.kinds
        and e.size_bin in objects.size_bins
        and (objects.split == "all" or e.split == objects.split)
    ]
    if not chosen:
        raise ValueError(
            f"{manifest}: no asset matches kinds={objects.kinds} split={objects.split} "
            f"size_bins={objects.size_bins}"
        )
    rigid = [e for e in chosen if e.kind == "rigid"]
    soft = [e for e in chosen if e.kind == "deformable"]
    rigid = [rigid[i] for i in rng.permutation(len(rigid))]
    soft = [soft[i] for i in rng.permutation(len(soft))]
    n_soft = 0
    if soft and rigid:
        n_soft = int(round(objects.soft_fraction * num_worlds))
        n_soft = min(max(n_soft, 1 if num_worlds > 1 else 0), num_worlds - 1)
    elif soft:
        n_soft = num_worlds
    world_entries = [soft[i % len(soft)] for i in range(n_soft)]
    world_entries += [rigid[i % len(rigid)] for i in range(num_worlds - n_soft)]
    return manifest, world_entries


def set_tet_damping(model: newton.Model, ranges: Iterable[tuple[int, int, float]]) -> None:
    """Write damping ``d`` on the model's tets ``[start, end)`` for each ``(start, end, d)``: Newton
    does not read a tet's damping from USD (column 2 of ``tet_materials``)."""
    ranges = list(ranges)
    if not model.tet_count or not ranges:
        return
    mats = model.tet_materials.numpy()
    for start, end, d in ranges:
        mats[start:end, 2] = d
    model.tet_materials.assign(mats)


def apply_soft_damping(model: newton.Model, layout: SceneLayout, soft_damping: float | None) -> None:
    """Set each soft object's tet damping from its manifest entry's material (or ``soft_damping``
    for all, when given)."""
    set_tet_damping(
        model,
        (
            (
                int(layout.tet_start[w]),
                int(layout.tet_start[w] + layout.tet_count[w]),
                soft_damping if soft_damping is not None else float(e.material.get("damping", 0.0)),
            )
            for w, e in enumerate(layout.entries)
            if e.kind == "deformable"
        ),
    )


def pad_object_friction(model: newton.Model, layout: SceneLayout) -> np.ndarray:
    """(W,) the friction coefficient SolverVBD applies where a pad meets each world's rigid object:
    the geometric mean of the two shapes' coefficients (``rigid_vbd_kernels``), the object's over its
    colliding shapes (its first shape is the visual mesh, which does not collide); NaN for a soft
    object, whose contacts follow the particle law."""
    mu = model.shape_material_mu.numpy()
    colliding = (model.shape_flags.numpy() & int(newton.ShapeFlags.COLLIDE_SHAPES)) != 0
    out = np.full(len(layout.object_shapes), np.nan)
    for w, shapes in enumerate(layout.object_shapes):
        hulls = [s for s in shapes if colliding[s]]
        if hulls:
            out[w] = np.sqrt(float(mu[layout.pad_shapes[w]].mean()) * float(mu[hulls].mean()))
    return out
