"""Ingest of video files and frame folders: timing, sizes, intrinsics and bad input."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from egosim.pipeline.geometry import intrinsics_from_fov, project_points
from egosim.pipeline.media import write_video_file
from egosim.pipeline.stage import ClipRejected, ConfigError
from egosim.stages.common.frame_plan import plan_resize
from egosim.stages.ingest.stage import IngestConfig, IngestStage
from egosim.stages.ingest.standardise import WindowPolicy, resample_windows
from egosim.stages.ingest.video_source import read_video_clips
from tests.conftest import shared_data, smooth_frames

SMALL = {"height": 48, "width": 80, "num_frames": 8, "fps": 8.0}


def test_resample_picks_nearest_source_frames_for_any_rate() -> None:
    src = [(i / 30.0, np.array([i])) for i in range(90)]  # 3 s at 30 fps
    policy = WindowPolicy(fps=16.0, num_frames=10, min_frames=9, tail="drop")
    windows = list(resample_windows(iter(src), policy, source_fps=30.0))
    assert len(windows) == 4  # 48 target frames in 3 s -> 4 windows of 10
    np.testing.assert_allclose(windows[1].timestamps, (10 + np.arange(10)) / 16.0)
    expected = np.rint((10 + np.arange(10)) / 16.0 * 30.0).astype(int)
    np.testing.assert_array_equal(windows[1].source_indices, expected)
    strided = WindowPolicy(fps=16.0, num_frames=10, stride=5, min_frames=9, tail="drop")
    assert [w.index for w in resample_windows(iter(src), strided)] == list(range(8))


def test_resize_plan_keeps_projection_consistent() -> None:
    plan = plan_resize(1280, 720, 832, 480)
    src_k = intrinsics_from_fov(1280, 720, 70.0)
    point = np.array([0.2, -0.1, 1.5])
    uv_src, _ = project_points(point, src_k)
    uv_dst, _ = project_points(point, plan.intrinsics(src_k))
    scale = np.array([plan.scaled_width / 1280, plan.scaled_height / 720])  # as cv2.resize maps
    expected = uv_src * scale - [plan.crop_x, plan.crop_y]
    np.testing.assert_allclose(uv_dst, expected, atol=1e-9)
    frame = np.zeros((720, 1280, 3), np.uint8)
    assert plan.apply(frame).shape == (480, 832, 3)


def test_video_file_becomes_standard_clips(video_file: Path) -> None:
    cfg = IngestConfig(**SMALL)
    clips = list(read_video_clips(video_file, cfg))
    assert len(clips) == 2  # 2 s at 8 fps = 16 target frames = 2 clips of 8
    clip = clips[1]
    assert clip.frames.shape == (8, 48, 80, 3)
    np.testing.assert_allclose(clip.timestamps, (8 + np.arange(8)) / 8.0)
    assert clip.clip_id == "moving-w001" and clip.source_uri == str(video_file)
    fx, fy, cx, cy = clip.intrinsics
    assert (cx, cy) == (40.0, 24.0) and fx == fy


def test_short_video_is_rejected_with_the_reason(tmp_path: Path) -> None:
    path = tmp_path / "short.mp4"
    write_video_file(path, smooth_frames(5, 32, 32), fps=30.0)
    with pytest.raises(ClipRejected, match=r"short\.mp4 is shorter than one clip.*minimum is 8"):
        list(read_video_clips(path, IngestConfig(**SMALL)))


@pytest.mark.parametrize(
    ("suffix", "fmt", "codec"),
    [
        (".ts", "mpegts", "libx264"),
        (".MTS", "mpegts", "libx264"),  # AVCHD camcorders, upper case as they write it
        (".m2ts", "mpegts", "libx264"),
        (".3gp", "3gp", "libx264"),
        (".mpg", "mpeg", "mpeg2video"),
        (".avi", "avi", "mjpeg"),
    ],
)
def test_camera_and_phone_containers_are_found_and_ingested(
    tmp_path: Path, suffix: str, fmt: str, codec: str
) -> None:
    import av

    frames = smooth_frames(32, 48, 64)
    path = tmp_path / f"cam{suffix}"
    with av.open(str(path), mode="w", format=fmt) as container:
        stream = container.add_stream(codec, rate=16)
        stream.width, stream.height = 64, 48
        stream.pix_fmt = "yuvj420p" if codec == "mjpeg" else "yuv420p"
        for image in frames:
            container.mux(stream.encode(av.VideoFrame.from_ndarray(image, format="rgb24")))
        container.mux(stream.encode())
    (tmp_path / "notes.txt").write_text("not a video")
    stage = IngestStage(IngestConfig(**SMALL))
    assert stage.list_units(str(tmp_path)) == [f"video:{path}"]
    rows = list(stage.process_unit(f"video:{path}"))
    assert len(rows) == 2  # 2 s at 8 fps: 2 clips of 8 (MPEG-TS stamps start at 1.4 s)
    np.testing.assert_allclose(rows[1]["timestamps"], (8 + np.arange(8)) / 8.0, atol=1e-6)
    np.testing.assert_array_equal(rows[1]["source_frame_indices"], 2 * (8 + np.arange(8)))


def test_unreadable_video_is_rejected_naming_the_file(tmp_path: Path) -> None:
    path = tmp_path / "broken.mp4"
    path.write_bytes(b"\x00\x00\x00\x18ftypmp42 this is not a video")
    with pytest.raises(ClipRejected, match=r"broken\.mp4"):
        list(read_video_clips(path, IngestConfig(**SMALL)))


def test_empty_folder_and_missing_input_are_clear_errors(tmp_path: Path) -> None:
    stage = IngestStage(IngestConfig(source="video"))
    assert stage.list_units(str(tmp_path)) == []
    with pytest.raises(ConfigError, match="does not exist"):
        stage.list_units(str(tmp_path / "nope"))
    with pytest.raises(ConfigError, match="needs an --input"):
        stage.list_units(None)


def test_frame_folder_needs_a_rate_and_is_resampled(tmp_path: Path) -> None:
    import cv2

    folder = tmp_path / "frames"
    folder.mkdir()
    for i, frame in enumerate(smooth_frames(20, 40, 60)):
        cv2.imwrite(str(folder / f"{i:04d}.png"), frame[..., ::-1])
    stage = IngestStage(IngestConfig(**SMALL, frames_fps=10.0))
    (unit,) = stage.list_units(str(folder))
    assert unit.startswith("frames:")
    rows = list(stage.process_unit(unit))
    assert len(rows) == 2  # frames span 1.9 s: 16 targets at 8 fps (up to 1.875 s), 2 clips
    np.testing.assert_allclose(rows[1]["timestamps"], (8 + np.arange(8)) / 8.0)
    no_rate = IngestStage(IngestConfig(**SMALL))
    with pytest.raises(ClipRejected, match="frames_fps"):
        list(no_rate.process_unit(unit))


def test_too_few_frames_are_rejected_naming_the_count_with_or_without_a_rate(
    tmp_path: Path,
) -> None:
    import cv2

    folder = tmp_path / "few"
    folder.mkdir()
    for i, frame in enumerate(smooth_frames(8, 40, 60)):
        cv2.imwrite(str(folder / f"{i:04d}.jpg"), frame[..., ::-1])
    for cfg in (IngestConfig(), IngestConfig(frames_fps=30.0)):  # egosim preset: 33 at least
        stage = IngestStage(cfg)
        (unit,) = stage.list_units(str(folder))
        with pytest.raises(ClipRejected, match=r"few is shorter than one clip: it holds 8 "):
            list(stage.process_unit(unit))
        with pytest.raises(ClipRejected, match=r"minimum is 33 frames \(a full clip 61\)"):
            list(stage.process_unit(unit))


def test_real_epic_frames_with_defaults_are_a_clear_reject() -> None:
    folder = shared_data("epic_kitchens_frames")
    stage = IngestStage(IngestConfig())  # no frames_fps: what a new user runs
    (unit,) = stage.list_units(str(folder))
    with pytest.raises(ClipRejected, match=r"holds 8 frame\(s\); the minimum is 33"):
        list(stage.process_unit(unit))


def test_real_egocentric_frames(tmp_path: Path) -> None:
    folder = shared_data("epic_kitchens_frames")
    cfg = IngestConfig(height=128, width=224, num_frames=8, fps=12.0, frames_fps=12.0)
    stage = IngestStage(cfg)
    (unit,) = stage.list_units(str(folder))
    (row,) = list(stage.process_unit(unit))
    assert row["num_frames"] == 8 and (row["height"], row["width"]) == (128, 224)


def test_real_egocentric_video() -> None:
    path = shared_data("hot3d_video", "ego_centric_aria.mp4")
    cfg = IngestConfig(height=96, width=160, num_frames=16, fps=16.0, max_clips_per_source=2)
    clips = list(read_video_clips(path, cfg))
    assert len(clips) == 2
    assert clips[0].frames.shape == (16, 96, 160, 3)
    assert clips[0].frames.std() > 10  # real content, not a blank decode


def _egodex_episode(tmp_path: Path, frames: int = 40) -> Path:
    """A synthetic EgoDex episode (hdf5 + mp4, 30 fps, 64x48): camera orbit, two hands."""
    from egosim.pipeline.geometry import look_at
    from egosim.pipeline.records import Clip
    from egosim.world.egodex_export import write_egodex

    rng = np.random.default_rng(0)
    poses = np.stack([look_at([0.01 * i, -0.45, 1.25], [0.0, 0.0, 0.8]) for i in range(frames)])
    centres = np.array([[-0.1, 0.0, 0.8], [0.1, 0.0, 0.8]])  # (2, 3)
    joints = centres[None, :, None] + rng.uniform(-0.06, 0.06, (frames, 2, 21, 3))
    clip = Clip(
        clip_id="episode",
        source="synthetic",
        source_uri="",
        fps=30.0,
        timestamps=np.arange(frames) / 30.0,
        intrinsics=np.array([60.0, 60.0, 32.0, 24.0]),
        frames=smooth_frames(frames, 48, 64),
        world_from_cam=poses,
        hand_joints=joints.astype(np.float32),
        hand_valid=np.ones((frames, 2), bool),
        hand_confidence=rng.uniform(0.2, 1.0, (frames, 2, 21)).astype(np.float32),
        text="pick up the cup",
    )
    hdf5_path, _ = write_egodex(clip, tmp_path / "task", stem="0")
    return hdf5_path


def test_egodex_streaming_reader_gives_the_whole_episode_readers_clips(tmp_path: Path) -> None:
    from egosim.stages.ingest.egodex import read_egodex_clip, read_egodex_clips
    from egosim.stages.ingest.video_source import standardise_clip

    hdf5_path = _egodex_episode(tmp_path)
    cfg = IngestConfig(height=32, width=48, num_frames=9, min_frames=5, fps=10.0)
    old = list(standardise_clip(read_egodex_clip(hdf5_path), cfg))
    new = list(read_egodex_clips(hdf5_path, cfg))
    assert len(new) == len(old) == 2  # 40 frames at 30 fps: 14 at 10 fps, one 9 + a 5 tail
    for a, b in zip(old, new, strict=True):
        assert (a.clip_id, a.fps, a.clip_policy, a.text) == (
            b.clip_id,
            b.fps,
            b.clip_policy,
            b.text,
        )
        np.testing.assert_array_equal(a.frames, b.frames)
        np.testing.assert_array_equal(a.source_frame_indices, b.source_frame_indices)
        np.testing.assert_array_equal(a.timestamps, b.timestamps)
        np.testing.assert_array_equal(a.intrinsics, b.intrinsics)
        np.testing.assert_array_equal(a.world_from_cam, b.world_from_cam)
        np.testing.assert_array_equal(a.hand_joints, b.hand_joints)
        np.testing.assert_array_equal(a.hand_valid, b.hand_valid)
        np.testing.assert_array_equal(a.hand_confidence, b.hand_confidence)
        assert (a.source_fps, a.source_num_frames) == (b.source_fps, b.source_num_frames)


def test_egodex_video_shorter_than_its_labels_is_rejected_before_any_clip(tmp_path: Path) -> None:
    from egosim.stages.ingest.egodex import read_egodex_clips

    hdf5_path = _egodex_episode(tmp_path)
    write_video_file(hdf5_path.with_suffix(".mp4"), smooth_frames(30, 48, 64), fps=30.0)
    cfg = IngestConfig(height=32, width=48, num_frames=9, min_frames=5, fps=10.0)
    clips = read_egodex_clips(hdf5_path, cfg)
    with pytest.raises(
        ClipRejected, match=r"frame count mismatch: hdf5 has 40 frames, 0\.mp4 has 30"
    ):
        next(clips)
