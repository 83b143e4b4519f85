"""Tests of the synthetic world's "alt" variant: another made world, with correct ground truth."""

from __future__ import annotations

import numpy as np
import pytest

from egosim.pipeline.geometry import project_world_points, transform_points, unproject_depth
from egosim.pipeline.records import Clip
from egosim.stages.ingest import synthetic_source
from egosim.stages.ingest.stage import IngestConfig
from egosim.world import WorldConfig, WorldConfigError, render_clip
from egosim.world.camera_alt import alt_fov_deg
from egosim.world.clip import hand_joints
from egosim.world.hands_alt import (
    FOREARM_LENGTH_ALT,
    MAX_STRETCH,
    UPPER_ARM_LENGTH,
    AltBody,
    elbow,
    ellipsoids,
    lean,
    tube,
)
from egosim.world.interaction import script_interaction
from egosim.world.render import WorldRenderer
from egosim.world.scene_alt import ALT_COLOURS, build_scene_alt
from egosim.world.textures import COLOURS

H, W = 96, 160


@pytest.fixture(scope="module")
def alt_pick() -> Clip:
    return render_clip(WorldConfig(seed=7, height=H, width=W, num_frames=12, variant="alt"))


@pytest.fixture(scope="module")
def alt_lid() -> Clip:
    cfg = WorldConfig(seed=5, height=H, width=W, num_frames=9, articulated=True, variant="alt")
    return render_clip(cfg)


@pytest.fixture(scope="module")
def alt_wild() -> Clip:
    cfg = WorldConfig(seed=11, mode="wild", height=H, width=W, num_frames=9, variant="alt")
    return render_clip(cfg)


@pytest.fixture(scope="module")
def default_pick() -> Clip:
    return render_clip(WorldConfig(seed=7, height=H, width=W, num_frames=12))


ALT = ["alt_pick", "alt_lid", "alt_wild"]


def test_variant_is_validated_and_defaults_to_the_tuning_world() -> None:
    assert WorldConfig().variant == "default"
    with pytest.raises(WorldConfigError, match=r"variant must be one of .*got 'fancy'"):
        WorldConfig(variant="fancy")
    with pytest.raises(WorldConfigError, match=r"variant.*got None"):
        WorldConfig(variant=None)  # type: ignore[arg-type]


@pytest.mark.parametrize("name", ALT)
def test_alt_clip_is_a_valid_clip(name: str, request: pytest.FixtureRequest) -> None:
    c: Clip = request.getfixturevalue(name)
    assert c.problems() == []
    assert "-alt-" in c.clip_id
    assert set(np.unique(c.hand_mask)) <= {0, 1} and c.hand_mask.any()
    assert not np.any(c.object_mask[c.hand_mask == 1])
    assert np.all(c.depth > 0) and np.all(c.static_depth > 0)  # closed room: every ray hits
    assert c.hand_valid.any(axis=0).all()  # both hands show up at some point
    assert "right hand" in c.text


def test_alt_differs_from_default_for_the_same_seed(alt_pick: Clip, default_pick: Clip) -> None:
    """Camera, scene and body all change: other FOV, path, objects and hand/arm pixels."""
    assert abs(alt_pick.intrinsics[0] - default_pick.intrinsics[0]) > 1.0
    eye_shift = np.linalg.norm(
        alt_pick.world_from_cam[:, :3, 3] - default_pick.world_from_cam[:, :3, 3], axis=1
    )
    assert eye_shift.min() > 0.05
    a, d = alt_pick.hand_mask.astype(bool), default_pick.hand_mask.astype(bool)
    iou = (a & d).sum() / (a | d).sum()
    assert iou < 0.5
    # The skeleton is the same scripted one: only its surface, the camera and the scene differ.
    np.testing.assert_array_equal(alt_pick.hand_joints.shape, default_pick.hand_joints.shape)
    names = {w for w in alt_pick.text.split() if w in ALT_COLOURS or w in COLOURS}
    assert names and names <= set(ALT_COLOURS) and not set(ALT_COLOURS) & set(COLOURS)


def test_alt_fov_varies_per_seed_around_the_configured_one() -> None:
    fovs = np.array([alt_fov_deg(s, 75.0) for s in range(20)])
    assert np.all((fovs >= 60.0) & (fovs <= 90.0))
    assert fovs.max() - fovs.min() > 15.0
    c = render_clip(WorldConfig(seed=3, height=16, width=24, num_frames=1, variant="alt"))
    np.testing.assert_allclose(c.intrinsics[0], 12.0 / np.tan(np.deg2rad(alt_fov_deg(3, 75.0)) / 2))


@pytest.mark.parametrize("name", ALT)
def test_visible_joints_project_onto_hand_mask(name: str, request: pytest.FixtureRequest) -> None:
    """>= 95% of in-image joints not hidden by the scene land on a hand-mask pixel.

    Every finger joint is the centre of a sphere at least 0.95 times the default bone radius; the
    wrist is inside the palm hull and the forearm tube. A joint is hidden when the scene is in
    front of it by more than that bound (as in tests/test_world.py).
    """
    c: Clip = request.getfixturevalue(name)
    margin = np.full(21, 0.012)
    margin[[1, 2, 5, 9, 13, 17]] = 0.015
    margin[0] = 0.03
    margin = np.tile(margin, 2)  # (42,)
    on_hand = counted = in_image = 0
    for t in range(c.num_frames):
        joints = c.hand_joints[t].reshape(-1, 3)  # (42, 3)
        uv, z = project_world_points(joints, c.world_from_cam[t], c.intrinsics)
        inside = (z > 0) & np.all(np.isfinite(uv), axis=1)
        inside &= (uv[:, 0] >= 0) & (uv[:, 0] < W) & (uv[:, 1] >= 0) & (uv[:, 1] < H)
        cols, rows = np.floor(uv[inside, 0]).astype(int), np.floor(uv[inside, 1]).astype(int)
        hit_hand = c.hand_mask[t, rows, cols] == 1
        hidden = ~hit_hand & (c.depth[t, rows, cols] < z[inside] - margin[inside])
        in_image += int(inside.sum())
        counted += int((~hidden).sum())
        on_hand += int(hit_hand.sum())
    assert counted >= 0.5 * in_image > 0
    assert on_hand / counted >= 0.95


@pytest.mark.parametrize("name", ALT)
def test_static_video_and_depth_match_outside_hands(
    name: str, request: pytest.FixtureRequest
) -> None:
    """Bit-exact off the hand mask until an object moves; clean first frame is static frame 0."""
    c: Clip = request.getfixturevalue(name)
    np.testing.assert_array_equal(c.static_frames[0], c.first_frame_clean)
    still = [t for t in range(c.num_frames) if np.array_equal(c.object_poses[t], c.object_poses[0])]
    assert still[:2] == [0, 1]
    for t in still:
        off = c.hand_mask[t] == 0
        np.testing.assert_array_equal(c.frames[t][off], c.static_frames[t][off])
        np.testing.assert_array_equal(c.depth[t][off], c.static_depth[t][off])
        on = ~off
        assert np.all(c.depth[t][on] < c.static_depth[t][on])  # the body is in front of the scene
    assert len(still) < c.num_frames, "the interaction should move an object"


def test_static_depth_reprojects_consistently_with_rolled_cameras(alt_wild: Clip) -> None:
    """Static depth of frame t moved into frame t+k agrees with frame t+k's static depth."""
    c = alt_wild
    errors = []
    for t, k in [(0, 3), (2, 5), (4, 2)]:
        points = unproject_depth(c.static_depth[t], c.intrinsics).reshape(-1, 3)
        world = transform_points(c.world_from_cam[t], points)
        uv, z = project_world_points(world, c.world_from_cam[t + k], c.intrinsics)
        ok = (z > 0) & (uv[:, 0] >= 1) & (uv[:, 0] < W - 1) & (uv[:, 1] >= 1) & (uv[:, 1] < H - 1)
        cols, rows = np.floor(uv[ok, 0]).astype(int), np.floor(uv[ok, 1]).astype(int)
        sampled = c.static_depth[t + k][rows, cols]
        errors.append(np.abs(z[ok] - sampled) / sampled)
    rel = np.concatenate(errors)
    assert len(rel) > 0.3 * H * W
    assert np.median(rel) < 0.01


def test_hand_mask_is_the_whole_body_sleeves_included(alt_pick: Clip) -> None:
    """The mask is every pixel where hand, bare forearm or sleeve is in front of the scene.

    Rebuilt from the alt body's meshes for a few frames; sleeve pixels are a real share of it and
    the arms run to the image border (they enter the view, they do not float).
    """
    cfg = WorldConfig(seed=7, height=H, width=W, num_frames=12, variant="alt")
    scene = build_scene_alt(cfg.seed, cfg.articulated)
    inter = script_interaction(scene, cfg.seed, cfg.num_frames, cfg.articulated)
    joints = hand_joints(inter)
    body = AltBody(cfg.seed)
    renderer = WorldRenderer(scene, alt_pick.intrinsics, H, W)
    np.testing.assert_allclose(joints, alt_pick.hand_joints, atol=1e-6)
    sleeve_share = []
    for t in (0, 5, 11):
        cam = alt_pick.world_from_cam[t]
        layer = renderer.render_meshes(
            cam, body.parts(joints[t], inter.world_from_hand[t], cam), body.colours
        )
        scene_depth = renderer.render_static(cam, inter.object_poses[t]).depth
        expected = layer.depth < scene_depth
        np.testing.assert_array_equal(alt_pick.hand_mask[t] == 1, expected)
        sleeve_share.append(np.mean(np.isin(layer.ids[expected], [1, 3])))
        mask = alt_pick.hand_mask[t] == 1
        assert mask[-1].any() or mask[:, 0].any() or mask[:, -1].any()
    assert max(sleeve_share) > 0.1


def test_arm_geometry() -> None:
    """Two-bone IK keeps the bone lengths and bends down; lean caps the stretch; meshes sized."""
    sh = np.array([-0.4, -0.19, 1.2])
    wrist = np.array([-0.15, -0.2, 0.8])
    el = elbow(sh, wrist, side=1)
    np.testing.assert_allclose(np.linalg.norm(el - sh), UPPER_ARM_LENGTH, atol=1e-9)
    np.testing.assert_allclose(np.linalg.norm(wrist - el), FOREARM_LENGTH_ALT, atol=1e-9)
    mid = 0.5 * (sh + wrist)
    assert el[2] < mid[2] and el[1] < mid[1]  # down and outwards (the right is -y)
    far = np.array([0.5, 0.0, 0.75])
    leaned = lean(sh, far)
    reach = np.linalg.norm(far - leaned)
    np.testing.assert_allclose(reach, MAX_STRETCH * (UPPER_ARM_LENGTH + FOREARM_LENGTH_ALT))
    np.testing.assert_array_equal(lean(sh, wrist), sh)
    verts, faces = ellipsoids(np.zeros((1, 3)), np.eye(3)[None], np.array([[0.1, 0.2, 0.3]]))
    np.testing.assert_allclose(np.abs(verts).max(0), [0.1, 0.2, 0.3], rtol=0.05)
    assert faces.max() < len(verts)
    verts, faces = tube(np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]]), np.array([0.1, 0.2]), 0.5)
    np.testing.assert_allclose(verts[:, 1].min(), -0.2, atol=1e-6)  # sideways: full radius
    np.testing.assert_allclose(verts[:, 2].max(), 0.1, rtol=0.03)  # up: flattened
    assert faces.max() < len(verts)


def test_ingest_names_and_renders_the_variant() -> None:
    cfg = IngestConfig(
        source="synthetic", height=32, width=48, num_frames=5, synthetic_count=3,
        synthetic_variant="alt", seed=4,
    )  # fmt: skip
    units = synthetic_source.list_units(cfg)
    assert units == [
        "synthetic:tabletop:4:alt",
        "synthetic:tabletop:5:alt",
        "synthetic:tabletop:6:articulated:alt",
    ]
    plain = synthetic_source.list_units(IngestConfig(synthetic_count=3, seed=4))
    assert plain == [
        "synthetic:tabletop:4",
        "synthetic:tabletop:5",
        "synthetic:tabletop:6:articulated",
    ]
    clip = synthetic_source.render_unit(units[2].partition(":")[2], cfg)
    assert clip.clip_id == "synth-alt-art-00006"
    direct = render_clip(
        WorldConfig(
            seed=6, height=32, width=48, num_frames=5, fps=cfg.fps, articulated=True, variant="alt"
        )
    )
    np.testing.assert_array_equal(clip.frames, direct.frames)
