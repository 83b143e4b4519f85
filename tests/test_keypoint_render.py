"""keypoint_render: projection against hand-built matrices, drawing, the stage end to end."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from egosim.pipeline import media
from egosim.pipeline.clip_io import write_clips
from egosim.pipeline.execute import ShardTask, run_shard_task
from egosim.pipeline.shards import open_shard
from egosim.schemas.keypoints import KEYPOINTS
from egosim.stages.keypoint_render.draw import (
    FINGER_COLOURS,
    draw_skeleton_frame,
    project_hands,
)
from egosim.world.clip import render_clip
from egosim.world.config import WorldConfig
from tests.conftest import translated, write_cameras, write_poses

H, W, T = 64, 112, 6


@pytest.fixture(scope="module")
def world_clip():
    """A tiny synthetic clip with GT joints, poses and hand masks."""
    return render_clip(WorldConfig(seed=5, mode="tabletop", height=H, width=W, num_frames=T))


def reference_projection(joints: np.ndarray, poses: np.ndarray, k: np.ndarray) -> np.ndarray:
    """Independent oracle: ``K @ inv(world_from_cam) @ [X; 1]`` with homogeneous division."""
    kmat = np.array([[k[0], 0, k[2]], [0, k[1], k[3]], [0, 0, 1.0]])
    out = np.zeros((*joints.shape[:-1], 2))
    for f in range(len(joints)):
        cam_from_world = np.linalg.inv(poses[f])[:3]  # (3, 4)
        homog = np.concatenate([joints[f], np.ones((*joints.shape[1:-1], 1))], -1)  # (2, 21, 4)
        pix = homog @ cam_from_world.T @ kmat.T  # (2, 21, 3)
        out[f] = pix[..., :2] / pix[..., 2:]
    return out


def test_projection_matches_ground_truth(world_clip) -> None:
    joints = world_clip.hand_joints.astype(np.float64)
    proj = project_hands(
        joints, world_clip.hand_valid, world_clip.world_from_cam, world_clip.intrinsics, H, W
    )
    expected = reference_projection(joints, world_clip.world_from_cam, world_clip.intrinsics)
    err = np.abs(proj.uv - expected)[proj.visible]
    assert proj.visible.mean() > 0.5
    assert err.max() < 1e-3
    # The projected joints land on the rendered hands (the world's own hand masks).
    v = np.floor(proj.uv[..., 1][proj.visible]).astype(int)
    u = np.floor(proj.uv[..., 0][proj.visible]).astype(int)
    frames = np.nonzero(proj.visible)[0]
    on_hand = world_clip.hand_mask[frames, v, u].mean()
    assert on_hand > 0.8, on_hand


def test_behind_camera_and_invalid_hands_skipped() -> None:
    joints = np.zeros((1, 2, 21, 3))
    joints[0, 0, :, 2] = 0.5  # left hand in front
    joints[0, 0, :, 0] = np.linspace(-0.05, 0.05, 21)
    joints[0, 1, :, 2] = -0.5  # right hand behind
    k = np.array([100.0, 100.0, 40.0, 30.0])
    proj = project_hands(joints, np.ones((1, 2), bool), np.eye(4)[None], k, 60, 80)
    assert proj.visible[0, 0].all() and not proj.visible[0, 1].any()
    assert np.isnan(proj.uv[0, 1]).all()
    image = draw_skeleton_frame(proj.uv[0], proj.depth[0], 60, 80)
    assert image.any()
    proj = project_hands(joints, np.zeros((1, 2), bool), np.eye(4)[None], k, 60, 80)
    assert not proj.visible.any()
    assert not draw_skeleton_frame(proj.uv[0], proj.depth[0], 60, 80).any()


def _hand(depth: float) -> tuple[np.ndarray, np.ndarray]:
    """A flat synthetic hand facing the camera at ``depth``: uv (2, 21, 2), depth (2, 21)."""
    uv = np.full((2, 21, 2), np.nan)
    z = np.full((2, 21), np.nan)
    for f in range(5):
        for j in range(4):
            uv[1, 1 + 4 * f + j] = [20 + 10 * f, 50 - 8 * j]
    uv[1, 0] = [40, 60]
    z[1] = depth
    return uv, z


def test_finger_colours_and_depth_scaled_width() -> None:
    near = draw_skeleton_frame(*_hand(0.25), 80, 80)
    far = draw_skeleton_frame(*_hand(1.0), 80, 80)
    assert (near.any(-1)).sum() > 1.5 * (far.any(-1)).sum()
    # The thumb's colour is present and the little finger's too (right hand, full shade).
    for fid in (0, 4):
        colour = FINGER_COLOURS[fid].astype(int)
        assert np.any(np.all(np.abs(near.astype(int) - colour) <= 2, axis=-1))
    gripper = draw_skeleton_frame(*_hand(0.5), 80, 80, variant="gripper")
    middle = FINGER_COLOURS[2].astype(int)
    assert not np.any(np.all(np.abs(gripper.astype(int) - middle) <= 2, axis=-1))
    assert gripper.any()


def task(stage: str, out: Path, inputs: dict, params: dict) -> ShardTask:
    """A one-shard task of ``stage`` writing ``out``."""
    return ShardTask(
        step=stage,
        stage=stage,
        params=params,
        shard_index=0,
        shard_count=1,
        output=out,
        rejects=out.with_suffix(".rejects.parquet"),
        inputs=inputs,
    )


def test_stage_end_to_end(world_clip, tmp_path: Path) -> None:
    clips = tmp_path / "clips.parquet"
    write_clips(clips, [world_clip])
    hands = tmp_path / "hands.parquet"
    run_shard_task(task("hands", hands, {"clips": clips}, {"despike": False}))
    out = tmp_path / "keypoints.parquet"
    result = run_shard_task(
        task("keypoint_render", out, {"clips": clips, "hands": hands}, {"variant": "hand"})
    )
    assert result.rows == 1 and result.rejected == 0
    with open_shard(out, KEYPOINTS) as reader:
        row = next(reader.iter_rows())
    uv = np.asarray(row["keypoints_2d"], dtype=np.float64).reshape(T, 2, 21, 2)
    vis = np.asarray(row["keypoint_visible"], dtype=bool).reshape(T, 2, 21)
    expected = reference_projection(
        world_clip.hand_joints.astype(np.float64), world_clip.world_from_cam, world_clip.intrinsics
    )
    # float32 storage of pixels below 112: about 1e-5 px.
    assert np.abs(uv - expected)[vis].max() < 1e-3
    video = media.decode_rgb_video(row["skeleton_video"], H, W)
    assert video.shape == (T, H, W, 3) and video.any()


def test_stage_uses_connected_poses_and_camera_intrinsics(world_clip, tmp_path: Path) -> None:
    clips = tmp_path / "clips.parquet"
    write_clips(clips, [world_clip])
    offset = np.array([0.03, -0.02, 0.01])
    moved = translated(world_clip.world_from_cam, offset)
    k = world_clip.intrinsics * np.array([1.1, 1.1, 1.0, 1.0])  # estimated focal length
    # poses beat cameras for the trajectory; cameras beat the clip for the intrinsics.
    cameras = write_cameras(
        tmp_path / "cameras.parquet", world_clip, world_clip.world_from_cam, k, world_clip.depth[0]
    )
    poses = write_poses(tmp_path / "poses.parquet", world_clip, moved)
    hands = tmp_path / "hands.parquet"
    run_shard_task(task("hands", hands, {"clips": clips}, {"despike": False}))
    out = tmp_path / "keypoints.parquet"
    inputs = {"clips": clips, "hands": hands, "poses": poses, "cameras": cameras}
    result = run_shard_task(task("keypoint_render", out, inputs, {}))
    assert result.rows == 1 and result.rejected == 0
    with open_shard(out, KEYPOINTS) as reader:
        row = next(reader.iter_rows())
    uv = np.asarray(row["keypoints_2d"], dtype=np.float64).reshape(T, 2, 21, 2)
    vis = np.asarray(row["keypoint_visible"], dtype=bool).reshape(T, 2, 21)
    joints = world_clip.hand_joints.astype(np.float64)
    expected = reference_projection(joints, moved, k)
    assert vis.mean() > 0.3
    assert np.abs(uv - expected)[vis].max() < 1e-3
    own = reference_projection(joints, world_clip.world_from_cam, world_clip.intrinsics)
    assert np.abs(uv - own)[vis].mean() > 1.0  # the keypoints did move
