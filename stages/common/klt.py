"""Pyramidal Lucas-Kanade point tracking checked forwards and backwards (OpenCV).

Several stages follow sparse points from one grey frame to the next and keep those whose
backward track returns to where they started (``hand_mask``'s ``carry`` moves a missed hand's
keypoints with them; ``depth_camera``'s ``tracking`` carries a model's points into frames the
mapper missed). This is the tracking they share; each caller applies its own thresholds to what
it returns. Pixel coordinates follow OpenCV (pixel centres at integers).
"""

from __future__ import annotations

from typing import NamedTuple

import cv2
import numpy as np


class ForwardBackward(NamedTuple):
    """Where ``N`` points went, and how well each was tracked."""

    uv_b: np.ndarray  # (N, 2) float32 where each point is in the second frame (pixels)
    fb_px: np.ndarray  # (N,) distance from the start to where the backward track lands (pixels)
    converged: np.ndarray  # (N,) bool: both directions found the point
    error: np.ndarray  # (N,) float32 the forward track's mean grey-level difference of windows


def track_forward_backward(
    grey_a: np.ndarray, grey_b: np.ndarray, uv_a: np.ndarray, window: int = 21, levels: int = 4
) -> ForwardBackward:
    """Track ``uv_a (N, 2)`` pixels of ``grey_a (H, W)`` uint8 into ``grey_b (H, W)`` and back.

    Pyramidal Lucas-Kanade with a ``window`` x ``window`` window over ``levels`` pyramid levels
    above the full resolution (at most 30 iterations or 0.01 px per level), forwards from
    ``grey_a`` to ``grey_b`` and then backwards from the forward result. ``fb_px`` is measured
    against ``uv_a`` as given (its dtype), so a caller's threshold sees the same numbers as its
    own arithmetic would. Nothing is dropped here: no point is checked against the image's
    bounds or any threshold.
    """
    n = len(uv_a)
    if n == 0:
        empty = np.zeros((0, 2), np.float32)
        return ForwardBackward(empty, np.zeros(0), np.zeros(0, bool), np.zeros(0, np.float32))
    pts = np.asarray(uv_a).reshape(-1, 1, 2).astype(np.float32)  # (N, 1, 2) as OpenCV wants
    lk = {
        "winSize": (window, window),
        "maxLevel": levels,
        "criteria": (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01),
    }
    fwd, ok_f, err = cv2.calcOpticalFlowPyrLK(grey_a, grey_b, pts, None, **lk)
    back, ok_b, _ = cv2.calcOpticalFlowPyrLK(grey_b, grey_a, fwd, None, **lk)
    fb = np.linalg.norm(back.reshape(-1, 2) - np.asarray(uv_a).reshape(-1, 2), axis=1)  # (N,)
    converged = (ok_f[:, 0] == 1) & (ok_b[:, 0] == 1)  # (N,)
    return ForwardBackward(fwd.reshape(-1, 2), fb, converged, err[:, 0])
