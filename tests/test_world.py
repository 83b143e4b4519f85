"""Tests of the procedural synthetic world, the oracle of the project's other tests."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from egosim.pipeline.geometry import (
    invert_se3,
    look_at,
    project_world_points,
    rotation_angle_deg,
    transform_points,
    unproject_depth,
)
from egosim.pipeline.records import Clip
from egosim.world import WorldConfig, WorldConfigError, render_clip
from egosim.world.hands import hand_joints_local
from egosim.world.interaction import script_interaction
from egosim.world.render import WorldRenderer
from egosim.world.scene import TABLE_TOP_Z, build_scene

H, W = 96, 160
MIDDLE_CHAIN = [0, 9, 10, 11, 12]


@pytest.fixture(scope="module")
def pick_clip() -> Clip:
    return render_clip(WorldConfig(seed=7, height=H, width=W, num_frames=12))


@pytest.fixture(scope="module")
def lid_clip() -> Clip:
    return render_clip(WorldConfig(seed=5, height=H, width=W, num_frames=12, articulated=True))


@pytest.fixture(scope="module")
def wild_clip() -> Clip:
    return render_clip(WorldConfig(seed=11, mode="wild", height=H, width=W, num_frames=10))


def _all_clips(request: pytest.FixtureRequest) -> list[Clip]:
    return [request.getfixturevalue(n) for n in ("pick_clip", "lid_clip", "wild_clip")]


def _bilinear(image: np.ndarray, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sample ``image (H, W)`` at pixel coordinates (centres at +0.5); also the 2x2 spread."""
    x, y = u - 0.5, v - 0.5
    x0 = np.clip(np.floor(x).astype(int), 0, image.shape[1] - 2)
    y0 = np.clip(np.floor(y).astype(int), 0, image.shape[0] - 2)
    fx, fy = np.clip(x - x0, 0, 1), np.clip(y - y0, 0, 1)
    q = np.stack(
        [image[y0, x0], image[y0, x0 + 1], image[y0 + 1, x0], image[y0 + 1, x0 + 1]]
    )  # (4, n)
    value = (q[0] * (1 - fx) + q[1] * fx) * (1 - fy) + (q[2] * (1 - fx) + q[3] * fx) * fy
    return value, q.max(0) - q.min(0)


def test_clip_shapes_dtypes_and_polarity(pick_clip: Clip) -> None:
    c = pick_clip
    assert c.problems() == []
    assert c.source == "synthetic" and c.source_uri == ""
    assert c.frames.shape == (12, H, W, 3) and c.frames.dtype == np.uint8
    np.testing.assert_allclose(c.timestamps, np.arange(12) / 16.0)
    assert set(np.unique(c.hand_mask)) <= {0, 1} and c.hand_mask.any()
    n = c.object_poses.shape[1]
    assert 3 <= n <= 6
    assert c.object_mask.max() <= n and c.object_mask.any()
    assert not np.any(c.object_mask[c.hand_mask == 1])  # objects only, hands excluded
    assert np.all(c.depth > 0) and np.all(c.static_depth > 0)  # closed room: every ray hits
    assert c.hand_valid.all()  # both hands stay in view in this tabletop clip
    assert "right hand" in c.text


def test_depth_is_z_depth_against_a_hand_built_camera() -> None:
    """A camera 2 m above the floor looking straight down sees depth 2.0 at every pixel."""
    scene = build_scene(0, articulated=False)
    k = np.array([200.0, 200.0, 40.0, 30.0])  # narrow view: floor only
    cam = look_at([1.5, 1.5, 2.0], [1.5, 1.5, 0.0], up=(1.0, 0.0, 0.0))
    layer = WorldRenderer(scene, k, 60, 80).render_static(cam, scene.initial_object_poses)
    np.testing.assert_allclose(layer.depth, 2.0, rtol=1e-6)
    world = transform_points(cam, unproject_depth(layer.depth, k))  # (H, W, 3)
    np.testing.assert_allclose(world[..., 2], 0.0, atol=1e-5)
    # Hand-computed: camera x is world -y and camera y is world -x here; pixel (30, 40) has its
    # centre at (u, v) = (40.5, 30.5), i.e. 0.5 px right of and below the principal point.
    np.testing.assert_allclose(world[30, 40], [1.495, 1.495, 0.0], atol=1e-5)
    uv, z = project_world_points(world[0, 0], cam, k)
    np.testing.assert_allclose(uv, [0.5, 0.5], atol=1e-4)
    np.testing.assert_allclose(z, 2.0, rtol=1e-6)


@pytest.mark.parametrize("name", ["pick_clip", "lid_clip", "wild_clip"])
def test_visible_joints_project_onto_hand_mask(name: str, request: pytest.FixtureRequest) -> None:
    """>= 95% of in-image joints not hidden by the scene land on a hand-mask pixel.

    A joint lies on its bone's axis, inside the capsule. It is hidden by the scene when the pixel
    it projects to shows a non-hand surface in front of it by more than the capsule's radius bound
    (3 cm at the wrist, inside the forearm; 1.5 cm at the thumb base and knuckles; 1.2 cm
    elsewhere); a joint hidden by its own hand still lands on the hand mask and counts.
    """
    c: Clip = request.getfixturevalue(name)
    margin = np.full(21, 0.012)
    margin[[1, 2, 5, 9, 13, 17]] = 0.015
    margin[0] = 0.03
    margin = np.tile(margin, 2)  # (42,) both hands
    on_hand = counted = in_image = 0
    for t in range(c.num_frames):
        joints = c.hand_joints[t].reshape(-1, 3)  # (42, 3)
        uv, z = project_world_points(joints, c.world_from_cam[t], c.intrinsics)
        inside = (z > 0) & np.all(np.isfinite(uv), axis=1)
        inside &= (uv[:, 0] >= 0) & (uv[:, 0] < W) & (uv[:, 1] >= 0) & (uv[:, 1] < H)
        cols = np.floor(uv[inside, 0]).astype(int)
        rows = np.floor(uv[inside, 1]).astype(int)
        hit_hand = c.hand_mask[t, rows, cols] == 1
        hidden = ~hit_hand & (c.depth[t, rows, cols] < z[inside] - margin[inside])
        in_image += int(inside.sum())
        counted += int((~hidden).sum())
        on_hand += int(hit_hand.sum())
    assert counted >= 0.5 * in_image > 0
    assert on_hand / counted >= 0.95


@pytest.mark.parametrize("name", ["pick_clip", "wild_clip"])
def test_static_depth_reprojects_consistently(name: str, request: pytest.FixtureRequest) -> None:
    """Static depth of frame t moved into frame t+k agrees with frame t+k's static depth."""
    c: Clip = request.getfixturevalue(name)
    errors = []
    for t, k in [(0, 3), (2, 5), (4, 2)]:
        points = unproject_depth(c.static_depth[t], c.intrinsics).reshape(-1, 3)  # (H*W, 3)
        world = transform_points(c.world_from_cam[t], points)
        uv, z = project_world_points(world, c.world_from_cam[t + k], c.intrinsics)
        ok = (z > 0) & (uv[:, 0] >= 1) & (uv[:, 0] < W - 1) & (uv[:, 1] >= 1) & (uv[:, 1] < H - 1)
        sampled, spread = _bilinear(c.static_depth[t + k], uv[ok, 0], uv[ok, 1])
        smooth = spread < 0.02 * sampled  # away from depth edges
        errors.append(np.abs(z[ok][smooth] - sampled[smooth]) / sampled[smooth])
    rel = np.concatenate(errors)
    assert len(rel) > 0.5 * H * W
    assert np.median(rel) < 1e-3
    assert np.percentile(rel, 90) < 0.01


@pytest.mark.parametrize("name", ["pick_clip", "lid_clip", "wild_clip"])
def test_static_video_matches_outside_hands_until_objects_move(
    name: str, request: pytest.FixtureRequest
) -> None:
    """Bit-exact: frame 0 static == clean first frame; off-hand pixels equal until a move."""
    c: Clip = request.getfixturevalue(name)
    np.testing.assert_array_equal(c.static_frames[0], c.first_frame_clean)
    still = [t for t in range(c.num_frames) if np.array_equal(c.object_poses[t], c.object_poses[0])]
    assert still[:3] == [0, 1, 2]
    for t in still:
        off = c.hand_mask[t] == 0
        np.testing.assert_array_equal(c.frames[t][off], c.static_frames[t][off])
        np.testing.assert_array_equal(c.depth[t][off], c.static_depth[t][off])
    moved = [t for t in range(c.num_frames) if t not in still]
    assert moved, "the interaction should move an object"
    assert all(not np.array_equal(c.frames[t], c.static_frames[t]) for t in range(c.num_frames))


def test_same_seed_same_bytes_different_seed_different_scene(pick_clip: Clip) -> None:
    again = render_clip(WorldConfig(seed=7, height=H, width=W, num_frames=12))
    for field in (
        "frames",
        "depth",
        "static_frames",
        "static_depth",
        "hand_joints",
        "hand_mask",
        "object_mask",
        "object_poses",
        "world_from_cam",
        "intrinsics",
    ):
        np.testing.assert_array_equal(getattr(again, field), getattr(pick_clip, field), field)
    assert again.text == pick_clip.text and again.clip_id == pick_clip.clip_id
    other = render_clip(WorldConfig(seed=8, height=H, width=W, num_frames=12))
    assert np.mean(other.frames[0] != pick_clip.frames[0]) > 0.5
    assert other.object_poses.shape != pick_clip.object_poses.shape or not np.allclose(
        other.object_poses[0], pick_clip.object_poses[0]
    )


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"num_frames": 0}, "num_frames must be >= 1, got 0"),
        ({"height": -4}, "height must be an int >= 8, got -4"),
        ({"width": 0}, "width must be an int >= 8, got 0"),
        ({"mode": "moon"}, "mode must be one of ('tabletop', 'wild'), got 'moon'"),
        ({"fps": 0.0}, "fps must be a positive number, got 0.0"),
        ({"horizontal_fov_deg": 200.0}, "horizontal_fov_deg must be in [10, 150], got 200.0"),
        ({"seed": -1}, "seed must be a non-negative int, got -1"),
    ],
)
def test_invalid_config_raises_value_error(kwargs: dict, message: str) -> None:
    with pytest.raises(ValueError, match=None) as info:
        WorldConfig(**kwargs)
    assert isinstance(info.value, WorldConfigError)
    assert message in str(info.value)


def test_invalid_config_reports_every_problem() -> None:
    with pytest.raises(WorldConfigError) as info:
        WorldConfig(num_frames=0, mode="x")
    assert "num_frames" in str(info.value) and "mode" in str(info.value)


def test_hand_is_metric_and_rigid(pick_clip: Clip) -> None:
    """Wrist to middle fingertip is ~18 cm (flat hand); bone lengths never change."""
    for side in (-1, 1):
        flat = hand_joints_local(0.0, side)
        assert 0.17 <= np.linalg.norm(flat[12] - flat[0]) <= 0.20
    bones = np.linalg.norm(np.diff(pick_clip.hand_joints[:, :, MIDDLE_CHAIN], axis=2), axis=-1)
    np.testing.assert_allclose(bones.sum(-1), 0.185, atol=0.01)
    np.testing.assert_allclose(bones, np.broadcast_to(bones[:1], bones.shape), atol=1e-5)
    # Hand 0 is the left hand: its thumb lies on the left of its index knuckle seen from above.
    joints = pick_clip.hand_joints[0]
    assert joints[0, 1, 1] > joints[1, 1, 1] - 1.0  # both hands exist
    assert joints[0, 0, 1] > joints[1, 0, 1]  # left wrist is at larger y (person's left)


@pytest.mark.parametrize("name", ["pick_clip", "lid_clip", "wild_clip"])
def test_hands_stay_above_the_table(name: str, request: pytest.FixtureRequest) -> None:
    """No joint sinks into the table top (capsule radii are below 1.2 cm)."""
    c: Clip = request.getfixturevalue(name)
    assert c.hand_joints[..., 2].min() >= TABLE_TOP_Z + 0.012 - 1e-6


def test_grasped_object_moves_rigidly_with_the_hand() -> None:
    scene = build_scene(7, articulated=False)
    inter = script_interaction(scene, 7, 30, articulated=False)
    held = np.flatnonzero(inter.held)
    rel = invert_se3(inter.world_from_hand[held, 1]) @ inter.object_poses[held, inter.target]
    np.testing.assert_allclose(rel, np.broadcast_to(rel[0], rel.shape), atol=1e-9)
    start, end = inter.object_poses[0, inter.target], inter.object_poses[-1, inter.target]
    assert np.linalg.norm(end[:3, 3] - start[:3, 3]) > 0.08  # it was moved...
    assert abs(end[2, 3] - TABLE_TOP_Z) < 1e-9  # ...and put back on the table
    others = np.delete(inter.object_poses, inter.target, axis=1)
    np.testing.assert_array_equal(others, np.broadcast_to(others[:1], others.shape))


def test_held_object_follows_hand_joints_in_the_clip(pick_clip: Clip) -> None:
    """In the rendered clip, the right hand's knuckles are fixed in the held object's frame."""
    scene = build_scene(7, articulated=False)
    inter = script_interaction(scene, 7, 12, articulated=False)
    held = np.flatnonzero(inter.held)
    assert len(held) >= 3
    local = np.stack(
        [
            transform_points(
                invert_se3(pick_clip.object_poses[t, inter.target]),
                pick_clip.hand_joints[t, 1, [0, 5, 9, 17]],
            )
            for t in held
        ]
    )  # (len(held), 4, 3)
    np.testing.assert_allclose(local, np.broadcast_to(local[:1], local.shape), atol=1e-5)


def test_lid_swings_open_about_its_hinge(lid_clip: Clip) -> None:
    scene = build_scene(5, articulated=True)
    lid = next(k for k, o in enumerate(scene.objects) if o.kind == "lid")
    poses = lid_clip.object_poses[:, lid]
    np.testing.assert_allclose(
        poses[:, :3, 3], np.broadcast_to(poses[0, :3, 3], (12, 3)), atol=1e-9
    )
    assert rotation_angle_deg(poses[0, :3, :3], poses[-1, :3, :3]) > 80.0
    base = lid_clip.object_poses[:, lid - 1]
    np.testing.assert_array_equal(base, np.broadcast_to(base[:1], base.shape))
    assert "lid" in lid_clip.text


def test_every_surface_is_textured_for_feature_matching() -> None:
    scene = build_scene(3, articulated=True)
    for body in scene.background + scene.objects:
        grey = cv2.cvtColor(body.texture.image, cv2.COLOR_RGB2GRAY).astype(np.float32)
        assert cv2.Laplacian(grey, cv2.CV_32F).std() > 4.0, body.name
    clip = render_clip(WorldConfig(seed=3, height=240, width=416, num_frames=1))
    grey = cv2.cvtColor(clip.static_frames[0], cv2.COLOR_RGB2GRAY)
    keypoints = cv2.SIFT_create().detect(grey, None)
    assert len(keypoints) > 300


def test_single_frame_clip() -> None:
    clip = render_clip(WorldConfig(seed=2, height=32, width=48, num_frames=1), clip_id="one")
    assert clip.clip_id == "one" and clip.num_frames == 1
