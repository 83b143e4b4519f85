"""Ingest backend for the built-in synthetic world (no input files needed)."""

from __future__ import annotations

from dataclasses import replace
from typing import Protocol

import numpy as np

from egosim.pipeline.records import Clip
from egosim.pipeline.stage import ClipRejected
from egosim.stages.common.gripper import gripper_geometry, gripper_hand_arrays
from egosim.stages.common.urdf_mask import arm_masks
from egosim.world.clip import render_clip
from egosim.world.config import VARIANTS, WorldConfig
from egosim.world.robot import render_robot_clip

ROBOT_GRIPPER = "egosim_arm"  # gripper preset of the world's URDF arm


class SyntheticFormat(Protocol):
    """Ingest parameters the synthetic source reads (an ``IngestConfig`` satisfies it)."""

    preset: str
    fps: float
    num_frames: int
    height: int
    width: int
    synthetic_count: int
    synthetic_mode: str
    synthetic_articulated_every: int
    synthetic_variant: str
    synthetic_robot_every: int
    robot_mask_dilate_px: int
    seed: int


def list_units(cfg: SyntheticFormat) -> list[str]:
    """One unit per generated clip: ``synthetic:<mode>:<seed>[:articulated|:robot][:<variant>]``.

    The variant is named only when it is not the default one, so default units are unchanged.
    Every ``synthetic_robot_every``-th clip is a robot clip (counted from the first); it takes
    precedence over the hinged lid.
    """
    units = []
    for i in range(cfg.synthetic_count):
        every = cfg.synthetic_articulated_every
        articulated = every > 0 and i % every == every - 1
        robot = cfg.synthetic_robot_every > 0 and i % cfg.synthetic_robot_every == 0
        suffix = ":robot" if robot else ":articulated" if articulated else ""
        if cfg.synthetic_variant != "default":
            suffix += f":{cfg.synthetic_variant}"
        units.append(f"synthetic:{cfg.synthetic_mode}:{cfg.seed + i}{suffix}")
    return units


def render_unit(spec: str, cfg: SyntheticFormat) -> Clip:
    """Render the clip a unit spec (``<mode>:<seed>[:articulated|:robot][:<variant>]``) names.

    The world renders exactly ``num_frames`` frames at ``fps``, so the clip is one full window
    of its own source (``source_frame_indices`` 0..T-1).
    """
    parts = spec.split(":")
    try:
        mode, seed = parts[0], int(parts[1])
    except (IndexError, ValueError) as exc:
        raise ClipRejected(f"bad synthetic unit {spec!r}") from exc
    variants = [p for p in parts[2:] if p in VARIANTS]
    world = WorldConfig(
        seed=seed,
        mode=mode,
        height=cfg.height,
        width=cfg.width,
        num_frames=cfg.num_frames,
        fps=cfg.fps,
        articulated="articulated" in parts[2:],
        variant=variants[-1] if variants else "default",
    )
    if "robot" in parts[2:]:  # the URDF arm in the same scene (the lid is not used)
        return _robot_clip(world, cfg)
    kind = "art" if world.articulated else mode
    tag = "" if world.variant == "default" else f"{world.variant}-"
    clip = render_clip(world, clip_id=f"synth-{tag}{kind}-{seed:05d}")
    return replace(
        clip,
        source_fps=float(cfg.fps),
        source_num_frames=clip.num_frames,
        source_frame_indices=np.arange(clip.num_frames),
        clip_policy=f"full:{cfg.preset}" if cfg.preset else "full",
        source_crop=np.array([0.0, 0.0, clip.width, clip.height]),  # rendered at the clip size
    ).check()


def _robot_clip(world: WorldConfig, cfg: SyntheticFormat) -> Clip:
    """The robot clip of ``world``: the arm's gripper skeleton in the right-hand slot, its
    opening, and ``embodiment_mask`` derived as a robot log's reader would (the URDF the world
    wrote plus the joint states, :func:`arm_masks`); ``hand_mask`` holds the true arm mask."""
    robot = render_robot_clip(world)
    t = robot.frames.shape[0]
    joints, valid, confidence = gripper_hand_arrays(
        robot.world_from_ee[:, None], robot.opening[:, None], gripper_geometry(ROBOT_GRIPPER), (1,)
    )
    opening = np.full((t, 2), np.nan, np.float32)
    opening[:, 1] = robot.opening
    embodiment = arm_masks(
        robot.urdf,
        list(robot.joint_names),
        robot.joint_positions,
        robot.world_from_base,
        robot.world_from_cam,
        robot.intrinsics,
        world.height,
        world.width,
        dilate_px=cfg.robot_mask_dilate_px,
    )
    what = f"the {robot.target}" if robot.target else "an object"
    tag = "" if world.variant == "default" else f"{world.variant}-"
    return Clip(
        clip_id=f"synth-{tag}robot-{world.seed:05d}",
        source="synthetic",
        source_uri="",
        fps=robot.fps,
        timestamps=np.arange(t) / robot.fps,
        intrinsics=robot.intrinsics,
        frames=robot.frames,
        world_from_cam=robot.world_from_cam,
        depth=robot.depth,
        static_frames=robot.static_frames,
        static_depth=robot.static_depth,
        first_frame_clean=robot.static_frames[0],
        hand_joints=joints.astype(np.float32),
        hand_valid=valid,
        hand_confidence=confidence.astype(np.float32),
        hand_mask=robot.arm_mask,
        embodiment_mask=embodiment,
        gripper_opening=opening,
        text=f"A robot arm reaches over {what} and closes its gripper.",
        source_fps=float(cfg.fps),
        source_num_frames=t,
        source_frame_indices=np.arange(t),
        clip_policy=f"full:{cfg.preset}" if cfg.preset else "full",
        source_crop=np.array([0.0, 0.0, world.width, world.height]),  # rendered at the clip size
    ).check()
