"""Fill the hand pixels of frame 0 from later frames aligned in the image (no depth needed).

For clips without depth, a static camera above all (the ``depth_camera`` stage gives a static
camera no depth): each later frame is aligned to frame 0 by a homography fitted to features
outside the hand masks (ORB matches, RANSAC), or by the identity when the camera is known to be
static. A masked pixel of frame 0 then takes the per-channel **median** of the colours that the
first ``candidates`` aligned frames show there unoccluded (their own masks, dilated): with a still
camera this is the plain temporal median, and a median over several frames leaves no ghost of a
hand that one frame's mask missed. A fitted homography is checked where it matters: round the
hole (a ring of ``ring_px`` outside frame 0's mask, off both frames' hands) the aligned frame
must match frame 0 to within ``max_residual`` grey levels (median absolute difference), else
the frame is not used (a plane's homography does not align a 3D scene seen from far apart).
The same check is also made near each hole pixel (``local_residual``, :func:`local_residual_map`):
a homography that holds on one side of the hole and not on the other fills that side only.
What no frame sees goes to :func:`unseen_fill`.

Optionally (``confirm > 1``; off by default, see ``InpaintConfig.aligned_confirm``) a colour
fewer than ``confirm`` frames gave is unconfirmed: where a hand stays put, the later frames see
its hole only where their masks miss part of the hand (or where the scene moved), and their
single sample pastes that ghost. Such pixels take the mean of the fill and OpenCV's fill of the
whole hole (``unseen_method``); their ``fill_source`` stays reprojected.
"""

from __future__ import annotations

import cv2
import numpy as np

from egosim.schemas.inpaint import FILL_OPENCV, FILL_ORIGINAL, FILL_REPROJECTED
from egosim.stages.inpaint.reproject_fill import (
    MIN_SHIFT_EVIDENCE,
    FillResult,
    OccluderColours,
    best_shift,
    dilate,
    evidence,
    local_residual_map,
    slot_median,
    unseen_fill,
)

MIN_MATCHES = 12  # fewer good feature matches than this: the frame is not used


def orb_features(image: np.ndarray, mask: np.ndarray) -> tuple[tuple, np.ndarray | None]:
    """ORB keypoints and descriptors of ``image (H, W, 3)`` RGB off ``mask (H, W)`` (hands)."""
    grey = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
    return cv2.ORB_create(1500).detectAndCompute(grey, (mask == 0).astype(np.uint8) * 255)


def homography_to_first(
    frame: np.ndarray, mask: np.ndarray, first: tuple[tuple, np.ndarray | None]
) -> np.ndarray | None:
    """Homography ``(3, 3)`` taking pixels of ``frame`` to frame 0 (OpenCV coordinates).

    ``first``: frame 0's :func:`orb_features` (off its hands, computed once per clip); features
    under ``mask`` (this frame's hands) are ignored. None when too few matches or RANSAC inliers
    support one.
    """
    kp_a, des_a = orb_features(frame, mask)
    kp_b, des_b = first
    if des_a is None or des_b is None or len(kp_a) < MIN_MATCHES or len(kp_b) < MIN_MATCHES:
        return None
    matches = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True).match(des_a, des_b)
    if len(matches) < MIN_MATCHES:
        return None
    src = np.float32([kp_a[m.queryIdx].pt for m in matches])  # (M, 2)
    dst = np.float32([kp_b[m.trainIdx].pt for m in matches])  # (M, 2)
    hom, inliers = cv2.findHomography(src, dst, cv2.RANSAC, 3.0)
    if hom is None or inliers is None or int(inliers.sum()) < MIN_MATCHES:
        return None
    return hom


def image_shift(
    grey: np.ndarray, grey0: np.ndarray, check: np.ndarray, radius: int, min_gain: float
) -> tuple[int, int]:
    """The whole-pixel shift ``(dx, dy)``, ``|dx|, |dy| < radius``, that best aligns the warped
    ``grey (H, W)`` with frame 0's ``grey0 (H, W)`` on the ``check (H, W)`` pixels (the ring),
    or ``(0, 0)``: the mean absolute difference of ``grey[y + dy, x + dx]`` and ``grey0[y, x]``,
    kept when it is ``min_gain`` (a fraction) below the unshifted one and the best does not lie
    on the window's edge (as :func:`~egosim.stages.inpaint.reproject_fill.ring_shift`).
    """
    if radius <= 0:
        return (0, 0)
    h, w = grey0.shape
    cy, cx = np.nonzero(check)  # (C,)
    inner = (cy >= radius) & (cy < h - radius) & (cx >= radius) & (cx < w - radius)
    cy, cx = cy[inner], cx[inner]
    if len(cy) < MIN_SHIFT_EVIDENCE:
        return (0, 0)
    keep = evidence(len(cy))
    cy, cx = cy[keep], cx[keep]  # (C',) at most MAX_SHIFT_EVIDENCE
    ref = grey0[cy, cx].astype(np.float32)  # (C,)
    return best_shift(
        lambda dx, dy: np.mean(np.abs(grey[cy + dy, cx + dx] - ref)), radius, min_gain
    )


def aligned_fill(
    frames: np.ndarray,
    hand_mask: np.ndarray,
    static_camera: bool = False,
    dilate_px: int = 2,
    candidates: int = 5,
    inpaint_radius: float = 5.0,
    unseen_method: str = "telea",
    max_residual: float = 10.0,
    occluder_ratio: float = 0.0,
    ring_px: int = 15,
    local_residual: float = 0.0,
    shift_px: int = 0,
    shift_gain: float = 0.2,
    confirm: int = 1,
) -> FillResult:
    """Remove the hand from ``frames[0]``; see the module docstring.

    ``frames (T, H, W, 3)`` uint8 RGB, ``hand_mask (T, H, W)`` 1 = hand. ``static_camera``: use
    the identity instead of fitted homographies. ``candidates``: frames whose colours are
    medianed per pixel (the earliest that see it). ``max_residual``, ``ring_px``: the alignment
    check of fitted homographies (see the module docstring).
    ``occluder_ratio``: samples that look like frame 0's hands are not used (see
    :class:`~egosim.stages.inpaint.reproject_fill.OccluderColours`; 0: off).
    ``local_residual``: a fitted homography fills only the hole pixels whose nearby ring matches
    frame 0 within this many grey levels (mean absolute difference; 0: off).
    ``shift_px > 0``: each fitted warp is moved by :func:`image_shift` (the whole-pixel shift,
    less than ``shift_px``, that aligns the ring, kept when it lowers its residual by
    ``shift_gain``) before the checks: a homography fitted over the whole frame can sit a few
    pixels off round the hole. ``confirm > 1``: a hole pixel that some but fewer than
    ``confirm`` frames filled takes the mean of its fill and OpenCV's fill of the whole hole
    (see the module docstring; 1: off).
    """
    t, h, w = frames.shape[:3]
    masks = dilate(hand_mask > 0, dilate_px)  # (T, H, W)
    target = masks[0] > 0  # (H, W)
    image = frames[0].copy()
    fill_source = np.zeros((h, w), np.uint8)
    source_frame = np.zeros((h, w), np.uint16)
    if not target.any():
        return FillResult(image, fill_source, source_frame, target)
    ys, xs = np.nonzero(target)  # (M,)
    ring = (dilate(target, ring_px) > 0) & ~target  # (H, W) round the hole
    occluders = None
    if occluder_ratio > 0:
        occluders = OccluderColours(frames[0], hand_mask[0] > 0, target, occluder_ratio)
    grey0 = cv2.cvtColor(frames[0], cv2.COLOR_RGB2GRAY).astype(np.int16)  # (H, W)
    first = None if static_camera else orb_features(frames[0], masks[0])
    samples = np.zeros((candidates, len(ys), 3), np.float32)  # colours per candidate slot
    count = np.zeros(len(ys), np.int32)  # (M,) slots used per pixel
    first_frame = np.zeros(len(ys), np.uint16)  # (M,) earliest frame that filled the pixel
    for k in range(1, t):
        if count.min() >= candidates:
            break
        if static_camera:
            warped, free = frames[k], masks[k] == 0
        else:
            hom = homography_to_first(frames[k], masks[k], first)
            if hom is None:
                continue
            warped = cv2.warpPerspective(frames[k], hom, (w, h), flags=cv2.INTER_LINEAR)
            seen = cv2.warpPerspective(
                (masks[k] == 0).astype(np.uint8), hom, (w, h), flags=cv2.INTER_NEAREST
            )  # (H, W) 1 = unoccluded and inside frame k
            free = seen > 0
            check = ring & free  # (H, W)
            if check.sum() < MIN_SHIFT_EVIDENCE:
                continue
            grey = cv2.cvtColor(warped, cv2.COLOR_RGB2GRAY).astype(np.int16)
            dx, dy = image_shift(grey, grey0, check, shift_px, shift_gain)
            if dx or dy:  # move the warp by the shift that aligns the ring
                hom = np.array([[1.0, 0.0, -dx], [0.0, 1.0, -dy], [0.0, 0.0, 1.0]]) @ hom
                warped = cv2.warpPerspective(frames[k], hom, (w, h), flags=cv2.INTER_LINEAR)
                seen = cv2.warpPerspective(
                    (masks[k] == 0).astype(np.uint8), hom, (w, h), flags=cv2.INTER_NEAREST
                )
                free = seen > 0
                check = ring & free
                if check.sum() < MIN_SHIFT_EVIDENCE:  # the shift left too little ring to check
                    continue
                grey = cv2.cvtColor(warped, cv2.COLOR_RGB2GRAY).astype(np.int16)
            diff = np.abs(grey - grey0)  # (H, W) alignment residual
            if float(np.median(diff[check])) > max_residual:
                continue
        ok = free[ys, xs] & (count < candidates)  # (M,)
        if local_residual > 0 and not static_camera:
            near = local_residual_map(diff, check, target)  # (H, W)
            ok &= near[ys, xs] <= local_residual
        if not ok.any():
            continue
        idx = np.nonzero(ok)[0]
        if occluders is not None:  # not another frame's missed hand or arm
            idx = idx[~occluders.hand_like(warped[ys[idx], xs[idx]])]
        samples[count[idx], idx] = warped[ys[idx], xs[idx]]
        first_frame[idx[count[idx] == 0]] = k
        count[idx] += 1
    done = count > 0
    if done.any():
        filled = slot_median(samples, count)[done]  # (M', 3)
        image[ys[done], xs[done]] = np.clip(np.round(filled), 0, 255).astype(np.uint8)
        fill_source[ys[done], xs[done]] = FILL_REPROJECTED
        source_frame[ys[done], xs[done]] = first_frame[done]
    unseen = np.zeros((h, w), np.uint8)
    unseen[ys[~done], xs[~done]] = 1
    if unseen.any():
        image = unseen_fill(image, unseen, inpaint_radius, unseen_method)
        fill_source[unseen > 0] = FILL_OPENCV
    weak = done & (count < confirm)  # (M,) unconfirmed: 1..confirm-1 frames gave the colour
    if confirm > 1 and weak.any():
        hole = unseen_fill(frames[0], target.astype(np.uint8), inpaint_radius, unseen_method)
        wy, wx = ys[weak], xs[weak]
        both = (image[wy, wx].astype(np.float32) + hole[wy, wx]) / 2  # (W', 3)
        image[wy, wx] = np.round(both).astype(np.uint8)
    fill_source[~target] = FILL_ORIGINAL
    return FillResult(image, fill_source, source_frame, target)
