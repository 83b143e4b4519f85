"""Carry a hand's 2D keypoints into the frames where it was missed, by tracking its pixels.

A hand the detector finds in frame ``t`` but misses in frame ``t + 1`` (motion blur, a fast
reach, a grasp) is usually still there, moved. The mask propagation (``propagate``) carries the
mask itself, pixel by pixel through a dense flow that must be forward-backward consistent; a
hand moving 30 px between frames fails that test nearly everywhere and is lost. Here the hand
is tracked as a whole instead: points inside its drawn capsules (corners plus a grid, since
skin has few corners) are followed by pyramidal Lucas-Kanade from the last frame that has the
hand to the next, kept where the backward track returns within ``fb_px``, and a similarity
(rotation, scale, shift) fitted to them by RANSAC moves all 21 keypoints. Repeated frame to
frame, forwards and backwards in time, for at most ``max_frames`` frames from a detection; a
frame reached from both sides takes the nearer detection's keypoints (the earlier one's when
both are as near). The track stops where
fewer than ``min_points`` points track and follow the fit (the hand left the view or was
covered) or where the fit scales or turns more than a hand does between two frames, or where the
median colour of the carried hand's skeleton changes by more than ``colour_tolerance`` in one
step: a hand that leaves the view fast fails the backward check on its own pixels, while the
background it uncovers inside its capsules tracks well and moves the keypoints with the
floor (HOT3D w001: skin, L 88, to the floor and black bar, L 11, a jump of 78; a carried
synthetic hand's skeleton changes by at most 57 in one step, its own sleeve). (Asking
for a fraction of the seeded points as well stopped most tracks: grid points on plain skin
rarely pass the backward check. Measured: default-world MediaPipe-joint IoU of tabletop 1
0.510 without, 0.418 with half the points; DWM 00013 recall 0.839 without, 0.815 with a
quarter.)

The carried hands then get masks like detected ones (``arm_region``); what stays missed is
left to ``propagate``.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from egosim.stages.common.klt import track_forward_backward
from egosim.stages.hand_mask.capsules import CapsuleParams, draw_hand, hand_scale_px


@dataclass(frozen=True)
class CarryParams:
    """How far and how a missed hand's keypoints are carried."""

    max_frames: int = 8  # carry at most this many frames from a frame that detected the hand
    min_points: int = 12  # tracked points (inliers of the fit) needed to carry a hand
    max_error: float = 25.0  # a point's mean grey-level difference between its two windows
    fb_px: float = 1.0  # a point is kept when tracking it back lands within this (pixels)
    ransac_px: float = 3.0  # RANSAC inlier distance of the similarity fit (pixels)
    max_scale_step: float = 0.25  # the fit's scale may change by at most this per frame
    max_turn_deg: float = 30.0  # ... and turn by at most this per frame
    grid_px: int = 6  # spacing of the grid of points inside the hand (plus corners)
    window_px: int = 21  # Lucas-Kanade window (pixels)
    colour_tolerance: float = 40.0  # the carried hand's skeleton (median Lab, OpenCV 8-bit
    # units) may change at most this much in one step: beyond, what tracked was the background
    # the hand uncovered (it left the view), not the hand (0: off)

    def __post_init__(self) -> None:
        problems = []
        if not 0 <= self.max_frames <= 1000:
            problems.append(f"max_frames must be in [0, 1000], got {self.max_frames}")
        if self.min_points < 3:
            problems.append(f"min_points must be >= 3, got {self.min_points}")
        if not 0.0 <= self.colour_tolerance <= 500.0:
            problems.append(f"colour_tolerance must be in [0, 500], got {self.colour_tolerance}")
        for name in ("fb_px", "ransac_px", "max_scale_step", "max_turn_deg", "max_error"):
            if not 0.0 < getattr(self, name) <= 100.0:
                problems.append(f"{name} must be in (0, 100], got {getattr(self, name)}")
        if self.grid_px < 1 or self.window_px < 5:
            problems.append(
                f"grid_px >= 1 and window_px >= 5, got {self.grid_px}, {self.window_px}"
            )
        if problems:
            raise ValueError("; ".join(problems))


def _track_points(
    grey_a: np.ndarray, grey_b: np.ndarray, region: np.ndarray, p: CarryParams
) -> tuple[np.ndarray, np.ndarray]:
    """Points ``(N, 2)`` in ``grey_a`` inside ``region (H, W)`` and where they are in
    ``grey_b`` ``(N, 2)``: kept where the backward track returns within ``fb_px``, the two
    windows match within ``max_error`` grey levels and the point lands inside ``grey_b``."""
    corners = cv2.goodFeaturesToTrack(grey_a, 200, 0.01, 3, mask=region)
    ys, xs = np.nonzero(region[:: p.grid_px, :: p.grid_px])
    grid = np.stack([xs, ys], axis=1).astype(np.float32) * p.grid_px  # (G, 2)
    pts = grid if corners is None else np.concatenate([corners.reshape(-1, 2), grid])
    if len(pts) < p.min_points:
        return np.zeros((0, 2), np.float32), np.zeros((0, 2), np.float32)
    pts = pts.astype(np.float32)  # (N, 2)
    track = track_forward_backward(grey_a, grey_b, pts, p.window_px, levels=4)
    good = track.converged & (track.error <= p.max_error) & (track.fb_px <= p.fb_px)  # (N,)
    h, w = grey_b.shape
    x, y = track.uv_b[:, 0], track.uv_b[:, 1]
    good &= (x >= 0) & (x < w) & (y >= 0) & (y < h)
    return pts[good], track.uv_b[good]


def carry_step(
    grey_a: np.ndarray, grey_b: np.ndarray, keypoints: np.ndarray, p: CarryParams
) -> np.ndarray | None:
    """One hand's keypoints ``(21, 2)`` (pixels) in frame ``a`` moved into frame ``b``, or None.

    ``grey_a``, ``grey_b`` ``(H, W)`` uint8. None when too few points of the hand track (see
    the module docstring) or the fit is not a plausible frame-to-frame motion of a hand.
    """
    h, w = grey_a.shape
    scale = hand_scale_px(keypoints)
    if not np.isfinite(scale) or scale <= 0:
        return None
    region, _ = draw_hand(keypoints, 0, h, w, CapsuleParams(forearm=False))  # (H, W) uint8
    if int(region.sum()) < p.min_points:
        return None
    src, dst = _track_points(grey_a, grey_b, region, p)
    if len(src) < p.min_points:
        return None
    fit, inliers = cv2.estimateAffinePartial2D(
        src, dst, method=cv2.RANSAC, ransacReprojThreshold=p.ransac_px
    )
    if fit is None or inliers is None or int(inliers.sum()) < p.min_points:
        return None
    s = float(np.hypot(fit[0, 0], fit[1, 0]))
    turn = float(np.degrees(np.arctan2(fit[1, 0], fit[0, 0])))
    if abs(s - 1.0) > p.max_scale_step or abs(turn) > p.max_turn_deg:
        return None
    # Keypoints are pixel-centre coordinates (+0.5); the tracked points are pixel indices.
    moved = (keypoints - 0.5) @ fit[:, :2].T + fit[:, 2] + 0.5  # (21, 2) NaN stays NaN
    return moved.astype(keypoints.dtype)


def carry_keypoints(
    frames: np.ndarray, keypoints: np.ndarray, valid: np.ndarray, params: CarryParams | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(keypoints (T, K, 21, 2), valid (T, K), carried (T, K))`` with missed hands carried.

    ``frames (T, H, W, 3)`` uint8 RGB; ``keypoints (T, K, 21, 2)`` pixels (NaN = unknown);
    ``valid (T, K)`` the hands found. A hand is carried from the nearest frame (at most
    ``max_frames`` away, either direction) that found it, frame by frame (see the module
    docstring); ``carried`` marks the frames and hands filled so. Found hands are unchanged; one
    found without a wrist (NaN) is not carried from, and no track passes through it.
    """
    p = params or CarryParams()
    kp = np.array(keypoints, dtype=np.float64, copy=True)
    ok = np.asarray(valid, bool).copy()
    carried = np.zeros_like(ok)
    t_count, k_count = ok.shape
    if p.max_frames == 0 or t_count < 2:
        return kp, ok, carried
    greys: dict[int, np.ndarray] = {}

    def grey(t: int) -> np.ndarray:
        if t not in greys:
            greys[t] = cv2.cvtColor(frames[t], cv2.COLOR_RGB2GRAY)
        return greys[t]

    labs: dict[int, np.ndarray] = {}

    def skeleton_colour(t: int, hand: np.ndarray) -> np.ndarray | None:
        """Median Lab ``(3,)`` of ``hand``'s skeleton in frame ``t`` (None: none drawn)."""
        if t not in labs:
            labs[t] = cv2.cvtColor(frames[t], cv2.COLOR_RGB2LAB)
        h, w = labs[t].shape[:2]
        _, core = draw_hand(hand, 0, h, w, CapsuleParams(forearm=False))
        pixels = labs[t][core > 0]
        return np.median(pixels, axis=0) if len(pixels) else None

    found = ok & np.isfinite(kp[:, :, 0, 0])  # (T, K) found, with a wrist to carry from
    for k in range(k_count):
        best: dict[int, tuple[int, np.ndarray]] = {}  # frame -> (distance, keypoints)
        for step in (1, -1):
            order = range(t_count) if step == 1 else range(t_count - 1, -1, -1)
            last, age, colour = None, 0, None
            for t in order:
                if found[t, k]:
                    last, age = kp[t, k], 0
                    colour = skeleton_colour(t, last) if p.colour_tolerance > 0 else None
                    continue
                if ok[t, k]:  # found without a wrist: kept as it is, and no track crosses it
                    last = None
                    continue
                if last is None or age >= p.max_frames:
                    last = None
                    continue
                if t in best and best[t][0] <= age + 1:
                    # The forward pass reached t as near (it wins ties) and, having come from
                    # the found frame behind t, is nearer at every frame this track would reach
                    # next: the step could change nothing.
                    last = None
                    continue
                moved = carry_step(grey(t - step), grey(t), last, p)
                if moved is None:
                    last = None
                    continue
                if colour is not None:
                    here = skeleton_colour(t, moved)
                    if here is None or np.linalg.norm(here - colour) > p.colour_tolerance:
                        last = None  # the background the hand uncovered tracked, not the hand
                        continue
                    colour = here
                age += 1
                last = moved
                if t not in best or age < best[t][0]:
                    best[t] = (age, moved)
        for t, (_, moved) in best.items():
            kp[t, k], ok[t, k], carried[t, k] = moved, True, True
    return kp, ok, carried
