"""What the robot sources (``agibot``, ``lerobot``) share: one decoded episode -> one Clip.

A reader fills a :class:`RobotEpisode` with arrays already in egosim's conventions (metres,
seconds, OpenCV camera axes, ``world_from_cam`` camera-to-world, end-effector poses
``world_from_ee`` in the same world frame) and the raw gripper readings;
:func:`episode_clip` checks it (lengths agree, states finite, poses rigid) and turns it into a
:class:`~egosim.pipeline.records.Clip` whose hand columns hold the gripper skeleton
(:mod:`egosim.stages.common.gripper`). Ingest then standardises that clip like any other source.

The gripper opening is the ``gripper_opening`` column (clips v3), NaN in slots without a
gripper; it also equals the thumb-to-index fingertip distance of the stored skeleton.

When the log has joint states and the user gives the robot's URDF (:class:`ArmModel`), the arm's
silhouette along the episode becomes the ``embodiment_mask`` column (clips v4;
:func:`egosim.stages.common.urdf_mask.arm_masks`), which ``hand_mask`` unions into its masks.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from egosim.pipeline.geometry import make_se3, matrix_from_quat
from egosim.pipeline.records import Clip
from egosim.pipeline.stage import ClipRejected
from egosim.schemas.invariants import se3_problems
from egosim.stages.common.gripper import GripperGeometry, gripper_hand_arrays
from egosim.stages.common.urdf_mask import UrdfMaskError, arm_masks


@dataclass
class RobotEpisode:
    """One robot episode, decoded, in egosim's conventions (see the module docstring)."""

    name: str  # episode name: clip ids start with it and rejects quote it
    source: str  # "agibot" or "lerobot"
    uri: str  # file or folder the episode came from
    frames: np.ndarray  # (T, H, W, 3) uint8 RGB of the head (or chosen) camera
    fps: float  # frame rate of the frames
    timestamps: np.ndarray  # (T,) seconds from the episode's start
    intrinsics: np.ndarray  # (4,) fx, fy, cx, cy in pixels of ``frames``
    world_from_cam: np.ndarray  # (T, 4, 4) camera-to-world, OpenCV axes, metres
    world_from_ee: np.ndarray  # (S, G, 4, 4) end-effector poses of G grippers, same world
    gripper_state: np.ndarray  # (S, G) raw gripper readings (geometry maps them to metres)
    hands: tuple[int, ...]  # hand slot of each gripper: 0 = left, 1 = right
    text: str | None = None  # task instruction (the caption source)
    joint_positions: np.ndarray | None = None  # (T, J) joint states of the log, if it has them
    joint_names: tuple[str, ...] = ()  # the log's own name of each joint-state column, if any


@dataclass(frozen=True)
class ArmModel:
    """The robot's URDF and how the log's joint states and frame map onto it (user-given)."""

    urdf: str  # URDF file path (mesh files resolved next to it)
    joint_names: tuple[str, ...] = ()  # URDF joint of each joint-state column; () = log's names
    world_from_base: tuple[float, ...] = ()  # URDF root pose, 16 row-major values; () = identity
    dilate_px: int = 2  # growth of the mask, pixels of the episode's frames


def pose_from_xyz_quat(position: np.ndarray, quat: np.ndarray, order: str = "xyzw") -> np.ndarray:
    """``(..., 4, 4)`` poses from positions ``(..., 3)`` and quaternions ``(..., 4)``.

    ``order`` is ``"xyzw"`` (scalar last: ROS, SciPy, AgiBot) or ``"wxyz"`` (scalar first, as
    egosim's :func:`~egosim.pipeline.geometry.matrix_from_quat`). Quaternions are normalised;
    a zero or non-finite quaternion gives a NaN pose (the episode check then rejects it).
    """
    q = np.asarray(quat, dtype=np.float64)
    if order == "xyzw":
        q = q[..., [3, 0, 1, 2]]
    elif order != "wxyz":
        raise ValueError(f"quaternion order must be 'xyzw' or 'wxyz', got {order!r}")
    norm = np.linalg.norm(q, axis=-1, keepdims=True)  # (..., 1)
    ok = np.isfinite(q).all(axis=-1) & (norm[..., 0] > 1e-9)  # (...)
    safe = np.where(ok[..., None], q / np.where(norm > 1e-9, norm, 1.0), [1.0, 0.0, 0.0, 0.0])
    pose = make_se3(matrix_from_quat(safe), position)  # (..., 4, 4)
    pose[~ok] = np.nan
    return pose


def _first_bad(mask: np.ndarray) -> str:
    bad = np.flatnonzero(mask)
    return f"{bad.size} frame(s), first {bad[:5].tolist()}"


def episode_problems(ep: RobotEpisode) -> list[str]:
    """Every reason ``ep`` cannot become a clip (empty when it can)."""
    problems: list[str] = []
    t = len(ep.frames)
    s = len(ep.world_from_ee)
    if t == 0:
        problems.append("the video has no frames")
    if s != t:
        problems.append(f"length mismatch: {s} state rows but {t} video frames")
    if ep.gripper_state.shape != ep.world_from_ee.shape[:2]:
        problems.append(
            f"gripper state shape {ep.gripper_state.shape} does not match the end-effector "
            f"poses' {ep.world_from_ee.shape[:2]}"
        )
    if len(ep.world_from_cam) != t:
        problems.append(f"length mismatch: {len(ep.world_from_cam)} camera poses, {t} frames")
    if len(ep.timestamps) != t:
        problems.append(f"length mismatch: {len(ep.timestamps)} timestamps, {t} frames")
    if ep.joint_positions is not None and len(ep.joint_positions) != t:
        problems.append(f"length mismatch: {len(ep.joint_positions)} joint states, {t} frames")
    if problems:
        return problems
    if ep.joint_positions is not None:
        joints_bad = ~np.isfinite(ep.joint_positions).all(axis=1)  # (T,)
        if joints_bad.any():
            problems.append(f"joint states are NaN or infinite in {_first_bad(joints_bad)}")
    ee_bad = ~np.isfinite(ep.world_from_ee).all(axis=(1, 2, 3))  # (T,)
    if ee_bad.any():
        problems.append(f"end-effector poses are NaN or infinite in {_first_bad(ee_bad)}")
    grip_bad = ~np.isfinite(ep.gripper_state).all(axis=1)  # (T,)
    if grip_bad.any():
        problems.append(f"gripper states are NaN or infinite in {_first_bad(grip_bad)}")
    cam_bad = ~np.isfinite(ep.world_from_cam).all(axis=(1, 2))  # (T,)
    if cam_bad.any():
        problems.append(f"camera poses are NaN or infinite in {_first_bad(cam_bad)}")
    ts = np.asarray(ep.timestamps, dtype=np.float64)
    if not np.isfinite(ts).all() or (t > 1 and not np.all(np.diff(ts) > 0)):
        problems.append("timestamps are not finite and strictly increasing")
    if not problems:
        problems += [f"camera pose: {p}" for p in se3_problems(ep.world_from_cam)]
        ee = ep.world_from_ee.reshape(-1, 4, 4)
        problems += [f"end-effector pose: {p}" for p in se3_problems(ee)]
    return problems


def embodiment_mask(ep: RobotEpisode, arm: ArmModel) -> np.ndarray:
    """The arm's masks ``(T, H, W)`` for a checked episode with joint states (see ArmModel)."""
    where = f"{ep.source} episode {ep.name} ({ep.uri})"
    if ep.joint_positions is None:
        raise ClipRejected(f"{where}: a URDF was given but the log has no joint states")
    names = arm.joint_names or ep.joint_names
    q = np.asarray(ep.joint_positions, dtype=np.float64)
    if len(names) != q.shape[1]:
        raise ClipRejected(
            f"{where}: {q.shape[1]} joint-state columns but {len(names)} joint names {names}"
        )
    base = np.eye(4) if not arm.world_from_base else np.reshape(arm.world_from_base, (4, 4))
    h, w = ep.frames.shape[1:3]
    try:
        return arm_masks(
            arm.urdf, list(names), q, base, ep.world_from_cam, ep.intrinsics, h, w, arm.dilate_px
        )
    except UrdfMaskError as exc:
        raise ClipRejected(f"{where}: {exc}") from exc


def episode_clip(ep: RobotEpisode, geometry: GripperGeometry, arm: ArmModel | None = None) -> Clip:
    """The clip of a checked episode: frames, camera, gripper skeleton in the hand columns, and
    with ``arm`` the URDF arm mask (``embodiment_mask``).

    Raises :class:`ClipRejected` naming the episode and every problem found
    (:func:`episode_problems`).
    """
    problems = episode_problems(ep)
    if problems:
        raise ClipRejected(f"{ep.source} episode {ep.name} ({ep.uri}): " + "; ".join(problems))
    opening = geometry.opening_from_state(ep.gripper_state)  # (T, G) metres
    joints, valid, conf = gripper_hand_arrays(ep.world_from_ee, opening, geometry, ep.hands)
    per_slot = np.full((len(opening), 2), np.nan)  # (T, 2)
    per_slot[:, list(ep.hands)] = opening
    return Clip(
        clip_id=ep.name,
        source=ep.source,
        source_uri=ep.uri,
        fps=float(ep.fps),
        timestamps=np.asarray(ep.timestamps, dtype=np.float64),
        intrinsics=np.asarray(ep.intrinsics, dtype=np.float64),
        frames=ep.frames,
        world_from_cam=np.asarray(ep.world_from_cam, dtype=np.float64),
        hand_joints=joints.astype(np.float32),
        hand_valid=valid,
        hand_confidence=conf.astype(np.float32),
        text=ep.text,
        gripper_opening=per_slot.astype(np.float32),
        embodiment_mask=None if arm is None else embodiment_mask(ep, arm),
    ).check()
