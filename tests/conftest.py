"""Shared fixtures: tiny hand-built clips and small video files with known content."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from egosim.pipeline import media
from egosim.pipeline.execute import ShardTask
from egosim.pipeline.geometry import intrinsics_from_fov, look_at
from egosim.pipeline.media import write_video_file
from egosim.pipeline.records import Clip
from egosim.pipeline.shards import ShardWriter
from egosim.schemas.depth_camera import DEPTH_CAMERA
from egosim.schemas.poses import POSES

SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


def smooth_frames(num_frames: int, height: int, width: int, seed: int = 0) -> np.ndarray:
    """Frames of a moving luminance pattern with a slow colour tint (like natural video)."""
    rng = np.random.default_rng(seed)
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    phase = rng.uniform(0, 2 * np.pi)
    tint = rng.uniform(0.7, 1.0, 3)
    frames = []
    for t in range(num_frames):
        luma = 127 + 90 * np.sin(u / 7 + v / 11 + phase + 0.2 * t) * np.cos(v / 17 - 0.1 * t)
        frames.append(luma[..., None] * tint + 20 * np.sin(u / width * np.pi)[..., None])
    return np.clip(np.stack(frames), 0, 255).astype(np.uint8)


def make_clip(
    clip_id: str = "c0", num_frames: int = 6, height: int = 24, width: int = 32, seed: int = 0
) -> Clip:
    """A small valid clip with every optional column filled."""
    rng = np.random.default_rng(seed)
    t = num_frames
    poses = np.stack([look_at([0.02 * i, -0.5, 0.6], [0, 0, 0]) for i in range(t)])
    return Clip(
        clip_id=clip_id,
        source="synthetic",
        source_uri="",
        fps=16.0,
        timestamps=np.arange(t) / 16.0,
        intrinsics=intrinsics_from_fov(width, height, 70.0),
        frames=smooth_frames(t, height, width, seed),
        world_from_cam=poses,
        depth=rng.uniform(0.3, 2.0, (t, height, width)).astype(np.float32),
        static_frames=smooth_frames(t, height, width, seed + 1),
        static_depth=rng.uniform(0.3, 2.0, (t, height, width)).astype(np.float32),
        first_frame_clean=smooth_frames(1, height, width, seed + 1)[0],
        hand_joints=rng.normal(0, 0.1, (t, 2, 21, 3)).astype(np.float32),
        hand_valid=np.ones((t, 2), dtype=bool),
        hand_confidence=np.ones((t, 2, 21), dtype=np.float32),
        hand_mask=(rng.random((t, height, width)) > 0.7).astype(np.uint8),
        object_mask=rng.integers(0, 4, (t, height, width), dtype=np.uint8),
        object_poses=np.tile(np.eye(4), (t, 3, 1, 1)),
        text="a hand picks up a box",
    )


def translated(world_from_cam: np.ndarray, offset: np.ndarray) -> np.ndarray:
    """``world_from_cam (T, 4, 4)`` with every camera centre moved by ``offset (3,)`` metres."""
    out = np.array(world_from_cam, dtype=np.float64)  # (T, 4, 4)
    out[:, :3, 3] += offset
    return out


def write_poses(path: Path, clip: Clip, world_from_cam: np.ndarray) -> Path:
    """A one-row ``poses`` shard (as ``pose_clean`` writes) giving ``clip`` these poses."""
    t = clip.num_frames
    row = {
        "clip_id": clip.clip_id,
        "num_frames": t,
        "world_from_cam": np.asarray(world_from_cam).reshape(t, 16).tolist(),
        "outlier_frames": [],
        "method": "kalman_rts",
        **dict.fromkeys(("jitter_before_mm", "jitter_after_mm"), 0.0),
        **dict.fromkeys(("jitter_before_deg", "jitter_after_deg"), 0.0),
    }
    with ShardWriter(path, POSES, stage="test") as writer:
        writer.write_row(row)
    return path


def write_cameras(
    path: Path,
    clip: Clip,
    world_from_cam: np.ndarray,
    intrinsics: np.ndarray | None = None,
    depth0: np.ndarray | None = None,
) -> Path:
    """A one-row ``depth_camera`` shard for ``clip``; no ``depth0`` means a static camera."""
    t, h, w = clip.num_frames, clip.height, clip.width
    k = clip.intrinsics if intrinsics is None else intrinsics
    static = depth0 is None
    unit = None if static else media.depth_unit_for(depth0[None])
    row = {
        "clip_id": clip.clip_id,
        "num_frames": t,
        "width": w,
        "height": h,
        "intrinsics": np.asarray(k, dtype=np.float64).tolist(),
        "world_from_cam": np.asarray(world_from_cam).reshape(t, 16).tolist(),
        "registered": [True] * t,
        "static_camera": static,
        "depth0": None if static else media.encode_depth_video(depth0[None], unit),
        "depth_unit_m": unit,
        "confidence0": None if static else media.encode_mask_video(np.full((1, h, w), 255)),
        "backend": "given",
        **dict.fromkeys(("reprojection_error_px", "num_points3d", "confident_fraction")),
        "depth_source_frames": None,
        "camera_model": "static" if static else "given",
        "posed_by": [4] * t,
        "focal_prior_px": None,
        "metric_scale": 1.0,
        "scale_source": "source",
        "scale_spread": 0.0,
    }
    with ShardWriter(path, DEPTH_CAMERA, stage="test") as writer:
        writer.write_row(row)
    return path


@pytest.fixture
def clip() -> Clip:
    """One small clip with all ground truth."""
    return make_clip()


@pytest.fixture
def video_file(tmp_path: Path) -> Path:
    """A 2-second 30 fps 96x128 video (60 frames) of moving patterns."""
    path = tmp_path / "videos" / "moving.mp4"
    path.parent.mkdir()
    write_video_file(path, smooth_frames(60, 96, 128), fps=30.0)
    return path


def shared_data(*parts: str) -> Path:
    """A path under ../shared/data, skipping the test when it is absent."""
    path = SHARED_DATA.joinpath(*parts)
    if not path.exists():
        pytest.skip(f"{path} is absent")
    return path


def egodex_portrait_frames() -> np.ndarray:
    """``(33, 480, 832, 3)``: the EgoDex portrait variant's frames (docs/design.md, "Hands: the
    curtain hand, scene cues"), rebuilt without either lossy encode: the sample's centre 9:16
    cut at 1080x1920, ingest's 480x832 band at 0.625, 33 frames at 16 fps. Skips without
    ../shared/data."""
    import cv2

    from egosim.stages.common.frame_plan import plan_resize

    video, stamps = media.read_video_file(shared_data("egodex_sample", "sample.mp4"))
    stamps = np.asarray(stamps) - stamps[0]
    pick = [int(np.abs(stamps - t).argmin()) for t in np.arange(33) / 16.0]
    h, w = video.shape[1:3]
    cut = round(h * 9 / 16)
    plan = plan_resize(1080, 1920, 832, 480, (0.5, 0.625))
    return np.stack(
        [
            plan.apply(
                cv2.resize(
                    video[i][:, (w - cut) // 2 : (w - cut) // 2 + cut],
                    (1080, 1920),
                    interpolation=cv2.INTER_AREA,
                )
            )
            for i in pick
        ]
    )


def one_shard_task(
    stage: str,
    out_dir: Path,
    inputs: dict[str, Path],
    name: str | None = None,
    params: dict | None = None,
) -> ShardTask:
    """A one-shard task of ``stage`` writing ``out_dir/<name>.parquet`` (and its rejects)."""
    name = name or stage
    return ShardTask(
        step=stage,
        stage=stage,
        params=params or {},
        shard_index=0,
        shard_count=1,
        output=out_dir / f"{name}.parquet",
        rejects=out_dir / f"{name}-rejects.parquet",
        inputs=inputs,
    )
