"""Objects the hands carry (stages/state_fusion/carry.py): placed by the palm's rigid motion.

Unit tests on hand-built hands (the synthetic world's joint model) and boxes of points, with the
answers computed by hand; the end-to-end figures (fusion from a plane-sweep depth) are in
``bench_state_fusion_estimated_depth`` and the slow test below.
"""

from __future__ import annotations

import numpy as np
import pytest

from egosim.pipeline.geometry import invert_se3, make_se3, transform_points
from egosim.stages.state_fusion.carry import carried_objects, closure, grip_points
from egosim.stages.state_fusion.config import StateFusionConfig
from egosim.stages.state_fusion.fusion import SupportPlane
from egosim.world.hands import hand_joints_local

OPEN, CLOSED = 0.15, 0.5  # the synthetic world's rest and grasp closures
RIGHT = 1


def _plane() -> SupportPlane:
    """The plane z = 0, 1 m square around the origin."""
    basis = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    return SupportPlane(np.array([0.0, 0.0, 1.0]), 0.0, basis, np.full(2, -0.5), np.full(2, 0.5))


def _box(centre_xy: tuple[float, float], size: float = 0.05, height: float = 0.06) -> np.ndarray:
    """Surface points ``(n, 3)`` of a box standing on z = 0 (a 5 mm grid, bottom left out)."""
    g = np.arange(-size / 2, size / 2 + 1e-9, 0.005)
    z = np.arange(0.0, height + 1e-9, 0.005)
    sides = [np.stack(np.meshgrid(g, [s * size / 2], z), -1).reshape(-1, 3) for s in (-1, 1)]
    sides += [np.stack(np.meshgrid([s * size / 2], g, z), -1).reshape(-1, 3) for s in (-1, 1)]
    top = np.stack(np.meshgrid(g, g, [height]), -1).reshape(-1, 3)
    return np.concatenate([*sides, top]) + np.array([centre_xy[0], centre_xy[1], 0.0])


def _script(grasp_at: np.ndarray, place: np.ndarray, lift: float, close: bool = True):
    """A right hand over 20 frames: reach (open), hold still (closing at frame 6), lift by
    ``lift``, move and turn to ``place (4, 4)`` (relative to the grasp pose), put down, open
    at frame 15, leave. Returns joints ``(T, 2, 21, 3)`` (left hand invalid), valid ``(T, 2)``
    and the world_from_hand poses ``(T, 4, 4)``."""
    t = 20
    hands = np.zeros((t, 4, 4))
    curls = np.full(t, OPEN)
    start = grasp_at.copy()
    start[:3, 3] += [-0.15, 0.0, 0.05]
    for k in range(t):
        if k < 5:  # reach
            a = k / 5
            pose = start.copy()
            pose[:3, 3] = (1 - a) * start[:3, 3] + a * grasp_at[:3, 3]
        elif k < 8:  # hold still, closing
            pose = grasp_at.copy()
        elif k < 14:  # lift, move, put down (sin arc), at the place from frame 12
            a = min(1.0, (k - 7) / 5)
            rel = np.eye(4)
            rel[:3, :3] = _rz(a * _angle(place))
            rel[:3, 3] = a * place[:3, 3] + [0.0, 0.0, lift * np.sin(np.pi * a)]
            pose = _about(grasp_at, rel)
        else:  # let go: straight up
            pose = _about(grasp_at, place)
            pose[2, 3] += 0.02 * (k - 13)
        hands[k] = pose
        curls[k] = CLOSED if close and 6 <= k < 15 else OPEN
    joints = np.zeros((t, 2, 21, 3))
    for k in range(t):
        joints[k, RIGHT] = transform_points(hands[k], hand_joints_local(curls[k], RIGHT))
    valid = np.zeros((t, 2), bool)
    valid[:, RIGHT] = True
    return joints, valid, hands


def _rz(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _angle(pose: np.ndarray) -> float:
    return float(np.arctan2(pose[1, 0], pose[0, 0]))


def _about(grasp_at: np.ndarray, rel: np.ndarray) -> np.ndarray:
    """The hand moved by ``rel`` (rotation about the grasp point's vertical, then shift)."""
    grip = grip_points(hand_joints_local(CLOSED, RIGHT))
    at = transform_points(grasp_at, grip[None])[0]
    world = make_se3(rel[:3, :3], at + rel[:3, 3] - rel[:3, :3] @ at)
    return world @ grasp_at


def _grasp_pose(centre_xy: tuple[float, float]) -> np.ndarray:
    """A right hand whose closed grip point sits inside the box at ``centre_xy``, 4 cm up."""
    rot = _rz(0.3) @ np.array([[0.77, 0, 0.64], [0, 1, 0], [-0.64, 0, 0.77]])  # pitched down
    grip = grip_points(hand_joints_local(CLOSED, RIGHT))
    return make_se3(rot, np.array([*centre_xy, 0.04]) - rot @ grip)


@pytest.fixture
def scene():
    target, other = _box((0.1, 0.0)), _box((-0.2, 0.25))
    points = np.concatenate([target, other]).astype(np.float32)
    instance = np.r_[np.zeros(len(target)), np.full(len(other), 2)].astype(np.int32)
    return points, instance, len(target)


def test_closure_drops_when_the_hand_closes():
    spread = closure(np.stack([hand_joints_local(c, RIGHT) for c in (0.0, OPEN, CLOSED, 1.0)]))
    assert np.all(np.diff(spread) < 0)
    assert spread[1] - spread[2] > 0.15  # open vs grasp: measured 1.16 vs 0.97


def test_carried_box_lands_where_the_hand_put_it(scene):
    """Picked, lifted 6 cm, moved 15 cm and turned 40 deg, put down: the carry's transform is
    the hand's (within 1 mm on every point), the other box is not carried."""
    points, instance, n_target = scene
    place = make_se3(_rz(np.deg2rad(40.0)), [0.0, 0.15, 0.0])
    joints, valid, hands = _script(_grasp_pose((0.1, 0.0)), place, lift=0.06)
    (carry,) = carried_objects(joints, valid, points, instance, _plane(), StateFusionConfig())
    assert carry.hand == RIGHT and carry.instance == 0
    assert 5 <= carry.grasp <= 7 and carry.release in (12, 13)
    # every point of the box above the plane's inlier band (1 cm) goes with it
    np.testing.assert_array_equal(carry.source, np.flatnonzero(points[:n_target, 2] > 0.01))
    truth = hands[carry.release] @ invert_se3(hands[carry.grasp])
    src = points[carry.source]
    err = np.linalg.norm(transform_points(carry.moved, src) - transform_points(truth, src), axis=1)
    assert err.max() < 1e-3, err.max()
    moved = transform_points(carry.moved, src)
    assert abs(moved[:, 2].min() - src[:, 2].min()) < 0.005  # resting on the plane again
    centre = np.array([0.1, 0.15])  # the box's centre moved by the place's shift
    assert np.linalg.norm(moved[:, :2].mean(0) - centre) < 0.005


def test_no_carry_without_a_grip_a_lift_or_a_put_down(scene):
    points, instance, _ = scene
    config = StateFusionConfig()
    place = make_se3(np.eye(3), [0.0, 0.15, 0.0])
    grasp = _grasp_pose((0.1, 0.0))
    # an open hand that moves over the same path carries nothing
    joints, valid, _ = _script(grasp, place, lift=0.06, close=False)
    assert carried_objects(joints, valid, points, instance, _plane(), config) == []
    # pushed along the table (no lift): not carried
    joints, valid, _ = _script(grasp, place, lift=0.0)
    assert carried_objects(joints, valid, points, instance, _plane(), config) == []
    # lifted and never put down (the hand ends 3 cm up, still closed): not carried
    up = place.copy()
    up[2, 3] = 0.03
    joints, valid, _ = _script(grasp, up, lift=0.06)
    assert carried_objects(joints, valid, points, instance, _plane(), config) == []
    # a hand that is not seen carries nothing
    joints, valid, _ = _script(grasp, place, lift=0.06)
    assert carried_objects(joints, valid & False, points, instance, _plane(), config) == []


def test_a_carried_instance_goes_whole(scene):
    """The grip touches part of instance 2 only: the carry takes all of its points."""
    points, instance, n_target = scene
    place = make_se3(np.eye(3), [0.0, -0.15, 0.0])
    joints, valid, _ = _script(_grasp_pose((-0.2, 0.25)), place, lift=0.06)
    (carry,) = carried_objects(joints, valid, points, instance, _plane(), StateFusionConfig())
    assert carry.instance == 2
    np.testing.assert_array_equal(carry.source, np.arange(n_target, len(points)))


@pytest.mark.slow
def test_flat_coloured_object_is_carried_with_estimated_depth():
    """Fusion from the plane sweep's depth (seed 0, default world: tuned) registers the moved
    box by the hand's motion: measured 20.0 mm from the truly visible surface, no update
    125.7 mm, flagged; without the carry 211.7 mm, not flagged."""
    from bench.bench_state_fusion import SMALL, measure_state_update
    from egosim.world import WorldConfig

    fusion = StateFusionConfig(depth_source="estimate")
    figures = measure_state_update(WorldConfig(seed=0, **SMALL), look_back=False, fusion=fusion)
    (obj,) = figures["objects"]
    assert obj["interactive"]
    assert obj["error"] < 0.03
    assert obj["error"] < 0.3 * obj["baseline_error"]
