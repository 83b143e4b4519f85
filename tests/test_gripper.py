"""The gripper skeleton (stages/common/gripper.py) against hand-computed joint positions."""

from __future__ import annotations

import numpy as np
import pytest

from egosim.pipeline.geometry import make_se3
from egosim.stages.common.gripper import (
    GRIPPER_JOINTS,
    GripperError,
    GripperGeometry,
    gripper_box_masks,
    gripper_geometry,
    gripper_hand_arrays,
    gripper_skeleton,
    opening_from_joints,
)

TOL_M = 1e-12  # float64 arithmetic on a handful of terms

GEOM = GripperGeometry(palm_offset_m=0.1, finger_length_m=0.06, max_opening_m=0.08)


def test_identity_pose_places_the_chains_on_the_finger_faces() -> None:
    """EE at the origin, z approach, y opening: joints by hand from palm 0.1 m, fingers 0.06 m."""
    joints, conf = gripper_skeleton(np.eye(4), np.array(0.04), GEOM)
    expected_thumb = [[0, 0.02, 0.10], [0, 0.02, 0.12], [0, 0.02, 0.14], [0, 0.02, 0.16]]
    expected_index = [[0, -0.02, 0.10], [0, -0.02, 0.12], [0, -0.02, 0.14], [0, -0.02, 0.16]]
    np.testing.assert_allclose(joints[0], [0, 0, 0], atol=TOL_M)
    np.testing.assert_allclose(joints[1:5], expected_thumb, atol=TOL_M)
    np.testing.assert_allclose(joints[5:9], expected_index, atol=TOL_M)
    assert np.isnan(joints[9:]).all()
    np.testing.assert_array_equal(conf[list(GRIPPER_JOINTS)], 1.0)
    np.testing.assert_array_equal(conf[9:], 0.0)
    assert opening_from_joints(joints) == pytest.approx(0.04, abs=TOL_M)


def test_rotated_translated_pose_and_other_axes() -> None:
    """EE rotated 90 deg about z and moved: approach +x (EE) and opening -z (EE), thumb at -side."""
    geom = GripperGeometry(
        approach_axis="+x", opening_axis="-z", thumb_side=-1.0, palm_offset_m=0.0,
        finger_length_m=0.03, max_opening_m=0.1,
    )  # fmt: skip
    rot = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # EE x -> world y
    pose = make_se3(rot, np.array([1.0, 2.0, 3.0]))
    joints, _ = gripper_skeleton(pose, np.array(0.06), geom)
    # EE approach +x -> world +y; EE opening -z -> world -z; thumb at -0.03 along opening -> +z.
    np.testing.assert_allclose(joints[4], [1.0, 2.03, 3.03], atol=TOL_M)
    np.testing.assert_allclose(joints[8], [1.0, 2.03, 2.97], atol=TOL_M)
    np.testing.assert_allclose(joints[1], [1.0, 2.0, 3.03], atol=TOL_M)
    np.testing.assert_allclose(joints[6], [1.0, 2.01, 2.97], atol=TOL_M)


def test_batched_and_non_finite_inputs() -> None:
    poses = np.stack([np.eye(4), np.full((4, 4), np.nan), np.eye(4)])  # (3, 4, 4)
    openings = np.array([0.0, 0.05, np.nan])
    joints, conf = gripper_skeleton(poses, openings, GEOM)
    assert joints.shape == (3, 21, 3) and conf.shape == (3, 21)
    np.testing.assert_allclose(joints[0, 4], joints[0, 8], atol=TOL_M)  # closed: tips touch
    assert np.isnan(joints[1:]).all() and not conf[1:].any()


def test_hand_arrays_are_finite_for_valid_hands_with_unused_joints_on_the_wrist() -> None:
    t = 2
    poses = np.tile(make_se3(np.eye(3), np.array([0.5, 0.0, 0.2])), (t, 2, 1, 1))  # (T, 2, 4, 4)
    openings = np.array([[0.02, 0.03], [0.04, np.nan]])
    joints, valid, conf = gripper_hand_arrays(poses, openings, GEOM, hands=(0, 1))
    np.testing.assert_array_equal(valid, [[True, True], [True, False]])
    assert np.isfinite(joints).all()
    np.testing.assert_allclose(joints[0, 0, 9:], np.tile([0.5, 0.0, 0.2], (12, 1)), atol=TOL_M)
    np.testing.assert_array_equal(joints[1, 1], 0.0)
    np.testing.assert_allclose(opening_from_joints(joints[:, 0]), [0.02, 0.04], atol=TOL_M)
    np.testing.assert_array_equal(conf[0, 0, 9:], 0.0)
    # One gripper on the right hand only: the left slot stays invalid.
    _, valid1, _ = gripper_hand_arrays(poses[:, :1], openings[:, :1], GEOM, hands=(1,))
    np.testing.assert_array_equal(valid1, [[False, True], [False, True]])


def test_state_maps_linearly_onto_the_opening_and_back() -> None:
    geom = gripper_geometry("agibot_g1")  # 0 = open (0.12 m) .. 120 = closed
    np.testing.assert_allclose(geom.opening_from_state([0.0, 60.0, 120.0, 200.0]),
                               [0.12, 0.06, 0.0, 0.0])  # fmt: skip
    np.testing.assert_allclose(geom.state_from_opening(geom.opening_from_state(30.0)), 30.0)


def test_bad_geometry_is_refused_quoting_the_values() -> None:
    with pytest.raises(GripperError, match=r"approach_axis must be one of .* got 'z'"):
        GripperGeometry(approach_axis="z")
    with pytest.raises(GripperError, match="different axes, got '\\+y' and '-y'"):
        GripperGeometry(approach_axis="+y", opening_axis="-y")
    with pytest.raises(GripperError, match="max_opening_m must be > 0, got -1"):
        GripperGeometry(max_opening_m=-1)
    with pytest.raises(GripperError, match=r"robot must be one of .* got 'r2d2'"):
        gripper_geometry("r2d2")
    with pytest.raises(GripperError, match=r"got \(4, 4\) and \(2,\)"):
        gripper_skeleton(np.eye(4), np.zeros(2), GEOM)


def test_box_mask_around_the_projected_gripper_by_hand() -> None:
    """Camera at the origin (fx = fy = 100, c = (50, 40)), EE 0.5 m ahead, opening 0.04 m.

    Joints project to u = 50 and v from 40 - 100 * 0.02 / 0.6 = 36.67 to 40 + 3.33 = 43.33; the
    2 cm margin at the nearest depth (the wrist, 0.5 m) is 4 px: the box is u in [46, 54],
    v in [32.67, 47.33], i.e. pixel columns 46..53 and rows 33..46 (centres at +0.5).
    """
    ee = make_se3(np.eye(3), np.array([0.0, 0.0, 0.5]))[None, None]  # (T=1, G=1, 4, 4)
    joints, valid, conf = gripper_hand_arrays(ee, np.array([[0.04]]), GEOM, hands=(1,))
    k = np.array([100.0, 100.0, 50.0, 40.0])
    mask = gripper_box_masks(joints, conf, valid, np.eye(4)[None], k, 80, 100, margin_m=0.02)
    expected = np.zeros((1, 80, 100), dtype=np.uint8)
    expected[0, 33:47, 46:54] = 1
    np.testing.assert_array_equal(mask, expected)
    behind = gripper_box_masks(joints, conf, valid, np.diag([1.0, -1, -1, 1])[None], k, 80, 100)
    assert not behind.any()  # camera turned round: the gripper is behind it
    assert not gripper_box_masks(joints, conf, ~valid, np.eye(4)[None], k, 80, 100).any()
