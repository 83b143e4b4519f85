"""Pre-flight checks before SfM: is there texture, and did the camera move at all?

Corners (Shi-Tomasi, spread over a grid so a plain wall or table still gets its share) outside
the hand mask of the first frame are tracked by pyramidal Lucas-Kanade into every ``stride``-th
frame (forward-backward checked). The background is, per frame, either

- the corners that did not move (displacement below ``static_motion_px``) when they are at least
  ``STILL_FRACTION`` of the tracked corners: a still camera whose view is mostly moved objects
  (a can lifted and put back elsewhere against a plain wall) still has that many; a camera
  that moves, even slowly, has almost none; or else
- the dominant consistent set: the inliers of a RANSAC homography from frame 0 to frame k.
  Hands and moved objects are outliers to it as long as they cover less of the tracked corners
  than the background.

The camera is static when, in every decided frame, the background's median displacement stays
below ``static_motion_px`` (and its 95th percentile below ``3 x static_motion_px``: no roll or
zoom about the centre hiding under the median); up to ``BUMP_FRACTION`` of the decided frames
may break that by a bump of at most ``BUMP_MOTION_FACTOR x static_motion_px`` (median), as when
the camera is touched to stop the recording. A frame where fewer than half of ``min_corners``
corners survive tracking (a hand over the view, a pour) is undecided; the camera can be called
static only when at least ``MIN_DECIDED`` of the checked frames are decided. Too few corners
means a textureless scene (SfM would fail or abort).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from egosim.stages.depth_camera.rotation_model import RotationParams, detect_corners
from egosim.stages.depth_camera.tracking import TrackingParams, grey_frames, track_points

TAIL_MOTION_FACTOR = 3.0  # the background's 95th percentile displacement may be this x the median's
STILL_FRACTION = 0.3  # this share of tracked corners did not move: they are the background
BUMP_FRACTION = 0.1  # this share of the decided frames may move (a camera bumped at the end) ...
BUMP_MOTION_FACTOR = 3.0  # ... by at most this x static_motion_px (median), and still be static
MIN_DECIDED = 0.5  # static needs this share of the checked frames decided (enough corners tracked)


@dataclass(frozen=True)
class MotionCheck:
    """What the pre-flight check found on one clip."""

    num_corners: int  # corners found outside the hand mask of frame 0
    max_median_motion_px: float  # largest over frames of the background's median displacement
    max_tail_motion_px: float  # largest over frames of the background's 95th pct displacement
    min_background_fraction: float  # smallest over frames of the dominant set's share of tracks
    textureless: bool  # fewer corners than required
    static: bool  # the camera did not move (and the scene has texture)


def background_motion(a: np.ndarray, b: np.ndarray, ransac_px: float) -> tuple[float, float, float]:
    """Motion of the dominant consistent set between matched pixels ``a, b (N, 2)``.

    Returns ``(median and 95th percentile displacement of the homography inliers, inlier
    fraction)``.
    """
    h_mat, inl = cv2.findHomography(a, b, cv2.RANSAC, ransac_px, maxIters=2000, confidence=0.999)
    if h_mat is None:
        return float("inf"), float("inf"), 0.0
    inl = inl[:, 0].astype(bool)
    shift = np.linalg.norm(b[inl] - a[inl], axis=1)  # (I,)
    return float(np.median(shift)), float(np.percentile(shift, 95)), float(inl.mean())


def check_motion(
    frames: np.ndarray,
    hand_mask: np.ndarray | None,
    min_corners: int = 50,
    static_motion_px: float = 1.0,
    stride: int = 5,
) -> MotionCheck:
    """Find corners in ``frames[0]`` and measure the background's motion into later frames.

    ``frames (T, H, W, 3)`` uint8 RGB; ``hand_mask (T, H, W)`` 1 = hand, or None. Displacements
    are in pixels of the given frames.
    """
    grey = grey_frames(frames)
    usable = None
    if hand_mask is not None:
        usable = cv2.dilate(hand_mask[0].astype(np.uint8), np.ones((15, 15), np.uint8)) == 0
    corners = detect_corners(grey[0], usable, RotationParams(max_corners=400))
    n = len(corners)
    if n < min_corners:
        return MotionCheck(n, 0.0, 0.0, 0.0, textureless=True, static=False)
    params = TrackingParams(levels=3)
    motion = tail_motion = 0.0
    fraction = 1.0
    ransac_px = max(static_motion_px, 0.5)
    checked = list(range(stride, len(frames), stride))
    if len(frames) > 1 and (not checked or checked[-1] != len(frames) - 1):
        checked.append(len(frames) - 1)
    decided = moving = 0
    for k in checked:
        moved, ok = track_points(grey[0], grey[k], corners, params)
        if ok.sum() < min_corners // 2:  # lost most corners: occluded view, or a large move
            continue
        decided += 1
        shift = np.linalg.norm(moved[ok] - corners[ok], axis=1)  # (N_ok,)
        still = shift < static_motion_px
        if still.mean() >= STILL_FRACTION:
            still_shift = shift[still]  # (S,) the corners that did not move are the background
            med, tail = float(np.median(still_shift)), float(np.percentile(still_shift, 95))
            frac = float(still.mean())
        else:
            med, tail, frac = background_motion(corners[ok], moved[ok], ransac_px)
        motion, tail_motion = max(motion, med), max(tail_motion, tail)
        fraction = min(fraction, frac)
        moving += not (med < static_motion_px and tail < TAIL_MOTION_FACTOR * static_motion_px)
    if decided < MIN_DECIDED * len(checked):  # too little seen to call it still
        motion = tail_motion = float("inf")
        fraction = 0.0
    static = (
        moving <= BUMP_FRACTION * decided  # still in (nearly) every decided frame ...
        and motion < BUMP_MOTION_FACTOR * static_motion_px  # ... and a bump stays small
    )
    return MotionCheck(n, motion, tail_motion, fraction, textureless=False, static=static)
