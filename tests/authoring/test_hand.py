"""The DexHand13 USD: structure, read-back of limits/drives/masses, FK against an independent NumPy FK.

The reference FK below is written from the spec's URDF convention (child = parent · T(xyz) · Rz·Ry·Rx ·
Rz(q)) and shares no code with ``d3grasp.authoring.hand_spec`` or the hand's writer and loader.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import newton
import numpy as np
import pytest
import warp as wp

from d3grasp.authoring.hand_newton import add_hand
from d3grasp.authoring.hand_spec import (
    PAD_COLLIDER,
    PAD_NORMAL_AXIS,
    PAD_NORMAL_SIGN,
    PALM_NORMAL,
    HandPhysics,
    load_spec,
    palm_pose_to_root_q,
)
from d3grasp.authoring.hand_usd import write_hand_usd
from d3grasp.dexhand13 import (
    FINGER_JOINT_NAMES,
    LINK_NAMES,
    PAD_NAMES,
    ROOT_JOINT_NAMES,
    pad_finger,
    pad_groups,
)
from d3grasp.geometry import matrix_to_quat_xyzw_nonneg_w

REPO = Path(__file__).resolve().parents[2]
SPEC_PATH = REPO / "tools" / "specs" / "dexhand13_kinematics.json"
HAND_USD = REPO / "assets_usd" / "hands" / "dexhand13.usda"

# ---------------------------------------------------------------- independent NumPy reference


def _rot_x(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]], dtype=np.float64)


def _rot_y(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]], dtype=np.float64)


def _rot_z(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]], dtype=np.float64)


def _tf(p, r: np.ndarray) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = r
    m[:3, 3] = p
    return m


def _urdf(xyz, rpy) -> np.ndarray:
    return _tf(xyz, _rot_z(rpy[2]) @ _rot_y(rpy[1]) @ _rot_x(rpy[0]))


def _quat_to_rot(q) -> np.ndarray:
    x, y, z, w = q / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def _pose(row) -> np.ndarray:
    return _tf(row[:3], _quat_to_rot(np.asarray(row[3:7], dtype=np.float64)))


def _rot_err(a: np.ndarray, b: np.ndarray) -> float:
    """Angle [rad] of the rotation between two rotation matrices."""
    c = (np.trace(a.T @ b) - 1.0) / 2.0
    return math.acos(max(-1.0, min(1.0, c)))


def _reference_fk(spec: dict, q: dict[str, float], base: np.ndarray) -> dict[str, np.ndarray]:
    """World frames of every link and pad for finger joint values ``q`` and palm frame ``base``."""
    frames = {spec["root"]: base}
    todo = list(spec["joints"])
    while todo:
        for j in list(todo):
            if j["parent"] in frames:
                frames[j["child"]] = (
                    frames[j["parent"]] @ _urdf(j["xyz"], j["rpy"]) @ _tf((0, 0, 0), _rot_z(q[j["name"]]))
                )
                todo.remove(j)
    for p in spec["tactile_pads"]:
        frames[p["child"]] = frames[p["parent"]] @ _urdf(p["xyz"], p["rpy"])
    return frames


# ---------------------------------------------------------------- fixtures


@pytest.fixture(scope="module")
def spec() -> dict:
    return json.loads(SPEC_PATH.read_text())


@pytest.fixture(scope="module")
def plain_builder():
    """The committed USD loaded with the bare Newton API (no helper)."""
    builder = newton.ModelBuilder()
    builder.add_usd(str(HAND_USD))
    return builder


def _index(labels, suffix: str) -> int:
    hits = [i for i, label in enumerate(labels) if label.endswith(suffix)]
    assert len(hits) == 1, f"{suffix}: {hits}"
    return hits[0]


# ---------------------------------------------------------------- tests


def test_committed_usd_is_current(tmp_path, assert_usda_matches):
    """The committed asset is what the authoring code writes from the spec (up to round-off)."""
    out = write_hand_usd(tmp_path / "hand.usda", load_spec(SPEC_PATH), HandPhysics())
    assert_usda_matches(out.read_text(), HAND_USD.read_text(), "run: python tools/build_hand.py")


def _nudged(value, step: list[int]):
    """``value`` with every float moved one ulp, alternately up and down (step counts them); joint
    axes stay exact (the spec declares them, the loader checks they are local z)."""
    if isinstance(value, float):
        step[0] += 1
        return float(np.nextafter(value, np.inf if step[0] % 2 else -np.inf))
    if isinstance(value, dict):
        return {k: v if k == "axis" else _nudged(v, step) for k, v in value.items()}
    if isinstance(value, list):
        return [_nudged(v, step) for v in value]
    return value


def test_authored_hand_ignores_last_digit_differences(tmp_path):
    """Arithmetic that differs in its last digits (another CPU's SIMD paths) writes the same bytes:
    every input float of the spec moved by one ulp gives a byte-identical file."""
    raw = json.loads(SPEC_PATH.read_text())
    count = [0]
    nudged = tmp_path / "nudged.json"
    nudged.write_text(json.dumps(_nudged(raw, count)))
    assert count[0] > 100  # the spec's figures really were moved
    a = write_hand_usd(tmp_path / "a.usda", load_spec(SPEC_PATH), HandPhysics())
    b = write_hand_usd(tmp_path / "b.usda", load_spec(nudged), HandPhysics())
    assert a.read_bytes() == b.read_bytes()


def test_names_and_groups(spec):
    assert len(FINGER_JOINT_NAMES) == 16 and len(set(FINGER_JOINT_NAMES)) == 16
    assert sorted(FINGER_JOINT_NAMES) == sorted(j["name"] for j in spec["joints"])
    assert len(PAD_NAMES) == 11
    assert sorted(PAD_NAMES) == sorted(p["child"] for p in spec["tactile_pads"])
    assert pad_finger("right_thumb_tactile_link_1") == "thumb"
    assert pad_finger(0) == "index"
    assert pad_groups() == {"thumb": [9, 10], "fingers": list(range(9))}
    with pytest.raises(ValueError):
        pad_finger("left_index_tactile_link_0")


def test_structure_limits_drives_masses(plain_builder, spec):
    b = plain_builder
    assert b.joint_count == 22 and b.joint_dof_count == 22  # 16 finger + 6 root
    phys = HandPhysics()
    for j in spec["joints"]:
        ji = _index(b.joint_label, f"/joints/{j['name']}")
        assert b.joint_type[ji] == newton.JointType.REVOLUTE
        dof = b.joint_qd_start[ji]
        assert b.joint_limit_lower[dof] == pytest.approx(j["lower"], abs=1e-6)
        assert b.joint_limit_upper[dof] == pytest.approx(j["upper"], abs=1e-6)
        assert b.joint_target_ke[dof] == pytest.approx(phys.finger_stiffness, rel=1e-5)
        assert b.joint_target_kd[dof] == pytest.approx(phys.finger_damping, rel=1e-5)
        assert b.joint_effort_limit[dof] == pytest.approx(phys.finger_max_force, rel=1e-6)
        assert b.body_label[b.joint_parent[ji]].endswith("/" + j["parent"])
        assert b.body_label[b.joint_child[ji]].endswith("/" + j["child"])
    kinds = [newton.JointType.PRISMATIC] * 3 + [newton.JointType.REVOLUTE] * 3
    axes = [(1, 0, 0), (0, 1, 0), (0, 0, 1), (0, 0, 1), (0, 1, 0), (1, 0, 0)]
    for i, name in enumerate(ROOT_JOINT_NAMES):
        ji = _index(b.joint_label, f"/joints/{name}")
        dof = b.joint_qd_start[ji]
        assert b.joint_type[ji] == kinds[i]
        np.testing.assert_allclose(b.joint_axis[dof], axes[i], atol=1e-6)
        ke = phys.root_linear_stiffness if i < 3 else phys.root_angular_stiffness
        assert b.joint_target_ke[dof] == pytest.approx(ke, rel=1e-5)
    assert b.joint_parent[_index(b.joint_label, "/joints/root_x")] == -1  # anchored to the world
    palm = _index(b.body_label, "/right_palm_link")
    assert b.joint_child[_index(b.joint_label, "/joints/root_rx")] == palm

    total = sum(b.body_mass[_index(b.body_label, "/" + n)] for n in LINK_NAMES)
    assert total == pytest.approx(phys.total_mass(), rel=1e-6)
    assert 0.9 < total < 1.3  # a ~1 kg class hand, not the 0.19 kg CAD shells
    # Inertia of the palm = solid box of its mass filling the spec box.
    ext = np.subtract(
        spec["links"]["right_palm_link"]["box_max"], spec["links"]["right_palm_link"]["box_min"]
    )
    m = phys.palm_mass
    expect = (
        m / 12.0 * np.array([ext[1] ** 2 + ext[2] ** 2, ext[0] ** 2 + ext[2] ** 2, ext[0] ** 2 + ext[1] ** 2])
    )
    np.testing.assert_allclose(
        np.array(b.body_inertia[palm], dtype=np.float64).reshape(3, 3), np.diag(expect), rtol=1e-5, atol=1e-12
    )

    # 11 pad colliders, each on the spec's parent link, a box the size of the spec's pad box.
    for p in spec["tactile_pads"]:
        s = _index(b.shape_label, f"/{p['child']}/{PAD_COLLIDER}")
        assert b.shape_type[s] == newton.GeoType.BOX
        assert b.body_label[b.shape_body[s]].endswith("/" + p["parent"])
        size = np.subtract(spec["links"][p["child"]]["box_max"], spec["links"][p["child"]]["box_min"])
        np.testing.assert_allclose(2.0 * np.array(b.shape_scale[s]), size, atol=1e-6)
        assert b.shape_flags[s] & newton.ShapeFlags.COLLIDE_SHAPES


def test_self_collision_filtered(plain_builder):
    """Every pair of colliders on hand bodies is filtered (links overlap by design)."""
    b = plain_builder
    colliders = [s for s in range(b.shape_count) if b.shape_flags[s] & newton.ShapeFlags.COLLIDE_SHAPES]
    pairs = {tuple(sorted(p)) for p in b.shape_collision_filter_pairs}
    for i, s0 in enumerate(colliders):
        for s1 in colliders[i + 1 :]:
            if b.shape_body[s0] != b.shape_body[s1]:
                assert (min(s0, s1), max(s0, s1)) in pairs


def test_add_hand_indices():
    b = newton.ModelBuilder()
    b.add_ground_plane()  # something before the hand, so ranges must be offset correctly
    first = add_hand(b, HAND_USD)
    second = add_hand(b, HAND_USD)
    for idx in (first, second):
        assert len(idx.finger_q) == 16 and len(idx.root_q) == 6 and len(idx.pad_shapes) == 11
        for k, name in enumerate(FINGER_JOINT_NAMES):
            assert b.joint_label[idx.finger_joints[k]].endswith("/" + name)
        for k, pad in enumerate(PAD_NAMES):
            assert b.shape_label[idx.pad_shapes[k]].endswith(f"/{pad}/{PAD_COLLIDER}")
            assert b.shape_body[idx.pad_shapes[k]] == idx.pad_bodies[k]
    assert second.body_range[0] == first.body_range[1]
    assert set(second.pad_shapes).isdisjoint(first.pad_shapes)


def test_palm_pose_root_q_round_trip():
    rng = np.random.default_rng(3)
    for _ in range(20):
        rz, ry, rx = rng.uniform(-3.0, 3.0), rng.uniform(-1.4, 1.4), rng.uniform(-3.0, 3.0)
        r = _rot_z(rz) @ _rot_y(ry) @ _rot_x(rx)
        q = matrix_to_quat_xyzw_nonneg_w(r)
        np.testing.assert_allclose(_quat_to_rot(q), r, atol=1e-12)
        root = palm_pose_to_root_q((0.1, 0.2, 0.3), q)
        np.testing.assert_allclose(root, [0.1, 0.2, 0.3, rz, ry, rx], atol=1e-9)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_fk_matches_numpy(spec, seed):
    """Newton FK of every link and pad frame equals the NumPy FK of the spec at a random pose."""
    rng = np.random.default_rng(seed)
    anchor_r = _rot_z(rng.uniform(-3, 3)) @ _rot_y(rng.uniform(-1, 1)) @ _rot_x(rng.uniform(-3, 3))
    anchor_p = rng.uniform(-1, 1, 3)
    anchor_q = matrix_to_quat_xyzw_nonneg_w(anchor_r)
    builder = newton.ModelBuilder()
    idx = add_hand(builder, HAND_USD, xform=wp.transform(wp.vec3(*anchor_p), wp.quat(*anchor_q)))
    model = builder.finalize(device="cpu")

    q = model.joint_q.numpy()
    finger_q = {}
    for j in spec["joints"]:
        v = rng.uniform(j["lower"], j["upper"])
        finger_q[j["name"]] = v
        q[idx.finger_q[FINGER_JOINT_NAMES.index(j["name"])]] = v
    root = np.concatenate(
        [rng.uniform(-0.5, 0.5, 3), rng.uniform(-3, 3, 1), rng.uniform(-1.2, 1.2, 1), rng.uniform(-3, 3, 1)]
    )
    q[idx.root_q] = root
    model.joint_q.assign(q)
    state = model.state()
    newton.eval_fk(model, model.joint_q, model.joint_qd, state)
    body_q = state.body_q.numpy().astype(np.float64)

    palm = _tf(anchor_p, anchor_r) @ _tf(root[:3], _rot_z(root[3]) @ _rot_y(root[4]) @ _rot_x(root[5]))
    ref = _reference_fk(spec, finger_q, palm)
    for name in LINK_NAMES:
        got = _pose(body_q[idx.link_bodies[name]])
        assert np.linalg.norm(got[:3, 3] - ref[name][:3, 3]) < 5e-4, name
        assert _rot_err(got[:3, :3], ref[name][:3, :3]) < 1e-3, name

    shape_tf = model.shape_transform.numpy().astype(np.float64)
    for k, pad in enumerate(PAD_NAMES):
        body = _pose(body_q[idx.pad_bodies[k]])
        # Pad frame from the loaded model: collider transform minus the spec box centre.
        centre = 0.5 * np.add(spec["links"][pad]["box_min"], spec["links"][pad]["box_max"])
        from_shape = body @ _pose(shape_tf[idx.pad_shapes[k]]) @ _tf(-centre, np.eye(3))
        from_helper = body @ _pose(idx.pad_xform_in_body[k])
        for got in (from_shape, from_helper):
            assert np.linalg.norm(got[:3, 3] - ref[pad][:3, 3]) < 5e-4, pad
            assert _rot_err(got[:3, :3], ref[pad][:3, :3]) < 1e-3, pad


def test_pad_normal_faces_palmar_side(spec):
    """At rest each finger pad's +z faces the palmar side (palm +z); the thumb pads face the fingers (+x)."""
    ref = _reference_fk(spec, {j["name"]: 0.0 for j in spec["joints"]}, np.eye(4))
    for pad in PAD_NAMES:
        normal = PAD_NORMAL_SIGN * ref[pad][:3, PAD_NORMAL_AXIS]
        toward = np.array([1.0, 0, 0]) if pad_finger(pad) == "thumb" else np.array(PALM_NORMAL)
        assert normal @ toward > 0.95, pad
    # Flexing a finger turns its tip towards the palmar side.
    bent = _reference_fk(
        spec,
        {j["name"]: (0.5 if j["name"] == "right_index_joint_1" else 0.0) for j in spec["joints"]},
        np.eye(4),
    )
    assert bent["right_index_link_3"][2, 3] > ref["right_index_link_3"][2, 3] + 0.02


def test_driven_hand_tracks_targets_with_vbd(spec):
    """SolverVBD at the design settings: the palm lifts 0.1 m and the fingers reach random targets.

    ~8 s with a warm Warp kernel cache (the VBD kernels compile once, shared with the env tests).
    """
    builder = newton.ModelBuilder()
    base_z = 0.3
    idx = add_hand(builder, HAND_USD, xform=wp.transform(wp.vec3(0.0, 0.0, base_z), wp.quat_identity()))
    builder.color()
    model = builder.finalize(device="cpu")
    pipeline = newton.CollisionPipeline(model, contact_matching="sticky")
    contacts = pipeline.contacts()
    solver = newton.solvers.SolverVBD(model, iterations=5, rigid_contact_history=True)
    s0, s1, control = model.state(), model.state(), model.control()
    fps, substeps = 60, 10
    dt = 1.0 / (fps * substeps)

    rng = np.random.default_rng(1)
    lo = np.array([spec["joints"][i]["lower"] for i in range(16)])
    hi = np.array([spec["joints"][i]["upper"] for i in range(16)])
    names = [j["name"] for j in spec["joints"]]
    order = [names.index(n) for n in FINGER_JOINT_NAMES]
    goal = rng.uniform(lo, hi)[order]
    target = control.joint_target_q.numpy()
    lag = 0.0
    for step in range(90):  # 1.5 s: lift over 1 s, hold 0.5 s
        t = (step + 1) / fps
        target[idx.root_q] = [0.0, 0.0, 0.1 * min(1.0, t), 0.0, 0.0, 0.0]
        target[idx.finger_q] = goal * min(1.0, t / 0.5)
        control.joint_target_q.assign(target)
        for _ in range(substeps):
            s0.clear_forces()
            pipeline.collide(s0, contacts)
            solver.step(s0, s1, control, contacts, dt)
            s0, s1 = s1, s0
        palm_z = s0.body_q.numpy()[idx.palm_body, 2] - base_z
        lag = max(lag, abs(palm_z - target[idx.root_q[2]]))
    print(f"max palm height tracking error during the lift {lag * 1e3:.2f} mm")
    assert lag < 5e-3
    body_q = s0.body_q.numpy()
    assert np.isfinite(body_q).all()
    palm = _pose(body_q[idx.palm_body])
    pos_err = np.linalg.norm(palm[:3, 3] - [0.0, 0.0, base_z + 0.1])
    rot_err = _rot_err(palm[:3, :3], np.eye(3))
    print(f"palm position error {pos_err * 1e3:.2f} mm, rotation error {math.degrees(rot_err):.3f} deg")
    assert pos_err < 3e-3
    assert rot_err < 0.01
    q, qd = wp.zeros_like(model.joint_q), wp.zeros_like(model.joint_qd)
    newton.eval_ik(model, s0, q, qd)
    # eval_ik may return an angle 2*pi away from the target; compare on the circle.
    err = np.abs(np.angle(np.exp(1j * (q.numpy()[idx.finger_q] - goal))))
    print(f"finger joint error max {err.max():.4f} rad")
    assert err.max() < 0.06, dict(zip(FINGER_JOINT_NAMES, err.round(3), strict=True))
