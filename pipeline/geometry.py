"""Shared geometry: SE(3), quaternions, pinhole projection, Umeyama alignment, Plücker rays.

One convention for the whole project (docs/design.md, "Conventions"; ARCHITECTURE.md section 2):

- Camera axes are OpenCV's: x right, y down, z forward.
- Intrinsics are a 4-vector ``(fx, fy, cx, cy)`` in pixels of the stored resolution.
- Poses are ``world_from_cam`` 4x4 matrices (camera-to-world); a point in camera coordinates maps
  to world coordinates as ``points_world = R @ points_cam + t``.
- Quaternions are Hamilton, scalar first: ``(w, x, y, z)``.

Every stage that needs one of these calls the function here; nothing is copied into stages.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from egosim.schemas.invariants import se3_problems as se3_problems  # re-exported

FloatArray = np.ndarray


def intrinsics_matrix(intrinsics: FloatArray) -> FloatArray:
    """Return the 3x3 pinhole matrix ``K`` for ``intrinsics = (fx, fy, cx, cy)``."""
    fx, fy, cx, cy = (float(v) for v in np.asarray(intrinsics, dtype=np.float64).reshape(4))
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def intrinsics_from_fov(width: int, height: int, horizontal_fov_deg: float) -> FloatArray:
    """Intrinsics ``(fx, fy, cx, cy)`` of a centred pinhole with square pixels and the given FOV."""
    fx = 0.5 * width / np.tan(np.deg2rad(horizontal_fov_deg) / 2.0)
    return np.array([fx, fx, width / 2.0, height / 2.0])


def scale_intrinsics(intrinsics: FloatArray, sx: float, sy: float) -> FloatArray:
    """Intrinsics after resizing the image by ``sx`` horizontally and ``sy`` vertically.

    Uses the pixel-corner convention: pixel centres sit at integer + 0.5, so ``c' = c * s``.
    """
    fx, fy, cx, cy = np.asarray(intrinsics, dtype=np.float64)
    return np.array([fx * sx, fy * sy, cx * sx, cy * sy])


def crop_intrinsics(intrinsics: FloatArray, x0: float, y0: float) -> FloatArray:
    """Intrinsics after cropping an image so that its new origin is pixel ``(x0, y0)``."""
    fx, fy, cx, cy = np.asarray(intrinsics, dtype=np.float64)
    return np.array([fx, fy, cx - x0, cy - y0])


def make_se3(rotation: FloatArray, translation: FloatArray) -> FloatArray:
    """Stack ``R (..., 3, 3)`` and ``t (..., 3)`` into ``(..., 4, 4)`` homogeneous matrices."""
    rotation = np.asarray(rotation, dtype=np.float64)
    translation = np.asarray(translation, dtype=np.float64)
    out = np.zeros((*rotation.shape[:-2], 4, 4))
    out[..., :3, :3] = rotation
    out[..., :3, 3] = translation
    out[..., 3, 3] = 1.0
    return out


def invert_se3(transform: FloatArray) -> FloatArray:
    """Invert rigid transforms ``(..., 4, 4)`` exactly (transpose rotation, rotate translation)."""
    transform = np.asarray(transform, dtype=np.float64)
    rot_t = np.swapaxes(transform[..., :3, :3], -1, -2)  # (..., 3, 3)
    trans = -np.einsum("...ij,...j->...i", rot_t, transform[..., :3, 3])  # (..., 3)
    return make_se3(rot_t, trans)


def transform_points(transform: FloatArray, points: FloatArray) -> FloatArray:
    """Apply ``transform (4, 4)`` to ``points (..., 3)``; returns ``(..., 3)``."""
    transform = np.asarray(transform, dtype=np.float64)
    points = np.asarray(points, dtype=np.float64)
    return points @ transform[:3, :3].T + transform[:3, 3]


def project_points(points_cam: FloatArray, intrinsics: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Project camera-frame points ``(..., 3)`` to pixels.

    Returns ``(uv (..., 2), depth (...,))``. Points with ``depth <= 0`` get NaN pixels: callers
    decide what to do with what is behind the camera.
    """
    points_cam = np.asarray(points_cam, dtype=np.float64)
    fx, fy, cx, cy = np.asarray(intrinsics, dtype=np.float64)
    z = points_cam[..., 2]  # (...,)
    with np.errstate(divide="ignore", invalid="ignore"):
        safe_z = np.where(z > 0, z, np.nan)
        u = fx * points_cam[..., 0] / safe_z + cx
        v = fy * points_cam[..., 1] / safe_z + cy
    return np.stack([u, v], axis=-1), z


def project_world_points(
    points_world: FloatArray, world_from_cam: FloatArray, intrinsics: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Project world points ``(..., 3)`` through one camera; see :func:`project_points`."""
    points_cam = transform_points(invert_se3(world_from_cam), points_world)
    return project_points(points_cam, intrinsics)


def pixel_grid(height: int, width: int) -> FloatArray:
    """Pixel-centre coordinates ``(H, W, 2)`` as ``(u, v)`` with centres at integer + 0.5."""
    v, u = np.mgrid[0:height, 0:width].astype(np.float64) + 0.5
    return np.stack([u, v], axis=-1)


def unproject_depth(depth: FloatArray, intrinsics: FloatArray) -> FloatArray:
    """Lift a z-depth map ``(H, W)`` to camera-frame points ``(H, W, 3)`` at pixel centres."""
    depth = np.asarray(depth, dtype=np.float64)
    fx, fy, cx, cy = np.asarray(intrinsics, dtype=np.float64)
    uv = pixel_grid(*depth.shape)  # (H, W, 2)
    x = (uv[..., 0] - cx) / fx * depth
    y = (uv[..., 1] - cy) / fy * depth
    return np.stack([x, y, depth], axis=-1)


def look_at(eye: FloatArray, target: FloatArray, up: FloatArray = (0.0, 0.0, 1.0)) -> FloatArray:
    """``world_from_cam`` of a camera at ``eye`` looking at ``target`` (OpenCV axes).

    The camera's y axis (down in the image) points away from ``up``.
    """
    eye = np.asarray(eye, dtype=np.float64)
    forward = np.asarray(target, dtype=np.float64) - eye
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, np.asarray(up, dtype=np.float64))
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    rot = np.stack([right, down, forward], axis=1)  # columns are camera axes in world
    return make_se3(rot, eye)


def quat_from_matrix(rotation: FloatArray) -> FloatArray:
    """Rotation matrices ``(..., 3, 3)`` to unit quaternions ``(..., 4)`` in ``(w, x, y, z)``."""
    rotation = np.asarray(rotation, dtype=np.float64)
    flat = Rotation.from_matrix(rotation.reshape(-1, 3, 3)).as_quat(scalar_first=True)
    return flat.reshape((*rotation.shape[:-2], 4))


def xyzw_from_matrix(rotation: FloatArray) -> FloatArray:
    """Rotations ``(..., 3, 3)`` -> quaternions ``(..., 4)`` in ``(x, y, z, w)``; NaN stays NaN.

    Scalar last, as ROS, SciPy, AgiBot and LeRobot datasets store them.
    """
    rot = np.asarray(rotation, dtype=np.float64)
    ok = np.isfinite(rot).all(axis=(-2, -1))  # (...)
    out = np.full((*rot.shape[:-2], 4), np.nan)
    out[ok] = quat_from_matrix(rot[ok])[..., [1, 2, 3, 0]]
    return out


def matrix_from_quat(quat: FloatArray) -> FloatArray:
    """Quaternions ``(..., 4)`` in ``(w, x, y, z)`` (normalised first) to ``(..., 3, 3)``."""
    quat = np.asarray(quat, dtype=np.float64)
    flat = Rotation.from_quat(quat.reshape(-1, 4), scalar_first=True).as_matrix()
    return flat.reshape((*quat.shape[:-1], 3, 3))


def quat_align_hemisphere(quat: FloatArray) -> FloatArray:
    """Flip signs along a sequence ``(T, 4)`` so consecutive quaternions have a positive dot."""
    out = np.array(quat, dtype=np.float64, copy=True)
    for i in range(1, len(out)):
        if np.dot(out[i], out[i - 1]) < 0.0:
            out[i] = -out[i]
    return out


def slerp_rotations(times: FloatArray, rotations: FloatArray, query: FloatArray) -> FloatArray:
    """Spherically interpolate rotations ``(T, 3, 3)`` at ``times (T,)`` to ``query (Q,)``."""
    slerp = Slerp(np.asarray(times, dtype=np.float64), Rotation.from_matrix(rotations))
    return slerp(np.clip(query, times[0], times[-1])).as_matrix()


def rotation_angle_deg(rot_a: FloatArray, rot_b: FloatArray) -> FloatArray:
    """Angle in degrees of ``rot_a^T rot_b`` for rotations ``(..., 3, 3)``."""
    rel = np.swapaxes(np.asarray(rot_a), -1, -2) @ np.asarray(rot_b)
    cos = (np.trace(rel, axis1=-2, axis2=-1) - 1.0) / 2.0
    return np.rad2deg(np.arccos(np.clip(cos, -1.0, 1.0)))


def umeyama(
    src: FloatArray, dst: FloatArray, with_scale: bool = True
) -> tuple[float, FloatArray, FloatArray]:
    """Least-squares similarity ``dst ~ s R src + t`` for point sets ``(N, 3)`` (Umeyama 1991).

    Returns ``(s, R (3, 3), t (3,))``; ``s`` is 1 when ``with_scale`` is False.
    """
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3 or len(src) < 3:
        raise ValueError(f"umeyama needs two (N>=3, 3) arrays, got {src.shape} and {dst.shape}")
    mu_src, mu_dst = src.mean(0), dst.mean(0)
    src_c, dst_c = src - mu_src, dst - mu_dst
    cov = dst_c.T @ src_c / len(src)  # (3, 3)
    u, d, vt = np.linalg.svd(cov)
    sign = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        sign[2, 2] = -1.0
    rot = u @ sign @ vt
    var_src = (src_c**2).sum() / len(src)
    scale = float(np.trace(np.diag(d) @ sign) / var_src) if with_scale else 1.0
    trans = mu_dst - scale * rot @ mu_src
    return scale, rot, trans


def plucker_rays(
    intrinsics: np.ndarray, world_from_cam: np.ndarray, height: int, width: int
) -> np.ndarray:
    """Per-pixel Plücker coordinates (T, H, W, 6) = (d, c x d) with unit world direction d.

    intrinsics: (4,) or (T, 4) ``(fx, fy, cx, cy)``; world_from_cam: (T, 4, 4).
    ``d = normalise(R K^-1 [u, v, 1])`` at pixel centres, ``c`` the camera centre.
    """
    poses = np.asarray(world_from_cam, dtype=np.float64).reshape(-1, 4, 4)  # (T, 4, 4)
    k = np.asarray(intrinsics, dtype=np.float64).reshape(-1, 4)
    k = np.broadcast_to(k, (poses.shape[0], 4))  # (T, 4)
    uv1 = np.concatenate([pixel_grid(height, width), np.ones((height, width, 1))], axis=-1)
    rays = []
    for kt, pose in zip(k, poses, strict=True):
        d_cam = uv1 @ np.linalg.inv(intrinsics_matrix(kt)).T  # (H, W, 3)
        d = d_cam @ pose[:3, :3].T  # (H, W, 3) world directions
        d = d / np.linalg.norm(d, axis=-1, keepdims=True)
        m = np.cross(np.broadcast_to(pose[:3, 3], d.shape), d)  # (H, W, 3) moment c x d
        rays.append(np.concatenate([d, m], axis=-1))  # (H, W, 6)
    return np.stack(rays)


def camera_error(
    intrinsics: np.ndarray,
    world_from_cam_a: np.ndarray,
    world_from_cam_b: np.ndarray,
    height: int,
    width: int,
) -> float:
    """Cam-ERR: mean over frames and pixels of the L2 distance between Plücker embeddings.

    Both sequences use the same intrinsics; poses must be expressed in one world frame (align
    and scale them first when they come from separate reconstructions).
    """
    a = plucker_rays(intrinsics, world_from_cam_a, height, width)
    b = plucker_rays(intrinsics, world_from_cam_b, height, width)
    if a.shape != b.shape:
        raise ValueError(f"camera_error: {a.shape[0]} vs {b.shape[0]} frames")
    return float(np.linalg.norm(a - b, axis=-1).mean())


def project_world_points_torch(
    points_world: Any, cam_from_world: Any, intrinsics: FloatArray
) -> tuple[Any, Any, Any]:
    """Torch twin of :func:`project_world_points` for renderers, channel-first for speed.

    ``points_world (3, N)`` tensor (rows x, y, z: contiguous rows make the transform one small
    matmul), ``cam_from_world (4, 4)`` tensor on the same device and dtype. Same convention as
    :func:`project_points` (``u = fx x / z + cx``), folded into one ``K [R | t]`` product. Returns
    ``(u (N,), v (N,), depth (N,))``; points with ``depth <= 0`` get NaN pixels. torch is imported
    lazily so that this module stays light for numpy-only stages.
    """
    import torch

    k = torch.as_tensor(
        intrinsics_matrix(intrinsics), dtype=cam_from_world.dtype, device=cam_from_world.device
    )
    proj = k @ cam_from_world[:3]  # (3, 4) pixels from world
    homog = torch.addmm(proj[:, 3:], proj[:, :3], points_world)  # (3, N)
    z = homog[2]  # (N,) camera z, since K's last row is (0, 0, 1)
    safe_z = torch.where(z > 0, z, float("nan"))  # (N,)
    return homog[0] / safe_z, homog[1] / safe_z, z
