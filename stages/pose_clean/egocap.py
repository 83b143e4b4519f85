"""EgoCap-style trajectory refinement (paper Sec. on EgoCap capture): re-interpolate the jump
frames with a cubic spline (translation) and SLERP (rotation), then a global Savitzky-Golay
filter suppresses the high-frequency jitter; quaternions stay unit and sign-continuous.
"""

from __future__ import annotations

import numpy as np
from scipy.interpolate import CubicSpline
from scipy.signal import savgol_filter

from egosim.pipeline.geometry import (
    make_se3,
    matrix_from_quat,
    quat_align_hemisphere,
    quat_from_matrix,
    slerp_rotations,
)


def interpolate_outliers(world_from_cam: np.ndarray, outliers: np.ndarray) -> np.ndarray:
    """Re-sample flagged frames of ``world_from_cam (T, 4, 4)`` from the good ones.

    Translation: a cubic spline through the good frames' centres (natural ends; linear when
    only two good frames remain); rotation: SLERP between the good frames. Frames outside the
    good range copy the nearest good frame. Raises ``ValueError`` when fewer than 2 are good.
    """
    poses = np.array(world_from_cam, dtype=np.float64, copy=True)
    bad = np.asarray(outliers, dtype=bool)
    if not bad.any():
        return poses
    good = np.flatnonzero(~bad)
    if len(good) < 2:
        raise ValueError(f"only {len(good)} good frames: cannot interpolate the others")
    idx = np.flatnonzero(bad)
    query = np.clip(idx, good[0], good[-1]).astype(np.float64)  # (K,)
    spline = CubicSpline(good.astype(np.float64), poses[good, :3, 3], bc_type="natural")
    trans = spline(query)  # (K, 3)
    rots = slerp_rotations(good.astype(np.float64), poses[good, :3, :3], query)  # (K, 3, 3)
    poses[idx] = make_se3(rots, trans)
    return poses


def savgol_poses(world_from_cam: np.ndarray, window: int, polyorder: int) -> np.ndarray:
    """Savitzky-Golay smoothing of centres and hemisphere-aligned quaternions; ``(T, 4, 4)``.

    ``window`` is shrunk to the largest odd length <= T (no smoothing when that is not above
    ``polyorder``). Quaternions are renormalised after filtering.
    """
    poses = np.asarray(world_from_cam, dtype=np.float64)
    t = len(poses)
    win = min(window, t if t % 2 == 1 else t - 1)
    if win <= polyorder:
        return poses.copy()
    centres = savgol_filter(poses[:, :3, 3], win, polyorder, axis=0, mode="interp")  # (T, 3)
    quats = quat_align_hemisphere(quat_from_matrix(poses[:, :3, :3]))  # (T, 4)
    quats = savgol_filter(quats, win, polyorder, axis=0, mode="interp")  # (T, 4)
    quats /= np.linalg.norm(quats, axis=1, keepdims=True)
    return make_se3(matrix_from_quat(quats), centres)
