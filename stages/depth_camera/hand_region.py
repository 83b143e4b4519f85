"""Hands and forearms masked from MediaPipe's landmarks before SfM.

In the dataset workflow the ``cameras`` step runs before ``hands`` and ``hand_mask``, so it gets
no hand mask. Where the clip starts with the arms in view, their features then enter SfM and
the frame-0 plane sweep: arms move with the head, not with the scene. Measured on a window of
DWM 00013 that starts at its frame 8 with both forearms in view (the kept-aside rehearsal,
heldout1): no plane-sweep pixel over confidence 0.5 in frame 0, and camera steps about 9x too
long for the depth, so the scene render emptied along the clip (46% of it covered on average,
1.5% at the last frame). With the hands masked (the truth renders grown and joined to the bottom
border) the same clip gave confident depth on 14% of frame 0 and steps in scale with it.

Since depth_camera v16 (``DepthCameraConfig.mask_hands``, on by default) the mask is used only
where frame 0 shows a hand, and only for SfM's features and its PnP tracking: not for the plane
sweep, whose frame-0 depth beside the hands the metric scale compares them with, nor for the
static check and the rotation model.

:func:`landmark_hand_mask` draws each detected hand's convex hull joined to a band along its
forearm (from the wrist away from the middle knuckle, as wide as the palm, to the image's
edge), grown by ``grow`` of the hand's size. It needs no world axis or cameras, only the 2D
landmarks of :func:`~egosim.stages.common.hand_landmarks.detect_hand_landmarks` (the detector the
metric scale runs on the same clip, so the detections are shared).
"""

from __future__ import annotations

import cv2
import numpy as np

from egosim.stages.common.hand_landmarks import RawLandmarks, hand_size

WRIST, MIDDLE_MCP = 0, 9  # MediaPipe landmark indices


def forearm_band(uv: np.ndarray, reach: float) -> np.ndarray | None:
    """``(4, 2)`` corners of the band along the forearm of the hand ``uv (21, 2)``: from the
    wrist, away from the middle knuckle, ``reach`` pixels long and as wide as the palm (wrist to
    middle knuckle); None when the two landmarks coincide (no direction)."""
    wrist, knuckle = uv[WRIST], uv[MIDDLE_MCP]
    axis = wrist - knuckle  # (2,) towards the elbow
    length = float(np.linalg.norm(axis))
    if length < 1e-6:
        return None
    axis /= length
    side = np.array([-axis[1], axis[0]]) * 0.5 * length  # (2,) half the palm's length across
    end = wrist + axis * reach
    return np.stack([wrist - side, wrist + side, end + side, end - side])


def landmark_hand_mask(raw: RawLandmarks, shape: tuple[int, int], grow: float = 0.25) -> np.ndarray:
    """``(T, H, W)`` uint8 mask (1 = hand or forearm) of the hands in ``raw`` on frames of
    ``shape`` (H, W): per present hand, the convex hull of its landmarks and its
    :func:`forearm_band` to the image's edge, dilated by ``grow`` times the hand's size."""
    h, w = shape
    t = raw.present.shape[0]
    out = np.zeros((t, h, w), dtype=np.uint8)
    reach = float(2 * (h + w))  # past any edge of the frame
    for f in range(t):
        for k in np.flatnonzero(raw.present[f]):
            uv = raw.uv[f, k]  # (21, 2)
            if not np.isfinite(uv).all():
                continue
            band = forearm_band(uv, reach)
            points = uv if band is None else np.concatenate([uv, band])
            one = np.zeros((h, w), dtype=np.uint8)
            hull = cv2.convexHull(np.round(points).astype(np.int32))
            cv2.fillConvexPoly(one, hull, 1)
            radius = round(grow * float(hand_size(uv)))
            if radius > 0:
                side = 2 * radius + 1
                kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (side, side))
                one = cv2.dilate(one, kernel)
            out[f] |= one
    return out
