"""Articulated capsule hands: a 21-joint skeleton in MANO/OpenPose order and its meshes.

Hand frame (``world_from_hand``): origin at the wrist, x from the wrist towards the fingers, z out
of the back of the hand, y = z cross x, so the thumb lies on +y for the right hand and on -y for
the left. Finger flexion turns a finger about the hand's y axis towards the palm (-z).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from egosim.pipeline.geometry import transform_points
from egosim.world.meshes import CapsuleTemplate, Mesh, box, merge

# Metacarpophalangeal joint (x, y for the right hand) and phalanx lengths, metres, per finger.
FINGERS = (
    ((0.088, 0.024), (0.040, 0.024, 0.020)),  # index
    ((0.092, 0.003), (0.045, 0.027, 0.021)),  # middle: wrist to tip 0.185 when flat
    ((0.086, -0.017), (0.042, 0.026, 0.020)),  # ring
    ((0.078, -0.034), (0.033, 0.019, 0.018)),  # little
)
THUMB_BASE = (0.022, 0.024, -0.012)  # thumb CMC joint (x, y right hand, z)
THUMB_LENGTHS = (0.042, 0.032, 0.027)  # CMC-MCP, MCP-IP, IP-tip
FLEX_DEG = np.array([75.0, 95.0, 60.0])  # MCP, PIP, DIP flexion at curl 1
# Bones as (parent joint, child joint, radius at parent, radius at child).
BONES = [(0, 1, 0.013, 0.012), (1, 2, 0.012, 0.0105), (2, 3, 0.0105, 0.009), (3, 4, 0.009, 0.008)]
for _f in range(4):
    _b = 5 + 4 * _f
    _r = 0.0095 - 0.0008 * _f * (_f > 1)
    BONES += [
        (0, _b, 0.012, 0.011),
        (_b, _b + 1, _r + 0.001, _r),
        (_b + 1, _b + 2, _r, _r - 0.0008),
        (_b + 2, _b + 3, _r - 0.0008, _r - 0.0016),
    ]
BONES += [(5, 17, 0.011, 0.010)]  # knuckle line
FOREARM_LENGTH = 0.26  # wrist to elbow, metres
FOREARM_RADII = (0.024, 0.031)  # at the wrist, at the elbow


def axis_rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rotation matrix ``(3, 3)`` of ``angle`` radians about unit ``axis``."""
    return Rotation.from_rotvec(np.asarray(axis, np.float64) * angle).as_matrix()


def hand_joints_local(curl: float, side: int) -> np.ndarray:
    """Joints ``(21, 3)`` in the hand frame for finger closure ``curl`` in [0, 1].

    ``side`` is +1 for the right hand and -1 for the left (mirrors y).
    """
    joints = np.zeros((21, 3))
    y_axis = np.array([0.0, 1.0, 0.0])
    for f, ((mx, my), lengths) in enumerate(FINGERS):
        base = 5 + 4 * f
        joints[base] = [mx, side * my, 0.0]
        spread = side * np.deg2rad([6.0, 0.0, -6.0, -12.0][f]) * (1.0 - curl)
        direction = np.array([np.cos(spread), np.sin(spread), 0.0])
        angle = 0.0
        for k in range(3):
            angle += np.deg2rad(FLEX_DEG[k]) * curl
            joints[base + k + 1] = joints[base + k] + lengths[k] * (
                axis_rotation(y_axis, angle) @ direction
            )
    # Thumb: opposition swings it under the palm, then it bends towards the fingers.
    joints[1] = [THUMB_BASE[0], side * THUMB_BASE[1], THUMB_BASE[2]]
    opposition = axis_rotation(np.array([1.0, 0.0, 0.0]), -side * np.deg2rad(55.0) * curl)
    direction = opposition @ np.array([0.75, side * 0.62, -0.22])
    direction /= np.linalg.norm(direction)
    bend_axis = np.cross(direction, opposition @ np.array([0.0, 0.0, 1.0]))
    bend_axis /= np.linalg.norm(bend_axis)
    angle = np.deg2rad(10.0)
    for k in range(3):
        joints[2 + k] = joints[1 + k] + THUMB_LENGTHS[k] * (
            axis_rotation(bend_axis, -angle) @ direction
        )
        angle += np.deg2rad([25.0, 30.0, 25.0][k]) * curl
    return joints


def hand_joints_world(world_from_hand: np.ndarray, curl: float, side: int) -> np.ndarray:
    """Joints ``(21, 3)`` in world metres for a hand at ``world_from_hand (4, 4)``."""
    return transform_points(world_from_hand, hand_joints_local(curl, side))


_TEMPLATE = CapsuleTemplate(segments=10, rings=3)


def hand_mesh(joints_world: np.ndarray, world_from_hand: np.ndarray, side: int) -> Mesh:
    """World-space mesh of one hand (bones as tapered capsules plus a palm slab)."""
    bones = np.array([(a, b) for a, b, _, _ in BONES])  # (B, 2)
    radii = np.array([(r0, r1) for _, _, r0, r1 in BONES])  # (B, 2)
    capsules = _TEMPLATE.build(
        joints_world[bones[:, 0]], joints_world[bones[:, 1]], radii[:, 0], radii[:, 1]
    )
    lo, hi = np.array([0.0, -0.034, -0.013]), np.array([0.088, 0.024, 0.009])
    if side < 0:
        lo[1], hi[1] = -hi[1], -lo[1]
    pv, pf = box(lo, hi)
    palm = (transform_points(world_from_hand, pv).astype(np.float32), pf)
    return merge([capsules, palm])


def forearm_mesh(wrist: np.ndarray, elbow: np.ndarray) -> Mesh:
    """World-space mesh of a forearm from ``wrist (3,)`` to ``elbow (3,)``."""
    return _TEMPLATE.build(
        wrist[None], elbow[None], np.array([FOREARM_RADII[0]]), np.array([FOREARM_RADII[1]])
    )
