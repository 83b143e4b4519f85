"""The "alt" variant's hands and arms: a second, differently built body for held-out checks.

The skeleton is the default one (:func:`egosim.world.hands.hand_joints_local`, the 21
MANO-order joints are ground truth); only the surface around it is built differently:

- hand: a sphere at every finger joint, a flattened ellipsoid on every phalanx and a convex-hull
  palm (wrist, thumb base and knuckles, thickened along the back of the hand); girth per seed;
- arm: a shoulder beside and below the head, an elbow from two-bone inverse kinematics (bent
  outwards and down), an elliptical forearm tube in skin and a cloth sleeve over the upper part of
  the forearm, the elbow and the whole upper arm, which runs out of the image towards the
  shoulder;
- colours: a continuous skin-tone ramp (not the default's four tones) and a cloth palette.

Each side gives two meshes, skin (hand and bare forearm) and sleeve, in the default's part order
``[left skin, left sleeve, right skin, right sleeve]`` so that part id // 2 is the hand index.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import ConvexHull

from egosim.pipeline.geometry import invert_se3, transform_points
from egosim.world.hands import BONES
from egosim.world.meshes import Mesh, lathe, merge

# Skin-tone ramp (RGB 0..1), light to deep; a seed picks a point on it.
SKIN_RAMP = np.array(
    [
        [0.99, 0.86, 0.80],
        [0.86, 0.68, 0.52],
        [0.70, 0.50, 0.36],
        [0.48, 0.32, 0.22],
        [0.32, 0.21, 0.15],
    ]
)
CLOTH = np.array(
    [
        [0.12, 0.16, 0.36],  # navy
        [0.46, 0.08, 0.12],  # maroon
        [0.55, 0.56, 0.58],  # heather grey
        [0.10, 0.36, 0.18],  # forest green
        [0.05, 0.45, 0.50],  # teal
        [0.92, 0.92, 0.90],  # white
        [0.08, 0.08, 0.09],  # black
        [0.22, 0.32, 0.80],  # royal blue
    ]
)
UPPER_ARM_LENGTH = 0.30  # shoulder to elbow, metres
FOREARM_LENGTH_ALT = 0.27  # elbow to wrist, metres (a reach further than both is a straight arm)
MAX_STRETCH = 1.1  # a longer reach leans the shoulder forwards (see lean)
FINGER_BONES = [(a, b, r0, r1) for a, b, r0, r1 in BONES if a != 0 and (a, b) != (5, 17)]
PALM_JOINTS = [0, 1, 5, 9, 13, 17]  # wrist, thumb base, index/middle/ring/little knuckles


def _unit_sphere(segments: int = 10, rings: int = 6) -> Mesh:
    """Unit sphere ``(V, 3)``, poles on local z."""
    lat = np.linspace(-np.pi / 2, np.pi / 2, rings + 1)
    profile = np.stack([np.cos(lat), np.sin(lat)], 1)  # (R+1, 2) radius, z
    profile[0, 0] = profile[-1, 0] = 0.0
    return lathe(profile, segments)


_SPHERE_V, _SPHERE_F = _unit_sphere()


def ellipsoids(centres: np.ndarray, axes: np.ndarray, radii: np.ndarray) -> Mesh:
    """Ellipsoids at ``centres (C, 3)``, axis columns ``axes (C, 3, 3)``, ``radii (C, 3)``."""
    local = _SPHERE_V.astype(np.float64)[None] * radii[:, None, :]  # (C, V, 3)
    verts = np.einsum("cij,cvj->cvi", axes, local) + centres[:, None]  # (C, V, 3)
    faces = _SPHERE_F[None] + (np.arange(len(centres)) * len(_SPHERE_V))[:, None, None]
    return verts.reshape(-1, 3).astype(np.float32), faces.reshape(-1, 3).astype(np.int32)


def _frames(direction: np.ndarray, up: np.ndarray) -> np.ndarray:
    """Axis columns ``(C, 3, 3)``: (side, up-ish, direction) for unit ``direction (C, 3)``.

    ``up (3,)`` fixes the roll: the second axis is ``up`` made orthogonal to the direction (any
    orthogonal axis where the two are parallel).
    """
    side = np.cross(up[None], direction)  # (C, 3)
    weak = np.linalg.norm(side, axis=1) < 1e-6
    side[weak] = np.cross([0.0, 1.0, 0.0] if abs(up[0]) > 0.9 else [1.0, 0.0, 0.0], up)
    side /= np.linalg.norm(side, axis=1, keepdims=True)
    upish = np.cross(direction, side)  # (C, 3)
    return np.stack([side, upish, direction], axis=-1)


def alt_hand_mesh(joints_world: np.ndarray, world_from_hand: np.ndarray, girth: float) -> Mesh:
    """World mesh of one hand: joint spheres, phalanx ellipsoids and a convex-hull palm.

    ``girth`` scales every finger radius (1 = the default hand's bone radii).
    """
    back = world_from_hand[:3, 2]  # (3,) out of the back of the hand
    a = np.array([b[0] for b in FINGER_BONES])
    b = np.array([b[1] for b in FINGER_BONES])
    r = girth * np.array([0.5 * (b[2] + b[3]) for b in FINGER_BONES])  # (B,)
    start, end = joints_world[a], joints_world[b]  # (B, 3)
    length = np.linalg.norm(end - start, axis=1)  # (B,)
    direction = (end - start) / np.maximum(length, 1e-9)[:, None]
    phalanges = ellipsoids(
        0.5 * (start + end),
        _frames(direction, back),
        np.stack([1.12 * r, 0.88 * r, 0.5 * length + 0.25 * r], axis=1),
    )
    # One sphere per finger joint, as thick as the bone that starts (or, at a tip, ends) there.
    joint_r = np.zeros(21)
    for j0, j1, r0, r1 in FINGER_BONES:
        joint_r[j0] = max(joint_r[j0], girth * r0)
        joint_r[j1] = max(joint_r[j1], girth * r1)
    idx = np.flatnonzero(joint_r)
    knuckles = ellipsoids(
        joints_world[idx], np.repeat(np.eye(3)[None], len(idx), 0), joint_r[idx, None] * np.ones(3)
    )
    # Palm: hull of the palm joints (wrist widened) pushed out to the back and the palm side.
    local = transform_points(invert_se3(world_from_hand), joints_world[PALM_JOINTS])  # (6, 3)
    width = 0.55 * abs(local[2, 1] - local[5, 1])  # (thumb side to little side) / 2 * 1.1
    wrist_edge = np.array([[0.0, width * 0.8, 0.0], [0.0, -width * 0.8, 0.0]])
    core = np.concatenate([local, wrist_edge, local[2:] + np.array([0.008, 0.0, 0.0])])  # (12, 3)
    thick = np.array([0.0, 0.0, 1.0]) * girth
    hull_points = np.concatenate([core + 0.011 * thick, core - 0.013 * thick])  # (24, 3)
    hull = ConvexHull(hull_points)
    palm = (
        transform_points(world_from_hand, hull_points).astype(np.float32),
        hull.simplices.astype(np.int32),
    )
    return merge([phalanges, knuckles, palm])


def tube(centres: np.ndarray, radii: np.ndarray, flatten: float, segments: int = 14) -> Mesh:
    """Closed tube along the polyline ``centres (P, 3)`` with ring radii ``radii (P,)``.

    Cross-sections are ellipses, ``flatten`` times thinner towards world up than sideways (an arm
    is wider than deep); ring planes follow the mean direction of the adjacent segments.
    """
    seg = np.diff(centres, axis=0)  # (P-1, 3)
    seg /= np.linalg.norm(seg, axis=1, keepdims=True)
    tangent = np.concatenate([seg[:1], seg[:-1] + seg[1:], seg[-1:]])  # (P, 3)
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    axes = _frames(tangent, np.array([0.0, 0.0, 1.0]))  # (P, 3, 3)
    angles = np.linspace(0.0, 2.0 * np.pi, segments, endpoint=False)  # (S,)
    ring = np.stack([np.cos(angles), flatten * np.sin(angles), np.zeros(segments)], 1)  # (S, 3)
    verts = np.einsum("pij,sj->psi", axes, ring) * radii[:, None, None] + centres[:, None]
    verts = np.concatenate([verts.reshape(-1, 3), centres[[0, -1]]])  # (P*S + 2, 3) + caps
    p = np.arange(len(centres) - 1)[:, None]
    s = np.arange(segments)[None]
    q0, q1 = p * segments + s, p * segments + (s + 1) % segments
    q2, q3 = q0 + segments, q1 + segments
    side = np.concatenate([np.stack([q0, q1, q3], -1), np.stack([q0, q3, q2], -1)]).reshape(-1, 3)
    first, last = len(verts) - 2, len(verts) - 1
    s1 = (np.arange(segments) + 1) % segments
    cap0 = np.stack([np.full(segments, first), s1, np.arange(segments)], 1)
    top = (len(centres) - 1) * segments
    cap1 = np.stack([np.full(segments, last), top + np.arange(segments), top + s1], 1)
    faces = np.concatenate([side, cap0, cap1])
    return verts.astype(np.float32), faces.astype(np.int32)


def shoulder(world_from_cam: np.ndarray, side: int) -> np.ndarray:
    """Shoulder ``(3,)`` of ``side``: beside and below the head camera, a little behind it."""
    forward = world_from_cam[:3, 2] * [1.0, 1.0, 0.0]
    forward /= max(float(np.linalg.norm(forward)), 1e-9)
    right = np.cross(forward, [0.0, 0.0, 1.0])  # (3,) horizontal, to the person's right
    return world_from_cam[:3, 3] + 0.19 * side * right - 0.04 * forward - [0.0, 0.0, 0.22]


def lean(shoulder_pt: np.ndarray, wrist: np.ndarray) -> np.ndarray:
    """Shoulder ``(3,)`` moved towards ``wrist`` until the arm stretches by at most 10 %."""
    reach = wrist - shoulder_pt
    d = float(np.linalg.norm(reach))
    longest = MAX_STRETCH * (UPPER_ARM_LENGTH + FOREARM_LENGTH_ALT)
    return shoulder_pt + reach * max(0.0, 1.0 - longest / max(d, 1e-9))


def elbow(shoulder_pt: np.ndarray, wrist: np.ndarray, side: int) -> np.ndarray:
    """Elbow ``(3,)`` by two-bone inverse kinematics, bent outwards (towards ``side``) and down.

    Beyond reach the arm is straight and both bones stretch in proportion.
    """
    a, b = UPPER_ARM_LENGTH, FOREARM_LENGTH_ALT
    reach = wrist - shoulder_pt
    d = float(np.linalg.norm(reach))
    u = reach / max(d, 1e-9)
    if d >= 0.98 * (a + b):
        return shoulder_pt + u * d * a / (a + b)
    d = max(d, abs(a - b) + 1e-3)
    cos_a = (a * a + d * d - b * b) / (2.0 * a * d)
    pole = np.array([0.0, -0.6 * side, -0.8])  # outwards and down (world; person faces +x)
    pole -= u * float(pole @ u)
    pole /= max(float(np.linalg.norm(pole)), 1e-9)
    return shoulder_pt + a * cos_a * u + a * np.sqrt(max(1.0 - cos_a * cos_a, 0.0)) * pole


class AltBody:
    """Per-seed look of the alt hands and arms; :meth:`parts` builds one frame's meshes."""

    def __init__(self, seed: int) -> None:
        """Skin tone, sleeve colour, hand girth and sleeve length of ``seed``."""
        rng = np.random.default_rng([seed, 14])
        pos = rng.uniform(0.0, len(SKIN_RAMP) - 1.0)
        k = min(int(pos), len(SKIN_RAMP) - 2)
        skin = (SKIN_RAMP[k] * (k + 1 - pos) + SKIN_RAMP[k + 1] * (pos - k)) * rng.uniform(
            0.96, 1.04, 3
        )
        cloth = CLOTH[int(rng.integers(0, len(CLOTH)))] * rng.uniform(0.9, 1.1, 3)
        self.colours = np.clip(np.stack([skin, cloth, skin, cloth]), 0, 1).astype(np.float32)
        self.girth = float(rng.uniform(0.95, 1.15))  # finger radii against the default hand
        self.cuff = rng.uniform(0.3, 0.65, 2)  # (2,) sleeve end, fraction wrist -> elbow, per side

    def parts(
        self, joints: np.ndarray, world_from_hand: np.ndarray, world_from_cam: np.ndarray
    ) -> list[Mesh]:
        """``[left skin, left sleeve, right skin, right sleeve]`` world meshes of one frame.

        ``joints (2, 21, 3)`` and ``world_from_hand (2, 4, 4)`` are the left and right hands.
        """
        parts: list[Mesh] = []
        for h, side in enumerate((-1, 1)):
            wrist = joints[h, 0]
            torso = shoulder(world_from_cam, side)
            sh = lean(torso, wrist)
            el = elbow(sh, wrist, side)
            cuff = wrist + self.cuff[h] * (el - wrist)
            beyond = wrist + (self.cuff[h] + 0.12) * (el - wrist)  # skin runs on under the cuff
            arm = tube(np.stack([wrist, beyond]), np.array([0.026, 0.030]), 0.72)
            # The sleeve runs on past the shoulder (back to the unleaned one) out of the view.
            behind = torso if np.linalg.norm(sh - torso) > 0.01 else sh
            back = behind + 0.12 * (behind - el) / max(float(np.linalg.norm(behind - el)), 1e-9)
            line = [cuff, el, sh] + ([torso] if behind is torso else []) + [back]
            radii = [0.040, 0.046, 0.055] + ([0.058] if behind is torso else []) + [0.06]
            sleeve = tube(np.stack(line), np.array(radii), 0.85)
            elbow_ball = ellipsoids(el[None], np.eye(3)[None], np.full((1, 3), 0.046))
            hand = alt_hand_mesh(joints[h], world_from_hand[h], self.girth)
            parts += [merge([hand, arm]), merge([sleeve, elbow_ball])]
        return parts
