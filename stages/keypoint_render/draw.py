"""Project hand joints with the clip's camera and draw the skeleton video.

One camera model for the scene and the hands: :func:`project_hands` uses the clip's own
intrinsics and ``world_from_cam`` through :func:`egosim.pipeline.geometry.project_world_points`,
the function the scene renderer's torch twin mirrors. (The published code projected hands with
another focal than the scene, which misaligns the two conditions.)

Drawing: black background, one colour per finger (thumb, index, middle, ring, little; the left
hand a darker shade of the same colours), line width scaled by depth (``width_px * ref_depth /
depth``, clamped), joints as dots. Bones with an end at or behind the near plane are skipped.
The ``gripper`` variant draws the wrist-thumb and wrist-index chains only.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import cv2
import numpy as np

from egosim.pipeline.geometry import project_world_points

FINGERS = (  # joint chains from the wrist (MANO/OpenPose order)
    (0, 1, 2, 3, 4),  # thumb
    (0, 5, 6, 7, 8),  # index
    (0, 9, 10, 11, 12),  # middle
    (0, 13, 14, 15, 16),  # ring
    (0, 17, 18, 19, 20),  # little
)
GRIPPER_FINGERS = (0, 1)  # thumb and index chains only
FINGER_COLOURS = np.array(  # RGB per finger (right hand); the left hand uses 60 % of it
    [[255, 64, 64], [255, 200, 0], [64, 220, 64], [0, 200, 255], [200, 64, 255]], dtype=np.float64
)
LEFT_SHADE = 0.6  # left hand colour = LEFT_SHADE * right hand colour
_SHIFT = 4  # cv2 fixed-point bits: sub-pixel accurate lines and circles


class KeypointError(ValueError):
    """Inputs of the projection disagree (shapes, frame counts)."""


@dataclass(frozen=True)
class Projected:
    """Projected joints of a clip."""

    uv: np.ndarray  # (T, 2, 21, 2) float64 pixels, NaN for invalid hands or depth <= near
    depth: np.ndarray  # (T, 2, 21) float64 camera z metres, NaN for invalid hands
    visible: np.ndarray  # (T, 2, 21) bool valid hand, depth > near, inside the image


def project_hands(
    joints: np.ndarray,
    valid: np.ndarray,
    world_from_cam: np.ndarray,
    intrinsics: np.ndarray,
    height: int,
    width: int,
    near: float = 0.01,
) -> Projected:
    """Project ``joints (T, 2, 21, 3)`` world metres through ``world_from_cam (T, 4, 4)``."""
    t = joints.shape[0]
    if joints.shape[1:] != (2, 21, 3) or valid.shape != (t, 2) or world_from_cam.shape != (t, 4, 4):
        raise KeypointError(
            f"joints {joints.shape}, valid {valid.shape} and poses {world_from_cam.shape} "
            "must be (T, 2, 21, 3), (T, 2), (T, 4, 4)"
        )
    uv = np.full((t, 2, 21, 2), np.nan)
    depth = np.full((t, 2, 21), np.nan)
    for f in range(t):
        uv[f], depth[f] = project_world_points(joints[f], world_from_cam[f], intrinsics)
    depth[~valid] = np.nan
    front = valid[..., None] & (np.nan_to_num(depth, nan=-1.0) > near)  # (T, 2, 21)
    uv[~front] = np.nan
    with np.errstate(invalid="ignore"):
        inside = (uv[..., 0] >= 0) & (uv[..., 0] < width) & (uv[..., 1] >= 0)
        inside &= uv[..., 1] < height
    return Projected(uv=uv, depth=depth, visible=front & inside)


def draw_skeleton_frame(
    uv: np.ndarray,
    depth: np.ndarray,
    height: int,
    width: int,
    variant: str = "hand",
    width_px: float = 3.0,
    ref_depth: float = 0.5,
) -> np.ndarray:
    """Draw both hands ``uv (2, 21, 2)``, ``depth (2, 21)`` on black; returns ``(H, W, 3)`` uint8.

    Bones with a NaN end (invalid hand, behind the camera) are skipped; lines run off the
    image freely. Line width is ``width_px * ref_depth / mean bone depth`` clamped to [1, 4 x].
    """
    image = np.zeros((height, width, 3), dtype=np.uint8)
    fingers = [FINGERS[i] for i in GRIPPER_FINGERS] if variant == "gripper" else list(FINGERS)
    finger_ids = GRIPPER_FINGERS if variant == "gripper" else range(len(FINGERS))
    scale = 1 << _SHIFT
    for hand in range(2):
        shade = LEFT_SHADE if hand == 0 else 1.0
        for fid, chain in zip(finger_ids, fingers, strict=True):
            colour = tuple(float(c) for c in FINGER_COLOURS[fid] * shade)
            for a, b in itertools.pairwise(chain):
                pa, pb = uv[hand, a], uv[hand, b]
                if not (np.all(np.isfinite(pa)) and np.all(np.isfinite(pb))):
                    continue
                z = 0.5 * (depth[hand, a] + depth[hand, b])
                thick = int(np.clip(round(width_px * ref_depth / z), 1, 4 * width_px))
                # cv2 pixel centres sit at integers: shift by -0.5 from ours.
                p0 = tuple(round((c - 0.5) * scale) for c in pa)
                p1 = tuple(round((c - 0.5) * scale) for c in pb)
                cv2.line(image, p0, p1, colour, thick, cv2.LINE_AA, _SHIFT)
            for j in chain[1:] if fid else chain:
                p = uv[hand, j]
                if np.all(np.isfinite(p)):
                    radius = int(np.clip(width_px * ref_depth / depth[hand, j], 1, 4 * width_px))
                    centre = tuple(round((c - 0.5) * scale) for c in p)
                    cv2.circle(image, centre, radius * scale, colour, -1, cv2.LINE_AA, _SHIFT)
    return image


def draw_skeleton_video(
    projected: Projected, height: int, width: int, variant: str = "hand", width_px: float = 3.0
) -> np.ndarray:
    """Skeleton frames ``(T, H, W, 3)`` uint8 for every frame of ``projected``."""
    return np.stack(
        [
            draw_skeleton_frame(
                projected.uv[f], projected.depth[f], height, width, variant, width_px
            )
            for f in range(projected.uv.shape[0])
        ]
    )
