"""Robot sources (agibot, lerobot) against episodes written from known arrays.

The head camera is the synthetic world's (frames, intrinsics, poses); a scripted end-effector
path in front of it gives the ground truth. Tolerances: poses 1e-6 (LeRobot stores float32, so
1e-6 m / 1e-6 of a rotation entry), gripper-skeleton pixels 1e-3 px, openings 1e-6 m.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from egosim.pipeline.clip_io import clip_from_row
from egosim.pipeline.geometry import make_se3, project_world_points
from egosim.pipeline.records import Clip
from egosim.pipeline.stage import ClipRejected
from egosim.stages.common.gripper import (
    GRIPPER_JOINTS,
    gripper_geometry,
    gripper_skeleton,
    opening_from_joints,
)
from egosim.stages.ingest.agibot_source import _seconds, find_episodes, read_agibot_episode
from egosim.stages.ingest.lerobot_source import LeRobotOptions, read_lerobot_episode
from egosim.stages.ingest.robot_writers import (
    RobotEpisodeArrays,
    write_agibot_episode,
    write_lerobot_dataset,
)
from egosim.stages.ingest.stage import IngestConfig, IngestStage
from egosim.world import WorldConfig, render_clip

T, H, W, FPS = 9, 64, 112, 16.0
POSE_TOL = 1e-6  # pose entries, metres and rotation-matrix entries
PIXEL_TOL = 1e-3  # projected gripper joints, pixels
OPENING_TOL = 1e-6  # metres
FRAME_TOL = 9.0  # mean |difference| of a decoded frame (0..255): writer + clip codec losses


@pytest.fixture(scope="module")
def world() -> Clip:
    """A small tabletop render: its camera is the robot's head camera."""
    return render_clip(WorldConfig(seed=3, height=H, width=W, num_frames=T, fps=FPS))


def scripted(world: Clip, grippers: int, robot: str) -> tuple[RobotEpisodeArrays, np.ndarray]:
    """An episode with ``grippers`` end effectors moving in front of the head camera.

    Returns the arrays and the ground-truth openings ``(T, G)`` in metres.
    """
    geom = gripper_geometry(robot)
    k = np.arange(T) / (T - 1)  # 0..1 over the episode
    poses, openings = [], []
    for g in range(grippers):
        side = -1.0 if (g == 0 and grippers == 2) else 1.0
        rot = Rotation.from_euler("xyz", np.stack([-0.4 + 0.2 * k, 0.1 * k, 0.3 * side * k], 1))
        trans = np.stack([0.07 * side + 0.02 * k, 0.04 - 0.03 * k, 0.32 + 0.05 * k], 1)
        cam_from_ee = make_se3(rot.as_matrix(), trans)  # (T, 4, 4)
        poses.append(world.world_from_cam @ cam_from_ee)
        openings.append(geom.max_opening_m * (0.2 + 0.6 * k if g == 0 else 0.9 - 0.5 * k))
    world_from_ee = np.stack(poses, axis=1)  # (T, G, 4, 4)
    opening = np.stack(openings, axis=1)  # (T, G)
    ep = RobotEpisodeArrays(
        frames=world.frames,
        fps=FPS,
        intrinsics=world.intrinsics,
        world_from_cam=world.world_from_cam,
        world_from_ee=world_from_ee,
        gripper_state=geom.state_from_opening(opening),
        task="put the cup on the plate",
        actions=["grasp the cup", "place it on the plate"],
    )
    return ep, opening


def ingest(source: str, path: Path, **params: object) -> list[Clip]:
    """Run the ingest stage on ``path`` (small clips, no resampling) and decode its rows."""
    cfg = IngestConfig(
        source=source, fps=FPS, num_frames=T, min_frames=T, height=H, width=W, **params
    )  # type: ignore[arg-type]
    stage = IngestStage(cfg)
    return [clip_from_row(r) for u in stage.list_units(str(path)) for r in stage.process_unit(u)]


def check_against_truth(
    clip: Clip, ep: RobotEpisodeArrays, opening: np.ndarray, hands: tuple[int, ...], robot: str
) -> float:
    """Assert poses, skeleton pixels and openings; returns the largest pixel error."""
    assert clip.num_frames == T and clip.height == H and clip.width == W
    np.testing.assert_allclose(clip.world_from_cam, ep.world_from_cam, atol=POSE_TOL)
    np.testing.assert_allclose(clip.intrinsics, ep.intrinsics, atol=1e-9)
    truth, _ = gripper_skeleton(ep.world_from_ee, opening, gripper_geometry(robot))  # (T,G,21,3)
    worst = 0.0
    joints = list(GRIPPER_JOINTS)
    for g, hand in enumerate(hands):
        assert clip.hand_valid[:, hand].all()
        np.testing.assert_array_equal(clip.hand_confidence[:, hand, joints], 1.0)
        np.testing.assert_array_equal(clip.hand_confidence[:, hand, 9:], 0.0)
        np.testing.assert_allclose(
            opening_from_joints(clip.hand_joints[:, hand]), opening[:, g], atol=OPENING_TOL
        )
        np.testing.assert_allclose(clip.gripper_opening[:, hand], opening[:, g], atol=OPENING_TOL)
        for t in range(T):
            uv_true, z = project_world_points(
                truth[t, g, joints], ep.world_from_cam[t], ep.intrinsics
            )
            uv, _ = project_world_points(
                clip.hand_joints[t, hand, joints].astype(np.float64),
                clip.world_from_cam[t],
                clip.intrinsics,
            )
            assert (z > 0).all()
            worst = max(worst, float(np.abs(uv - uv_true).max()))
    assert worst <= PIXEL_TOL, f"gripper skeleton off by {worst:.2e} px"
    return worst


def test_agibot_episode_round_trips_through_ingest(world: Clip, tmp_path: Path) -> None:
    ep, opening = scripted(world, grippers=2, robot="agibot_g1")
    write_agibot_episode(tmp_path, "327", "648642", ep)
    clips = ingest("agibot", tmp_path)
    assert [c.clip_id for c in clips] == ["agibot_327_648642-w000"]
    clip = clips[0]
    assert clip.source == "agibot"
    assert clip.text == "put the cup on the plate: grasp the cup; place it on the plate"
    np.testing.assert_allclose(clip.timestamps, np.arange(T) / FPS, atol=1e-9)
    check_against_truth(clip, ep, opening, hands=(0, 1), robot="agibot_g1")
    # auto finds the episode too, and neither its video nor its h5 as another source
    assert [c.source for c in ingest("auto", tmp_path)] == ["agibot"]


@pytest.mark.parametrize(
    ("version", "codec"), [("v3.0", "h264"), ("v3.0", "av1"), ("v2.1", "h264")]
)
def test_lerobot_dataset_round_trips_through_ingest(
    world: Clip, tmp_path: Path, version: str, codec: str
) -> None:
    ep0, open0 = scripted(world, grippers=1, robot="franka")
    ep1 = RobotEpisodeArrays(**{**ep0.__dict__, "task": "open the drawer"})
    ep1.frames = ep0.frames[::-1].copy()  # tells the episodes' frames apart in a shared file
    ep1.world_from_ee = ep0.world_from_ee[::-1].copy()  # the same path backwards
    ep1.gripper_state = ep0.gripper_state[::-1].copy()
    root = write_lerobot_dataset(tmp_path / "so_robot", [ep0, ep1], version=version, codec=codec)
    clips = ingest("lerobot", root, robot="franka", intrinsics=tuple(world.intrinsics))
    assert [c.clip_id for c in clips] == ["so_robot_ep000000-w000", "so_robot_ep000001-w000"]
    assert [c.text for c in clips] == ["put the cup on the plate", "open the drawer"]
    check_against_truth(clips[0], ep0, open0, hands=(1,), robot="franka")
    check_against_truth(clips[1], ep1, open0[::-1], hands=(1,), robot="franka")
    for clip, ep in zip(clips, (ep0, ep1), strict=True):  # each episode's own frames (lossy)
        err = np.abs(clip.frames.astype(np.float64) - ep.frames).mean(axis=(1, 2, 3))  # (T,)
        other = np.abs(clip.frames.astype(np.float64) - ep.frames[::-1]).mean(axis=(1, 2, 3))
        assert err.max() < FRAME_TOL and other.max() > err.max() + 5.0  # measured ~7 vs ~16
    assert not clips[0].hand_valid[:, 0].any()  # one gripper: the left hand slot stays empty
    assert np.isnan(clips[0].gripper_opening[:, 0]).all()
    assert {c.source for c in ingest("auto", tmp_path, robot="franka")} == {"lerobot"}


def test_lerobot_fixed_camera_pose_from_the_config(world: Clip, tmp_path: Path) -> None:
    ep, _ = scripted(world, grippers=1, robot="generic")
    root = write_lerobot_dataset(tmp_path / "fixed", [ep], camera_pose=False)
    fixed = world.world_from_cam[0]
    with pytest.raises(ClipRejected, match=r"lerobot episode 0 of .*fixed: no camera pose"):
        read_lerobot_episode(root, 0)
    clip = read_lerobot_episode(root, 0, LeRobotOptions(camera_pose=tuple(fixed.ravel())))
    np.testing.assert_allclose(clip.world_from_cam, np.repeat(fixed[None], T, 0), atol=1e-12)
    # An OpenGL-axes camera pose is converted once: y and z flip.
    gl = LeRobotOptions(camera_pose=tuple(fixed.ravel()), camera_axes="opengl")
    clip_gl = read_lerobot_episode(root, 0, gl)
    np.testing.assert_allclose(clip_gl.world_from_cam[0], fixed @ np.diag([1, -1, -1, 1.0]))


# --- malformed episodes: rejected with reasons naming the episode -------------------------------


def small_episode(grippers: int) -> RobotEpisodeArrays:
    rng = np.random.default_rng(0)
    t = 5
    ee = np.tile(make_se3(np.eye(3), np.array([0.0, 0.0, 0.4])), (t, grippers, 1, 1))
    return RobotEpisodeArrays(
        frames=rng.integers(0, 255, (t, 32, 48, 3), dtype=np.uint8),
        fps=10.0,
        intrinsics=np.array([40.0, 40.0, 24.0, 16.0]),
        world_from_cam=np.tile(np.eye(4), (t, 1, 1)),
        world_from_ee=ee,
        gripper_state=np.full((t, grippers), 60.0),
    )


def test_agibot_malformed_episodes_are_rejected(tmp_path: Path) -> None:
    ep = small_episode(2)
    h5 = write_agibot_episode(tmp_path / "a", "350", "1", ep, drop_keys=("state/end/orientation",))
    with pytest.raises(
        ClipRejected, match=r"agibot_350_1: .* lacks proprio key.*'state/end/orient"
    ):
        read_agibot_episode(h5)
    h5 = write_agibot_episode(tmp_path / "b", "350", "2", ep, state_rows=3)
    with pytest.raises(ClipRejected, match=r"agibot_350_2 .*length mismatch: 3 state rows but 5"):
        read_agibot_episode(h5)
    bad = small_episode(2)
    bad.gripper_state[2, 1] = np.nan
    bad.world_from_ee[4, 0, 0, 3] = np.nan
    h5 = write_agibot_episode(tmp_path / "c", "350", "3", bad)
    with pytest.raises(ClipRejected, match=r"agibot_350_3 .*") as err:
        read_agibot_episode(h5)
    assert "end-effector poses are NaN or infinite in 1 frame(s), first [4]" in str(err.value)
    assert "gripper states are NaN or infinite in 1 frame(s), first [2]" in str(err.value)
    (h5.parents[3] / "observations/350/3/videos/head_color.mp4").unlink()
    with pytest.raises(ClipRejected, match=r"agibot_350_3: video .*head_color.mp4 is missing"):
        read_agibot_episode(h5)
    stray = tmp_path / "d" / "proprio_stats.h5"  # not in the layout: not found, and refused
    stray.parent.mkdir()
    stray.write_bytes(h5.read_bytes())
    assert find_episodes(tmp_path / "d") == []
    with pytest.raises(ClipRejected, match=r"is not at ROOT/proprio_stats/TASK/EPISODE/"):
        read_agibot_episode(stray)
    # Through the stage: a unit that fails raises ClipRejected (the executor's rejects table).
    stage = IngestStage(
        IngestConfig(source="agibot", num_frames=5, min_frames=5, height=32, width=48)
    )
    units = stage.list_units(str(tmp_path / "a"))
    with pytest.raises(ClipRejected, match="agibot_350_1"):
        list(stage.process_unit(units[0]))


def test_lerobot_malformed_episodes_are_rejected(tmp_path: Path) -> None:
    ep = small_episode(1)
    ep.gripper_state = np.full((5, 1), 0.04)
    bad = small_episode(1)
    bad.world_from_ee[1, 0, :3, :3] = np.nan  # NaN quaternion in row 1
    root = write_lerobot_dataset(tmp_path / "ds", [ep, bad], version="v2.1")
    assert read_lerobot_episode(root, 0).num_frames == 5
    with pytest.raises(ClipRejected, match=r"lerobot episode ds_ep000001 .*NaN .* first \[1\]"):
        read_lerobot_episode(root, 1)
    # A video longer than the states (v2.1: one file per episode).
    longer = small_episode(1)
    longer.frames = np.concatenate([longer.frames, longer.frames[:2]])
    root = write_lerobot_dataset(tmp_path / "long", [longer], version="v2.1")
    with pytest.raises(
        ClipRejected, match=r"episode 0 .*length mismatch: 5 state rows but 7 frames"
    ):
        read_lerobot_episode(root, 0)
    root = write_lerobot_dataset(tmp_path / "long3", [ep, longer], version="v3.0")
    assert read_lerobot_episode(root, 0).num_frames == 5  # located by from_timestamp
    with pytest.raises(
        ClipRejected, match=r"episode 1 .*length mismatch: 5 state rows but 7 frames"
    ):
        read_lerobot_episode(root, 1)
    # Joint states only: no end-effector pose to place the gripper.
    joints = [f"joint_{i}" for i in range(7)] + ["gripper"]
    root = write_lerobot_dataset(tmp_path / "joints", [ep], state_names=joints)
    with pytest.raises(ClipRejected, match=r"episode 0 of .*joints: no end-effector pose"):
        read_lerobot_episode(root, 0)
    with pytest.raises(ClipRejected, match="no such episode"):
        read_lerobot_episode(root, 7)


def test_agibot_timestamps_in_nanoseconds_or_seconds() -> None:
    ns = np.array([1_700_000_000_000_000_000, 1_700_000_000_100_000_000], dtype=np.int64)
    np.testing.assert_allclose(_seconds(ns), [0.0, 0.1], atol=1e-12)
    np.testing.assert_allclose(_seconds(np.array([12.5, 12.6, 12.7])), [0.0, 0.1, 0.2], atol=1e-9)
    np.testing.assert_allclose(_seconds(ns.astype(np.float64)), [0.0, 0.1], atol=1e-6)


def test_keypoint_render_auto_draws_robot_clips_as_grippers(world: Clip, tmp_path: Path) -> None:
    """variant auto: a robot clip gets the gripper drawing (no dot of other fingers' colours)."""
    from egosim.pipeline.clip_io import row_from_clip
    from egosim.stages.hands.stage import HandsStage
    from egosim.stages.keypoint_render.stage import KeypointRenderConfig, KeypointRenderStage

    ep, _ = scripted(world, grippers=2, robot="agibot_g1")
    write_agibot_episode(tmp_path, "327", "1", ep)
    (clip,) = ingest("agibot", tmp_path)
    row = row_from_clip(clip)
    hands = HandsStage().process({"clips": row})
    auto = KeypointRenderStage(KeypointRenderConfig(variant="auto"))
    out = auto.process({"clips": row, "hands": hands})
    grip = KeypointRenderStage(KeypointRenderConfig(variant="gripper"))
    assert out["variant"] == "gripper"
    assert out["skeleton_video"] == grip.process({"clips": row, "hands": hands})["skeleton_video"]
    human = row_from_clip(world)
    out = auto.process({"clips": human, "hands": HandsStage().process({"clips": human})})
    assert out["variant"] == "hand"
