"""Ingest's clip policy: presets, short sources, the source rate kept, strided windows, the tail,
ground truth picked with the frames, clips v2 rows, and the frame counts pack and the model take.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from egosim.model.conditioning import TrainingSample, latent_frames
from egosim.pipeline.clip_io import clip_from_row, read_clips, row_from_clip, write_clips
from egosim.pipeline.execute import run_shard_task
from egosim.pipeline.media import write_video_file
from egosim.pipeline.stage import ClipRejected, ConfigError, build_config
from egosim.schemas import CLIPS
from egosim.schemas.base import RowValidationError, SchemaCompatibilityError
from egosim.stages.common.packed import sample_from_pack_row
from egosim.stages.ingest.stage import CLIP_PRESETS, IngestConfig
from egosim.stages.ingest.standardise import WindowPolicy, longest_model_clip, resample_windows
from egosim.stages.ingest.video_source import read_video_clips, standardise_clip
from egosim.stages.pack.stage import sample_frame_indices
from egosim.world import WorldConfig, render_clip
from tests.conftest import make_clip, one_shard_task, shared_data, smooth_frames

SIZE = {"height": 48, "width": 80}  # small frames: the policy is about time


def _video(tmp_path: Path, name: str, num_frames: int, fps: float) -> Path:
    path = tmp_path / f"{name}.mp4"
    write_video_file(path, smooth_frames(num_frames, 48, 80), fps=fps)
    return path


def _stream(num_frames: int, fps: float, jitter: float = 0.0) -> list[tuple[float, np.ndarray]]:
    rng = np.random.default_rng(0)
    times = np.arange(num_frames) / fps + rng.uniform(-jitter, jitter, num_frames)
    return [(float(t), np.array([i])) for i, t in enumerate(times)]


def test_presets_fill_the_fields_left_at_zero_and_given_values_win() -> None:
    egosim = IngestConfig()
    assert (egosim.fps, egosim.num_frames, egosim.height, egosim.width) == (16.0, 61, 480, 832)
    assert egosim.min_frames == 33
    dwm = IngestConfig(preset="dwm")
    assert (dwm.fps, dwm.num_frames, dwm.height, dwm.width) == (8.0, 49, 480, 720)
    mixed = build_config(IngestConfig, {"preset": "dwm", "fps": "4", "min_frames": 17}, "t")
    assert (mixed.fps, mixed.num_frames, mixed.min_frames) == (4.0, 49, 17)
    resolved = dataclasses.asdict(mixed)  # what provenance records rebuilds the same config
    assert build_config(IngestConfig, resolved, "t") == mixed
    assert set(CLIP_PRESETS) == {"egosim", "dwm"}
    with pytest.raises(ConfigError, match=r"must be one of \['egosim', 'dwm'\], got 'wan'"):
        build_config(IngestConfig, {"preset": "wan"}, "t")
    with pytest.raises(ConfigError, match=r"min_frames must be >= 1, got -3.*tail must be"):
        IngestConfig(min_frames=-3, tail="sometimes")  # type: ignore[arg-type]


def test_longest_model_clip_is_1_plus_4k() -> None:
    got = [longest_model_clip(n) for n in (0, 1, 4, 5, 48, 50, 61)]
    assert got == [0, 1, 1, 5, 45, 49, 61]


def test_3_second_30fps_video_gives_one_short_45_frame_clip(tmp_path: Path) -> None:
    path = _video(tmp_path, "ninety", 90, 30.0)  # 2.97 s: 48 frames at 16 fps, < 61
    (clip,) = read_video_clips(path, IngestConfig(**SIZE))
    assert (clip.num_frames, clip.fps, clip.clip_policy) == (45, 16.0, "short:egosim")
    assert clip.source_fps == pytest.approx(30.0) and clip.source_num_frames == 90
    np.testing.assert_allclose(clip.timestamps, np.arange(45) / 16.0)
    src_times = clip.source_frame_indices / 30.0  # the nearest source frame of each target
    assert np.all(np.abs(src_times - clip.timestamps) <= 0.5 / 30.0 + 1e-6)
    assert np.all(np.diff(clip.source_frame_indices) >= 1)  # never a source frame twice
    row = row_from_clip(clip)
    CLIPS.validate_row(row)
    back = clip_from_row(row)
    np.testing.assert_array_equal(back.source_frame_indices, clip.source_frame_indices)
    assert (back.source_fps, back.source_num_frames, back.clip_policy) == (
        clip.source_fps,
        90,
        "short:egosim",
    )


def test_a_slower_source_keeps_its_rate_and_real_timestamps(tmp_path: Path) -> None:
    path = _video(tmp_path, "slow", 70, 8.0)  # 8 fps < 16: 61 source frames make a full clip
    (clip,) = read_video_clips(path, IngestConfig(**SIZE))  # 9 left over: below 33, no tail
    assert (clip.num_frames, clip.fps, clip.clip_policy) == (61, 8.0, "full:egosim")
    np.testing.assert_array_equal(clip.source_frame_indices, np.arange(61))
    np.testing.assert_allclose(clip.timestamps, np.arange(61) / 8.0, atol=1e-3)
    # Irregular capture times stay as they were: the clip's timestamps are the frames' own.
    stream = _stream(40, 8.0, jitter=0.02)
    (window,) = resample_windows(stream, WindowPolicy(fps=16.0, num_frames=61, min_frames=33), 8.0)
    assert (window.kind, window.fps, len(window.timestamps)) == ("short", 8.0, 37)
    np.testing.assert_allclose(window.timestamps, [t - stream[0][0] for t, _ in stream[:37]])
    with pytest.raises(RowValidationError, match="exceeds source_fps"):
        CLIPS.validate_row({**row_from_clip(clip), "fps": 16.0})  # an upsampled clip is refused


def test_a_too_short_video_is_rejected_naming_it_its_duration_and_the_minimum(
    tmp_path: Path,
) -> None:
    path = _video(tmp_path, "blink", 20, 30.0)  # 0.63 s: 11 frames at 16 fps
    pattern = r"blink\.mp4 is shorter than one clip: 20 .* over 0\.63 s .* minimum is 33 frames"
    with pytest.raises(ClipRejected, match=pattern):
        list(read_video_clips(path, IngestConfig(**SIZE)))


def test_long_sources_give_strided_windows_and_a_tail_by_choice() -> None:
    stream = _stream(200, 30.0)  # 6.63 s: 107 frames at 16 fps
    keep = WindowPolicy(fps=16.0, num_frames=61, min_frames=33, stride=30, preset="egosim")
    windows = list(resample_windows(stream, keep, 30.0))
    assert [(w.index, w.kind, len(w.timestamps)) for w in windows] == [
        (0, "full", 61),
        (1, "full", 61),
        (2, "tail", 45),  # starts at frame 60, the next stride; 47 remain -> 45 = 1 + 4 * 11
    ]
    np.testing.assert_allclose(windows[1].timestamps, (30 + np.arange(61)) / 16.0)
    np.testing.assert_allclose(windows[2].timestamps, (60 + np.arange(45)) / 16.0)
    assert keep.label("tail") == "tail:egosim"
    drop = dataclasses.replace(keep, tail="drop")
    assert [w.kind for w in resample_windows(stream, drop, 30.0)] == ["full", "full"]
    high_minimum = dataclasses.replace(keep, min_frames=49)  # 45 < 49: no tail
    assert len(list(resample_windows(stream, high_minimum, 30.0))) == 2
    capped = dataclasses.replace(keep, max_windows=1)
    assert [w.kind for w in resample_windows(stream, capped, 30.0)] == ["full"]


def test_ground_truth_is_picked_with_the_same_source_frames() -> None:
    t = 90
    source = make_clip("gt", num_frames=t, height=24, width=32)
    source = dataclasses.replace(source, fps=30.0, timestamps=np.arange(t) / 30.0)
    cfg = IngestConfig(height=24, width=32, num_frames=21, min_frames=5)  # 48 at 16 fps: 2x21+5
    clips = list(standardise_clip(source, cfg))
    assert [(c.clip_id, c.num_frames, c.clip_policy) for c in clips] == [
        ("gt-w000", 21, "full:egosim"),
        ("gt-w001", 21, "full:egosim"),
        ("gt-w002", 5, "tail:egosim"),
    ]
    for clip in clips:
        idx = clip.source_frame_indices
        for name in ("world_from_cam", "hand_joints", "hand_valid", "hand_confidence"):
            np.testing.assert_array_equal(getattr(clip, name), getattr(source, name)[idx], name)
        for name in ("depth", "static_depth", "hand_mask", "object_mask", "object_poses"):
            np.testing.assert_array_equal(getattr(clip, name), getattr(source, name)[idx], name)
        assert (clip.source_fps, clip.source_num_frames) == (30.0, t)
    assert clips[0].first_frame_clean is not None and clips[1].first_frame_clean is None
    # Standardising again keeps indices into the original source.
    (again,) = standardise_clip(clips[1], IngestConfig(height=24, width=32, fps=8.0, min_frames=9))
    assert again.clip_policy == "short:egosim" and again.num_frames == 9
    np.testing.assert_array_equal(
        again.source_frame_indices, clips[1].source_frame_indices[::2][:9]
    )


def test_clips_v1_shards_are_refused_with_a_compatibility_error(tmp_path: Path) -> None:
    new = {"source_fps", "source_num_frames", "source_frame_indices", "clip_policy"}
    new |= {"gripper_opening"}  # clips v3
    new |= {"embodiment_mask"}  # clips v4
    new |= {"source_crop"}  # clips v5
    v1_fields = [f for f in CLIPS.arrow if f.name not in new]
    v1 = pa.schema(
        v1_fields, metadata={b"egosim.schema.name": b"clips", b"egosim.schema.version": b"1"}
    )
    pq.write_table(pa.Table.from_pylist([], schema=v1), tmp_path / "v1.parquet")
    with pytest.raises(
        SchemaCompatibilityError, match="'clips' version 1, expected 'clips' version 5"
    ):
        list(read_clips(tmp_path / "v1.parquet"))


def test_real_egodex_sample_gives_one_49_frame_clip_at_16_fps() -> None:
    path = shared_data("egodex_sample", "sample.mp4")  # 94 frames at 30 fps, 3.1 s
    (clip,) = read_video_clips(path, IngestConfig())
    assert (clip.num_frames, clip.fps, clip.clip_policy) == (49, 16.0, "short:egosim")
    assert clip.frames.shape == (49, 480, 832, 3) and clip.frames.std() > 10
    assert clip.source_num_frames == 94 and clip.source_frame_indices[-1] <= 93


def test_dwm_preset_keeps_dwm_clips_whole() -> None:
    videos = sorted(shared_data("dwm_realworld", "realworld_dynamic", "videos").glob("*.mp4"))
    assert videos
    for path in videos:  # 49 frames at 8 fps, 720x480 already
        (clip,) = read_video_clips(path, IngestConfig(preset="dwm"))
        assert (clip.num_frames, clip.fps, clip.height, clip.width) == (49, 8.0, 480, 720)
        assert clip.clip_policy == "full:dwm"
        np.testing.assert_array_equal(clip.source_frame_indices, np.arange(49))


def test_a_short_synthetic_clip_packs_and_makes_valid_training_samples(tmp_path: Path) -> None:
    truth = render_clip(WorldConfig(seed=3, height=32, width=56, num_frames=36, fps=16.0))
    (clip,) = standardise_clip(truth, IngestConfig(height=32, width=56))  # 36 -> 33 frames
    assert clip.num_frames == 33 and clip.clip_policy == "short:egosim"
    np.testing.assert_array_equal(clip.world_from_cam, truth.world_from_cam[:33])
    write_clips(tmp_path / "clips.parquet", [clip])
    out = {"clips": tmp_path / "clips.parquet"}
    roles = {"clips": "clips", "scene_render": "scene_render", "keypoints": "keypoints"}
    roles |= {"captions": "captions", "hand_mask": "hand_mask"}
    steps = (
        ("hands", "hands", {"clips": "clips"}, {"backend": "given"}),
        ("keypoints", "keypoint_render", {"clips": "clips", "hands": "hands"}, None),
        ("hand_mask", "hand_mask", {"clips": "clips", "hands": "hands"}, None),
        ("scene_cloud", "scene_cloud", {"clips": "clips"}, None),
        ("scene_render", "scene_render", {"clips": "clips", "scene_cloud": "scene_cloud"}, None),
        ("captions", "caption", {"clips": "clips"}, None),
        ("pack", "pack", roles, None),  # num_frames 0: the most 1 + 4k that fit
        ("pack9", "pack", roles, {"num_frames": 9, "frame_stride": 4}),
        ("pack61", "pack", roles, {"num_frames": 61}),
    )
    for step, stage, inputs, params in steps:
        task = one_shard_task(stage, tmp_path, {r: out[s] for r, s in inputs.items()}, step, params)
        result = run_shard_task(task)
        out[step] = tmp_path / f"{step}.parquet"
        assert result.rows == (0 if step == "pack61" else 1), (step, result)
    from egosim.pipeline.shards import ShardReader

    for step, frames in (("pack", 33), ("pack9", 9)):
        with ShardReader(out[step]) as reader:
            row = next(reader.iter_rows())
        sample = sample_from_pack_row(row)
        assert isinstance(sample, TrainingSample) and sample.num_frames == frames
    with ShardReader(tmp_path / "pack61-rejects.parquet") as reader:
        (reason,) = reader.read_column("reason")
    assert "33 frames: too short for 61 sample frames" in reason


@pytest.mark.parametrize("frames", [33, 37, 45, 49, 61])
def test_pack_takes_every_clip_length_the_policy_allows(frames: int) -> None:
    whole = sample_frame_indices(frames, 0, 1)
    assert len(whole) == frames and latent_frames(len(whole)) == 1 + (frames - 1) // 4
    strided = sample_frame_indices(frames, 0, 4)  # dataset.yaml packs every 4th frame
    assert len(strided) >= 9 and (len(strided) - 1) % 4 == 0 and strided[-1] < frames
