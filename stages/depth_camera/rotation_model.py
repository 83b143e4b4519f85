"""Rotation-only camera model: per-frame rotations from frame-to-frame homographies.

When the head mostly turns, parallax is too small to triangulate, but the image motion of a
purely rotating camera is the homography ``H = K R K^-1`` whatever the depth. Corners outside
the hands are tracked by KLT from frame ``k-1`` into frame ``k``; a RANSAC homography over the
dominant consistent set gives ``H_k``; ``K^-1 H_k K`` (scaled to unit determinant) projected to
SO(3) is the rotation ``cam_k_from_cam_{k-1}``; chained, ``cam_k_from_cam_0``. The same tracks
also get a RANSAC fundamental matrix: the homography's residual on the epipolar-consistent
tracks says whether a pure rotation explains the motion (a translating camera over a scene with
depth leaves parallax the homography cannot absorb).

The focal can be self-calibrated: with a wrong ``K``, ``K^-1 H K`` is not a rotation. The focal
that makes the normalised matrices closest to rotations (summed Frobenius distance to their
SO(3) projection) over a range of fields of view is kept when the rotations are large enough to
constrain it.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from egosim.pipeline.geometry import intrinsics_matrix
from egosim.stages.depth_camera.tracking import TrackingParams, grey_frames, track_points


@dataclass(frozen=True)
class RotationParams:
    """Knobs of :func:`estimate_rotations` and :func:`pair_motion`."""

    max_corners: int = 600  # corners detected per frame (spread over a grid)
    grid: int = 6  # corners are detected in grid x grid cells, max_corners / grid^2 each
    ransac_px: float = 1.5  # homography / fundamental RANSAC threshold, pixels
    min_tracks: int = 30  # fewer tracked corners than this = the pair fails
    max_h_residual_px: float = 1.0  # median H residual on F-inliers above this = parallax
    min_h_inlier_ratio: float = 0.6  # H inliers / F inliers below this = parallax
    min_calibration_deg: float = 5.0  # self-calibrate f only when rotations reach this much
    fov_range_deg: tuple[float, float] = (40.0, 110.0)  # self-calibration search range
    max_bridge: int = 8  # a failed pair is bridged from up to this many frames back


@dataclass(frozen=True)
class PairMotion:
    """Homography figures of one frame pair."""

    homography: np.ndarray | None  # (3, 3) maps frame a pixels to frame b, None when failed
    num_tracks: int  # KLT tracks between the frames
    h_inlier_ratio: float  # H inliers / F inliers (1 = the homography explains everything)
    h_residual_px: float  # median H transfer error over the F inliers, pixels
    motion_px: float  # median displacement of the H inliers, pixels

    def rotation_explains(self, params: RotationParams) -> bool:
        """True when the homography explains the epipolar-consistent tracks (no parallax)."""
        return (
            self.homography is not None
            and self.h_inlier_ratio >= params.min_h_inlier_ratio
            and self.h_residual_px <= params.max_h_residual_px
        )


@dataclass(frozen=True)
class RotationEstimate:
    """Rotations of a clip relative to frame 0 and how well homographies explain it."""

    cam_from_cam0: np.ndarray  # (T, 3, 3) rotation of frame k relative to frame 0
    posed: np.ndarray  # (T,) bool, frames reached by a chain of explained pairs
    intrinsics: np.ndarray  # (4,) fx, fy, cx, cy used (focal possibly self-calibrated)
    pairs: list[PairMotion]  # (T-1,) figures of pairs (k-1, k)
    explained_fraction: float  # fraction of pairs whose motion a rotation explains
    focal_calibrated: bool  # True when the focal came from self-calibration


def detect_corners(
    grey: np.ndarray, usable: np.ndarray | None, params: RotationParams
) -> np.ndarray:
    """``(N, 2)`` Shi-Tomasi corners spread over a grid of cells, off ``usable`` False pixels."""
    h, w = grey.shape
    per_cell = max(4, params.max_corners // (params.grid * params.grid))
    found = []
    for gy in range(params.grid):
        for gx in range(params.grid):
            y0, y1 = gy * h // params.grid, (gy + 1) * h // params.grid
            x0, x1 = gx * w // params.grid, (gx + 1) * w // params.grid
            mask = None
            if usable is not None:
                mask = usable[y0:y1, x0:x1].astype(np.uint8) * 255
                if not mask.any():
                    continue
            c = cv2.goodFeaturesToTrack(
                np.ascontiguousarray(grey[y0:y1, x0:x1]),
                maxCorners=per_cell,
                qualityLevel=0.001,
                minDistance=7,
                mask=mask,
            )
            if c is not None:
                found.append(c.reshape(-1, 2) + np.array([x0, y0]))
    return np.concatenate(found) if found else np.zeros((0, 2))


def pair_motion(
    grey_a: np.ndarray,
    grey_b: np.ndarray,
    usable_a: np.ndarray | None,
    usable_b: np.ndarray | None,
    params: RotationParams,
) -> PairMotion:
    """Track corners of ``grey_a`` into ``grey_b`` and fit a homography and an F matrix."""
    uv_a = detect_corners(grey_a, usable_a, params)
    uv_b, ok = track_points(grey_a, grey_b, uv_a, TrackingParams(), usable_b)
    a, b = uv_a[ok], uv_b[ok]  # (N, 2) each
    if len(a) < params.min_tracks:
        return PairMotion(None, len(a), 0.0, float("inf"), float("inf"))
    h, h_in = cv2.findHomography(
        a, b, cv2.RANSAC, params.ransac_px, maxIters=2000, confidence=0.999
    )
    if h is None:
        return PairMotion(None, len(a), 0.0, float("inf"), float("inf"))
    h_in = h_in[:, 0].astype(bool)
    f_in = np.ones(len(a), dtype=bool)
    f, mask = cv2.findFundamentalMat(a, b, cv2.FM_RANSAC, params.ransac_px, 0.999)
    if f is not None and mask is not None and f.shape == (3, 3):
        f_in = mask[:, 0].astype(bool)
    f_in |= h_in  # a point a homography explains is epipolar-consistent too
    proj = cv2.perspectiveTransform(a[f_in].reshape(-1, 1, 2), h).reshape(-1, 2)
    residual = float(np.median(np.linalg.norm(proj - b[f_in], axis=1)))
    motion = float(np.median(np.linalg.norm(b[h_in] - a[h_in], axis=1))) if h_in.any() else 0.0
    return PairMotion(h, len(a), float(h_in.sum() / f_in.sum()), residual, motion)


def rotation_from_homography(homography: np.ndarray, intrinsics: np.ndarray) -> np.ndarray:
    """The rotation ``(3, 3)`` closest to ``K^-1 H K`` (scaled to determinant 1)."""
    k = intrinsics_matrix(intrinsics)
    m = np.linalg.inv(k) @ homography @ k  # (3, 3)
    m = m / np.cbrt(np.linalg.det(m))
    u, _, vt = np.linalg.svd(m)
    return u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt


def _non_rotation(homographies: list[np.ndarray], intrinsics: np.ndarray) -> float:
    """Summed distance of ``K^-1 H K`` (unit determinant) from its SO(3) projection."""
    k = intrinsics_matrix(intrinsics)
    k_inv = np.linalg.inv(k)
    total = 0.0
    for h in homographies:
        m = k_inv @ h @ k
        m = m / np.cbrt(np.linalg.det(m))
        total += float(np.linalg.norm(m - rotation_from_homography(h, intrinsics)))
    return total


def self_calibrate_focal(
    homographies: list[np.ndarray], intrinsics: np.ndarray, width: int, params: RotationParams
) -> float:
    """The focal (pixels) in ``fov_range_deg`` that makes the homographies most rotation-like."""
    low, high = params.fov_range_deg
    fovs = np.linspace(low, high, 141)
    focals = 0.5 * width / np.tan(np.radians(fovs) / 2)
    costs = [_non_rotation(homographies, np.r_[f, f, intrinsics[2:]]) for f in focals]
    best = int(np.argmin(costs))
    lo, hi = max(best - 1, 0), min(best + 1, len(focals) - 1)
    fine = np.linspace(focals[lo], focals[hi], 41)
    costs = [_non_rotation(homographies, np.r_[f, f, intrinsics[2:]]) for f in fine]
    return float(fine[int(np.argmin(costs))])


def estimate_rotations(
    frames: np.ndarray,
    usable: np.ndarray | None,
    intrinsics: np.ndarray,
    params: RotationParams | None = None,
    calibrate: bool = True,
) -> RotationEstimate:
    """Rotation-only camera model of ``frames (T, H, W, 3)`` (see the module docstring).

    ``usable (T, H, W)`` bool marks pixels off the hands; ``intrinsics (4,)`` is the focal prior.
    A pair whose homography fails or does not explain the motion breaks the chain: later frames
    are posed relative to the last posed frame only when the chain holds, others stay unposed.
    """
    params = params or RotationParams()
    t, _, w = frames.shape[:3]
    grey = grey_frames(frames)
    pairs = [
        pair_motion(
            grey[k - 1],
            grey[k],
            None if usable is None else usable[k - 1],
            None if usable is None else usable[k],
            params,
        )
        for k in range(1, t)
    ]
    explained = [p.rotation_explains(params) for p in pairs]
    good_h = [p.homography for p, e in zip(pairs, explained, strict=True) if e]
    intrinsics = np.asarray(intrinsics, dtype=np.float64)
    calibrated = False
    if calibrate and good_h:
        traces = [np.trace(rotation_from_homography(h, intrinsics)) for h in good_h]
        angles = np.degrees(np.arccos(np.clip((np.asarray(traces) - 1) / 2, -1, 1)))  # (P,)
        if float(angles.sum()) >= params.min_calibration_deg:
            f = self_calibrate_focal(good_h, intrinsics, w, params)
            intrinsics = np.r_[f, f * intrinsics[1] / intrinsics[0], intrinsics[2:]]
            calibrated = True
    rot = np.tile(np.eye(3), (t, 1, 1))  # (T, 3, 3)
    posed = np.zeros(t, dtype=bool)
    posed[0] = True
    last = 0  # last posed frame
    for k in range(1, t):
        pair, ok = pairs[k - 1], explained[k - 1] and last == k - 1
        if not ok and k - last <= params.max_bridge:
            # Bridge a failed pair: the homography from the last posed frame straight to k.
            pair = pair_motion(
                grey[last],
                grey[k],
                None if usable is None else usable[last],
                None if usable is None else usable[k],
                params,
            )
            ok = pair.rotation_explains(params)
        if not ok:
            continue
        rot[k] = rotation_from_homography(pair.homography, intrinsics) @ rot[last]
        posed[k] = True
        last = k
    return RotationEstimate(
        cam_from_cam0=rot,
        posed=posed,
        intrinsics=intrinsics,
        pairs=pairs,
        explained_fraction=float(np.mean(explained)) if explained else 1.0,
        focal_calibrated=calibrated,
    )
