"""A robot's two-finger gripper as the thumb and index chains of the 21-joint hand skeleton.

EgoSim trains one model on human hands and robot grippers with one action: a gripper becomes
the wrist, thumb and index chains of the MANO-order hand skeleton (0 wrist; 1-4 thumb; 5-8
index) plus its opening (``ARCHITECTURE.md`` section 2). This module is that mapping, once.

Geometry (:class:`GripperGeometry`, one per robot): the end-effector (EE) frame's origin is the
wrist. Two of the EE frame's axes are named: ``approach_axis`` points from the wrist towards the
fingertips, ``opening_axis`` is the direction along which the two fingers separate. The fingers
are parallel plates; each chain's four joints lie on the inner (contact) face of its finger, at
``palm_offset_m + f * finger_length_m`` along the approach axis for ``f`` in
``joint_fractions`` (default 0, 1/3, 2/3, 1: finger base to fingertip), and at ``+/- opening/2``
along the opening axis (the thumb on the ``thumb_side`` of it). Hence the distance between the
thumb and index fingertips (joints 4 and 8) equals the opening: :func:`opening_from_joints`
recovers it from a skeleton.

Joints a gripper does not have (middle, ring, little: 9-20) are NaN with confidence 0 in
:func:`gripper_skeleton`. The ``clips`` schema requires finite joints for a valid hand, so
:func:`gripper_hand_arrays` (what ingest stores) puts them on the wrist, still with confidence 0.

The raw gripper reading of a robot log becomes an opening in metres through a linear map fixed
per robot (:meth:`GripperGeometry.opening_from_state`), clipped to ``[0, max_opening_m]``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from egosim.pipeline.geometry import invert_se3, project_points, transform_points

NUM_JOINTS = 21  # MANO / OpenPose hand joints
WRIST = 0
THUMB_CHAIN = (1, 2, 3, 4)  # thumb joints, base to tip
INDEX_CHAIN = (5, 6, 7, 8)  # index joints, base to tip
GRIPPER_JOINTS = (WRIST, *THUMB_CHAIN, *INDEX_CHAIN)  # joints a gripper has (confidence 1)
_AXES = {"+x": (0, 1.0), "-x": (0, -1.0), "+y": (1, 1.0), "-y": (1, -1.0)}
_AXES |= {"+z": (2, 1.0), "-z": (2, -1.0)}


class GripperError(ValueError):
    """Bad gripper geometry or inputs; the message quotes the bad value."""


@dataclass(frozen=True)
class GripperGeometry:
    """How one robot's end-effector frame and gripper reading map onto the hand skeleton."""

    name: str = "generic"  # robot name, recorded in the source description
    approach_axis: str = "+z"  # EE-frame axis from the wrist towards the fingertips
    opening_axis: str = "+y"  # EE-frame axis along which the fingers separate
    thumb_side: float = 1.0  # +1: thumb chain at +opening/2 along opening_axis; -1: at -opening/2
    palm_offset_m: float = 0.06  # from the EE origin to the finger bases, along approach_axis
    finger_length_m: float = 0.05  # finger base to fingertip, along approach_axis
    max_opening_m: float = 0.08  # widest opening between the finger faces, metres
    # where each chain's 4 joints sit on its finger: 0 = finger base, 1 = fingertip
    joint_fractions: tuple[float, ...] = (0.0, 1.0 / 3.0, 2.0 / 3.0, 1.0)
    state_open: float = 0.08  # raw gripper reading when fully open (max_opening_m)
    state_closed: float = 0.0  # raw gripper reading when closed (opening 0)

    def __post_init__(self) -> None:
        problems = []
        for name in ("approach_axis", "opening_axis"):
            if getattr(self, name) not in _AXES:
                problems.append(
                    f"{name} must be one of {sorted(_AXES)}, got {getattr(self, name)!r}"
                )
        if not problems and _AXES[self.approach_axis][0] == _AXES[self.opening_axis][0]:
            problems.append(
                f"approach_axis and opening_axis must be different axes, got "
                f"{self.approach_axis!r} and {self.opening_axis!r}"
            )
        if self.thumb_side not in (1.0, -1.0):
            problems.append(f"thumb_side must be 1 or -1, got {self.thumb_side}")
        for name in ("palm_offset_m", "finger_length_m"):
            if not (np.isfinite(getattr(self, name)) and getattr(self, name) >= 0):
                problems.append(f"{name} must be finite and >= 0, got {getattr(self, name)}")
        if not (np.isfinite(self.max_opening_m) and self.max_opening_m > 0):
            problems.append(f"max_opening_m must be > 0, got {self.max_opening_m}")
        if len(self.joint_fractions) != 4 or any(not 0.0 <= f <= 1.0 for f in self.joint_fractions):
            problems.append(
                f"joint_fractions must be 4 values in [0, 1], got {self.joint_fractions}"
            )
        if not (np.isfinite([self.state_open, self.state_closed]).all()) or (
            self.state_open == self.state_closed
        ):
            problems.append(
                f"state_open and state_closed must be finite and differ, got "
                f"{self.state_open} and {self.state_closed}"
            )
        if problems:
            raise GripperError("; ".join(problems))

    def axis(self, which: str) -> np.ndarray:
        """The unit vector ``(3,)`` in EE coordinates of ``approach`` or ``opening``."""
        index, sign = _AXES[self.approach_axis if which == "approach" else self.opening_axis]
        out = np.zeros(3)
        out[index] = sign
        return out

    def opening_from_state(self, state: np.ndarray) -> np.ndarray:
        """Raw gripper readings ``(...)`` -> openings in metres, clipped to ``[0, max]``.

        Linear: ``state_closed`` -> 0, ``state_open`` -> ``max_opening_m``. NaN stays NaN.
        """
        s = np.asarray(state, dtype=np.float64)
        frac = (s - self.state_closed) / (self.state_open - self.state_closed)
        return np.clip(frac, 0.0, 1.0) * self.max_opening_m

    def state_from_opening(self, opening_m: np.ndarray) -> np.ndarray:
        """Inverse of :meth:`opening_from_state` for openings in ``[0, max]`` (test writers)."""
        frac = np.asarray(opening_m, dtype=np.float64) / self.max_opening_m
        return self.state_closed + frac * (self.state_open - self.state_closed)

    def points_ee(self, opening_m: np.ndarray) -> np.ndarray:
        """``(..., 21, 3)`` joints in the EE frame for openings ``(...)``; NaN where not a joint."""
        opening = np.asarray(opening_m, dtype=np.float64)
        a, o = self.axis("approach"), self.axis("opening")
        out = np.full((*opening.shape, NUM_JOINTS, 3), np.nan)
        out[..., WRIST, :] = 0.0
        along = self.palm_offset_m + np.asarray(self.joint_fractions) * self.finger_length_m  # (4,)
        for chain, side in ((THUMB_CHAIN, self.thumb_side), (INDEX_CHAIN, -self.thumb_side)):
            half = (side * 0.5 * opening)[..., None, None]  # (..., 1, 1)
            out[..., list(chain), :] = along[:, None] * a + half * o  # (..., 4, 3)
        return out


def gripper_skeleton(
    world_from_ee: np.ndarray, opening_m: np.ndarray, geometry: GripperGeometry
) -> tuple[np.ndarray, np.ndarray]:
    """The hand skeleton of a gripper: ``(joints_world (..., 21, 3), confidence (..., 21))``.

    ``world_from_ee`` is ``(..., 4, 4)`` and ``opening_m`` ``(...)`` metres between the finger
    faces. The wrist is the EE origin; thumb and index chains are placed by ``geometry`` (see the
    module docstring); the other twelve joints are NaN with confidence 0, the nine gripper joints
    have confidence 1 (0 and NaN where the pose or opening is not finite).
    """
    pose = np.asarray(world_from_ee, dtype=np.float64)
    opening = np.asarray(opening_m, dtype=np.float64)
    if pose.shape[-2:] != (4, 4) or pose.shape[:-2] != opening.shape:
        raise GripperError(
            f"world_from_ee must be (..., 4, 4) and opening_m (...), got {pose.shape} and "
            f"{opening.shape}"
        )
    local = geometry.points_ee(opening)  # (..., 21, 3)
    rot, trans = pose[..., None, :3, :3], pose[..., None, :3, 3]  # (..., 1, 3, 3), (..., 1, 3)
    world = (rot @ local[..., None])[..., 0] + trans  # (..., 21, 3)
    conf = np.zeros((*opening.shape, NUM_JOINTS))
    ok = np.isfinite(pose).all(axis=(-2, -1)) & np.isfinite(opening)  # (...)
    conf[..., list(GRIPPER_JOINTS)] = ok[..., None].astype(np.float64)
    world[~ok] = np.nan
    return world, conf


def gripper_hand_arrays(
    world_from_ee: np.ndarray,
    opening_m: np.ndarray,
    geometry: GripperGeometry,
    hands: tuple[int, ...],
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Clip-ready hand columns for grippers: ``(joints, valid, confidence)``.

    Shapes ``(T, 2, 21, 3)``, ``(T, 2)`` and ``(T, 2, 21)``.

    ``world_from_ee`` is ``(T, G, 4, 4)`` and ``opening_m`` ``(T, G)`` for ``G`` grippers that
    take hand slots ``hands`` (0 = left, 1 = right). A hand is valid where its pose and opening
    are finite; joints a gripper lacks sit on the wrist with confidence 0 (finite, as the clips
    schema asks); an invalid or absent hand is all zeros with confidence 0.
    """
    pose = np.asarray(world_from_ee, dtype=np.float64)
    opening = np.asarray(opening_m, dtype=np.float64)
    if pose.ndim != 4 or opening.shape != pose.shape[:2] or len(hands) != pose.shape[1]:
        raise GripperError(
            f"world_from_ee must be (T, G, 4, 4), opening_m (T, G) and hands G slots, got "
            f"{pose.shape}, {opening.shape} and {hands}"
        )
    if any(h not in (0, 1) for h in hands) or len(set(hands)) != len(hands):
        raise GripperError(f"hands must be distinct slots 0 (left) or 1 (right), got {hands}")
    t = pose.shape[0]
    world, conf = gripper_skeleton(pose, opening, geometry)  # (T, G, 21, 3), (T, G, 21)
    joints = np.zeros((t, 2, NUM_JOINTS, 3))
    confidence = np.zeros((t, 2, NUM_JOINTS))
    valid = np.zeros((t, 2), dtype=bool)
    for g, hand in enumerate(hands):
        ok = conf[:, g, WRIST] > 0  # (T,)
        filled = np.where(np.isnan(world[:, g]), world[:, g, WRIST : WRIST + 1], world[:, g])
        joints[ok, hand] = filled[ok]
        confidence[:, hand] = conf[:, g]
        valid[:, hand] = ok
    return joints, valid, confidence


def opening_from_joints(joints: np.ndarray) -> np.ndarray:
    """Gripper openings ``(...)`` in metres from skeletons ``(..., 21, 3)``: thumb to index tip."""
    j = np.asarray(joints, dtype=np.float64)
    return np.linalg.norm(j[..., THUMB_CHAIN[-1], :] - j[..., INDEX_CHAIN[-1], :], axis=-1)


# Per-robot geometries by name (what ingest's ``robot`` parameter picks). Values are from the
# vendors' published drawings where given; check them against your robot before trusting
# millimetres. ``synthetic`` is the geometry the test writers use (exact by construction).
GRIPPER_PRESETS: dict[str, GripperGeometry] = {
    "generic": GripperGeometry(),
    # Franka Hand in the ``panda_hand`` frame: z along the fingers, y between them; fingers
    # start 58.4 mm from the flange and are ~45 mm long; 80 mm stroke; state = width in metres.
    "franka": GripperGeometry(
        name="franka", palm_offset_m=0.0584, finger_length_m=0.045, max_opening_m=0.08
    ),
    # AgiBot G1 with its two-finger gripper: the ``end`` frame of ``state/end/*`` with z along
    # the fingers and y between them (assumed), ~120 mm stroke; ``state/effector/position``
    # taken as 0 = open .. 120 = closed (assumed; AgiBot's 0..1 action maps onto 35..120).
    "agibot_g1": GripperGeometry(
        name="agibot_g1",
        palm_offset_m=0.10,
        finger_length_m=0.06,
        max_opening_m=0.12,
        state_open=0.0,
        state_closed=120.0,
    ),
    "synthetic": GripperGeometry(
        name="synthetic", palm_offset_m=0.04, finger_length_m=0.05, max_opening_m=0.08
    ),
    # The synthetic world's URDF arm (world/robot.py): EE = its ``palm`` link, z along
    # the fingers, the left finger (thumb chain) at +y; fingers from 0.03 m, 0.055 m long; the
    # inner faces are 2 x the finger joint apart (0..0.08 m).
    "egosim_arm": GripperGeometry(
        name="egosim_arm", palm_offset_m=0.03, finger_length_m=0.055, max_opening_m=0.08
    ),
}


def gripper_geometry(name: str) -> GripperGeometry:
    """The :data:`GRIPPER_PRESETS` entry ``name``; :class:`GripperError` quoting it otherwise."""
    if name not in GRIPPER_PRESETS:
        raise GripperError(f"robot must be one of {sorted(GRIPPER_PRESETS)}, got {name!r}")
    return GRIPPER_PRESETS[name]


def gripper_box_masks(
    joints: np.ndarray,
    confidence: np.ndarray,
    valid: np.ndarray,
    world_from_cam: np.ndarray,
    intrinsics: np.ndarray,
    height: int,
    width: int,
    margin_m: float = 0.02,
) -> np.ndarray:
    """Embodiment masks ``(T, H, W)`` uint8 (1 = gripper) without a robot model: one box per hand.

    The fallback when no URDF and joint states are available: per frame and valid hand, the
    axis-aligned box around the projections of its joints with confidence > 0 that lie in front
    of the camera, grown on every side by ``margin_m`` seen at the nearest such joint's depth
    (``fx * margin_m / z``, ``fy * margin_m / z``): finger thickness and the part of the arm
    next to the wrist. A pixel is in the mask when its centre (integer + 0.5) lies in the box.
    ``joints (T, 2, 21, 3)`` world metres, ``confidence (T, 2, 21)``, ``valid (T, 2)``,
    ``world_from_cam (T, 4, 4)``, ``intrinsics (4,)`` fx, fy, cx, cy.
    """
    j = np.asarray(joints, dtype=np.float64)
    t = j.shape[0]
    if j.shape[1:] != (2, NUM_JOINTS, 3) or np.shape(world_from_cam) != (t, 4, 4):
        raise GripperError(
            f"joints must be (T, 2, 21, 3) and world_from_cam (T, 4, 4), got {j.shape} and "
            f"{np.shape(world_from_cam)}"
        )
    if not (np.isfinite(margin_m) and margin_m >= 0):
        raise GripperError(f"margin_m must be finite and >= 0, got {margin_m}")
    fx, fy = np.asarray(intrinsics, dtype=np.float64)[:2]
    cam_from_world = invert_se3(world_from_cam)  # (T, 4, 4)
    centre_u = np.arange(width) + 0.5  # (W,)
    centre_v = np.arange(height) + 0.5  # (H,)
    masks = np.zeros((t, height, width), dtype=np.uint8)
    use = (np.asarray(confidence) > 0) & np.asarray(valid, dtype=bool)[..., None]  # (T, 2, 21)
    for f in range(t):
        # uv (2, 21, 2) pixels, depth (2, 21); NaN pixels behind the camera
        uv, depth = project_points(transform_points(cam_from_world[f], j[f]), intrinsics)
        seen = use[f] & np.isfinite(uv).all(axis=-1) & np.isfinite(depth) & (depth > 1e-6)
        for hand in range(2):
            if not seen[hand].any():
                continue
            u, v = uv[hand, seen[hand], 0], uv[hand, seen[hand], 1]  # (N,), (N,)
            z = depth[hand, seen[hand]].min()
            mu, mv = fx * margin_m / z, fy * margin_m / z
            cols = (centre_u >= u.min() - mu) & (centre_u <= u.max() + mu)  # (W,)
            rows = (centre_v >= v.min() - mv) & (centre_v <= v.max() + mv)  # (H,)
            masks[f] |= (rows[:, None] & cols[None, :]).astype(np.uint8)
    return masks
