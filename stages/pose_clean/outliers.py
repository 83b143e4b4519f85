"""Jump outliers in camera trajectories: detection (paper Eq. 4) and repair.

The paper flags frame ``i`` when its translation jump and its rotation jump to *both* neighbours
exceed thresholds. A raw jump ``|t_i - t_{i-1}|`` also grows with fast but smooth motion (a 5
degree-per-frame head turn looks like a jump), so here every jump is measured *relative to the
local motion*: the incoming jump is how far the step ``i-1 -> i`` departs from the step before
it, the outgoing jump how far ``i -> i+1`` departs from the step after it. Both are second
differences, of the camera centre (metres) and of the rotation (angle between consecutive
relative rotations, degrees):

    jump_in(i)  = |sd(i-1)|,   jump_out(i) = |sd(i+1)|,   sd(c) = x_{c+1} - 2 x_c + x_{c-1}

An isolated spike of size J at frame i gives ``|sd(i-1)| = |sd(i+1)| = J`` while its neighbours
see only one large side, so the test flags the spike and not the frames around it. The threshold
is ``ratio`` times the running median of ``|sd|`` (the local noise + motion level), floored.

Repair: translation by the (time-weighted) mean of the nearest good neighbours, rotation by their
normalised, hemisphere-aligned quaternion average.
"""

from __future__ import annotations

import numpy as np

from egosim.pipeline.geometry import (
    make_se3,
    matrix_from_quat,
    quat_from_matrix,
    rotation_angle_deg,
)

MIN_FRAMES_FOR_DETECTION = 5  # the two-sided test needs two frames on each side


def second_difference_norms(world_from_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Second-difference magnitudes of a trajectory ``(T, 4, 4)`` at centre frames 1..T-2.

    Returns ``(translation_m (T-2,), rotation_deg (T-2,))``: ``|c_{i+1} - 2 c_i + c_{i-1}|`` of
    the camera centre and the angle between the relative rotations ``R_{i-1}^T R_i`` and
    ``R_i^T R_{i+1}`` (zero for constant angular velocity about a body axis).
    """
    poses = np.asarray(world_from_cam, dtype=np.float64)
    if len(poses) < 3:
        return np.zeros(0), np.zeros(0)
    centres = poses[:, :3, 3]  # (T, 3)
    sd_t = np.linalg.norm(centres[2:] - 2.0 * centres[1:-1] + centres[:-2], axis=1)  # (T-2,)
    rots = poses[:, :3, :3]  # (T, 3, 3)
    rel = np.swapaxes(rots[:-1], -1, -2) @ rots[1:]  # (T-1, 3, 3) R_i^T R_{i+1}
    sd_r = rotation_angle_deg(rel[:-1], rel[1:])  # (T-2,)
    return sd_t, sd_r


def jitter(world_from_cam: np.ndarray) -> tuple[float, float]:
    """``(mm, deg)``: RMS of :func:`second_difference_norms`; zeros when ``T < 3``."""
    sd_t, sd_r = second_difference_norms(world_from_cam)
    if len(sd_t) == 0:
        return 0.0, 0.0
    return float(np.sqrt(np.mean(sd_t**2)) * 1e3), float(np.sqrt(np.mean(sd_r**2)))


def _running_median(values: np.ndarray, size: int) -> np.ndarray:
    """Median of ``size`` consecutive values around each entry of ``values (L,)``; near the ends
    the window shifts inwards (no padding, which would repeat an end spike)."""
    windows = np.lib.stride_tricks.sliding_window_view(values, size)  # (L - size + 1, size)
    medians = np.median(windows, axis=1)  # (L - size + 1,)
    start = np.clip(np.arange(len(values)) - size // 2, 0, len(values) - size)
    return medians[start]


def _two_sided_flags(sd: np.ndarray, threshold: np.ndarray) -> np.ndarray:
    """Frames ``(T,)`` whose incoming and outgoing jumps (``sd (T-2,)``) both exceed threshold."""
    t = len(sd) + 2
    big = np.zeros(t + 2, dtype=bool)  # big[c + 1] = |sd| at centre c is over its threshold
    big[2:-2] = sd > threshold[1:-1]
    c = np.arange(t)
    flags = big[c] & big[c + 2]  # interior: centres i-1 and i+1 both big
    # Ends, where one side is missing: frame 0 only moves sd(1); frame 1 moves sd(1), sd(2) but
    # not sd(3) (a spike at 2 would); mirrored at the far end.
    flags[0] = big[2] and not big[3]
    flags[1] = big[2] and big[3] and not big[4]
    flags[-1] = big[-3] and not big[-4]
    flags[-2] = big[-3] and big[-4] and not big[-5]
    return flags


def detect_outliers(
    world_from_cam: np.ndarray,
    ratio: float = 3.0,
    window: int = 15,
    min_translation_m: float = 0.01,
    min_rotation_deg: float = 1.0,
) -> np.ndarray:
    """Boolean mask ``(T,)`` of jump outliers in ``world_from_cam (T, 4, 4)`` (Eq. 4, see module).

    A frame is flagged when its translation jumps to both neighbours exceed
    ``max(ratio * local median, min_translation_m)``, or its rotation jumps do (same rule with
    ``min_rotation_deg``). ``window`` frames set the running median. Needs ``T >= 5``; shorter
    trajectories have no outliers.
    """
    poses = np.asarray(world_from_cam, dtype=np.float64)
    t = len(poses)
    if t < MIN_FRAMES_FOR_DETECTION:
        return np.zeros(t, dtype=bool)
    sd_t, sd_r = second_difference_norms(poses)  # (T-2,) each
    size = min(window, len(sd_t))
    flags = np.zeros(t, dtype=bool)
    for sd, floor in ((sd_t, min_translation_m), (sd_r, min_rotation_deg)):
        level = _running_median(sd, size)  # (T-2,) local noise + motion level
        thr = np.maximum(ratio * level, floor)  # (T-2,)
        per_frame = np.concatenate([thr[:1], thr, thr[-1:]])  # (T,) threshold at frame i
        flags |= _two_sided_flags(sd, per_frame)
    return flags


def repair_outliers(world_from_cam: np.ndarray, outliers: np.ndarray) -> np.ndarray:
    """Replace flagged frames of ``world_from_cam (T, 4, 4)`` by their good neighbours' mean.

    Translation: linear interpolation between the nearest good frames before and after (their
    mean for an isolated outlier); rotation: the normalised quaternion average with the same
    weights, after aligning the two quaternions' hemispheres. A flagged frame at an end copies
    the nearest good frame. Raises ``ValueError`` when every frame is flagged.
    """
    poses = np.array(world_from_cam, dtype=np.float64, copy=True)
    bad = np.asarray(outliers, dtype=bool)
    if not bad.any():
        return poses
    good = np.flatnonzero(~bad)
    if len(good) == 0:
        raise ValueError("every frame is an outlier: nothing to repair from")
    idx = np.flatnonzero(bad)  # (K,)
    after = np.searchsorted(good, idx)  # index into good of the next good frame
    prev_i = good[np.clip(after - 1, 0, len(good) - 1)]  # (K,)
    next_i = good[np.clip(after, 0, len(good) - 1)]  # (K,)
    prev_i = np.where(after == 0, next_i, prev_i)
    next_i = np.where(after == len(good), prev_i, next_i)
    span = np.maximum(next_i - prev_i, 1)
    w = np.where(next_i == prev_i, 0.0, (idx - prev_i) / span)[:, None]  # (K, 1)
    trans = (1.0 - w) * poses[prev_i, :3, 3] + w * poses[next_i, :3, 3]  # (K, 3)
    q_a = quat_from_matrix(poses[prev_i, :3, :3])  # (K, 4)
    q_b = quat_from_matrix(poses[next_i, :3, :3])  # (K, 4)
    q_b *= np.where(np.sum(q_a * q_b, axis=1) < 0.0, -1.0, 1.0)[:, None]
    q = (1.0 - w) * q_a + w * q_b  # (K, 4)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    poses[idx] = make_se3(matrix_from_quat(q), trans)
    return poses
