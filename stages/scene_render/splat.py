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

A cloud unprojected from one frame's depth grid (a ``scene_cloud`` row: one point per pixel of
its source frame) is also a surface: with ``mesh_max_step > 0`` and that frame's pose
(``mesh_from_cam``), :func:`grid_quads` recovers the grid (each point's pixel in the source
frame) and links every 2x2 block of neighbouring points into a quad unless its inverse depths
differ by more than ``mesh_max_step`` (relative: a tear, an occlusion edge). Each frame, the
quads' two triangles are rasterised. ``mesh_mode`` "surface" (:func:`surface_frame`): the
nearest triangle covers the pixel with the perspective-correct blend of its three corners'
colours, and the splats count only where no quad lands; "fill" (:func:`_fill_from_mesh`):
only pixels that every splat left empty take the nearest triangle's depth and its nearest
corner's colour. Points split apart by the camera's motion (a surface seen closer or less
obliquely than from the source frame, or two neighbouring pixels of the source frame whose
estimated depths differ by a few per cent) no longer leave holes, and a magnified surface is
drawn smooth instead of in blocks of one point's colour; torn quads still leave holes
(disocclusions).

Cracks that remain (the camera much closer than frame 0, beyond the widest splat, or a surface
seen more obliquely than from frame 0) are closed in image space by :func:`close_cracks`: every
hole of at most ``max_crack_px`` pixels that does not touch the image border, and every gap of at
most ``max_crack_width`` pixels between visible pixels, takes the colour of its surround (OpenCV
Telea inpainting) and the farther depth around it, and counts as visible. Larger holes
(disocclusions, the unseen world beyond frame 0) stay empty for the model to synthesise.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import cv2
import numpy as np
import torch

# The model's inpainting mask (1 = synthesise) from ``visible`` lives in pipeline so that the
# exporters share it; re-exported here, where it was first defined.
from egosim.pipeline.export.pack_rows import (
    inpaint_mask_from_visible as inpaint_mask_from_visible,
)
from egosim.pipeline.geometry import (
    invert_se3,
    project_world_points,
    project_world_points_torch,
    se3_problems,
)

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
    # surface quads linked from the cloud's depth grid (:func:`grid_quads`); 0 = splats only
    # (no mesh_from_cam, mesh_max_step 0, or the grid not recovered from mesh_from_cam)
    num_quads: int = 0


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
    quads: torch.Tensor | None = None  # (Q, 4) int64 corner points of surface quads, or None


def to_device_cloud(
    points_world: np.ndarray,
    colours: np.ndarray,
    point_size: np.ndarray | None = None,
    device: str = "cpu",
    quads: np.ndarray | None = None,
) -> DeviceCloud:
    """Move a cloud ``(N, 3)`` + colours ``(N, 3)`` uint8 (+ sizes ``(N,)``, + surface quads
    ``(Q, 4)`` from :func:`grid_quads`) to ``device``."""
    dev = torch.device(device)
    n = len(points_world)
    rgba = np.zeros((n, 4), dtype=np.uint8)  # (N, 4)
    rgba[:, :3] = colours
    return DeviceCloud(
        points=torch.as_tensor(np.ascontiguousarray(points_world.T), dtype=torch.float32).to(dev),
        colours=torch.as_tensor(rgba.view(np.int32).reshape(n)).to(dev),  # (N,)
        index=torch.arange(n, dtype=torch.int64, device=dev),
        size=None if point_size is None else torch.tensor(point_size, dtype=torch.float32).to(dev),
        quads=None if quads is None else torch.as_tensor(quads, dtype=torch.int64).to(dev),
    )


SEE_THROUGH_MARGIN = 0.05  # relative depth gap beyond which a wide splat hides a direct hit
GRID_TOLERANCE_PX = 0.02  # a point lies on its source pixel's centre when within this (float32)
MESH_MAX_QUAD_PX = 32  # default: a quad wider or taller than this in a frame is not drawn
MESH_MODES = ("fill", "surface")  # quads fill only what splats miss / are the surface itself
MESH_MAX_CANDIDATES = 1 << 24  # pixel-quad pairs tested per frame at most (the widest dropped)


def splat_frame(
    cloud: DeviceCloud,
    cam_from_world: torch.Tensor,
    intrinsics: np.ndarray,
    height: int,
    width: int,
    max_splat_radius: int = 0,
    near: float = 1e-3,
    mesh_max_px: float = MESH_MAX_QUAD_PX,
) -> torch.Tensor:
    """Z-buffer one frame; returns the winning keys ``(H*W,)`` int64 (``EMPTY_KEY`` where none).

    ``cam_from_world (4, 4)`` float32 on the cloud's device. Decode with :func:`decode_keys`.
    The cloud's quads (if any) fill what the splats left empty, those at most ``mesh_max_px``
    across in this frame.
    """
    u, v, z = project_world_points_torch(cloud.points, cam_from_world, intrinsics)  # (N,) each
    # NaN (behind the camera) fails every comparison, so it is never inside.
    inside = (z > near) & (u >= 0) & (u < width) & (v >= 0) & (v < height)  # (N,)
    u_exact, v_exact = u, v  # (N,) projections before flooring (the mesh pass needs them)
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
    if cloud.quads is not None and cloud.quads.numel() > 0:
        _fill_from_mesh(
            buffer, cloud.quads, u_exact, v_exact, z, cloud.index, width, height, near, mesh_max_px
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


def grid_quads(
    points_world: np.ndarray,
    world_from_cam: np.ndarray,
    intrinsics: np.ndarray,
    height: int,
    width: int,
    max_step: float,
) -> np.ndarray:
    """Surface quads ``(Q, 4)`` int64 of a cloud unprojected from one frame's depth grid.

    ``points_world (N, 3)``, the source frame's ``world_from_cam (4, 4)`` and ``intrinsics
    (fx, fy, cx, cy)``, its size ``height x width``. A point is on the grid when its projection
    into the source frame lies within ``GRID_TOLERANCE_PX`` of a pixel centre (unprojected pixels
    do; points from elsewhere, e.g. a fused state, almost never). Every 2x2 block of grid pixels
    whose four points exist gives a quad ``(top-left, top-right, bottom-left, bottom-right)``
    unless ``max(1/z) / min(1/z) - 1`` over its corners (source-frame depth ``z``) exceeds
    ``max_step``: the surface is torn there. Returns ``(0, 4)`` when nothing qualifies.
    """
    uv, z = project_world_points(points_world, world_from_cam, intrinsics)  # (N, 2), (N,)
    u, v = np.nan_to_num(uv[:, 0], nan=-1.0), np.nan_to_num(uv[:, 1], nan=-1.0)  # (N,) each
    col, row = np.floor(u), np.floor(v)  # (N,) each
    on = (z > 0) & (col >= 0) & (col < width) & (row >= 0) & (row < height)
    on &= (np.abs(u - col - 0.5) <= GRID_TOLERANCE_PX) & (
        np.abs(v - row - 0.5) <= GRID_TOLERANCE_PX
    )
    grid = np.full((height, width), -1, np.int64)  # (H, W) point index per source pixel
    grid[row[on].astype(np.int64), col[on].astype(np.int64)] = np.flatnonzero(on)
    corners = np.stack([grid[:-1, :-1], grid[:-1, 1:], grid[1:, :-1], grid[1:, 1:]], -1)
    corners = corners[(corners >= 0).all(-1)]  # (Q, 4)
    inv = 1.0 / np.where(z > 0, z, 1.0)  # (N,)
    corner_inv = inv[corners]  # (Q, 4)
    step = corner_inv.max(1) / corner_inv.min(1) - 1.0  # (Q,)
    return np.ascontiguousarray(corners[step <= max_step])


def _quad_candidates(
    quads: torch.Tensor,
    u: torch.Tensor,
    v: torch.Tensor,
    z: torch.Tensor,
    width: int,
    height: int,
    near: float,
    max_px: float,
    buffer: torch.Tensor | None = None,
) -> tuple[torch.Tensor, ...] | None:
    """Pixel centres each quad may cover: ``(q (M, 4), uq, vq, zq (M, 4), owner, px, py (C,))``.

    Quads with a corner at or behind ``near`` or over ``max_px`` pixels across are skipped, and
    the widest ones beyond ``MESH_MAX_CANDIDATES`` pairs in all; with ``buffer`` (z-buffer keys)
    only pixels still empty there are returned. None: no candidate.
    """
    zq = z[quads]  # (Q, 4)
    front = torch.nonzero((zq > near).all(1)).squeeze(1)
    if front.numel() == 0:
        return None
    q = quads[front]  # (M, 4)
    uq, vq, zq = u[q], v[q], zq[front]  # (M, 4) each
    lo_u, hi_u = uq.min(1).values, uq.max(1).values  # (M,)
    lo_v, hi_v = vq.min(1).values, vq.max(1).values  # (M,)
    x0 = (lo_u - 0.5).ceil().clamp(min=0)  # first pixel column whose centre may be inside
    x1 = (hi_u - 0.5).floor().clamp(max=width - 1)
    y0 = (lo_v - 0.5).ceil().clamp(min=0)
    y1 = (hi_v - 0.5).floor().clamp(max=height - 1)
    keep = (x1 >= x0) & (y1 >= y0)
    keep &= (hi_u - lo_u <= max_px) & (hi_v - lo_v <= max_px)
    sel = torch.nonzero(keep).squeeze(1)
    if sel.numel() == 0:
        return None
    q, uq, vq, zq = q[sel], uq[sel], vq[sel], zq[sel]  # (M', 4) each
    x0, y0 = x0[sel].to(torch.int64), y0[sel].to(torch.int64)  # (M',)
    x1, y1 = x1[sel].to(torch.int64), y1[sel].to(torch.int64)  # (M',)
    if buffer is not None:
        # Only quads whose box holds an empty pixel can change anything (summed-area table).
        empty = (buffer[: height * width] == EMPTY_KEY).view(height, width).to(torch.int32)
        table = torch.nn.functional.pad(empty.cumsum(0).cumsum(1), (1, 0, 1, 0))  # (H+1, W+1)
        holes = table[y1 + 1, x1 + 1] - table[y0, x1 + 1] - table[y1 + 1, x0] + table[y0, x0]
        sel = torch.nonzero(holes > 0).squeeze(1)
        if sel.numel() == 0:
            return None
        q, uq, vq, zq = q[sel], uq[sel], vq[sel], zq[sel]  # (M'', 4) each
        x0, y0, x1, y1 = x0[sel], y0[sel], x1[sel], y1[sel]  # (M'',) each
    nx, ny = x1 - x0 + 1, y1 - y0 + 1  # (M'',) box size in pixels
    counts = nx * ny  # (M'',) candidate pixel centres per quad
    if int(counts.sum()) > MESH_MAX_CANDIDATES:  # memory bound: the smallest quads first
        order = torch.argsort(counts)
        fits = order[counts[order].cumsum(0) <= MESH_MAX_CANDIDATES]
        q, uq, vq, zq = q[fits], uq[fits], vq[fits], zq[fits]
        x0, y0, nx, ny, counts = x0[fits], y0[fits], nx[fits], ny[fits], counts[fits]
    owner = torch.repeat_interleave(torch.arange(len(q), device=q.device), counts)  # (C,)
    local = torch.arange(len(owner), device=q.device) - (counts.cumsum(0) - counts)[owner]
    px = x0[owner] + local % nx[owner]  # (C,) pixel column
    py = y0[owner] + local // nx[owner]  # (C,) pixel row
    if buffer is not None:
        todo = torch.nonzero(buffer[py * width + px] == EMPTY_KEY).squeeze(1)  # empty pixels
        owner, px, py = owner[todo], px[todo], py[todo]  # (C',) each
    return q, uq, vq, zq, owner, px, py


TRIANGLES = ((0, 2, 1), (1, 2, 3))  # a quad's two triangles: corners (tl, bl, tr), (tr, bl, br)


def _triangle_hits(
    uq: torch.Tensor,
    vq: torch.Tensor,
    zq: torch.Tensor,
    owner: torch.Tensor,
    px: torch.Tensor,
    py: torch.Tensor,
    corners: tuple[int, int, int],
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Where each candidate pixel centre lies in one triangle of its quad: ``(inside (C,) bool,
    depth (C,), weights (C, 3))``, screen-space barycentric weights of ``corners``; ``1/z`` is
    linear in the image for a planar triangle, so the depth is exact."""
    a, b, c = corners
    pu, pv = px.to(uq.dtype) + 0.5, py.to(uq.dtype) + 0.5  # (C,) pixel centres
    ua, ub, uc = uq[owner, a], uq[owner, b], uq[owner, c]  # (C,) each
    va, vb, vc = vq[owner, a], vq[owner, b], vq[owner, c]
    den = (vb - vc) * (ua - uc) + (uc - ub) * (va - vc)  # (C,) twice the signed area
    safe = torch.where(den.abs() > 1e-12, den, 1.0)
    wa = ((vb - vc) * (pu - uc) + (uc - ub) * (pv - vc)) / safe  # (C,) barycentric weights
    wb = ((vc - va) * (pu - uc) + (ua - uc) * (pv - vc)) / safe
    wc = 1.0 - wa - wb
    inside = (den.abs() > 1e-12) & (wa >= -1e-6) & (wb >= -1e-6) & (wc >= -1e-6)
    inv = wa / zq[owner, a] + wb / zq[owner, b] + wc / zq[owner, c]  # (C,) 1/z
    inside &= inv > 0
    depth = 1.0 / torch.where(inside, inv, 1.0)  # (C,)
    return inside, depth, torch.stack([wa, wb, wc], 1)


def _fill_from_mesh(
    buffer: torch.Tensor,
    quads: torch.Tensor,
    u: torch.Tensor,
    v: torch.Tensor,
    z: torch.Tensor,
    index: torch.Tensor,
    width: int,
    height: int,
    near: float,
    max_px: float = MESH_MAX_QUAD_PX,
) -> None:
    """Fill pixels no splat reached with the nearest surface quad (see :func:`grid_quads`).

    ``u, v (N,)`` exact projections of the points, ``z (N,)`` their camera depth. Each quad is
    two triangles (top-left, bottom-left, top-right) and (top-right, bottom-left, bottom-right);
    a pixel whose centre lies in one takes the depth of the triangle there and the index of its
    corner of largest barycentric weight, and the z-test picks the nearest triangle. Quads with
    a corner at or behind ``near``, or over ``max_px`` pixels across (a sheet stretched over a
    disocclusion), are skipped. Only empty pixels of ``buffer`` change.
    """
    cand = _quad_candidates(quads, u, v, z, width, height, near, max_px, buffer)
    if cand is None:
        return
    q, uq, vq, zq, owner, px, py = cand
    dump = height * width
    mesh = torch.full_like(buffer, EMPTY_KEY)  # (H*W+1,)
    for corners in TRIANGLES:
        inside, depth, weights = _triangle_hits(uq, vq, zq, owner, px, py, corners)
        corner = torch.tensor(corners, device=q.device)[weights.argmax(1)]  # (C,)
        point = index[q[owner, corner]]  # (C,) point of the nearest corner
        keys = (depth.to(torch.float32).view(torch.int32).to(torch.int64) << INDEX_BITS) | point
        pix = torch.where(inside, py * width + px, dump)  # (C,)
        mesh.scatter_reduce_(0, pix, keys, reduce="amin")
    buffer.copy_(torch.where(buffer == EMPTY_KEY, mesh, buffer))


def surface_frame(
    cloud: DeviceCloud,
    cam_from_world: torch.Tensor,
    intrinsics: np.ndarray,
    height: int,
    width: int,
    near: float = 1e-3,
    max_px: float = MESH_MAX_QUAD_PX,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Rasterise the cloud's quads in one frame: ``(rgb (P, 3) uint8, hit (P,) bool, depth (P,)
    float32)`` over the ``P = H*W`` pixels; the nearest triangle wins and its colour is the
    perspective-correct blend of its three corners' colours."""
    dev = cloud.points.device
    p = height * width
    rgb = torch.zeros((p, 3), dtype=torch.uint8, device=dev)
    hit = torch.zeros(p, dtype=torch.bool, device=dev)
    depth_out = torch.zeros(p, dtype=torch.float32, device=dev)
    if cloud.quads is None or cloud.quads.numel() == 0:
        return rgb, hit, depth_out
    u, v, z = project_world_points_torch(cloud.points, cam_from_world, intrinsics)  # (N,) each
    cand = _quad_candidates(cloud.quads, u, v, z, width, height, near, max_px)
    if cand is None:
        return rgb, hit, depth_out
    q, uq, vq, zq, owner, px, py = cand
    pix_all, bits_all, points_all, weights_all = [], [], [], []
    for corners in TRIANGLES:
        inside, depth, weights = _triangle_hits(uq, vq, zq, owner, px, py, corners)
        keep = torch.nonzero(inside).squeeze(1)
        idx = torch.tensor(corners, device=dev)
        z3 = zq[owner[keep]][:, idx]  # (C', 3) corner depths
        persp = weights[keep] / z3  # (C', 3) perspective-correct weights
        pix_all.append((py * width + px)[keep])
        bits_all.append(depth[keep].to(torch.float32).view(torch.int32).to(torch.int64))
        points_all.append(q[owner[keep]][:, idx])  # (C', 3) corner points
        weights_all.append(persp / persp.sum(1, keepdim=True))
    pix, bits = torch.cat(pix_all), torch.cat(bits_all)  # (K,) each
    if pix.numel() == 0:
        return rgb, hit, depth_out
    nearest = torch.full((p,), torch.iinfo(torch.int64).max, dtype=torch.int64, device=dev)
    nearest.scatter_reduce_(0, pix, bits, reduce="amin")
    wins = torch.nonzero(bits == nearest[pix]).squeeze(1)  # candidates at their pixel's depth
    winner = torch.full((p,), -1, dtype=torch.int64, device=dev)
    winner.scatter_reduce_(0, pix[wins], wins, reduce="amax")  # one per pixel (ties: any)
    covered = torch.nonzero(winner >= 0).squeeze(1)
    best = winner[covered]  # (P',) candidate of each covered pixel
    corners_pts = torch.cat(points_all)[best]  # (P', 3)
    weights = torch.cat(weights_all)[best]  # (P', 3)
    colours = cloud.colours.view(torch.uint8).view(-1, 4)[:, :3].to(torch.float32)  # (N, 3)
    blend = (colours[corners_pts] * weights[..., None]).sum(1)  # (P', 3)
    rgb[covered] = blend.round().clamp(0, 255).to(torch.uint8)
    hit[covered] = True
    depth_out[covered] = bits[best].to(torch.int32).view(torch.float32)
    return rgb, hit, depth_out


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
    mesh_from_cam: np.ndarray | None = None,
    mesh_max_step: float = 0.0,
    mesh_max_px: float = MESH_MAX_QUAD_PX,
    mesh_mode: str = "surface",
) -> SplatResult:
    """Render a coloured cloud along a trajectory by z-buffered splatting.

    ``points_world (N, 3)`` metres, ``colours (N, 3)`` uint8 RGB, ``world_from_cam (T, 4, 4)``,
    ``intrinsics (fx, fy, cx, cy)``, ``point_size (N,)`` metres (needed only for splats wider
    than one pixel), ``device`` any torch device string ("cpu", "cuda", "cuda:1"). Points at or
    behind ``near`` metres of camera z are skipped; holes of at most ``max_crack_px`` pixels
    inside the render and gaps up to ``max_crack_width`` pixels wide are closed by
    :func:`close_cracks` (0 = off). With ``mesh_max_step > 0`` and the pose ``mesh_from_cam
    (4, 4)`` of the frame the cloud was unprojected from, the cloud's surface quads are drawn
    (:func:`grid_quads`; quads over ``mesh_max_px`` across in a frame are not drawn) before the
    cracks are closed: ``mesh_mode`` "surface" draws the quads over the splats with blended
    colours (:func:`surface_frame`), "fill" only fills the pixels no splat reached with a
    corner's colour (:func:`_fill_from_mesh`). Raises
    :class:`SplatError` for an empty cloud, non-finite points, non-rigid or NaN poses and shapes
    that disagree.
    """
    points_world = np.asarray(points_world)
    colours = np.asarray(colours)
    world_from_cam = np.asarray(world_from_cam, dtype=np.float64)
    if point_size is not None:
        point_size = np.asarray(point_size, dtype=np.float32)
    _check_inputs(points_world, colours, world_from_cam, intrinsics, height, width, point_size)
    if max_splat_radius < 0:
        raise SplatError(f"max_splat_radius must be >= 0, got {max_splat_radius}")
    if mesh_mode not in MESH_MODES:
        raise SplatError(f"mesh_mode must be one of {MESH_MODES}, got {mesh_mode!r}")
    if not (np.isfinite(mesh_max_step) and mesh_max_step >= 0):
        raise SplatError(f"mesh_max_step must be finite and >= 0, got {mesh_max_step}")
    quads = None
    if mesh_max_step > 0 and mesh_from_cam is not None:
        mesh_from_cam = np.asarray(mesh_from_cam, dtype=np.float64)
        problems = se3_problems(mesh_from_cam)
        if mesh_from_cam.shape != (4, 4):
            problems = [f"expected (4, 4), got shape {mesh_from_cam.shape}"]
        if problems:
            raise SplatError(f"mesh_from_cam: {'; '.join(problems)}")
        quads = grid_quads(points_world, mesh_from_cam, intrinsics, height, width, mesh_max_step)
    cloud = to_device_cloud(points_world, colours, point_size, device, quads)
    dev = cloud.points.device
    cam_from_world = torch.as_tensor(invert_se3(world_from_cam), dtype=torch.float32, device=dev)
    t = len(world_from_cam)
    out_rgb = torch.zeros((t, height * width, 3), dtype=torch.uint8, device=dev)
    out_vis = torch.zeros((t, height * width), dtype=torch.uint8, device=dev)
    out_depth = torch.zeros((t, height * width), dtype=torch.float32, device=dev)
    # "surface": splats without the quads' hole fill, then the surface over them; from the
    # source frame's own pose the splats are that frame exactly (every pixel centre has its
    # point), so the surface pass is skipped there (a static camera: every frame)
    splat_cloud = dataclasses.replace(cloud, quads=None) if mesh_mode == "surface" else cloud
    at_source = np.zeros(t, bool)  # (T,)
    loose = None  # (N,) bool: the points that are in no quad (only they may beat the surface)
    if cloud.quads is not None:
        loose = torch.ones(len(cloud.index), dtype=torch.bool, device=dev)
        loose[cloud.quads.flatten()] = False
    if quads is not None:
        at_source = np.abs(world_from_cam - mesh_from_cam).reshape(t, -1).max(1) <= 1e-9
    for i in range(t):
        keys = splat_frame(
            splat_cloud,
            cam_from_world[i],
            intrinsics,
            height,
            width,
            max_splat_radius,
            near,
            mesh_max_px,
        )
        rgb_i, hit_i, depth_i = shade(cloud, keys)  # (H*W, 3), (H*W,), (H*W,)
        if mesh_mode == "surface" and cloud.quads is not None and not at_source[i]:
            rgb_m, hit_m, depth_m = surface_frame(
                cloud, cam_from_world[i], intrinsics, height, width, near, mesh_max_px
            )
            # Where a quad lands it is the surface; the splats only where none does (their
            # widened squares would otherwise fatten edges and show noisy points over it), or
            # where a point in no quad (a thin object, one pixel wide in the source frame) is
            # clearly nearer: surface edges are all in quads, so they do not fatten.
            _, idx_i, _ = decode_keys(keys)  # (H*W,)
            nearer = depth_i < depth_m * (1.0 - SEE_THROUGH_MARGIN)  # (H*W,)
            use = hit_m & ~(hit_i & loose[idx_i] & nearer)
            rgb_i = torch.where(use[:, None], rgb_m, rgb_i)
            hit_i = hit_i | hit_m
            depth_i = torch.where(use, depth_m, depth_i)
        out_rgb[i], out_vis[i], out_depth[i] = rgb_i, hit_i, depth_i
    rgb = out_rgb.reshape(t, height, width, 3).cpu().numpy()
    visible = out_vis.reshape(t, height, width).cpu().numpy()
    depth = out_depth.reshape(t, height, width).cpu().numpy()
    if max_crack_px > 0 or max_crack_width > 0:
        for i in range(t):
            rgb[i], visible[i], depth[i] = close_cracks(
                rgb[i], visible[i], depth[i], max_crack_px, max_crack_width
            )
    num_quads = 0 if quads is None else len(quads)
    return SplatResult(rgb=rgb, visible=visible, depth=depth, num_quads=num_quads)
