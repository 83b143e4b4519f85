"""Export of processed clips as a LeRobot v3.0 dataset, read back by the documented format.

The ``lerobot`` package is not a dependency: the dataset is read back with
``egosim.stages.ingest.lerobot_source`` (written to LeRobot's documented v3.0 layout) and
pyarrow. Tolerances: camera poses 1e-6 (float32 storage), hand joints 1e-6 m.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from egosim.pipeline.clip_io import row_from_clip, write_clips
from egosim.pipeline.geometry import make_se3
from egosim.pipeline.records import Clip
from egosim.pipeline.shards import ShardWriter
from egosim.schemas import HANDS, KEYPOINTS
from egosim.stages.common.gripper import gripper_geometry
from egosim.stages.hands.stage import HandsStage
from egosim.stages.ingest import lerobot_source as reader
from egosim.stages.ingest.lerobot_export import HEAD_KEY, export_lerobot
from egosim.stages.ingest.robot_source import RobotEpisode, episode_clip, pose_from_xyz_quat
from egosim.stages.keypoint_render.stage import KeypointRenderConfig, KeypointRenderStage
from egosim.world import WorldConfig, render_clip

T, H, W = 9, 64, 112
POSE_TOL = 1e-6


def robot_clip(world: Clip) -> Clip:
    """A gripper clip on the world's frames and camera: one gripper 0.35 m ahead."""
    cam_from_ee = make_se3(np.eye(3), np.array([0.02, 0.03, 0.35]))
    ee = world.world_from_cam @ cam_from_ee  # (T, 4, 4)
    ep = RobotEpisode(
        name="robot0",
        source="lerobot",
        uri="",
        frames=world.frames,
        fps=world.fps,
        timestamps=world.timestamps,
        intrinsics=world.intrinsics,
        world_from_cam=world.world_from_cam,
        world_from_ee=ee[:, None],
        gripper_state=np.full((T, 1), 0.05),
        hands=(1,),
        text="stack the blocks",
    )
    return episode_clip(ep, gripper_geometry("generic"))


def make_run(run: Path) -> dict[str, dict]:
    """A run folder with ingest, hands and keypoints shards; returns the rows by clip id."""
    world = render_clip(WorldConfig(seed=1, height=H, width=W, num_frames=T, fps=16.0))
    small = render_clip(WorldConfig(seed=2, height=32, width=48, num_frames=T, fps=16.0))
    clips = [robot_clip(world), world, Clip(**{**small.__dict__, "clip_id": "small"})]
    for step in ("ingest", "hands", "keypoints"):
        (run / step).mkdir(parents=True)
    write_clips(run / "ingest" / "shard-00000.parquet", clips, stage="ingest")
    rows: dict[str, dict] = {}
    render = KeypointRenderStage(KeypointRenderConfig(variant="hand"))
    with (
        ShardWriter(run / "hands" / "shard-00000.parquet", HANDS, stage="hands") as hands_w,
        ShardWriter(run / "keypoints" / "shard-00000.parquet", KEYPOINTS, stage="kp") as kp_w,
    ):
        for clip in clips:
            row = row_from_clip(clip)
            hands = HandsStage().process({"clips": row})
            lifted = np.asarray(hands["hand_lifted"], dtype=bool)
            lifted[2:4] = False  # as if the backend had trusted only the 2D of frames 2-3
            hands["hand_lifted"] = lifted.tolist()
            kp = render.process({"clips": row, "hands": hands})
            hands_w.write_row(hands)
            kp_w.write_row(kp)
            rows[clip.clip_id] = {"clip": clip, "row": row, "hands": hands, "keypoints": kp}
    return rows


def test_export_reads_back_with_the_documented_layout(tmp_path: Path) -> None:
    run, out = tmp_path / "run", tmp_path / "lerobot"
    rows = make_run(run)
    report = export_lerobot(run, out)
    assert report.episodes == 2 and report.frames == 2 * T
    assert report.video_keys == [HEAD_KEY, "observation.images.skeleton"]
    assert report.skipped == {"small": "16 fps 32x48, the dataset is 16 fps 64x112"}
    info = reader.load_info(out)
    assert info["codebase_version"] == "v3.0" and info["total_episodes"] == 2
    assert info["features"]["observation.images.skeleton"]["dtype"] == "video"
    tasks = reader._tasks(out, info)
    for ep in reader.episode_table(out, info):
        want = rows[ep["egosim/clip_id"]]
        clip = want["clip"]
        data = reader._read_rows(out, info, ep)
        assert data.num_rows == T
        pose = np.asarray(data.column("observation.camera_pose").to_pylist())  # (T, 7)
        world_from_cam = pose_from_xyz_quat(pose[:, :3], pose[:, 3:], "xyzw")
        np.testing.assert_allclose(world_from_cam, clip.world_from_cam, atol=POSE_TOL)
        joints = np.asarray(data.column("observation.hand_joints").to_pylist())
        np.testing.assert_allclose(joints, np.asarray(want["hands"]["hand_joints"]), atol=1e-6)
        np.testing.assert_array_equal(
            data.column("observation.hand_valid").to_pylist(), want["hands"]["hand_valid"]
        )
        lifted = np.asarray(data.column("observation.hand_lifted").to_pylist())  # (T, 2)
        np.testing.assert_array_equal(lifted, want["hands"]["hand_lifted"])
        assert not lifted[2:4].any() and lifted.any() == np.any(want["hands"]["hand_valid"])
        np.testing.assert_allclose(
            data.column("observation.camera_intrinsics").to_pylist()[0], clip.intrinsics, 1e-6
        )
        assert tasks[data.column("task_index")[0].as_py()] == (clip.text or "")
        for key in report.video_keys:
            assert reader._read_frames(out, info, ep, key, T).shape == (T, H, W, 3)
        index = int(ep["episode_index"])
        head = out / info["video_path"].format(video_key=HEAD_KEY, chunk_index=0, file_index=index)
        assert head.read_bytes() == want["row"]["video"]  # copied, not re-encoded
        skeleton = head.parents[2] / "observation.images.skeleton" / "chunk-000" / head.name
        assert skeleton.read_bytes() == want["keypoints"]["skeleton_video"]
    assert json.loads((out / "meta" / "info.json").read_text())["total_frames"] == 2 * T
    with pytest.raises(FileExistsError, match="already holds a LeRobot dataset"):
        export_lerobot(run, out)


def test_export_command_writes_the_dataset_and_fails_on_an_empty_run(tmp_path: Path) -> None:
    from typer.testing import CliRunner

    from egosim.pipeline.cli import app

    run, out = tmp_path / "run", tmp_path / "lerobot"
    make_run(run)
    result = CliRunner().invoke(app, ["export", "lerobot", str(run), "--out", str(out)])
    assert result.exit_code == 0, result.output
    assert "2 episode(s)" in result.output and "skipped small" in result.output
    assert reader.load_info(out)["total_episodes"] == 2
    again = CliRunner().invoke(app, ["export", "lerobot", str(run), "--out", str(out)])
    assert again.exit_code == 2 and "already holds a LeRobot dataset" in again.output
    (tmp_path / "empty" / "ingest").mkdir(parents=True)
    empty = CliRunner().invoke(
        app, ["export", "lerobot", str(tmp_path / "empty"), "--out", str(tmp_path / "o2")]
    )
    assert empty.exit_code == 2, empty.output
