"""Typed input records (issue 12): ``process`` gets one record per role, parsed once, lazily.

Covers: the executor hands each role as its schema's record class; a record answers the plain
mapping access unmigrated stages use (with the declared-columns rule); media are decoded only
when asked for, once, and a stage that declares only ``video`` cannot reach depth; shape
checks and the one "no camera poses" reject.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import pytest

from egosim.pipeline import media
from egosim.pipeline.clip_io import row_from_clip, write_clips
from egosim.pipeline.execute import run_shard_task
from egosim.pipeline.records import (
    ClipsRecord,
    DepthCameraRecord,
    HandMaskRecord,
    HandsRecord,
    InputsDisagree,
    PosesRecord,
    Record,
    record_class,
    require_camera_poses,
)
from egosim.pipeline.shards import ShardReader
from egosim.pipeline.stage import (
    ClipRejected,
    ClipStage,
    UndeclaredColumnError,
    register_stage,
    registered_stages,
)
from egosim.schemas import CLIPS, REJECTS, ShardSchema
from egosim.schemas.captions import CAPTIONS
from egosim.schemas.poses import POSES
from tests.conftest import make_clip, one_shard_task, translated, write_poses


class _VideoOnlyStage(ClipStage):
    """Declares only the clip's video; writes the mean of frame 0 as its caption."""

    name = "test_records_video_only"
    description = "reads only video (tests/test_records.py)"
    inputs: ClassVar[Mapping[str, ShardSchema]] = {"clips": CLIPS}
    optional_inputs: ClassVar[Mapping[str, ShardSchema]] = {"poses": POSES}
    output = CAPTIONS
    columns: ClassVar[Mapping[str, tuple[str, ...]]] = {
        "clips": ("num_frames", "height", "width", "video"),
        "poses": ("num_frames", "world_from_cam"),
    }
    given: ClassVar[list[dict[str, Any]]] = []  # the records of every clip
    touch_depth: ClassVar[bool] = False  # also read the undeclared depth column

    def process(self, rows: Mapping[str, Mapping[str, Any]]) -> dict[str, Any]:
        """Frame 0's mean brightness as text."""
        type(self).given.append(dict(rows))
        clip = ClipsRecord.of(rows["clips"])
        if self.touch_depth:
            clip["depth"]
        return {"clip_id": clip.clip_id, "text": f"{clip.frames[0].mean():.3f}", "origin": "x"}


if _VideoOnlyStage.name not in registered_stages():  # test modules may be imported twice
    register_stage(_VideoOnlyStage)


@pytest.fixture
def clips_and_poses(tmp_path: Path) -> dict[str, Path]:
    clips = [make_clip("a", num_frames=4), make_clip("b", num_frames=5, seed=1)]
    write_clips(tmp_path / "clips.parquet", clips, stage="test")
    poses = write_poses(
        tmp_path / "poses.parquet", clips[1], translated(clips[1].world_from_cam, np.ones(3))
    )
    return {"clips": tmp_path / "clips.parquet", "poses": poses}


def test_the_executor_hands_each_role_as_its_schemas_record(
    clips_and_poses: dict[str, Path], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    _VideoOnlyStage.given.clear()
    calls: list[str] = []
    for name in ("decode_rgb_video", "decode_depth_video", "decode_lossless_video"):
        real = getattr(media, name)
        monkeypatch.setattr(
            media,
            name,
            lambda *a, _real=real, _name=name, **k: calls.append(_name) or _real(*a, **k),
        )
    task = one_shard_task("test_records_video_only", tmp_path / "out", clips_and_poses)
    assert run_shard_task(task).rows == 1  # clip "a" has no poses row
    (given,) = _VideoOnlyStage.given
    assert type(given["clips"]) is ClipsRecord and type(given["poses"]) is PosesRecord
    assert calls == ["decode_rgb_video"]  # the video once; no depth, no mask decoded
    poses = given["poses"].world_from_cam
    expected = translated(make_clip("b", num_frames=5, seed=1).world_from_cam, np.ones(3))
    np.testing.assert_allclose(poses, expected, atol=1e-12)  # (T, 4, 4), as written
    # The same mean brightness as decoding the clip in the test (H.264: what the shard holds).
    frames = media.decode_rgb_video(row_from_clip(make_clip("b", num_frames=5, seed=1))["video"])
    with ShardReader(tmp_path / "out" / "test_records_video_only.parquet") as reader:
        assert [r["text"] for r in reader.iter_rows()] == [f"{frames[0].mean():.3f}"]


def test_a_stage_declaring_only_video_cannot_reach_depth(
    clips_and_poses: dict[str, Path], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(_VideoOnlyStage, "touch_depth", True)
    task = one_shard_task("test_records_video_only", tmp_path / "out", clips_and_poses)
    with pytest.raises(UndeclaredColumnError, match="reads column 'depth' of input role 'clips'"):
        run_shard_task(task)


def test_a_record_answers_mapping_access_like_the_row() -> None:
    row = row_from_clip(make_clip("c", num_frames=3))
    part = {k: row[k] for k in ("clip_id", "num_frames", "fps", "text")}
    record = ClipsRecord(part, "s", "clips", CLIPS.column_names)
    assert isinstance(record, dict) and dict(record) == part  # unmigrated stages read it as before
    assert record["fps"] == row["fps"] and record.get("text") == row["text"]
    assert "video" not in record and record.get("nope", 7) == 7
    with pytest.raises(UndeclaredColumnError, match="stage 's' reads column 'video'"):
        record.get("video")
    with pytest.raises(UndeclaredColumnError, match="column 'world_from_cam'"):
        record.world_from_cam  # noqa: B018 (the typed accessor obeys the declaration too)
    assert (record.num_frames, record.fps, record.text) == (3, row["fps"], row["text"])
    assert ClipsRecord.of(record) is record  # a record passes through
    retyped = ClipsRecord.of(Record(part, "s", "clips", CLIPS.column_names))
    assert type(retyped) is ClipsRecord and retyped.num_frames == 3
    with pytest.raises(UndeclaredColumnError):  # ... and a generic one keeps its declaration
        retyped.frames  # noqa: B018
    assert record_class(CLIPS) is ClipsRecord and record_class(REJECTS) is Record


def test_typed_accessors_parse_once_with_the_schema_shapes() -> None:
    clip = make_clip("c", num_frames=4)
    record = ClipsRecord.of(row_from_clip(clip))  # a plain dict, as tests pass to process
    assert record.size == (4, clip.height, clip.width)
    assert record.world_from_cam.shape == (4, 4, 4)
    np.testing.assert_allclose(record.world_from_cam, clip.world_from_cam, atol=1e-12)
    assert record.world_from_cam is record.world_from_cam  # parsed once
    np.testing.assert_allclose(record.intrinsics, clip.intrinsics)
    frames = record.frames
    assert frames.shape == (4, clip.height, clip.width, 3) and record.frames is frames
    mask = record.mask_video("hand_mask")
    np.testing.assert_array_equal(mask, (clip.hand_mask > 0).astype(np.uint8))  # lossless
    hands = HandsRecord.of(
        {
            "clip_id": "c",
            "num_frames": 4,
            "hand_joints": clip.hand_joints.reshape(4, -1).tolist(),
            "hand_valid": clip.hand_valid.tolist(),
        }
    )
    np.testing.assert_allclose(hands.hand_joints, clip.hand_joints, atol=1e-6)
    np.testing.assert_array_equal(hands.hand_valid, clip.hand_valid)


def test_a_record_whose_media_disagree_with_its_size_is_rejected_naming_the_clip() -> None:
    row = row_from_clip(make_clip("c", num_frames=4))
    row["num_frames"] = 5  # the video holds 4
    with pytest.raises(ClipRejected, match=r"inputs disagree: clip 'c' video decodes to \(4,"):
        ClipsRecord.of(row).frames  # noqa: B018
    with pytest.raises(ClipRejected, match="clip 'c' world_from_cam has 64 values"):
        ClipsRecord.of(row).world_from_cam  # noqa: B018


def test_no_camera_poses_is_one_reject() -> None:
    poses = np.eye(4)[None]
    assert require_camera_poses(poses, "c") is poses
    with pytest.raises(ClipRejected, match=r"clip 'c': no camera poses \(world_from_cam is null\)"):
        require_camera_poses(None, "c")


def test_depth_hands_and_mask_accessors_match_the_clip() -> None:
    """Accessors added for hand_mask, inpaint and state_fusion: the clip's depth (all frames or
    frame 0 only), its hand labels (None when null), the cameras' depth0 and static flag, the
    hand mask row's masks; each decoded once and equal to what was written."""
    clip = make_clip("c", num_frames=4)
    row = row_from_clip(clip)
    record = ClipsRecord.of(row)
    unit = row["depth_unit_m"]
    depth = record.depth
    assert depth.shape == (4, clip.height, clip.width) and record.depth is depth
    np.testing.assert_allclose(depth, clip.depth, atol=unit / 2 + 1e-7)  # quantised to the unit
    np.testing.assert_array_equal(record.first_depth("static_depth"), _static_depth0(row))
    assert record.first_depth("static_depth") is record.first_depth("static_depth")
    np.testing.assert_allclose(record.hand_joints, clip.hand_joints, atol=1e-6)
    assert record.hand_joints.dtype == np.float64 and record.hand_valid.shape == (4, 2)
    np.testing.assert_array_equal(record.hand_confidence, clip.hand_confidence)
    bare = ClipsRecord.of({**row, "hand_joints": None, "depth": None})
    assert bare.hand_joints is None and bare.depth is None

    depth0 = clip.depth[0] * 2.0
    cam_unit = media.depth_unit_for(depth0[None])
    cams = DepthCameraRecord.of(
        {
            "clip_id": "c",
            "static_camera": False,
            "depth0": media.encode_depth_video(depth0[None], cam_unit),
            "depth_unit_m": cam_unit,
        }
    )
    assert cams.depth0.shape == (clip.height, clip.width) and cams.static_camera is False
    np.testing.assert_allclose(cams.depth0, depth0, atol=cam_unit / 2 + 1e-6)
    still = DepthCameraRecord.of({"clip_id": "c", "static_camera": True, "depth0": None})
    assert still.depth0 is None and still.static_camera is True

    masks = HandMaskRecord.of(
        {
            "clip_id": "c",
            "num_frames": 4,
            "height": clip.height,
            "width": clip.width,
            "hand_mask": media.encode_mask_video(clip.hand_mask),
        }
    )
    np.testing.assert_array_equal(masks.hand_mask, clip.hand_mask)


def _static_depth0(row: dict[str, Any]) -> np.ndarray:
    """Frame 0 of the row's static depth, decoded whole (the accessor decodes one frame)."""
    return media.decode_depth_video(row["static_depth"], row["depth_unit_m"])[0]


def test_media_that_disagree_with_the_size_say_how_for_a_stage_to_list_them() -> None:
    """``InputsDisagree`` is a ClipRejected worded "inputs disagree: <problem>"; ``problem``
    alone names the clip and column (state_fusion lists several at once), and rebuilding it as
    pickling does (Dask) keeps the message."""
    row = row_from_clip(make_clip("c", num_frames=4))
    row["num_frames"] = 5
    for read, problem in (
        (lambda r: r.frames, "clip 'c' video decodes to (4, 24, 32, 3), expected (5, 24, 32, 3)"),
        (lambda r: r.depth, "clip 'c' depth decodes to (4, 24, 32), expected (5, 24, 32)"),
        (
            lambda r: r.mask_video("hand_mask"),
            "clip 'c' hand_mask decodes to (4, 24, 32), expected (5, 24, 32)",
        ),
    ):
        with pytest.raises(InputsDisagree) as info:
            read(ClipsRecord.of(row))
        assert info.value.problem == problem
        assert str(info.value) == f"inputs disagree: {problem}"
        assert isinstance(info.value, ClipRejected)
        cls, args = info.value.__reduce__()  # what Dask's pickling rebuilds it from
        again = cls(*args)
        assert str(again) == str(info.value) and again.problem == problem
