"""Pose the frames the SfM mapper missed by tracking the model's points into them (KLT + PnP).

The mapper exports, per registered frame, the pixels where it observes the model's 3D points.
Starting from posed frames, those pixels are tracked by OpenCV pyramidal Lucas-Kanade into an
unposed neighbour (forward-backward checked, off the hand mask), and the neighbour's pose is
solved by ``cv2.solvePnPRansac`` with the model's intrinsics, then refined on the inliers by
Levenberg-Marquardt. A newly posed frame passes its inlier tracks on to its own neighbours, so
the model's points are carried through fast rotations where two-view triangulation fails (as
long as the points stay in view). Frame 0 gets posed this way too when the mapper missed it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import cv2
import numpy as np

from egosim.pipeline.geometry import intrinsics_matrix
from egosim.schemas.depth_camera import POSED_BY_MAPPER, POSED_BY_PNP
from egosim.stages.common.klt import track_forward_backward

if TYPE_CHECKING:
    from egosim.stages.depth_camera.sfm import SfmResult

NOT_POSED = -1  # internal: nothing posed the frame yet (the schema's codes are 0..4)


@dataclass(frozen=True)
class TrackingParams:
    """Knobs of :func:`register_missing_frames`."""

    window: int = 21  # KLT window side in pixels
    levels: int = 4  # KLT pyramid levels above the full resolution
    max_fb_error_px: float = 1.0  # forward-backward tracking error above this drops a track
    ransac_px: float = 3.0  # PnP RANSAC inlier threshold in pixels
    min_inliers: int = 20  # fewer PnP inliers than this = the frame stays unposed
    min_inlier_ratio: float = 0.5  # fewer inliers than this fraction of tracks = unposed


@dataclass(frozen=True)
class TrackingResult:
    """Poses after PnP tracking; frames that could not be posed keep ``NOT_POSED``."""

    cam_from_world: np.ndarray  # (T, 4, 4) world-to-camera, identity where not posed
    posed_by: np.ndarray  # (T,) int8: POSED_BY_MAPPER, POSED_BY_PNP or NOT_POSED
    num_inliers: np.ndarray  # (T,) int PnP inliers of PnP-posed frames, 0 otherwise
    frame_points: dict[int, np.ndarray]  # frame -> (P, 3) world points observed or tracked there


def grey_frames(frames: np.ndarray) -> list[np.ndarray]:
    """``frames (T, H, W, 3)`` RGB uint8 as a list of ``(H, W)`` uint8 grey images."""
    return [cv2.cvtColor(np.ascontiguousarray(f), cv2.COLOR_RGB2GRAY) for f in frames]


def track_points(
    grey_a: np.ndarray,
    grey_b: np.ndarray,
    uv_a: np.ndarray,
    params: TrackingParams,
    usable_b: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Track ``uv_a (N, 2)`` pixels of ``grey_a`` into ``grey_b``; returns ``(uv_b, ok)``.

    ``ok (N,)`` is True where both directions converged, the forward-backward error is below
    ``max_fb_error_px``, and the point lands inside ``grey_b`` and on ``usable_b (H, W)``.
    Pixel coordinates follow OpenCV (pixel centres at integers); callers convert consistently.
    """
    n = len(uv_a)
    if n == 0:
        return np.zeros((0, 2)), np.zeros(0, dtype=bool)
    t = track_forward_backward(grey_a, grey_b, uv_a, params.window, params.levels)
    uv_b = t.uv_b.astype(np.float64)  # (N, 2)
    h, w = grey_b.shape
    ok = t.converged & (t.fb_px < params.max_fb_error_px)
    ok &= (uv_b[:, 0] >= 0) & (uv_b[:, 0] <= w - 1) & (uv_b[:, 1] >= 0) & (uv_b[:, 1] <= h - 1)
    if usable_b is not None and ok.any():
        iu = np.clip(np.round(uv_b[:, 0]).astype(int), 0, w - 1)
        iv = np.clip(np.round(uv_b[:, 1]).astype(int), 0, h - 1)
        ok &= usable_b[iv, iu]
    return uv_b, ok


def solve_pnp(
    points_world: np.ndarray,
    uv: np.ndarray,
    intrinsics: np.ndarray,
    guess_cam_from_world: np.ndarray,
    params: TrackingParams,
) -> tuple[np.ndarray | None, np.ndarray]:
    """``cam_from_world (4, 4)`` from ``points_world (N, 3)`` seen at ``uv (N, 2)``, or None.

    RANSAC (seeded by ``guess_cam_from_world``) then Levenberg-Marquardt refinement on the
    inliers. Returns the pose (None when too few inliers) and the inlier mask ``(N,)``.
    """
    n = len(uv)
    inlier_mask = np.zeros(n, dtype=bool)
    if n < max(params.min_inliers, 6):
        return None, inlier_mask
    k = intrinsics_matrix(intrinsics)
    rvec, _ = cv2.Rodrigues(guess_cam_from_world[:3, :3])
    tvec = guess_cam_from_world[:3, 3].reshape(3, 1).copy()
    obj = points_world.reshape(-1, 1, 3).astype(np.float64)
    img = uv.reshape(-1, 1, 2).astype(np.float64)
    ok, rvec, tvec, inliers = cv2.solvePnPRansac(
        obj,
        img,
        k,
        None,
        rvec=rvec.copy(),
        tvec=tvec,
        useExtrinsicGuess=True,
        iterationsCount=200,
        reprojectionError=params.ransac_px,
        confidence=0.999,
        flags=cv2.SOLVEPNP_ITERATIVE,
    )
    if not ok or inliers is None:
        return None, inlier_mask
    inlier_mask[inliers[:, 0]] = True
    if inlier_mask.sum() < params.min_inliers or inlier_mask.mean() < params.min_inlier_ratio:
        return None, inlier_mask
    rvec, tvec = cv2.solvePnPRefineLM(obj[inlier_mask], img[inlier_mask], k, None, rvec, tvec)
    rot, _ = cv2.Rodrigues(rvec)
    pose = np.eye(4)
    pose[:3, :3], pose[:3, 3] = rot, tvec[:, 0]
    # Re-check the inliers under the refined pose.
    proj, _ = cv2.projectPoints(obj, rvec, tvec, k, None)
    err = np.linalg.norm(proj.reshape(-1, 2) - uv, axis=1)  # (N,)
    inlier_mask = err < params.ransac_px
    if inlier_mask.sum() < params.min_inliers:
        return None, inlier_mask
    return pose, inlier_mask


def register_missing_frames(
    frames: np.ndarray,
    usable: np.ndarray | None,
    intrinsics: np.ndarray,
    cam_from_world: np.ndarray,
    registered: np.ndarray,
    points_xyz: np.ndarray,
    point_ids: np.ndarray,
    obs_frame: np.ndarray,
    obs_uv: np.ndarray,
    obs_point_id: np.ndarray,
    params: TrackingParams | None = None,
) -> TrackingResult:
    """Pose the frames ``registered (T,)`` is False for by PnP on tracked model points.

    ``frames (T, H, W, 3)`` uint8 RGB; ``usable (T, H, W)`` bool (False on hands) or None;
    ``cam_from_world (T, 4, 4)`` of the registered frames (others ignored); the model's points
    ``points_xyz (Q, 3)`` with ``point_ids (Q,)``; observations ``obs_frame (N,)``,
    ``obs_uv (N, 2)`` (COLMAP pixels: centre of the first pixel at 0.5), ``obs_point_id (N,)``.
    Unposed frames are visited outward from posed ones, each tracked from its posed neighbour
    with the most observations.
    """
    params = params or TrackingParams()
    t = len(frames)
    grey = grey_frames(frames)
    xyz_of = dict(zip(point_ids.tolist(), range(len(point_ids)), strict=True))
    posed_by = np.where(registered, POSED_BY_MAPPER, NOT_POSED).astype(np.int8)
    poses = np.where(registered[:, None, None], cam_from_world, np.eye(4))  # (T, 4, 4)
    num_inliers = np.zeros(t, dtype=int)
    # frame -> (uv (P, 2) OpenCV pixels, xyz (P, 3)) of the model points it observes
    obs: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    rows = np.array([xyz_of.get(int(i), -1) for i in obs_point_id], dtype=int)  # (N,)
    for k in np.flatnonzero(registered):
        sel = (obs_frame == k) & (rows >= 0)
        obs[int(k)] = (obs_uv[sel] - 0.5, points_xyz[rows[sel]])
    tried: set[tuple[int, int]] = set()
    progress = True
    while progress and (posed_by == NOT_POSED).any():
        progress = False
        for j in np.flatnonzero(posed_by == NOT_POSED):
            neighbours = [
                i
                for i in (j - 1, j + 1)
                if 0 <= i < t and posed_by[i] != NOT_POSED and (int(j), int(i)) not in tried
            ]
            neighbours.sort(key=lambda i: -len(obs.get(int(i), ((), ()))[0]))
            for i in neighbours:
                tried.add((int(j), int(i)))
                uv_i, xyz_i = obs[int(i)]
                uv_j, ok = track_points(
                    grey[i], grey[j], uv_i, params, None if usable is None else usable[j]
                )
                pose, inl = solve_pnp(xyz_i[ok], uv_j[ok] + 0.5, intrinsics, poses[i], params)
                if pose is None:
                    continue
                poses[j] = pose
                posed_by[j] = POSED_BY_PNP
                num_inliers[j] = int(inl.sum())
                obs[int(j)] = (uv_j[ok][inl], xyz_i[ok][inl])
                progress = True
                break
    return TrackingResult(
        cam_from_world=poses,
        posed_by=posed_by,
        num_inliers=num_inliers,
        frame_points={k: v[1] for k, v in obs.items()},
    )


def register_from_sfm(
    frames: np.ndarray, usable: np.ndarray | None, sfm: SfmResult, params: TrackingParams
) -> TrackingResult:
    """:func:`register_missing_frames` with the model of ``sfm`` (an :class:`SfmResult` spread
    to all ``frames (T, H, W, 3)``): its poses, registered frames, points and observations."""
    return register_missing_frames(
        frames,
        usable,
        sfm.intrinsics,
        sfm.cam_from_world,
        np.asarray(sfm.registered, dtype=bool),
        sfm.all_points3d,
        sfm.all_point_ids,
        sfm.obs_frame,
        sfm.obs_uv,
        sfm.obs_point_id,
        params,
    )
