"""Candidate grasps in the object's frame: placement invariance, the table kept clear, determinism."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from d3grasp.envs.grasps import GRASPS, ObjectGrasp, object_grasp, rest_height
from d3grasp.planner.candidates import (
    MAX_PITCH,
    CandidateConfig,
    candidates,
    collision_pieces,
    perturbed,
)


def _object_in_palm(grasp: ObjectGrasp, obj_pos: np.ndarray, yaw: float) -> np.ndarray:
    pose = grasp.place(obj_pos, yaw)
    r = Rotation.from_quat(pose.palm_quat).as_matrix()
    return r.T @ (obj_pos - pose.palm_pos)


def test_a_placed_grasp_keeps_the_object_where_it_was_planned_in_the_hand() -> None:
    ex = np.array([0.05, 0.08, 0.09])
    g = object_grasp("pinch", ex, rest_height(ex), near_face_x=0.09, lateral_y=-0.02, top_z=0.04, pitch=0.2)
    ref = _object_in_palm(g, np.zeros(3), 0.0)
    for pos, yaw in ((np.array([0.01, -0.02, 0.046]), 0.7), (np.array([-0.3, 0.2, 0.046]), -2.5)):
        np.testing.assert_allclose(_object_in_palm(g, pos, yaw), ref, atol=1e-12)
        # The approach direction turns with the object (the palm's own normal).
        pose = g.place(pos, yaw)
        np.testing.assert_allclose(pose.approach_dir, Rotation.from_quat(pose.palm_quat).as_matrix()[:, 2])


def test_placement_values_put_the_object_as_asked() -> None:
    ex = np.array([0.05, 0.08, 0.09])
    g = object_grasp("top", ex, rest_height(ex), near_face_x=0.1, lateral_y=-0.03, top_z=0.04)
    local = _object_in_palm(g, np.zeros(3), 0.0)
    assert local[0] - 0.5 * ex[0] == pytest.approx(0.1)  # near face along the fingers
    assert local[1] == pytest.approx(-0.03)
    assert local[2] - 0.5 * ex[2] == pytest.approx(0.04)  # top face that far from the palm plane
    # long_side: the palm's x along the object's longer horizontal side (y here).
    g = object_grasp("top", ex, rest_height(ex), long_side=True)
    fingers = Rotation.from_quat(g.palm_quat).as_matrix()[:, 0]
    assert abs(fingers[1]) == pytest.approx(1.0)


def test_pitch_raises_the_finger_tips_of_a_palm_down_hand() -> None:
    ex = np.array([0.05, 0.06, 0.03])
    flat = object_grasp("pinch", ex, rest_height(ex))
    tipped = object_grasp("pinch", ex, rest_height(ex), pitch=0.3)
    fingers = Rotation.from_quat(tipped.palm_quat).as_matrix()[:, 0]
    assert fingers[2] == pytest.approx(math.sin(0.3))  # pointing up by the pitch
    assert Rotation.from_quat(flat.palm_quat).as_matrix()[2, 0] == pytest.approx(0.0, abs=1e-12)


def test_candidates_are_deterministic_per_object_and_seed() -> None:
    ex = np.array([0.06, 0.07, 0.08])
    a = candidates("box_x", ex, seed=3)
    b = candidates("box_x", ex, seed=3)
    assert [g.to_json() for g in a] == [g.to_json() for g in b]
    c = candidates("box_y", ex, seed=3)  # another object: other draws
    assert [g.to_json() for g in a] != [g.to_json() for g in c]
    cfg = CandidateConfig()
    assert len(a) == 3 * cfg.per_type  # a tall 8 cm object: every side wrap is feasible
    assert len(candidates("box_x", ex, seed=3, soft=True)) == 3 * cfg.per_type_soft
    # The first candidate of each type is the type's geometric placement.
    firsts = [a[k * cfg.per_type] for k in range(3)]
    assert [g.grasp for g in firsts] == list(GRASPS)
    for g in firsts:
        assert g.to_json() == object_grasp(g.grasp, ex, rest_height(ex)).to_json()


def test_candidates_under_the_palm_keep_the_object_off_the_palm() -> None:
    ex = np.array([0.06, 0.07, 0.08])
    for g in candidates("box_x", ex, seed=0):
        if GRASPS[g.grasp].palm_vertical:
            continue
        local = _object_in_palm(g, np.zeros(3), 0.0)
        r = Rotation.from_quat(g.palm_quat).as_matrix()
        along = abs(r[:, 0] @ ex)  # the object's extent along the fingers (no pitch: tall object)
        near = local[0] - 0.5 * along
        top = local[2] - 0.5 * ex[2]
        if near < 0.136:  # under the palm: its top below the palm face
            assert top > 0.0335, (near, top)


def test_perturbed_moves_the_object_relative_to_the_hand() -> None:
    ex = np.array([0.06, 0.07, 0.08])
    g = object_grasp("top", ex, rest_height(ex))
    p = perturbed(g, (0.004, -0.003), 0.08)
    # The hand moves as if the object were 5 mm and 0.08 rad away from where it is.
    np.testing.assert_allclose(
        p.palm_pos[:2] - Rotation.from_euler("z", 0.08).apply(g.palm_pos)[:2], [0.004, -0.003]
    )
    assert p.grasp == g.grasp and p.preshape == g.preshape


def test_object_grasp_json_round_trip_and_errors() -> None:
    ex = np.array([0.06, 0.07, 0.08])
    g = object_grasp("side", ex, rest_height(ex), preshape=(0.1, 0.0, -0.1, 0.2))
    back = ObjectGrasp.from_json(g.to_json())
    assert back.to_json() == g.to_json()
    bad = g.to_json() | {"grasp": "claw"}
    with pytest.raises(ValueError, match="unknown grasp type"):
        ObjectGrasp.from_json(bad)
    with pytest.raises(ValueError, match="palm_pos"):
        ObjectGrasp.from_json(g.to_json() | {"palm_pos": [0.0, 1.0]})


def _two_bar_usd(tmp_path) -> tuple[str, list[tuple[np.ndarray, np.ndarray]]]:
    """An L of two bars (8 x 2 x 2 cm along x, 2 x 6 x 2 cm along y) written as a rigid USD file,
    centred on its bounding box as the authoring tools centre objects, with the bars' boxes."""
    import trimesh

    from d3grasp.authoring.convex import hull_of
    from d3grasp.authoring.usd_rigid import mass_properties, write_rigid_usd

    a = trimesh.creation.box(extents=(0.08, 0.02, 0.02))
    a.apply_translation((0.0, -0.03, 0.0))
    b = trimesh.creation.box(extents=(0.02, 0.06, 0.02))
    b.apply_translation((0.03, 0.01, 0.0))
    shift = -0.5 * (np.array([-0.04, -0.04, -0.01]) + np.array([0.04, 0.04, 0.01]))
    for m in (a, b):
        m.apply_translation(shift)
    mesh = trimesh.util.concatenate([a, b])
    path = write_rigid_usd(
        tmp_path / "ell.usda",
        "ell",
        mesh,
        [hull_of(a.vertices), hull_of(b.vertices)],
        mass_properties(mesh, 500.0),
        density=500.0,
        friction=1.0,
    )
    boxes = [(np.array([0.0, -0.03, 0.0]) + shift, np.array([0.08, 0.02, 0.02]))]
    boxes.append((np.array([0.03, 0.01, 0.0]) + shift, np.array([0.02, 0.06, 0.02])))
    return str(path), boxes


def test_collision_pieces_read_each_hulls_box(tmp_path) -> None:
    path, boxes = _two_bar_usd(tmp_path)
    pieces = sorted(collision_pieces(path), key=lambda p: -p[1][0])
    assert len(pieces) == 2
    for (c, ex), (c_ref, ex_ref) in zip(pieces, boxes, strict=True):
        np.testing.assert_allclose(c, c_ref, atol=1e-6)
        np.testing.assert_allclose(ex, ex_ref, atol=1e-6)


def test_a_composite_gets_each_type_placed_on_its_pieces(tmp_path) -> None:
    _, boxes = _two_bar_usd(tmp_path)
    ex = np.array([0.08, 0.08, 0.02])
    plain = candidates("ell", ex, 0)
    with_pieces = candidates("ell", ex, 0, pieces=boxes)
    extra = [
        g for g in with_pieces if not any(g is p or np.array_equal(g.palm_pos, p.palm_pos) for p in plain)
    ]
    # The box's candidates are unchanged; the palm-down types (top, pinch) get one grasp per bar (the
    # side wrap of a 2 cm high object would put the hand's edge into the table).
    assert len(with_pieces) == len(plain) + len(extra)
    assert sorted(g.grasp for g in extra) == ["pinch", "pinch", "top", "top"]

    # Each holds its bar where the type's placement holds a lone object of the bar's size (pitched:
    # the bars' tops are 2.1 cm above the table, below the curling finger tips).
    def holds_bar_as_lone(g: ObjectGrasp, c: np.ndarray, bar: np.ndarray) -> bool:
        lone = object_grasp(g.grasp, bar, rest_height(ex) + c[2], pitch=0.5 * MAX_PITCH)
        r, r_lone = (Rotation.from_quat(x.palm_quat).as_matrix() for x in (g, lone))
        return bool(np.allclose(r.T @ (c - g.palm_pos), r_lone.T @ -lone.palm_pos, atol=1e-9))

    for grasp_type in ("top", "pinch"):
        mine = [g for g in extra if g.grasp == grasp_type]
        assert all(any(holds_bar_as_lone(g, c, bar) for g in mine) for c, bar in boxes)
    # A single piece adds nothing.
    assert len(candidates("ell", ex, 0, pieces=boxes[:1])) == len(plain)


def test_synthesised_candidates_follow_the_geometric_ones_on_the_hull() -> None:
    """``synthesised=1``: one grasp per type descended on the convex hull (a 6 x 4 x 8 cm box's
    corners here, outward winding) after the geometric placement; the synthesis is seeded by the
    object, so the candidates repeat."""
    from dataclasses import replace

    from scipy.spatial import ConvexHull

    from d3grasp.planner.candidates import CandidateConfig, candidates

    half = np.array([0.03, 0.02, 0.04])
    corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * half
    tri = ConvexHull(corners).simplices
    a, b, c = (corners[tri[:, k]] for k in range(3))
    flip = np.einsum("ij,ij->i", np.cross(b - a, c - a), a) < 0.0
    tri[flip] = tri[flip][:, [0, 2, 1]]
    cfg = replace(CandidateConfig(), per_type=1, synthesised=1, synthesis_starts=8, synthesis_steps=60)
    first = candidates("boxy", 2.0 * half, 0, cfg, hull=(corners, tri.astype(np.int32)))
    assert [g.grasp for g in first] == ["top", "top", "side", "side", "pinch", "pinch"]
    for g in first[1::2]:
        assert abs(np.linalg.norm(g.palm_quat) - 1.0) < 1e-6
        assert all(abs(a) <= 0.35 + 1e-6 for a in g.preshape[:3])  # the abduction joints' range
    again = candidates("boxy", 2.0 * half, 0, cfg, hull=(corners, tri.astype(np.int32)))
    assert [g.to_json() for g in again] == [g.to_json() for g in first]
    assert len(candidates("boxy", 2.0 * half, 0, replace(cfg, synthesised=0))) == 3
