"""Pre-flight checks before SfM: is there texture, and did the camera move at all?

Corners (Shi-Tomasi) outside the hand mask of the first frame are tracked by pyramidal
Lucas-Kanade into later frames. Too few corners means a textureless scene (SfM would fail or
abort); a median corner displacement that never exceeds ``static_motion_px`` means a static camera
(SfM cannot triangulate without parallax: DWM section 3.3's fixed-camera recipe applies instead).
Moving hands and objects are a minority of corners, so the median ignores them.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class MotionCheck:
    """What the pre-flight check found on one clip."""

    num_corners: int  # corners found outside the hand mask of frame 0
    max_median_motion_px: float  # largest over frames of the median corner displacement
    textureless: bool  # fewer corners than required
    static: bool  # the camera did not move (and the scene has texture)


def _grey(frame: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(np.ascontiguousarray(frame), cv2.COLOR_RGB2GRAY)


def check_motion(
    frames: np.ndarray,
    hand_mask: np.ndarray | None,
    min_corners: int = 50,
    static_motion_px: float = 1.0,
    stride: int = 5,
) -> MotionCheck:
    """Find corners in ``frames[0]`` and track them into every ``stride``-th frame.

    ``frames (T, H, W, 3)`` uint8 RGB; ``hand_mask (T, H, W)`` 1 = hand, or None. Displacements
    are in pixels of the given frames.
    """
    first = _grey(frames[0])
    keep = None
    if hand_mask is not None:
        keep = cv2.dilate(hand_mask[0].astype(np.uint8), np.ones((15, 15), np.uint8)) == 0
        keep = keep.astype(np.uint8) * 255
    corners = cv2.goodFeaturesToTrack(
        first, maxCorners=400, qualityLevel=0.01, minDistance=8, mask=keep
    )
    n = 0 if corners is None else len(corners)
    if n < min_corners:
        return MotionCheck(n, 0.0, textureless=True, static=False)
    motion = 0.0
    for k in range(stride, len(frames), stride):
        moved, status, _ = cv2.calcOpticalFlowPyrLK(
            first, _grey(frames[k]), corners, None, winSize=(21, 21), maxLevel=3
        )
        ok = status[:, 0] == 1
        if ok.sum() < min_corners // 2:  # lost most corners: the view changed a lot
            motion = max(motion, float("inf"))
            break
        shift = np.linalg.norm((moved - corners)[ok, 0], axis=1)  # (N,)
        motion = max(motion, float(np.median(shift)))
    return MotionCheck(n, motion, textureless=False, static=motion < static_motion_px)
