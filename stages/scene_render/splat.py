"""Z-buffered point splatting in torch (one code path on CPU and GPU) and the inpainting mask.

A point cloud ``(N, 3)`` in world metres with RGB colours is rendered through pinhole cameras
``world_from_cam (T, 4, 4)`` (OpenCV axes, intrinsics ``fx, fy, cx, cy``). Each point lands on the
pixel that contains its projection (pixel centres at integer + 0.5, so pixel ``floor(u), floor(v)``);
the nearest point per pixel wins. The z-test is one ``scatter_reduce(amin)`` over an int64 key
``float32_bits(depth) << 24 | point_index``: positive float32 depths order like their bit patterns,
so the key orders by depth first and breaks ties by index, and the winner's index comes back from
the low 24 bits (hence at most 2**24 points per cloud).

Near points cover more than one pixel: with ``max_splat_radius > 0`` and per-point world sizes
(``point_size``, the side of the pixel each point was unprojected from), a point whose projected
footprint ``f * size / depth`` exceeds one pixel is also written to the neighbouring pixels within
``radius = min(max_splat_radius, round((footprint - 1) / 2))`` (a square splat), which closes the
cracks that appear when the camera moves towards the surface.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from egosim.pipeline.geometry import invert_se3, project_points_torch, se3_problems

INDEX_BITS = 24  # low bits of the z-buffer key that hold the point index
MAX_POINTS = 1 << INDEX_BITS  # largest cloud the key can address
_EMPTY = torch.iinfo(torch.int64).max  # key of a pixel no point landed on


class SplatError(ValueError):
    """Inputs to the renderer are unusable (empty cloud, bad poses, shapes that disagree)."""


@dataclass(frozen=True)
class SplatResult:
    """What :func:`render_point_cloud` returns (numpy, on the host)."""

    rgb: np.ndarray  # (T, H, W, 3) uint8 colour of the nearest point; 0 where nothing landed
    visible: np.ndarray  # (T, H, W) uint8 1 = a scene point landed on the pixel, 0 = none
    depth: np.ndarray  # (T, H, W) float32 camera z of the nearest point in metres; 0 = none


def _check_inputs(
    points_world: np.ndarray,
    colours: np.ndarray,
    world_from_cam: np.ndarray,
    intrinsics: np.ndarray,
    height: int,
    width: int,
    point_size: np.ndarray | None,
) -> None:
    problems: list[str] = []
    if points_world.ndim != 2 or points_world.shape[1] != 3:
        problems.append(f"points_world must be (N, 3), got {points_world.shape}")
    elif len(points_world) == 0:
        problems.append("the point cloud is empty")
    elif len(points_world) >= MAX_POINTS:
        problems.append(f"at most {MAX_POINTS - 1} points, got {len(points_world)}")
    elif not np.all(np.isfinite(points_world)):
        problems.append("points_world contains NaN or infinite values")
    if colours.shape != points_world.shape:
        problems.append(f"colours shape {colours.shape} != points shape {points_world.shape}")
    if point_size is not None and point_size.shape != points_world.shape[:1]:
        problems.append(f"point_size shape {point_size.shape} != ({len(points_world)},)")
    if world_from_cam.ndim != 3 or world_from_cam.shape[1:] != (4, 4) or len(world_from_cam) < 1:
        problems.append(f"world_from_cam must be (T>=1, 4, 4), got {world_from_cam.shape}")
    else:
        problems += [f"world_from_cam: {p}" for p in se3_problems(world_from_cam)]
    k = np.asarray(intrinsics, dtype=np.float64)
    if k.shape != (4,) or not np.all(np.isfinite(k)) or k[0] <= 0 or k[1] <= 0:
        problems.append(f"intrinsics must be 4 finite values with fx, fy > 0, got {k.tolist()}")
    if height < 1 or width < 1:
        problems.append(f"image size must be positive, got {height}x{width}")
    if problems:
        raise SplatError("; ".join(problems))


def splat_frame(
    points_world: torch.Tensor,
    cam_from_world: torch.Tensor,
    intrinsics: np.ndarray,
    height: int,
    width: int,
    point_size: torch.Tensor | None = None,
    max_splat_radius: int = 0,
    near: float = 1e-3,
) -> torch.Tensor:
    """Z-buffer one frame; returns the winning keys ``(H*W,)`` int64 (``_EMPTY`` where none).

    ``points_world (N, 3)`` float32 and ``cam_from_world (4, 4)`` float32 share a device.
    Decode the keys with :func:`decode_keys`.
    """
    n = points_world.shape[0]
    device = points_world.device
    points_cam = points_world @ cam_from_world[:3, :3].T + cam_from_world[:3, 3]  # (N, 3)
    uv, z = project_points_torch(points_cam, intrinsics)  # (N, 2), (N,)
    front = z > near  # (N,)
    uv = torch.nan_to_num(uv, nan=-1.0, posinf=-1.0, neginf=-1.0).floor_()  # (N, 2) pixel
    # Clamp before the int cast so huge values near the camera plane cannot overflow.
    u = uv[:, 0].clamp_(-1, width).to(torch.int64)  # (N,)
    v = uv[:, 1].clamp_(-1, height).to(torch.int64)  # (N,)
    inside = front & (u >= 0) & (u < width) & (v >= 0) & (v < height)  # (N,)
    depth_bits = z.to(torch.float32).view(torch.int32).to(torch.int64)  # (N,) monotone in z > 0
    keys = (depth_bits << INDEX_BITS) | torch.arange(n, device=device, dtype=torch.int64)  # (N,)
    dump = height * width  # one extra slot collects every point that lands nowhere
    buffer = torch.full((dump + 1,), _EMPTY, dtype=torch.int64, device=device)
    pix = torch.where(inside, v * width + u, dump)  # (N,)
    buffer.scatter_reduce_(0, pix, keys, reduce="amin")
    if max_splat_radius > 0 and point_size is not None:
        fx = float(np.asarray(intrinsics, dtype=np.float64)[0])
        footprint = point_size * fx / z.clamp(min=near)  # (N,) pixels covered by the point
        radius = ((footprint - 1.0) * 0.5).round().clamp_(0, max_splat_radius).to(torch.int64)
        big = torch.nonzero(front & (radius > 0) & (u > -1) & (v > -1)).squeeze(1)  # (M,)
        if big.numel() > 0:
            u_b, v_b, r_b, k_b = u[big], v[big], radius[big], keys[big]  # (M,) each
            for dv in range(-max_splat_radius, max_splat_radius + 1):
                for du in range(-max_splat_radius, max_splat_radius + 1):
                    if du == 0 and dv == 0:
                        continue
                    uu, vv = u_b + du, v_b + dv  # (M,)
                    ok = (max(abs(du), abs(dv)) <= r_b) & (uu >= 0) & (uu < width)
                    ok &= (vv >= 0) & (vv < height)
                    buffer.scatter_reduce_(0, torch.where(ok, vv * width + uu, dump), k_b, "amin")
    return buffer[:dump]


def decode_keys(keys: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Split z-buffer keys ``(P,)`` into ``(hit (P,) bool, index (P,) int64, depth (P,) float32)``.

    ``index`` and ``depth`` are 0 where ``hit`` is False.
    """
    hit = keys != _EMPTY  # (P,)
    safe = torch.where(hit, keys, torch.zeros_like(keys))  # (P,)
    index = safe & (MAX_POINTS - 1)  # (P,)
    depth = (safe >> INDEX_BITS).to(torch.int32).view(torch.float32)  # (P,)
    return hit, index, depth


def render_point_cloud(
    points_world: np.ndarray,
    colours: np.ndarray,
    world_from_cam: np.ndarray,
    intrinsics: np.ndarray,
    height: int,
    width: int,
    point_size: np.ndarray | None = None,
    max_splat_radius: int = 0,
    near: float = 1e-3,
    device: str = "cpu",
) -> SplatResult:
    """Render a coloured cloud along a trajectory by z-buffered splatting.

    ``points_world (N, 3)`` metres, ``colours (N, 3)`` uint8 RGB, ``world_from_cam (T, 4, 4)``,
    ``intrinsics (fx, fy, cx, cy)``, ``point_size (N,)`` metres (needed only for splats wider
    than one pixel), ``device`` any torch device string ("cpu", "cuda", "cuda:1"). Points at or
    behind ``near`` metres of camera z are skipped. Raises :class:`SplatError` for an empty cloud,
    non-finite points, non-rigid or NaN poses and shapes that disagree.
    """
    points_world = np.asarray(points_world)
    colours = np.asarray(colours)
    world_from_cam = np.asarray(world_from_cam, dtype=np.float64)
    if point_size is not None:
        point_size = np.asarray(point_size, dtype=np.float32)
    _check_inputs(points_world, colours, world_from_cam, intrinsics, height, width, point_size)
    if max_splat_radius < 0:
        raise SplatError(f"max_splat_radius must be >= 0, got {max_splat_radius}")
    dev = torch.device(device)
    pts = torch.as_tensor(points_world, dtype=torch.float32, device=dev)  # (N, 3)
    rgb = torch.as_tensor(colours.astype(np.uint8), device=dev)  # (N, 3)
    size = None if point_size is None else torch.as_tensor(point_size, device=dev)  # (N,)
    cam_from_world = torch.as_tensor(invert_se3(world_from_cam), dtype=torch.float32, device=dev)
    t = len(world_from_cam)
    out_rgb = torch.zeros((t, height * width, 3), dtype=torch.uint8, device=dev)
    out_vis = torch.zeros((t, height * width), dtype=torch.uint8, device=dev)
    out_depth = torch.zeros((t, height * width), dtype=torch.float32, device=dev)
    for i in range(t):
        keys = splat_frame(
            pts, cam_from_world[i], intrinsics, height, width, size, max_splat_radius, near
        )  # (H*W,)
        hit, index, depth = decode_keys(keys)  # (H*W,) each
        out_rgb[i] = rgb[index] * hit[:, None]
        out_vis[i] = hit
        out_depth[i] = depth
    return SplatResult(
        rgb=out_rgb.reshape(t, height, width, 3).cpu().numpy(),
        visible=out_vis.reshape(t, height, width).cpu().numpy(),
        depth=out_depth.reshape(t, height, width).cpu().numpy(),
    )


def inpaint_mask_from_visible(visible: np.ndarray, dilate: int = 0) -> np.ndarray:
    """The model's inpainting mask from a visibility mask; the one place the polarity flips.

    Input ``visible (..., H, W)``: 1 = a scene point landed on the pixel (observed), 0 = none.
    Output ``(..., H, W)`` uint8: **1 = unobserved, the model must synthesise this pixel**,
    0 = the scene render is to be kept. This is the paper's "binary mask video that indicates the
    unobserved regions that require visual synthesis". ``dilate`` grows the synthesise region by
    that many pixels (a square neighbourhood), so thin seams around holes are regenerated too.
    """
    visible = np.asarray(visible)
    if visible.ndim < 2:
        raise SplatError(f"visible must be (..., H, W), got shape {visible.shape}")
    if dilate < 0:
        raise SplatError(f"dilate must be >= 0, got {dilate}")
    mask = (visible == 0).astype(np.uint8)  # (..., H, W)
    if dilate > 0:
        from scipy.ndimage import maximum_filter

        size = [1] * (mask.ndim - 2) + [2 * dilate + 1, 2 * dilate + 1]
        mask = maximum_filter(mask, size=size)
    return mask
