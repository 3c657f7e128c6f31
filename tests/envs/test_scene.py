"""The scene builder copies one parsed hand and one parsed object per asset into the worlds: the model
must be the one that parsing the USD files in every world gives (Newton's plain per-world import,
written out here as the reference), and the layout's indices must point at the same entities."""

from __future__ import annotations

import newton
import numpy as np
import pytest
import warp as wp

from d3grasp.authoring.hand_newton import add_hand  # noqa: E402
from d3grasp.authoring.manifest import read_manifest, resolve_asset_path  # noqa: E402
from d3grasp.dexhand13 import LINK_NAMES  # noqa: E402
from d3grasp.envs.scene import HAND_ANCHOR_QUAT, build_scene, pad_object_friction  # noqa: E402
from d3grasp.paths import default_manifest  # noqa: E402


def _entries(ids: list[str]):
    manifest = default_manifest()
    by_id = {e.id: e for e in read_manifest(manifest)}
    return [(by_id[i], resolve_asset_path(manifest, by_id[i])) for i in ids]


def _reference_model(entries, kinematic_palm: bool):
    """Every world parses the hand and its object from USD itself (no templates)."""
    b = newton.ModelBuilder()
    b.default_shape_cfg.mu = 1.0
    b.default_shape_cfg.gap = 0.005
    b.default_particle_radius = 0.003
    b.add_ground_plane(height=0.0)
    anchor = wp.transform((0.0, 0.0, 0.0), wp.quat(*HAND_ANCHOR_QUAT))
    if kinematic_palm:
        anchor = wp.transform_identity()
    hands, starts = [], []
    for w, (_, path) in enumerate(entries):
        b.begin_world(label=f"world_{w}")
        hands.append(add_hand(b, xform=anchor, kinematic_palm=kinematic_palm))
        starts.append((b.body_count, b.particle_count, b.tet_count))
        b.add_usd(str(path), xform=wp.transform_identity())
        b.end_world()
    b.color()
    return b.finalize(device="cpu"), hands, starts


def _arrays(model) -> dict[str, np.ndarray]:
    """The model's public arrays, less the addresses of its collision meshes (copies share one
    mesh) and the viewer's display colours (drawn from a palette as shapes are parsed); of the ray
    BVH's shape list only its filled rows (Newton allocates it uninitialised)."""
    arrays = {
        k: v.numpy()
        for k, v in vars(model).items()
        if isinstance(v, wp.array)
        and v.size
        and not k.startswith("_")
        and k not in ("shape_source_ptr", "shape_color", "bvh_shape_world_transforms")
    }
    arrays["bvh_shape_enabled"] = arrays["bvh_shape_enabled"][: model.bvh_shape_count_enabled]
    return arrays


@pytest.mark.parametrize("kinematic_palm", [True, False])
def test_templated_scene_is_the_per_world_import(kinematic_palm):
    # A rigid object twice (one template, two copies), another rigid one and a soft one.
    entries = _entries(["box_01", "sponge_cube_s", "box_01", "bottle_03"])
    model, layout = build_scene(entries, kinematic_palm=kinematic_palm, device="cpu")
    ref, hands, starts = _reference_model(entries, kinematic_palm)

    got, want = _arrays(model), _arrays(ref)
    assert sorted(got) == sorted(want)
    for name, a in want.items():
        if np.issubdtype(a.dtype, np.floating):
            np.testing.assert_allclose(got[name], a, rtol=1e-6, atol=1e-7, err_msg=name)
        else:
            np.testing.assert_array_equal(got[name], a, err_msg=name)

    # The collision meshes themselves: same vertices and faces shape by shape.
    for shape, (m, r) in enumerate(zip(model.shape_source, ref.shape_source, strict=True)):
        assert type(m) is type(r), shape
        if hasattr(r, "vertices"):
            np.testing.assert_allclose(np.asarray(m.vertices), np.asarray(r.vertices), rtol=0, atol=0)
            np.testing.assert_array_equal(np.asarray(m.indices), np.asarray(r.indices))

    for w, (hand, (body0, particle0, tet0)) in enumerate(zip(hands, starts, strict=True)):
        np.testing.assert_array_equal(layout.finger_q[w], hand.finger_q)
        np.testing.assert_array_equal(layout.finger_dof[w], hand.finger_dof)
        np.testing.assert_array_equal(layout.root_q[w], hand.root_q)
        np.testing.assert_array_equal(layout.root_dof[w], hand.root_dof)
        np.testing.assert_array_equal(layout.pad_shapes[w], hand.pad_shapes)
        np.testing.assert_array_equal(layout.link_bodies[w], [hand.link_bodies[n] for n in LINK_NAMES])
        np.testing.assert_array_equal(layout.hand_shapes[w], np.arange(*hand.shape_range))
        assert layout.palm_body[w] == hand.palm_body
        soft = entries[w][0].kind == "deformable"
        assert layout.object_body[w] == (-1 if soft else body0)
        assert layout.particle_start[w] == particle0
        assert layout.tet_start[w] == tet0
        if not soft:
            j = int(np.flatnonzero(ref.joint_child.numpy() == body0)[0])
            assert layout.object_joint_q[w] == ref.joint_q_start.numpy()[j]
            assert layout.object_joint_qd[w] == ref.joint_qd_start.numpy()[j]


def test_pad_object_friction_is_the_geometric_mean_with_the_objects_hull() -> None:
    """SolverVBD mixes a contact pair's coefficients by their geometric mean: a pad (the scene's shape
    coefficient, 1.0) on frustum_09's hull (its manifest friction, 0.6) meets sqrt(0.6); the object's
    visual mesh (first, non-colliding) does not count; a soft object has no shape coefficient."""
    entries = _entries(["frustum_09", "sponge_block_m"])
    with wp.ScopedDevice("cpu"):
        model, layout = build_scene(entries, shape_mu=1.0, particle_radius=0.003, table_height=0.0)
    friction = pad_object_friction(model, layout)
    assert entries[0][0].material["friction"] == 0.6
    assert friction[0] == pytest.approx(np.sqrt(0.6 * 1.0), rel=1e-6)
    assert np.isnan(friction[1])
