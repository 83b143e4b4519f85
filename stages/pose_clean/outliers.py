"""Jump outliers in camera trajectories: scale-free detection and repair.

A frame is a jump outlier when it is far from where its neighbours say it should be, measured
against the trajectory's own statistics, never against an absolute length (SfM poses are in
arbitrary units unless a metric scale is known):

1. **Leave-one-out prediction.** Each frame ``i`` is predicted from its ``neighbours`` nearest
   frames that are not ``i`` and not already flagged: a quadratic in time fitted by least squares
   to the camera centres and, separately, to the rotations as rotation vectors relative to the
   nearest neighbour's rotation, evaluated at ``i``. Smooth motion, even a fast head turn, is
   followed by the quadratic; a spike is not, and it does not pull its own prediction.
2. **Standardised residual.** ``e_t(i) = |c_i - c_hat_i|`` (trajectory units) and ``e_r(i) =
   angle(R_hat_i^T R_i)`` (degrees). With white noise of standard deviation ``s`` the residual has
   ``s * g_i``, ``g_i = sqrt(1 + |w_i|^2)`` (``w_i`` the fit's weights; ``g`` is larger at the ends,
   where the fit extrapolates), so ``e / g`` is comparable over frames.
3. **Threshold from the clip itself.** Frame ``i`` is over threshold when ``e(i) > max(ratio *
   median_j(e(j) / g_j) * g_i, floor_ratio * median |sd| * (g_i / median g)^2)``: ``ratio``
   times the clip's median standardised residual (its noise plus fit error), and at least
   ``floor_ratio`` times the median norm of the second difference ``sd`` (how much consecutive
   steps differ), more at the ends where the fit extrapolates. The floor keeps exact,
   noise-free trajectories, whose residuals are all tiny fit errors, from being cut up; a fast
   but smooth motion has large steps but small second differences, so the floor stays low
   there. Both terms scale with the trajectory: no length in metres appears anywhere.
4. **One at a time.** Of the frames over threshold, the one whose removal leaves the smallest
   sum of squared residuals (translation and rotation in units of their own threshold) is
   flagged, excluded from every fit, and everything is computed again; this repeats until no
   frame is over threshold (or ``max_fraction`` of the frames are flagged). Two or three
   spikes within a few frames of each other therefore cannot hide each other: the worst is
   removed first and no longer pulls its neighbour's prediction.

Frames given as ``protected`` are never flagged (they still take part in every fit): the stage
protects the frames an SfM mapper registered and bundle-adjusted against its map, whose pose is
better evidence than a smoothness test. At 8 fps a fast head turn (13 degrees in one frame,
steps of 5, 13, 7, 4, 5 degrees) looks like a run of jumps to a local quadratic, and repairing
it replaces the real turn by an interpolation.

Repair: translation by linear interpolation between the nearest good frames, rotation by their
normalised, hemisphere-aligned quaternion blend with the same weights.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from egosim.pipeline.geometry import (
    make_se3,
    matrix_from_quat,
    quat_from_matrix,
    rotation_angle_deg,
)

MIN_FRAMES_FOR_DETECTION = 5  # fewer frames leave too few neighbours for a leave-one-out fit
ROUNDING_REL = 1e-9  # translation residuals below this share of the centres' size are round-off
ROUNDING_DEG = 1e-6  # rotation residuals below this many degrees are round-off


def second_difference_norms(world_from_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Second-difference magnitudes of a trajectory ``(T, 4, 4)`` at centre frames 1..T-2.

    Returns ``(translation (T-2,) in the trajectory's units, rotation_deg (T-2,))``:
    ``|c_{i+1} - 2 c_i + c_{i-1}|`` of the camera centre and the angle between the relative
    rotations ``R_{i-1}^T R_i`` and ``R_i^T R_{i+1}`` (zero for constant angular velocity about
    a body axis).
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
    """``(milli-units, deg)``: RMS of :func:`second_difference_norms`; zeros when ``T < 3``.

    The translation figure is in thousandths of the trajectory's length unit: millimetres only
    when the poses are metric.
    """
    sd_t, sd_r = second_difference_norms(world_from_cam)
    if len(sd_t) == 0:
        return 0.0, 0.0
    return float(np.sqrt(np.mean(sd_t**2)) * 1e3), float(np.sqrt(np.mean(sd_r**2)))


def _neighbour_weights(flagged: np.ndarray, neighbours: int) -> tuple[np.ndarray, np.ndarray]:
    """Leave-one-out quadratic prediction weights for every frame.

    ``flagged (T,)``: frames no fit may use. Returns ``(index (T, N), weights (T, N))``: frame
    ``i`` is predicted as ``sum_k weights[i, k] * x[index[i, k]]`` from its ``N`` nearest usable
    frames other than itself (a least-squares quadratic in time evaluated at ``i``; linear when
    fewer than 4 frames are usable, constant when fewer than 2).
    """
    t = len(flagged)
    frames = np.arange(t)
    dist = np.abs(frames[None, :] - frames[:, None]).astype(np.float64)  # (T, T)
    dist += 1e-3 * (frames[None, :] > frames[:, None])  # ties: the earlier frame first
    dist[:, flagged] = np.inf
    np.fill_diagonal(dist, np.inf)
    usable = int(np.sum(~flagged)) - 1  # every frame has at least this many candidates
    n = max(1, min(neighbours, usable))
    index = np.argsort(dist, axis=1, kind="stable")[:, :n]  # (T, N)
    offset = (index - frames[:, None]).astype(np.float64)  # (T, N) frames from i
    degree = 2 if n >= 4 else (1 if n >= 2 else 0)
    design = offset[..., None] ** np.arange(degree + 1)  # (T, N, D) columns 1, d, d^2
    gram = np.swapaxes(design, 1, 2) @ design  # (T, D, D)
    # the prediction at offset 0 is the intercept: row 0 of (A^T A)^-1 A^T
    weights = np.linalg.solve(gram, np.swapaxes(design, 1, 2))[:, 0, :]  # (T, N)
    return index, weights


def loo_residuals(
    world_from_cam: np.ndarray, flagged: np.ndarray | None = None, neighbours: int = 6
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Leave-one-out residuals of ``world_from_cam (T, 4, 4)`` (see the module, step 1-2).

    Frames in ``flagged (T,)`` are used by no prediction. Returns ``(translation (T,) in the
    trajectory's units, rotation (T,) degrees, gain (T,))`` where ``gain`` is the factor by which
    white measurement noise grows in the residual, ``sqrt(1 + |w|^2)``.
    """
    poses = np.asarray(world_from_cam, dtype=np.float64)
    t = len(poses)
    flags = np.zeros(t, dtype=bool) if flagged is None else np.asarray(flagged, dtype=bool)
    index, weights = _neighbour_weights(flags, neighbours)  # (T, N) each
    centres = poses[:, :3, 3]  # (T, 3)
    pred_c = np.einsum("tn,tnc->tc", weights, centres[index])  # (T, 3)
    e_t = np.linalg.norm(centres - pred_c, axis=1)  # (T,)
    # rotation in the tangent space of the nearest neighbour's rotation: a constant angular
    # velocity about a fixed axis is linear in time there, so smooth turns fit exactly
    rots = Rotation.from_matrix(poses[:, :3, :3])
    ref = rots[index[:, 0]]  # (T,) reference rotation of each frame's fit
    rel_n = (ref[np.repeat(np.arange(t), index.shape[1])].inv() * rots[index.ravel()]).as_rotvec()
    rel_n = rel_n.reshape(*index.shape, 3)  # (T, N, 3) neighbours relative to the reference
    pred_r = Rotation.from_rotvec(np.einsum("tn,tnc->tc", weights, rel_n))  # (T,) predicted
    rel_i = ref.inv() * rots  # (T,) frame i relative to its reference
    e_r = np.rad2deg((pred_r.inv() * rel_i).magnitude())  # (T,)
    gain = np.sqrt(1.0 + np.sum(weights**2, axis=1))  # (T,)
    return e_t, e_r, gain


def detect_outliers(
    world_from_cam: np.ndarray,
    ratio: float = 4.0,
    floor_ratio: float = 2.0,
    neighbours: int = 6,
    max_fraction: float = 0.25,
    protected: np.ndarray | None = None,
) -> np.ndarray:
    """Boolean mask ``(T,)`` of jump outliers in ``world_from_cam (T, 4, 4)`` (see the module).

    ``ratio``: threshold in multiples of the clip's median standardised leave-one-out residual;
    ``floor_ratio``: the threshold is at least this many median second differences (more at the
    ends); both for translation and, in degrees, rotation. ``neighbours``: frames of each local
    quadratic fit. At most ``max_fraction`` of the frames are flagged. ``protected (T,)`` bool:
    frames never flagged (None: none). Needs ``T >= 5``; shorter trajectories have no outliers.
    """
    poses = np.asarray(world_from_cam, dtype=np.float64)
    t = len(poses)
    flagged = np.zeros(t, dtype=bool)
    keep = np.zeros(t, dtype=bool) if protected is None else np.asarray(protected, dtype=bool)
    if keep.shape != (t,):
        raise ValueError(f"protected must have shape ({t},), got {keep.shape}")
    if t < MIN_FRAMES_FOR_DETECTION:
        return flagged
    sd_t, sd_r = second_difference_norms(poses)  # (T-2,) each
    floors = floor_ratio * np.array([np.median(sd_t), np.median(sd_r)])  # (2,) units, degrees
    # rounding: exact trajectories whose second differences vanish (constant velocity) have
    # residuals of float64 round-off, which is no jump
    extent = float(np.max(np.abs(poses[:, :3, 3]))) if t else 0.0
    floors = np.maximum(floors, [ROUNDING_REL * extent, ROUNDING_DEG])
    for _ in range(int(max_fraction * t)):
        e_t, e_r, gain = loo_residuals(poses, flagged, neighbours)  # (T,) each
        resid = np.stack([e_t, e_r])  # (2, T)
        level = np.median(resid[:, ~flagged] / gain[~flagged], axis=1)  # (2,) noise + fit error
        # the floor grows with the fit's noise gain squared: an end frame is extrapolated, and
        # the fit error of smooth motion grows faster than the noise there
        floor = floors[:, None] * (gain / np.median(gain)) ** 2  # (2, T)
        thr = np.maximum(ratio * level[:, None] * gain, floor)  # (2, T)
        unit = np.maximum(ratio * level, floors)  # (2,) one threshold unit per channel
        unit = np.where(unit > 0, unit, 1.0)
        candidates = np.flatnonzero((resid > thr).any(axis=0) & ~flagged & ~keep)
        if len(candidates) == 0:
            break
        # A spike also inflates its neighbours' residuals (by their fit weight on it, which is
        # above 1 where an end frame is extrapolated), so neither the largest raw nor the
        # largest standardised residual reliably names it. Flag the candidate whose removal
        # leaves the smallest sum of squared residuals (in threshold units) over the rest.
        costs = []
        for c in candidates:
            trial = flagged.copy()
            trial[c] = True
            r_t, r_r, _ = loo_residuals(poses, trial, neighbours)
            rest = np.stack([r_t, r_r])[:, ~trial] / unit[:, None]  # (2, T - flagged)
            costs.append(float(np.sum(rest**2)))
        worst = int(candidates[int(np.argmin(costs))])
        flagged[worst] = True
    return flagged


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
