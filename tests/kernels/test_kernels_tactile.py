"""Tactile kernels against a NumPy/SciPy transcription on synthetic Newton-layout contact arrays."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import warp as wp
from d3grasp.kernels.tactile import (
    NUM_PADS,
    TactileConfig,
    TactileLayout,
    accumulate_pad_forces,
    pad_forces_in_pad_frames,
    pad_frame_forces,
)
from scipy.spatial.transform import Rotation

wp.config.log_level = wp.LOG_WARNING

W = 3
SHAPES_PER_WORLD = NUM_PADS + 2  # 11 pads + 2 non-pad shapes (palm, object) per world
NUM_SHAPES = 1 + W * SHAPES_PER_WORLD  # shape 0: the ground (world -1)


def build_scene(rng: np.random.Generator) -> dict:
    """Shape tables in Newton's layout: ground, then per world 11 pads in shuffled order + palm + object."""
    shape_pad = np.full(NUM_SHAPES, -1)
    shape_world = np.full(NUM_SHAPES, -1)
    shape_body = np.full(NUM_SHAPES, -1)
    body_count = 0
    for w in range(W):
        base = 1 + w * SHAPES_PER_WORLD
        slots = rng.permutation(NUM_PADS)
        for j in range(SHAPES_PER_WORLD):
            s = base + j
            shape_world[s] = w
            shape_body[s] = body_count
            body_count += 1
            if j < NUM_PADS:
                shape_pad[s] = slots[j]
    shape_rot = Rotation.random(NUM_SHAPES, random_state=5).as_quat()
    body_rot = Rotation.random(body_count, random_state=6).as_quat()
    body_q = np.concatenate([rng.normal(size=(body_count, 3)), body_rot], axis=1)
    return dict(
        shape_pad=shape_pad,
        shape_world=shape_world,
        shape_body=shape_body,
        shape_rot=shape_rot,
        body_q=body_q,
    )


def build_contacts(
    rng: np.random.Generator, n_rigid_max: int, n_rigid: int, n_soft_max: int, n_soft: int
) -> dict:
    s0 = rng.integers(0, NUM_SHAPES, n_rigid_max)
    s1 = rng.integers(0, NUM_SHAPES, n_rigid_max)
    soft_shape = rng.integers(0, NUM_SHAPES, n_soft_max)
    soft_shape[n_soft - 1] = -1  # an invalid record is skipped
    f = rng.normal(size=(n_rigid_max + n_soft_max, 6)) * 3.0
    return dict(s0=s0, s1=s1, soft_shape=soft_shape, f=f, n_rigid=n_rigid, n_soft=n_soft, rmax=n_rigid_max)


def ref_world_forces(scene: dict, c: dict) -> np.ndarray:
    out = np.zeros((W, NUM_PADS, 3))
    sp, sw = scene["shape_pad"], scene["shape_world"]
    for i in range(c["n_rigid"]):
        f = c["f"][i, :3]
        if sp[c["s0"][i]] >= 0:
            out[sw[c["s0"][i]], sp[c["s0"][i]]] += f
        if sp[c["s1"][i]] >= 0:
            out[sw[c["s1"][i]], sp[c["s1"][i]]] -= f
    for j in range(c["n_soft"]):
        s = c["soft_shape"][j]
        if s >= 0 and sp[s] >= 0:
            out[sw[s], sp[s]] += c["f"][c["rmax"] + j, :3]
    return out


def to_device(scene: dict, c: dict) -> tuple[TactileLayout, SimpleNamespace, wp.array]:
    layout = TactileLayout.from_arrays(
        scene["shape_pad"], scene["shape_world"], scene["shape_body"], scene["shape_rot"], W
    )
    i32 = lambda a: wp.array(np.asarray(a, dtype=np.int32), dtype=wp.int32)  # noqa: E731
    contacts = SimpleNamespace(
        rigid_contact_max=c["rmax"],
        rigid_contact_count=i32([c["n_rigid"]]),
        rigid_contact_shape0=i32(c["s0"]),
        rigid_contact_shape1=i32(c["s1"]),
        soft_contact_count=i32([c["n_soft"]]),
        soft_contact_shape=i32(c["soft_shape"]),
    )
    contact_f = wp.array(c["f"].astype(np.float32), dtype=wp.spatial_vector)
    return layout, contacts, contact_f


def test_accumulate_rigid_and_soft_rows_into_pads() -> None:
    rng = np.random.default_rng(20)
    scene = build_scene(rng)
    c = build_contacts(rng, n_rigid_max=400, n_rigid=300, n_soft_max=200, n_soft=150)
    layout, contacts, contact_f = to_device(scene, c)
    out = wp.full((W, NUM_PADS), wp.vec3(9.0, 9.0, 9.0), dtype=wp.vec3)  # stale values must be cleared
    accumulate_pad_forces(layout, contacts, contact_f, out)
    ref = ref_world_forces(scene, c)
    np.testing.assert_allclose(out.numpy(), ref, atol=1e-4)
    assert np.abs(ref).max() > 1.0


def test_only_pad_rows_count_with_signs() -> None:
    """Hand-made rows: pad as shape0 (+f), pad as shape1 (-f), non-pad pair (ignored), soft row on a pad."""
    rng = np.random.default_rng(21)
    scene = build_scene(rng)
    pad_shapes = np.nonzero(scene["shape_pad"] >= 0)[0]
    a, b = pad_shapes[0], pad_shapes[12]  # a pad of world 0, a pad of world 1
    palm = 1 + NUM_PADS  # non-pad shape of world 0
    c = dict(
        s0=np.array([a, palm, palm, 0]),
        s1=np.array([palm, b, 0, a]),
        soft_shape=np.array([b, palm]),
        f=np.zeros((6, 6)),
        n_rigid=3,  # row 3 lies beyond the active count: ignored
        n_soft=2,
        rmax=4,
    )
    c["f"][:, :3] = [[1, 0, 0], [0, 2, 0], [5, 5, 5], [7, 7, 7], [0, 0, 3], [4, 4, 4]]
    c["f"][:, 3:] = 100.0  # torques must not leak into forces
    layout, contacts, contact_f = to_device(scene, c)
    out = wp.zeros((W, NUM_PADS), dtype=wp.vec3)
    accumulate_pad_forces(layout, contacts, contact_f, out)
    got = out.numpy()
    expected = np.zeros((W, NUM_PADS, 3))
    expected[0, scene["shape_pad"][a]] = [1, 0, 0]
    expected[1, scene["shape_pad"][b]] = [0, -2, 3]
    np.testing.assert_allclose(got, expected, atol=1e-6)


def test_object_only_counts_contacts_with_the_object() -> None:
    """Hand-made rows: a pad pressing the table (shape 0, static) and a pad touching the palm are no
    touch of the object; a pad on the object shape counts with its sign either way round, and a soft
    contact (a pad on an object particle) always counts."""
    rng = np.random.default_rng(23)
    scene = build_scene(rng)
    pad_shapes = np.nonzero(scene["shape_pad"] >= 0)[0]
    a, b = pad_shapes[0], pad_shapes[1]  # two pads of world 0
    palm, obj, table = 1 + NUM_PADS, 2 + NUM_PADS, 0
    is_object = np.zeros(NUM_SHAPES, dtype=bool)
    is_object[obj] = True
    c = dict(
        s0=np.array([a, table, a, obj, b]),
        s1=np.array([table, b, palm, a, obj]),
        soft_shape=np.array([b]),
        f=np.zeros((6, 6)),
        n_rigid=5,
        n_soft=1,
        rmax=5,
    )
    c["f"][:, :3] = [[0, 0, 30], [0, 0, 20], [1, 0, 0], [0, 2, 0], [0, 0, 4], [0.5, 0, 0]]
    layout, contacts, contact_f = to_device(scene, c)
    layout = TactileLayout.from_arrays(
        scene["shape_pad"],
        scene["shape_world"],
        scene["shape_body"],
        scene["shape_rot"],
        W,
        shape_is_object=is_object,
    )
    out = wp.zeros((W, NUM_PADS), dtype=wp.vec3)
    accumulate_pad_forces(layout, contacts, contact_f, out, object_only=True)
    expected = np.zeros((W, NUM_PADS, 3))
    expected[0, scene["shape_pad"][a]] = [0, -2, 0]  # the object (shape0) pushes pad a (shape1): -f
    expected[0, scene["shape_pad"][b]] = [0.5, 0, 4]  # pad b on the object (+f) and a soft contact
    np.testing.assert_allclose(out.numpy(), expected, atol=1e-6)
    # All contacts: the table's 30 N and 20 N and the palm's 1 N are in the reading.
    accumulate_pad_forces(layout, contacts, contact_f, out)
    got = out.numpy()
    np.testing.assert_allclose(got[0, scene["shape_pad"][a]], [1, -2, 30], atol=1e-6)
    np.testing.assert_allclose(got[0, scene["shape_pad"][b]], [0.5, 0, -16], atol=1e-6)


def test_pad_frame_rotation_saturation_contact() -> None:
    rng = np.random.default_rng(22)
    scene = build_scene(rng)
    c = build_contacts(rng, 400, 400, 200, 200)
    layout, contacts, contact_f = to_device(scene, c)
    world = wp.zeros((W, NUM_PADS), dtype=wp.vec3)
    accumulate_pad_forces(layout, contacts, contact_f, world)
    body_q = wp.array(scene["body_q"].astype(np.float32), dtype=wp.transform)
    cfg = TactileConfig(saturation=(4.0, 5.0, 6.0), noise_std=0.0, contact_threshold=3.0)
    out_f = wp.zeros((W, NUM_PADS), dtype=wp.vec3)
    out_c = wp.zeros((W, NUM_PADS), dtype=float)
    pad_frame_forces(layout, world, body_q, cfg, out_f, out_c)

    ref_world = ref_world_forces(scene, c)
    ref = np.zeros_like(ref_world)
    for s in np.nonzero(scene["shape_pad"] >= 0)[0]:
        w, k = scene["shape_world"][s], scene["shape_pad"][s]
        q_world = Rotation.from_quat(scene["body_q"][scene["shape_body"][s], 3:]) * Rotation.from_quat(
            scene["shape_rot"][s]
        )
        ref[w, k] = q_world.inv().apply(ref_world[w, k])
    ref = np.clip(ref, -np.array([4.0, 5.0, 6.0]), [4.0, 5.0, 6.0])
    np.testing.assert_allclose(out_f.numpy(), ref, atol=1e-4)
    np.testing.assert_array_equal(out_c.numpy(), (np.linalg.norm(ref, axis=-1) > 3.0).astype(np.float32))
    assert 0 < out_c.numpy().sum() < W * NUM_PADS


def test_noise_statistics_and_seeding() -> None:
    w = 400
    layout = TactileLayout.from_arrays(
        np.tile(np.arange(NUM_PADS), w),
        np.repeat(np.arange(w), NUM_PADS),
        np.full(w * NUM_PADS, -1),
        np.tile([0.0, 0.0, 0.0, 1.0], (w * NUM_PADS, 1)),
        w,
    )
    world = wp.array(np.tile([0.0, 0.0, 2.0], (w, NUM_PADS, 1)).astype(np.float32), dtype=wp.vec3)
    cfg = TactileConfig(saturation=(0.0, 0.0, 0.0), noise_std=0.05, contact_threshold=0.1)
    body_q = wp.zeros(1, dtype=wp.transform)
    outs = []
    for reseed in (True, False, True):  # seed 1, its successor 2, seed 1 again
        if reseed:
            layout.set_noise_seed(1)
        f = wp.zeros((w, NUM_PADS), dtype=wp.vec3)
        cflag = wp.zeros((w, NUM_PADS), dtype=float)
        pad_frame_forces(layout, world, body_q, cfg, f, cflag)
        outs.append(f.numpy().reshape(-1, 3))
    assert int(layout.noise_seed.numpy()[0]) == 2
    noise = outs[0] - [0.0, 0.0, 2.0]
    assert np.abs(noise.mean(0)).max() < 0.005  # 4400 samples: 3 sigma of the mean is 0.0023
    np.testing.assert_allclose(noise.std(0), 0.05, rtol=0.06)
    np.testing.assert_array_equal(outs[0], outs[2])  # reproducible from a seed
    assert np.abs(outs[0] - outs[1]).max() > 0.01  # fresh noise on the next step
    noise_next = outs[1] - [0.0, 0.0, 2.0]
    assert abs(np.corrcoef(noise.ravel(), noise_next.ravel())[0, 1]) < 0.1  # independent draws


def test_public_wrapper_rotates_into_pad_frames() -> None:
    rng = np.random.default_rng(23)
    f = rng.normal(size=(4, NUM_PADS, 3)) * 100.0  # large: the wrapper must not saturate
    q = Rotation.random(4 * NUM_PADS, random_state=7).as_quat()
    got = pad_forces_in_pad_frames(f, q.reshape(4, NUM_PADS, 4) * 2.0)  # non-unit input is normalised
    ref = Rotation.from_quat(q).inv().apply(f.reshape(-1, 3)).reshape(f.shape)
    np.testing.assert_allclose(got, ref, rtol=1e-5, atol=1e-3)
    with pytest.raises(ValueError, match="pad_rotations"):
        pad_forces_in_pad_frames(f, q[:5])


def test_layout_rejects_duplicate_pad_slots() -> None:
    with pytest.raises(ValueError, match="more than one shape"):
        TactileLayout.from_arrays([0, 0], [0, 0], [0, 1], np.tile([0, 0, 0, 1.0], (2, 1)), 1)


def test_layout_from_newton_model() -> None:
    """Pads found by label in a two-world Newton model; pad frames are the shapes' own frames."""
    import newton  # a core dependency: its absence fails, not skips

    hand = newton.ModelBuilder()
    body = hand.add_body(xform=wp.transform_identity(), label="finger")
    rots = Rotation.random(NUM_PADS, random_state=8).as_quat()
    hand.add_shape_box(body, hx=0.01, hy=0.01, hz=0.01, label="palm")
    for k in range(NUM_PADS):
        xf = wp.transform(wp.vec3(0.0, 0.01 * k, 0.0), wp.quat(*rots[k]))
        hand.add_shape_box(body, xform=xf, hx=0.005, hy=0.005, hz=0.001, label=f"pad_{k}")
    scene = newton.ModelBuilder()
    scene.add_ground_plane()
    scene.replicate(hand, 2)
    model = scene.finalize(device="cpu")
    layout = TactileLayout.from_model(model, [f"pad_{k}" for k in range(NUM_PADS)])
    labels = list(model.shape_label)
    sp = layout.shape_pad.numpy()
    for s, lab in enumerate(labels):
        expected = int(lab.rsplit("pad_", 1)[1]) if "pad_" in lab else -1
        assert sp[s] == expected, lab
    assert sorted(layout.pad_body.numpy()[:, 0].tolist()) == [0, 1]
    for w in range(2):
        got = layout.pad_rot_in_body.numpy()[w]
        dots = np.abs(np.sum(got * rots, axis=1))
        np.testing.assert_allclose(dots, 1.0, atol=1e-6)


def test_kernel_pad_count_is_the_hands() -> None:
    """The kernels keep their own pad count (they import nothing of the package): it is the hand's."""
    from d3grasp.kernels import tactile as tactile_kernels

    from d3grasp.dexhand13 import NUM_PADS, PAD_NAMES

    assert tactile_kernels.NUM_PADS == NUM_PADS == len(PAD_NAMES) == 11
