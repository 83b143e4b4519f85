"""Plane-sweep multi-view stereo for the first frame, in torch (CPU or GPU).

Fronto-parallel planes of the reference camera, spaced uniformly in inverse depth over the depth
range of the SfM points, are warped into each source frame by their homography; the matching cost
is zero-mean normalised cross-correlation (ZNCC) over a square window. Per plane the scores of the
best ``top_k`` sources are averaged (robust to occlusion and to objects that moved), the winner
takes all, and a parabola through the neighbouring planes refines the inverse depth.

Confidence combines photometric consistency (the winning ZNCC) with a visibility-aware
cross-check: each source that sees the pixel at the chosen depth (its window inside the source
image and off the source's hand mask) finds its own winner, and at least ``min_support`` of them
must lie within ``agreement_planes`` plane steps of the chosen depth. Sources that cannot see the
pixel do not vote, so hands that later cover the scene, or a camera that pans away, no longer
veto pixels other sources agree on. Pixels whose reference window has no texture, that lie under
the hand mask, that no source sees, or whose winner is the first or last plane (the surface may
lie outside the depth range), get zero.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as nnf

from egosim.pipeline.geometry import intrinsics_matrix


class PlaneSweepError(ValueError):
    """The plane sweep cannot run on its inputs (shapes, depth range, no sources)."""


@dataclass(frozen=True)
class PlaneSweepParams:
    """Knobs of :func:`plane_sweep`."""

    num_planes: int = 64  # inverse-depth planes between the near and far depth
    window: int = 7  # ZNCC window side in pixels (odd)
    top_k: int = 2  # sources averaged per plane (best scores); <= number of sources
    min_zncc: float = 0.5  # winning ZNCC mapped to confidence 0 ...
    max_zncc: float = 0.9  # ... and this one to 1
    agreement_planes: float = 1.5  # a source agrees when its own winner is this close, plane steps
    min_support: int = 2  # sources that see the pixel and agree needed for any confidence
    min_texture: float = 2.0  # reference window standard deviation (grey levels) below = no texture
    device: str = "cpu"  # torch device


@dataclass(frozen=True)
class PlaneSweepResult:
    """Depth and confidence of the reference frame at the working resolution."""

    depth: np.ndarray  # (H, W) float32 z-depth in the poses' scale
    confidence: np.ndarray  # (H, W) float32 in [0, 1]
    zncc: np.ndarray  # (H, W) float32 winning aggregated ZNCC
    agreement: np.ndarray  # (H, W) bool, at least ``min_support`` sources agree
    support: np.ndarray  # (H, W) int, sources that see the pixel and agree with its depth
    visible: np.ndarray  # (H, W) int, sources that see the pixel at its depth


def _box(x: torch.Tensor, window: int) -> torch.Tensor:
    """Mean over a ``window x window`` box of ``x (N, 1, H, W)``, same size (edges averaged)."""
    return nnf.avg_pool2d(x, window, stride=1, padding=window // 2, count_include_pad=False)


def _zncc_volume(
    ref: torch.Tensor,
    ref_mean: torch.Tensor,
    ref_std: torch.Tensor,
    src: torch.Tensor,
    src_valid: torch.Tensor,
    grid: torch.Tensor,
    window: int,
) -> torch.Tensor:
    """ZNCC of ``ref (1, 1, H, W)`` against ``src (1, 1, H, W)`` warped by ``grid (D, H, W, 2)``.

    Returns ``(D, H, W)`` scores in [-1, 1]; -1 where the warped window leaves the source image or
    touches invalid (hand) pixels of the source.
    """
    d = grid.shape[0]
    warped = nnf.grid_sample(
        src.expand(d, -1, -1, -1), grid, mode="bilinear", padding_mode="zeros", align_corners=False
    )  # (D, 1, H, W)
    valid = nnf.grid_sample(
        src_valid.expand(d, -1, -1, -1),
        grid,
        mode="nearest",
        padding_mode="zeros",
        align_corners=False,
    )  # (D, 1, H, W), 0 outside the image or on a hand
    mean_j = _box(warped, window)  # (D, 1, H, W)
    var_j = (_box(warped * warped, window) - mean_j * mean_j).clamp_min(0.0)
    cov = _box(warped * ref, window) - mean_j * ref_mean  # (D, 1, H, W)
    zncc = cov / (ref_std * var_j.sqrt() + 1e-6)
    ok = _box(valid, window) > 0.999  # whole window valid
    return torch.where(ok, zncc.clamp(-1.0, 1.0), -1.0)[:, 0]  # (D, H, W)


def _grids(
    intrinsics: np.ndarray,
    src_from_ref: np.ndarray,
    inv_depths: torch.Tensor,
    height: int,
    width: int,
    device: str,
) -> torch.Tensor:
    """Normalised sampling grids ``(D, H, W, 2)`` of the planes ``1/inv_depths`` in one source."""
    k = torch.as_tensor(intrinsics_matrix(intrinsics), dtype=torch.float32, device=device)
    rot = torch.as_tensor(src_from_ref[:3, :3], dtype=torch.float32, device=device)
    trans = torch.as_tensor(src_from_ref[:3, 3], dtype=torch.float32, device=device)
    v, u = torch.meshgrid(
        torch.arange(height, device=device, dtype=torch.float32) + 0.5,
        torch.arange(width, device=device, dtype=torch.float32) + 0.5,
        indexing="ij",
    )
    pix = torch.stack([u, v, torch.ones_like(u)], dim=0).reshape(3, -1)  # (3, HW)
    a = k @ rot @ torch.linalg.inv(k) @ pix  # (3, HW): direction term, times depth
    b = (k @ trans)[:, None]  # (3, 1): translation term
    # x_src ~ d * a + b  =>  divide by d: a + b * (1/d)
    proj = a[None] + b[None] * inv_depths[:, None, None]  # (D, 3, HW)
    z = proj[:, 2].clamp_min(1e-6)  # (D, HW)
    us = proj[:, 0] / z
    vs = proj[:, 1] / z
    behind = proj[:, 2] <= 1e-6
    gx = torch.where(behind, -2.0, us / width * 2.0 - 1.0)  # align_corners=False convention
    gy = torch.where(behind, -2.0, vs / height * 2.0 - 1.0)
    return torch.stack([gx, gy], dim=-1).reshape(-1, height, width, 2)  # (D, H, W, 2)


def _winner(
    cost: torch.Tensor, inv_depths: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Winner-take-all over ``cost (D, H, W)`` (higher is better) with parabolic refinement.

    Returns ``(inverse depth (H, W), winning score (H, W), winning plane index (H, W))``.
    """
    d = cost.shape[0]
    best, idx = cost.max(dim=0)  # (H, W)
    lo = cost.gather(0, (idx - 1).clamp(0, d - 1)[None])[0]
    hi = cost.gather(0, (idx + 1).clamp(0, d - 1)[None])[0]
    denom = lo - 2.0 * best + hi
    offset = torch.where(
        (idx > 0) & (idx < d - 1) & (denom < -1e-6), 0.5 * (lo - hi) / denom, 0.0
    ).clamp(-0.5, 0.5)
    step = inv_depths[1] - inv_depths[0]
    inv = inv_depths[idx] + offset * step
    return inv, best, idx


def plane_sweep(
    ref_image: np.ndarray,
    src_images: np.ndarray,
    intrinsics: np.ndarray,
    ref_cam_from_world: np.ndarray,
    src_cam_from_world: np.ndarray,
    depth_range: tuple[float, float],
    ref_valid: np.ndarray | None = None,
    src_valid: np.ndarray | None = None,
    params: PlaneSweepParams | None = None,
) -> PlaneSweepResult:
    """Depth of ``ref_image (H, W)`` grey from ``src_images (S, H, W)`` grey by plane sweep.

    Poses are world-to-camera ``(4, 4)`` / ``(S, 4, 4)``; ``intrinsics`` at this resolution.
    ``ref_valid (H, W)`` / ``src_valid (S, H, W)`` are 1 where pixels may be used (0 = hand).
    ``depth_range`` is ``(near, far)`` in the poses' scale. Raises :class:`PlaneSweepError`.
    """
    p = params if params is not None else PlaneSweepParams()
    ref_image = np.asarray(ref_image, dtype=np.float32)
    src_images = np.asarray(src_images, dtype=np.float32)
    if ref_image.ndim != 2 or src_images.ndim != 3 or src_images.shape[1:] != ref_image.shape:
        raise PlaneSweepError(
            f"need ref (H, W) and sources (S, H, W), got {ref_image.shape} and {src_images.shape}"
        )
    s = len(src_images)
    near, far = float(depth_range[0]), float(depth_range[1])
    if s < 2:
        raise PlaneSweepError(f"plane sweep needs at least 2 source frames, got {s}")
    if not (np.isfinite(near) and np.isfinite(far) and 0 < near < far):
        raise PlaneSweepError(f"depth range must satisfy 0 < near < far, got {depth_range}")
    h, w = ref_image.shape
    dev = p.device
    if ref_valid is None:
        ref_valid = np.ones((h, w), np.float32)
    if src_valid is None:
        src_valid = np.ones((s, h, w), np.float32)
    inv_depths = torch.linspace(1.0 / far, 1.0 / near, p.num_planes, device=dev)  # (D,)
    ref = torch.as_tensor(ref_image, device=dev)[None, None]  # (1, 1, H, W)
    ref_mean = _box(ref, p.window)
    ref_std = (_box(ref * ref, p.window) - ref_mean * ref_mean).clamp_min(0.0).sqrt()
    scores = []
    for j in range(s):
        src_from_ref = src_cam_from_world[j] @ np.linalg.inv(ref_cam_from_world)  # (4, 4)
        grid = _grids(intrinsics, src_from_ref, inv_depths, h, w, dev)  # (D, H, W, 2)
        src = torch.as_tensor(src_images[j], device=dev)[None, None]
        valid = torch.as_tensor(np.asarray(src_valid[j], np.float32), device=dev)[None, None]
        scores.append(_zncc_volume(ref, ref_mean, ref_std, src, valid, grid, p.window))
        del grid
    vol = torch.stack(scores)  # (S, D, H, W)
    del scores
    k = max(1, min(p.top_k, s))
    agg = vol.topk(k, dim=0).values.mean(0)  # (D, H, W)
    inv, best, arg = _winner(agg, inv_depths)
    # a winner on the first or last plane is no peak: the surface may lie outside the range
    interior = (arg > 0) & (arg < p.num_planes - 1)
    step = float(inv_depths[1] - inv_depths[0])
    # Visibility-aware cross-check: every source that sees the pixel at the chosen depth (window
    # inside its image and off its hands) votes with its own winner; sources that do not see it
    # (out of view, or a hand covers the scene later in the clip) neither support nor veto.
    at_final = vol.gather(1, arg[None, None].expand(s, 1, -1, -1))[:, 0]  # (S, H, W)
    seen = at_final > -1.0  # (S, H, W)
    per_src = torch.stack([_winner(vol[j], inv_depths)[0] for j in range(s)])  # (S, H, W)
    agrees = seen & ((per_src - inv[None]).abs() <= p.agreement_planes * step)
    support = agrees.sum(0)
    visible = seen.sum(0)
    agree = support >= p.min_support
    del vol, agg, per_src, at_final
    photometric = ((best - p.min_zncc) / (p.max_zncc - p.min_zncc)).clamp(0.0, 1.0)
    textured = ref_std[0, 0] >= p.min_texture
    ref_ok = torch.as_tensor(np.asarray(ref_valid, np.float32), device=dev) > 0.5
    conf = photometric * agree * interior * textured * ref_ok * (best > -1.0)
    depth = 1.0 / inv.clamp_min(1.0 / (far * 4.0))
    return PlaneSweepResult(
        depth=depth.cpu().numpy().astype(np.float32),
        confidence=conf.cpu().numpy().astype(np.float32),
        zncc=best.cpu().numpy().astype(np.float32),
        agreement=agree.cpu().numpy(),
        support=support.cpu().numpy(),
        visible=visible.cpu().numpy(),
    )


def select_sources(
    cam_from_world: np.ndarray,
    candidates: np.ndarray,
    points_world: np.ndarray,
    intrinsics: np.ndarray,
    image_size: tuple[int, int],
    num_sources: int,
    median_depth: float | None = None,
    target_angle_deg: float = 8.0,
    min_overlap: float = 0.5,
    usable: np.ndarray | None = None,
) -> list[int]:
    """Pick source frames for frame 0 by triangulation angle and view overlap.

    ``cam_from_world (T, 4, 4)``, ``candidates (T,)`` bool (registered frames), ``points_world
    (P, 3)`` the SfM points frame 0 sees (may be empty when ``median_depth`` is given: overlap is
    then taken as 1). A point counts as seen by frame ``j`` when it projects inside the image and,
    given ``usable (T, H, W)`` bool, onto a usable (non-hand) pixel: hands that later cover part of
    the scene make a frame a worse source. A frame scores ``overlap * min(a / target, target / a)``
    for its angle ``a`` (baseline over the median scene depth); frames seeing less than
    ``min_overlap`` of the points are skipped; picks keep a minimum index gap so that they spread
    along the clip. Returns frame indices (may be fewer than ``num_sources``).
    """
    t = len(cam_from_world)
    h, w = image_size
    fx, fy, cx, cy = np.asarray(intrinsics, dtype=np.float64)
    world_from_cam0 = np.linalg.inv(cam_from_world[0])
    pts_cam0 = points_world @ cam_from_world[0, :3, :3].T + cam_from_world[0, :3, 3]  # (P, 3)
    z_med = float(np.median(pts_cam0[:, 2])) if median_depth is None else float(median_depth)
    scores = np.full(t, -np.inf)
    for j in np.flatnonzero(candidates):
        if j == 0:
            continue
        centre_j = np.linalg.inv(cam_from_world[j])[:3, 3]
        baseline = float(np.linalg.norm(centre_j - world_from_cam0[:3, 3]))
        angle = np.rad2deg(np.arctan2(baseline, z_med))
        pts = points_world @ cam_from_world[j, :3, :3].T + cam_from_world[j, :3, 3]  # (P, 3)
        z = pts[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = fx * pts[:, 0] / z + cx
            v = fy * pts[:, 1] / z + cy
        inside = (z > 0) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
        if usable is not None:
            ui = np.clip(np.nan_to_num(u), 0, w - 1).astype(int)
            vi = np.clip(np.nan_to_num(v), 0, h - 1).astype(int)
            inside &= usable[j][vi, ui]
        overlap = float(np.mean(inside)) if len(points_world) else 1.0
        if overlap < min_overlap or angle <= 0:
            continue
        scores[j] = overlap * min(angle / target_angle_deg, target_angle_deg / angle)
    order = [int(j) for j in np.argsort(-scores) if np.isfinite(scores[j])]
    gap = max(1, t // (2 * max(num_sources, 1)))
    chosen: list[int] = []
    while True:  # spread the picks; halve the gap when too few frames qualify (fast pans)
        for j in order:
            if len(chosen) == num_sources:
                break
            if j not in chosen and all(abs(j - c) >= gap for c in chosen):
                chosen.append(j)
        if len(chosen) == num_sources or gap == 1:
            return chosen
        gap = max(1, gap // 2)


def _grey_at(frame: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    import cv2

    grey = cv2.cvtColor(np.ascontiguousarray(frame), cv2.COLOR_RGB2GRAY)
    return cv2.resize(grey, (size[1], size[0]), interpolation=cv2.INTER_AREA).astype(np.float32)


def first_frame_depth(
    frames: np.ndarray,
    usable: np.ndarray | None,
    intrinsics: np.ndarray,
    cam_from_world: np.ndarray,
    sources: list[int],
    depth_range: tuple[float, float],
    scale: float,
    params: PlaneSweepParams,
    edge_rel: float = 0.1,
) -> tuple[np.ndarray, np.ndarray]:
    """Depth and confidence ``(H, W)`` of ``frames[0]`` at full resolution.

    The sweep runs at ``scale`` times the frame size; inverse depth is upsampled bilinearly and
    confidence by nearest neighbour, after zeroing it where the working-resolution depth jumps by
    more than ``edge_rel`` within 3x3 pixels (upsampling there would blend two surfaces).
    ``usable (T, H, W)`` is True where pixels may be matched (not hand); None = everywhere.
    """
    import cv2

    from egosim.pipeline.geometry import scale_intrinsics

    big_h, big_w = frames.shape[1:3]
    h, w = max(8, round(big_h * scale)), max(8, round(big_w * scale))
    k_small = scale_intrinsics(intrinsics, w / big_w, h / big_h)
    idx = [0, *sources]
    grey = np.stack([_grey_at(frames[i], (h, w)) for i in idx])  # (1+S, h, w)
    if usable is None:
        valid = np.ones((len(idx), h, w), np.float32)
    else:
        valid = np.stack(
            [
                cv2.resize(usable[i].astype(np.uint8), (w, h), interpolation=cv2.INTER_NEAREST)
                for i in idx
            ]
        ).astype(np.float32)
    result = plane_sweep(
        grey[0],
        grey[1:],
        k_small,
        cam_from_world[0],
        cam_from_world[sources],
        depth_range,
        valid[0],
        valid[1:],
        params,
    )
    kernel = np.ones((3, 3), np.uint8)
    local_max = cv2.dilate(result.depth, kernel)
    local_min = cv2.erode(result.depth, kernel)
    smooth = local_max <= local_min * (1.0 + edge_rel)
    conf = np.where(smooth, result.confidence, 0.0).astype(np.float32)
    inv = cv2.resize(1.0 / result.depth, (big_w, big_h), interpolation=cv2.INTER_LINEAR)
    conf_big = cv2.resize(conf, (big_w, big_h), interpolation=cv2.INTER_NEAREST)
    return (1.0 / inv).astype(np.float32), conf_big
