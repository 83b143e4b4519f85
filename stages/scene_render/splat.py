"""Z-buffered point splatting in torch (one code path on CPU and GPU) and the inpainting mask.

A point cloud ``(N, 3)`` in world metres with RGB colours is rendered through pinhole cameras
``world_from_cam (T, 4, 4)`` (OpenCV axes, intrinsics ``fx, fy, cx, cy``). Each point lands on the
pixel that contains its projection (centres at integer + 0.5: pixel ``floor(u), floor(v)``);
the nearest point per pixel wins. The z-test is one ``scatter_reduce(amin)`` over an int64 key
``float32_bits(depth) << 24 | point_index``: positive float32 depths order like their bit patterns,
so the key orders by depth first and breaks ties by index, and the winner's index comes back from
the low 24 bits (hence at most 2**24 points per cloud).

Near points cover more than one pixel: with ``max_splat_radius > 0`` and per-point world sizes
(``point_size``, the side of the pixel each point was unprojected from), a second pass splats
every point whose footprint ``fx * size / depth`` is about a pixel or more over a square of
radius ``min(max_splat_radius, ceil((footprint - 0.9) / 2))``, and pixels that the one-pixel pass
left empty take the nearest of those: the cracks that appear when the camera moves towards the
surface close, while pixels with a direct hit keep it.

Cracks that remain (the camera much closer than frame 0, beyond the widest splat, or a surface
seen more obliquely than from frame 0) are closed in image space by :func:`close_cracks`: every
hole of at most ``max_crack_px`` pixels that does not touch the image border, and every gap of at
most ``max_crack_width`` pixels between visible pixels, takes the colour of its surround (OpenCV
Telea inpainting) and the farther depth around it, and counts as visible. Larger holes
(disocclusions, the unseen world beyond frame 0) stay empty for the model to synthesise.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import torch

# The model's inpainting mask (1 = synthesise) from ``visible`` lives in pipeline so that the
# exporters share it; re-exported here, where it was first defined.
from egosim.pipeline.export.pack_rows import (
    inpaint_mask_from_visible as inpaint_mask_from_visible,
)
from egosim.pipeline.geometry import invert_se3, project_world_points_torch, se3_problems

INDEX_BITS = 24  # low bits of the z-buffer key that hold the point index
MAX_POINTS = 1 << INDEX_BITS  # largest cloud the key can address
EMPTY_KEY = torch.iinfo(torch.int64).max  # key of a pixel no point landed on


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
    if height < 1 or width < 1 or height * width >= MAX_POINTS:
        problems.append(f"image size must be positive and below 2**24 pixels, got {height}x{width}")
    if problems:
        raise SplatError("; ".join(problems))


@dataclass(frozen=True)
class DeviceCloud:
    """A cloud laid out for fast splatting on one device (see :func:`to_device_cloud`)."""

    points: torch.Tensor  # (3, N) float32 world metres, channel-first
    colours: torch.Tensor  # (N,) int32: RGBA bytes packed, A = 0, one gather per pixel
    index: torch.Tensor  # (N,) int64 0..N-1, the low bits of every z-buffer key
    size: torch.Tensor | None  # (N,) float32 world size of each point in metres, or None


def to_device_cloud(
    points_world: np.ndarray,
    colours: np.ndarray,
    point_size: np.ndarray | None = None,
    device: str = "cpu",
) -> DeviceCloud:
    """Move a cloud ``(N, 3)`` + colours ``(N, 3)`` uint8 (+ sizes ``(N,)``) to ``device``."""
    dev = torch.device(device)
    n = len(points_world)
    rgba = np.zeros((n, 4), dtype=np.uint8)  # (N, 4)
    rgba[:, :3] = colours
    return DeviceCloud(
        points=torch.as_tensor(np.ascontiguousarray(points_world.T), dtype=torch.float32).to(dev),
        colours=torch.as_tensor(rgba.view(np.int32).reshape(n)).to(dev),  # (N,)
        index=torch.arange(n, dtype=torch.int64, device=dev),
        size=None if point_size is None else torch.tensor(point_size, dtype=torch.float32).to(dev),
    )


SEE_THROUGH_MARGIN = 0.05  # relative depth gap beyond which a wide splat hides a direct hit


def splat_frame(
    cloud: DeviceCloud,
    cam_from_world: torch.Tensor,
    intrinsics: np.ndarray,
    height: int,
    width: int,
    max_splat_radius: int = 0,
    near: float = 1e-3,
) -> torch.Tensor:
    """Z-buffer one frame; returns the winning keys ``(H*W,)`` int64 (``EMPTY_KEY`` where none).

    ``cam_from_world (4, 4)`` float32 on the cloud's device. Decode with :func:`decode_keys`.
    """
    u, v, z = project_world_points_torch(cloud.points, cam_from_world, intrinsics)  # (N,) each
    # NaN (behind the camera) fails every comparison, so it is never inside.
    inside = (z > near) & (u >= 0) & (u < width) & (v >= 0) & (v < height)  # (N,)
    u, v = u.floor(), v.floor()  # (N,) pixel column and row, float
    dump = height * width  # one extra slot collects every point that lands nowhere
    # float32 holds every pixel index exactly (H*W < 2**24 is checked by the caller).
    pix = torch.where(inside, v * width + u, float(dump)).to(torch.int64)  # (N,)
    depth_bits = z.view(torch.int32).to(torch.int64)  # (N,) monotone in z for z > 0
    keys = (depth_bits << INDEX_BITS) | cloud.index  # (N,)
    buffer = torch.full((dump + 1,), EMPTY_KEY, dtype=torch.int64, device=keys.device)
    buffer.scatter_reduce_(0, pix, keys, reduce="amin")
    if max_splat_radius > 0 and cloud.size is not None:
        _splat_wide(
            buffer, cloud.size, u, v, z, keys, intrinsics, width, height, max_splat_radius, near
        )
    return buffer[:dump]


def _splat_wide(
    buffer: torch.Tensor,
    size: torch.Tensor,
    u: torch.Tensor,
    v: torch.Tensor,
    z: torch.Tensor,
    keys: torch.Tensor,
    intrinsics: np.ndarray,
    width: int,
    height: int,
    max_radius: int,
    near: float,
) -> None:
    """Fill pixels that the one-pixel pass left empty (or saw through) with wider splats.

    A point's footprint is ``f = fx * size / z`` pixels; it covers the square of radius
    ``ceil((f - 0.9) / 2)`` (capped at ``max_radius``): radius 1 as soon as the camera is about
    as close as the source camera was, where the one-pixel pass leaves cracks. Only pixels with
    no direct hit take a wide splat, so direct hits keep their exact colour; among the wide
    candidates the z-test still picks the nearest. A direct hit more than
    ``SEE_THROUGH_MARGIN`` (relative) behind the nearest wide splat on its pixel is replaced by
    it: that hit is a farther surface seen through a crack of the nearer one.
    """
    fx = float(np.asarray(intrinsics, dtype=np.float64)[0])
    footprint = size * fx / z.clamp(min=near)  # (N,) pixels covered by each point
    radius = ((footprint - 0.9) * 0.5).ceil().clamp(0, max_radius)  # (N,) float
    near_side = (z > near) & (radius > 0) & (u >= -max_radius) & (u < width + max_radius)
    near_side &= (v >= -max_radius) & (v < height + max_radius)
    big = torch.nonzero(near_side).squeeze(1)  # (M,)
    if big.numel() == 0:
        return
    u_b = u[big].to(torch.int64)  # (M,)
    v_b = v[big].to(torch.int64)  # (M,)
    r_b, k_b = radius[big].to(torch.int64), keys[big]  # (M,) each
    dump = height * width
    wide = torch.full_like(buffer, EMPTY_KEY)  # (H*W+1,)
    for ring in range(1, max_radius + 1):
        # Ring k (the offsets at Chebyshev distance k) only needs the points of radius >= k.
        keep = r_b >= ring
        if ring > 1:
            u_b, v_b, r_b, k_b = u_b[keep], v_b[keep], r_b[keep], k_b[keep]  # (M_k,)
        if u_b.numel() == 0:
            break
        for dv in range(-ring, ring + 1):
            for du in range(-ring, ring + 1):
                if max(abs(du), abs(dv)) != ring:
                    continue
                uu, vv = u_b + du, v_b + dv  # (M_k,)
                ok = (uu >= 0) & (uu < width) & (vv >= 0) & (vv < height)
                wide.scatter_reduce_(0, torch.where(ok, vv * width + uu, dump), k_b, "amin")
    empty = buffer == EMPTY_KEY  # (H*W+1,)
    # A direct hit well behind a wide splat is a farther surface seen through a crack of a
    # nearer one: the nearer surface covers the pixel (see-through removal).
    _, _, hit_depth = decode_keys(buffer)  # (H*W+1,)
    wide_hit, _, wide_depth = decode_keys(wide)  # (H*W+1,)
    see_through = ~empty & wide_hit & (wide_depth < hit_depth * (1.0 - SEE_THROUGH_MARGIN))
    buffer.copy_(torch.where(empty | see_through, wide, buffer))


def decode_keys(keys: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Split z-buffer keys ``(P,)`` into ``(hit (P,) bool, index (P,) int64, depth (P,) float32)``.

    ``index`` and ``depth`` are 0 where ``hit`` is False.
    """
    hit = keys != EMPTY_KEY  # (P,)
    safe = torch.where(hit, keys, 0)  # (P,)
    index = safe & (MAX_POINTS - 1)  # (P,)
    depth = (safe >> INDEX_BITS).to(torch.int32).view(torch.float32)  # (P,)
    return hit, index, depth


def shade(
    cloud: DeviceCloud, keys: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """One z-buffered frame's ``(rgb (P, 3) uint8, hit (P,) bool, depth (P,) float32)``."""
    hit, index, depth = decode_keys(keys)  # (P,) each
    packed = cloud.colours.index_select(0, index)  # (P,) int32 RGBA
    packed = torch.where(hit, packed, 0)  # (P,) black where nothing landed
    rgb = packed.view(torch.uint8).view(-1, 4)[:, :3]  # (P, 3)
    return rgb, hit, depth


def close_cracks(
    rgb: np.ndarray,
    visible: np.ndarray,
    depth: np.ndarray,
    max_crack_px: int,
    max_crack_width: int = 0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Fill the cracks of one rendered frame; returns new ``(rgb, visible, depth)``.

    ``rgb (H, W, 3)`` uint8, ``visible (H, W)`` uint8 1 = a point landed, ``depth (H, W)``
    float32. A crack pixel is invisible and either in a hole (4-connected invisible pixels) of at
    most ``max_crack_px`` pixels that does not touch the image border, or in a gap of at most
    ``max_crack_width`` pixels between visible pixels (morphological closing of ``visible``; it
    catches the connected grid of cracks that a surface magnified beyond the widest splat
    leaves). Its colour is inpainted from the pixels around it (``cv2.INPAINT_TELEA``), its depth
    is the largest depth among its visible neighbours (the farther surface, so a crack never pulls
    a foreground edge outward) and it becomes visible.
    """
    holes = (visible == 0).astype(np.uint8)  # (H, W)
    if (max_crack_px < 1 and max_crack_width < 1) or not holes.any():
        return rgb, visible, depth
    crack = np.zeros(holes.shape, bool)  # (H, W)
    if max_crack_px > 0:
        _, labels, stats, _ = cv2.connectedComponentsWithStats(holes, connectivity=4)
        x, y, w, h, area = (stats[:, i] for i in range(5))  # (components,) each
        width, height = holes.shape[1], holes.shape[0]
        inside = (x > 0) & (y > 0) & (x + w < width) & (y + h < height)  # (components,)
        small = (area <= max_crack_px) & inside
        small[0] = False  # label 0 is the visible pixels
        crack |= small[labels]
    if max_crack_width > 0:
        side = 2 * ((max_crack_width + 1) // 2) + 1  # closes gaps up to side - 1 pixels wide
        kernel = np.ones((side, side), np.uint8)
        closed = cv2.morphologyEx(visible.astype(np.uint8), cv2.MORPH_CLOSE, kernel)  # (H, W)
        crack |= (closed > 0) & (holes > 0)
    if not crack.any():
        return rgb, visible, depth
    filled = cv2.inpaint(np.ascontiguousarray(rgb), crack.astype(np.uint8), 2, cv2.INPAINT_TELEA)
    grown = np.where(visible > 0, depth, 0).astype(np.float32)  # (H, W)
    for _ in range(max(4, int(np.ceil(np.sqrt(max_crack_px))), max_crack_width)):
        if not (crack & (grown <= 0)).any():  # spread the farther neighbour inward
            break
        grown = np.where(grown > 0, grown, cv2.dilate(grown, np.ones((3, 3), np.uint8)))
    return (
        np.where(crack[..., None], filled, rgb),
        np.where(crack, np.uint8(1), visible).astype(np.uint8),
        np.where(crack, grown, depth).astype(np.float32),
    )


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
    max_crack_px: int = 0,
    max_crack_width: int = 0,
) -> SplatResult:
    """Render a coloured cloud along a trajectory by z-buffered splatting.

    ``points_world (N, 3)`` metres, ``colours (N, 3)`` uint8 RGB, ``world_from_cam (T, 4, 4)``,
    ``intrinsics (fx, fy, cx, cy)``, ``point_size (N,)`` metres (needed only for splats wider
    than one pixel), ``device`` any torch device string ("cpu", "cuda", "cuda:1"). Points at or
    behind ``near`` metres of camera z are skipped; holes of at most ``max_crack_px`` pixels
    inside the render and gaps up to ``max_crack_width`` pixels wide are closed by
    :func:`close_cracks` (0 = off). Raises :class:`SplatError`
    for an empty cloud, non-finite points, non-rigid or NaN poses and shapes that disagree.
    """
    points_world = np.asarray(points_world)
    colours = np.asarray(colours)
    world_from_cam = np.asarray(world_from_cam, dtype=np.float64)
    if point_size is not None:
        point_size = np.asarray(point_size, dtype=np.float32)
    _check_inputs(points_world, colours, world_from_cam, intrinsics, height, width, point_size)
    if max_splat_radius < 0:
        raise SplatError(f"max_splat_radius must be >= 0, got {max_splat_radius}")
    cloud = to_device_cloud(points_world, colours, point_size, device)
    dev = cloud.points.device
    cam_from_world = torch.as_tensor(invert_se3(world_from_cam), dtype=torch.float32, device=dev)
    t = len(world_from_cam)
    out_rgb = torch.zeros((t, height * width, 3), dtype=torch.uint8, device=dev)
    out_vis = torch.zeros((t, height * width), dtype=torch.uint8, device=dev)
    out_depth = torch.zeros((t, height * width), dtype=torch.float32, device=dev)
    for i in range(t):
        keys = splat_frame(
            cloud, cam_from_world[i], intrinsics, height, width, max_splat_radius, near
        )
        out_rgb[i], out_vis[i], out_depth[i] = shade(cloud, keys)  # (H*W, 3), (H*W,), (H*W,)
    rgb = out_rgb.reshape(t, height, width, 3).cpu().numpy()
    visible = out_vis.reshape(t, height, width).cpu().numpy()
    depth = out_depth.reshape(t, height, width).cpu().numpy()
    if max_crack_px > 0 or max_crack_width > 0:
        for i in range(t):
            rgb[i], visible[i], depth[i] = close_cracks(
                rgb[i], visible[i], depth[i], max_crack_px, max_crack_width
            )
    return SplatResult(rgb=rgb, visible=visible, depth=depth)
