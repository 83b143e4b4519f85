"""Robot arm masks from a URDF + joint states against the synthetic robot's ground truth.

The world renders its arm from its own forward kinematics (world/robot.py); the mask
path reads only the URDF the world wrote and the joint states (yourdfpy kinematics, trimesh
geometry, open3d ray casting). Tolerances: link poses 1e-9 m / rotation entries; undilated mask
IoU >= 0.99 (cylinder tessellations differ: 24 segments in the world, trimesh's own in the URDF
path); with the default-sized 1 px growth at 240x416, IoU >= 0.9 and recall >= 0.999.
"""

from __future__ import annotations

import numpy as np
import pytest

from egosim.stages.common.urdf_mask import UrdfMaskError, arm_masks, load_urdf
from egosim.world import WorldConfig
from egosim.world.robot import ARM, arm_urdf, link_poses, render_robot_clip

H, W, T = 240, 416, 6


@pytest.fixture(scope="module", params=["default", "alt"])
def robot_clip(request):
    """A short robot episode in the default world and in the held-out alt world."""
    return render_robot_clip(
        WorldConfig(seed=1, height=H, width=W, num_frames=T, variant=request.param)
    )


def test_urdf_kinematics_match_the_world() -> None:
    robot = load_urdf(arm_urdf())
    assert tuple(robot.actuated_joint_names) == ARM.moving_joints
    rng = np.random.default_rng(0)
    for _ in range(5):
        q = rng.uniform(-1.5, 1.5, len(ARM.moving_joints))
        q[-2:] = rng.uniform(0.0, 0.04, 2)  # prismatic fingers
        robot.update_cfg(q)
        truth = link_poses(q, np.eye(4))
        for link in ("upper_arm", "palm", "finger_left", "finger_right", "tool"):
            np.testing.assert_allclose(robot.get_transform(link), truth[link], atol=1e-9)


def _iou_recall(mask: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    m, g = mask.astype(bool), truth.astype(bool)
    return float((m & g).sum() / (m | g).sum()), float((m & g).sum() / g.sum())


def test_arm_mask_matches_the_ground_truth(robot_clip) -> None:
    c = robot_clip
    assert c.arm_mask.sum() > 20_000  # the arm is in view for most of the clip
    args = (c.urdf, list(c.joint_names), c.joint_positions, c.world_from_base)
    cams = (c.world_from_cam, c.intrinsics, H, W)
    iou, recall = _iou_recall(arm_masks(*args, *cams, dilate_px=0), c.arm_mask)
    assert iou >= 0.99, iou  # measured 0.999 (default and alt)
    iou, recall = _iou_recall(arm_masks(*args, *cams, dilate_px=1), c.arm_mask)
    assert iou >= 0.9 and recall >= 0.999, (iou, recall)  # measured 0.947 / 0.936, recall 1.0


def test_wrong_joint_states_move_the_mask(robot_clip) -> None:
    c = robot_clip
    bent = c.joint_positions.copy()
    bent[:, 1] += 0.3  # shoulder lift off by 17 degrees
    mask = arm_masks(c.urdf, list(c.joint_names), bent, c.world_from_base, c.world_from_cam,
                     c.intrinsics, H, W, dilate_px=0)  # fmt: skip
    assert _iou_recall(mask, c.arm_mask)[0] < 0.7


def test_bad_joint_states_are_refused(robot_clip) -> None:
    c = robot_clip
    cams = (c.world_from_cam, c.intrinsics, H, W)
    with pytest.raises(UrdfMaskError, match=r"lack the URDF's actuated joints \['elbow'\]"):
        names = [n if n != "elbow" else "elbow_typo" for n in c.joint_names]
        arm_masks(c.urdf, names, c.joint_positions, c.world_from_base, *cams)
    nan = c.joint_positions.copy()
    nan[2, 0] = np.nan
    with pytest.raises(UrdfMaskError, match=r"NaN or inf at frames \[2\]"):
        arm_masks(c.urdf, list(c.joint_names), nan, c.world_from_base, *cams)
    with pytest.raises(UrdfMaskError, match="cannot read URDF"):
        arm_masks("<robot><link></robot>", list(c.joint_names), c.joint_positions,
                  c.world_from_base, *cams)  # fmt: skip


def test_synthetic_robot_clip_through_ingest() -> None:
    """A robot unit of the synthetic source: the gripper skeleton lands on the rendered fingers
    (1e-3 px) and the embodiment mask (URDF + joint states) covers the true arm mask."""
    from egosim.pipeline.geometry import project_world_points
    from egosim.stages.ingest import synthetic_source
    from egosim.stages.ingest.stage import IngestConfig
    from egosim.world.robot import FINGER_LENGTH

    cfg = IngestConfig(  # 1 px growth at half the default size (the default 2 px at 480x832)
        synthetic_count=1, synthetic_robot_every=1, height=H, width=W, num_frames=5, fps=8.0,
        robot_mask_dilate_px=1,
    )  # fmt: skip
    (unit,) = synthetic_source.list_units(cfg)
    assert unit == "synthetic:tabletop:0:robot"
    clip = synthetic_source.render_unit(unit.split(":", 1)[1], cfg)
    robot = render_robot_clip(WorldConfig(seed=0, height=H, width=W, num_frames=5, fps=8.0))
    tips = []  # the true inner-face fingertip centres: thumb (left finger), index (right)
    for k, q in enumerate(robot.joint_positions):
        poses = link_poses(q, robot.world_from_base)
        left = poses["finger_left"] @ np.array([0.0, -0.006, FINGER_LENGTH, 1.0])
        right = poses["finger_right"] @ np.array([0.0, 0.006, FINGER_LENGTH, 1.0])
        tips.append([left[:3], right[:3]])
        np.testing.assert_allclose(poses["palm"], robot.world_from_ee[k], atol=1e-12)
    tips = np.asarray(tips)  # (T, 2, 3)
    skeleton = clip.hand_joints[:, 1][:, [4, 8]].astype(np.float64)  # (T, 2, 3)
    for k in range(len(tips)):
        truth = project_world_points(tips[k], robot.world_from_cam[k], robot.intrinsics)[0]
        got = project_world_points(skeleton[k], clip.world_from_cam[k], clip.intrinsics)[0]
        assert np.abs(got - truth).max() < 1e-3, (k, got, truth)
    np.testing.assert_allclose(clip.gripper_opening[:, 1], robot.opening, atol=1e-6)
    assert clip.hand_valid[:, 1].all() and not clip.hand_valid[:, 0].any()
    iou, recall = _iou_recall(clip.embodiment_mask, clip.hand_mask)
    assert iou >= 0.9 and recall >= 0.999, (iou, recall)


@pytest.mark.parametrize("source", ["lerobot", "agibot"])
def test_robot_logs_with_joint_states_and_a_urdf_get_the_arm_mask(tmp_path, source) -> None:
    """The synthetic robot's episode written as a LeRobot dataset / AgiBot episode with its joint
    states; ingest given the URDF renders the arm mask, which covers the true arm."""
    from egosim.pipeline.clip_io import clip_from_row
    from egosim.stages.common.gripper import gripper_geometry
    from egosim.stages.ingest.robot_writers import (
        RobotEpisodeArrays,
        write_agibot_episode,
        write_lerobot_dataset,
    )
    from egosim.stages.ingest.stage import IngestConfig, IngestStage

    t, h, w, fps = 5, 120, 208, 8.0
    robot = render_robot_clip(WorldConfig(seed=2, height=h, width=w, num_frames=t, fps=fps))
    urdf = tmp_path / "egosim_arm.urdf"
    urdf.write_text(robot.urdf)
    geom = gripper_geometry("egosim_arm")
    g = 1 if source == "lerobot" else 2  # AgiBot logs two arms: both slots hold this one
    ep = RobotEpisodeArrays(
        frames=robot.frames,
        fps=fps,
        intrinsics=robot.intrinsics,
        world_from_cam=robot.world_from_cam,
        world_from_ee=np.repeat(robot.world_from_ee[:, None], g, axis=1),
        gripper_state=np.repeat(geom.state_from_opening(robot.opening)[:, None], g, axis=1),
        task="reach over the box",
        joint_positions=robot.joint_positions,
        joint_names=list(robot.joint_names),
    )
    if source == "lerobot":
        path = write_lerobot_dataset(tmp_path / "ds", [ep])
        names: tuple[str, ...] = ()  # the dataset's feature names are the URDF's
    else:
        write_agibot_episode(tmp_path / "agibot", "327", "648642", ep)
        path = tmp_path / "agibot"
        names = robot.joint_names  # AgiBot's h5 has no names: the user gives them
    params = dict(
        source=source, fps=fps, num_frames=t, min_frames=t, height=h, width=w,
        robot="egosim_arm", robot_urdf=str(urdf), robot_joint_names=names,
        robot_base_pose=tuple(robot.world_from_base.ravel()), robot_mask_dilate_px=0,
        intrinsics=tuple(robot.intrinsics),
    )  # fmt: skip
    stage = IngestStage(IngestConfig(**params))
    (clip,) = [clip_from_row(r) for u in stage.list_units(str(path)) for r in stage.process_unit(u)]
    iou, recall = _iou_recall(clip.embodiment_mask, robot.arm_mask)
    assert iou >= 0.95 and recall >= 0.97, (iou, recall)  # float32 joint states, no growth
    bent = IngestStage(IngestConfig(**{**params, "robot_base_pose": ()}))  # base at the origin
    (moved,) = [clip_from_row(r) for u in bent.list_units(str(path)) for r in bent.process_unit(u)]
    assert _iou_recall(moved.embodiment_mask, robot.arm_mask)[0] < 0.5


def test_hand_mask_masks_the_robot_arm_of_a_robot_clip() -> None:
    """hand_mask adds the clip's embodiment mask: the whole true arm is masked (recall 1.0),
    where the gripper-skeleton keypoints alone cover only the gripper."""
    from egosim.pipeline import media
    from egosim.pipeline.clip_io import row_from_clip
    from egosim.stages.hand_mask.stage import HandMaskStage
    from egosim.stages.ingest import synthetic_source
    from egosim.stages.ingest.stage import IngestConfig

    cfg = IngestConfig(
        synthetic_count=1, synthetic_robot_every=1, height=H, width=W, num_frames=5, fps=8.0,
        robot_mask_dilate_px=1,
    )  # fmt: skip
    clip = synthetic_source.render_unit("tabletop:0:robot", cfg)
    row = row_from_clip(clip)
    out = HandMaskStage().process({"clips": row})
    masks = media.decode_lossless_video(out["hand_mask"]).astype(bool)
    truth = clip.hand_mask.astype(bool)  # the world's true arm mask
    assert (masks & truth).sum() / truth.sum() >= 0.999
    no_urdf = HandMaskStage().process({"clips": {**row, "embodiment_mask": None}})
    keypoints_only = media.decode_lossless_video(no_urdf["hand_mask"]).astype(bool)
    assert (keypoints_only & truth).sum() / truth.sum() < 0.6


def test_robot_logs_with_bad_joint_states_are_rejected_by_name(tmp_path) -> None:
    from egosim.pipeline.stage import ClipRejected
    from egosim.stages.common.gripper import gripper_geometry
    from egosim.stages.ingest.lerobot_source import LeRobotOptions, read_lerobot_episode
    from egosim.stages.ingest.robot_source import ArmModel
    from egosim.stages.ingest.robot_writers import RobotEpisodeArrays, write_lerobot_dataset

    t, fps = 4, 8.0
    robot = render_robot_clip(WorldConfig(seed=2, height=48, width=80, num_frames=t, fps=fps))
    urdf = tmp_path / "arm.urdf"
    urdf.write_text(robot.urdf)
    geom = gripper_geometry("egosim_arm")

    def episode(q: np.ndarray | None, names: list[str]) -> RobotEpisodeArrays:
        return RobotEpisodeArrays(
            frames=robot.frames, fps=fps, intrinsics=robot.intrinsics,
            world_from_cam=robot.world_from_cam, world_from_ee=robot.world_from_ee[:, None],
            gripper_state=geom.state_from_opening(robot.opening)[:, None],
            joint_positions=q, joint_names=names,
        )  # fmt: skip

    nan = robot.joint_positions.copy()
    nan[2, 3] = np.nan
    names = list(robot.joint_names)
    opts = LeRobotOptions(intrinsics=tuple(robot.intrinsics))
    arm = ArmModel(str(urdf), world_from_base=tuple(robot.world_from_base.ravel()))
    cases = [
        (episode(nan, names), r"ds0_ep000000 .*joint states are NaN or infinite in 1 frame"),
        (episode(None, []), r"ds1_ep000000 .*a URDF was given but the log has no joint states"),
        (episode(robot.joint_positions, []), r"ds2_ep000000 .*8 joint-state columns but 0 joint"),
    ]
    for i, (ep, message) in enumerate(cases):
        root = write_lerobot_dataset(tmp_path / f"ds{i}", [ep])
        with pytest.raises(ClipRejected, match=message):
            read_lerobot_episode(root, 0, opts, geom, arm)
