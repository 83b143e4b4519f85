"""Dense first-frame depth: keep what was measured, fill the rest edge-aware, say which is which.

Multi-view depth is confident only where there is texture (often 16-39% of a real frame), and
the depth between two surfaces is smeared across their occlusion edge (flying pixels). A scene
cloud built only from confident, edge-free pixels is full of holes; one built from every pixel is
full of streaks. :func:`densify_depth` does neither:

1. **Measured** pixels: known depth, confidence at or above ``min_confidence`` (every known pixel
   when there is no confidence), not excluded, not under ``unmeasured``.
2. **Flying pixels at depth edges only**: among measured pixels, those where inverse depth breaks
   planarity (:func:`flying_pixel_mask`) are left out (``drop_edges``: both sides of the edge,
   whose colours mix the two surfaces; rendering closes the two-pixel seam at t=0) or, without
   ``drop_edges``, only the pixels between the sides become unmeasured and are filled.
   Islands of estimated depth of at most ``speckle_px`` pixels (``cv2.filterSpeckles``; it cannot
   tell a right island from a wrong one, so keep it small) become unmeasured too. Nothing else is
   dropped.
3. **Segment planes**: the colour image is cut into superpixels that follow colour edges
   (``cv2.watershed`` flooded from a grid of seeds; fine superpixels first, then coarser ones
   for what the fine ones could not fill). In each segment a plane is fitted to the
   measured inverse depth (``1/z`` is affine in normalised image coordinates on any plane:
   least squares, then again on the inliers within ``plane_tolerance``); a segment whose inliers
   are enough (``min_plane_support`` pixels and ``min_plane_fraction`` of the segment) fills its
   unmeasured pixels with the plane, so a fill never crosses a colour edge. Measured pixels off
   such a plane by more than ``outlier_factor`` tolerances (confident matching errors) take the
   plane's depth too.
4. **Everything else** (segments with too little measured depth) is filled by OpenCV
   Navier-Stokes inpainting of inverse depth from all pixels known so far.

Every output pixel (except excluded ones) has depth, and :class:`DenseDepth` records how it got
it: ``MEASURED``, ``PLANE`` or ``INPAINTED``, plus a confidence in [0, 1] per pixel (the
measurement's own confidence, the segment plane's inlier share scaled into
``(0, PLANE_CONFIDENCE]``, or ``INPAINT_CONFIDENCE``).
"""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np

from egosim.pipeline.geometry import pixel_grid

EXCLUDED, MEASURED, PLANE, INPAINTED = 0, 1, 2, 3  # values of DenseDepth.source
PLANE_CONFIDENCE = 0.45  # confidence of a pixel filled by a plane whose segment is all inliers
INPAINT_CONFIDENCE = 0.1  # confidence of a pixel filled by inpainting
RIDGE = 1e-3  # plane fit: slope regulariser (per pixel, normalised coordinates)


@dataclasses.dataclass(frozen=True)
class DensifyParams:
    """How :func:`densify_depth` decides what is measured and how it fills the rest."""

    min_confidence: float = 0.5  # depth confidence at or above = measured (0..1)
    edge_threshold: float = 0.05  # flying pixel: |2nd difference of 1/z| / (1/z) above this
    drop_edges: bool = True  # True: both sides of a depth edge are left out, not filled
    speckle_px: int = 50  # islands of estimated depth of at most this many pixels ... (0 = off)
    speckle_rel: float = 0.03  # ... whose neighbours differ by at most this (relative 1/z) go
    segment_px: tuple[int, ...] = (20,)  # superpixel seed spacings, fine to coarse (pixels)
    plane_tolerance: float = 0.03  # plane inlier: |1/z - plane| / (1/z) at most this
    snap_to_planes: bool = False  # measured plane inliers take the plane's depth (denoising)
    outlier_factor: float = 3.0  # measured pixels off their superpixel's plane by more than this
    # x plane_tolerance are matching errors: they take the plane's depth (0 = keep them)
    min_plane_support: int = 12  # a segment plane needs at least this many inlier pixels ...
    min_plane_fraction: float = 0.05  # ... and this share of the segment's pixels
    inpaint_radius: float = 5.0  # Navier-Stokes inpainting radius (pixels) for the rest


@dataclasses.dataclass(frozen=True)
class DenseDepth:
    """A dense depth map and, per pixel, where its depth came from and how far to trust it."""

    depth: np.ndarray  # (H, W) float32 metres; 0 only where excluded
    source: np.ndarray  # (H, W) uint8 EXCLUDED / MEASURED / PLANE / INPAINTED
    confidence: np.ndarray  # (H, W) float32 in [0, 1]; 0 where excluded
    num_flying: int  # measured pixels dropped as flying pixels (left out or filled) or speckles
    num_outliers: int = 0  # measured pixels replaced by their superpixel's plane (outliers)


def flying_pixel_mask(
    depth: np.ndarray, edge_threshold: float, both_sides: bool = True
) -> np.ndarray:
    """``(H, W)`` bool, True where a pixel sits on a depth edge (a flying pixel candidate).

    ``depth (H, W)`` metres, 0 = unknown; ``d = 1/z``. A pixel is flagged when, along any of the
    four directions (row, column, two diagonals), inverse depth breaks planarity,
    ``|d(p-1) - 2 d(p) + d(p+1)| / d(p) > edge_threshold``: with ``both_sides`` the last pixel of
    each side of a step goes too (their colours mix the two surfaces); without it only a pixel
    that belongs to neither side (it differs from both neighbours by more than ``edge_threshold``
    of ``d(p)``: interpolated across the step, or a spike) is flagged. Neighbours of unknown
    depth or outside the image are ignored; planes (``1/z`` affine in pixels, even at grazing
    angles) are never flagged.
    """
    known = depth > 0  # (H, W)
    inv = np.where(known, 1.0 / np.where(known, depth, 1.0), np.nan)  # (H, W)
    pad = np.pad(inv, 1, constant_values=np.nan)  # (H+2, W+2)
    h, w = depth.shape
    centre = pad[1 : h + 1, 1 : w + 1]
    flagged = np.zeros((h, w), dtype=bool)
    for dy, dx in ((0, 1), (1, 0), (1, 1), (1, -1)):
        before = pad[1 - dy : h + 1 - dy, 1 - dx : w + 1 - dx]
        after = pad[1 + dy : h + 1 + dy, 1 + dx : w + 1 + dx]
        with np.errstate(invalid="ignore"):
            second = np.abs(before - 2.0 * centre + after) / centre  # (H, W), NaN at borders
            apart = np.minimum(np.abs(before - centre), np.abs(after - centre)) / centre
        edge = np.nan_to_num(second, nan=0.0) > edge_threshold  # (H, W)
        if not both_sides:
            edge &= np.nan_to_num(apart, nan=0.0) > edge_threshold
        flagged |= edge
    return flagged & known


def speckle_mask(depth: np.ndarray, max_px: int, rel: float) -> np.ndarray:
    """``(H, W)`` bool, True on blobs of known depth of at most ``max_px`` pixels.

    A blob is a 4-connected set of known pixels whose neighbours' inverse depths differ by at most
    ``rel`` of the median inverse depth (``cv2.filterSpeckles`` on quantised ``1/z``).
    """
    known = depth > 0  # (H, W)
    if max_px < 1 or not known.any():
        return np.zeros_like(known)
    inv = np.where(known, 1.0 / np.where(known, depth, 1.0), 0.0)  # (H, W)
    step = np.median(inv[known]) * rel / 8.0  # 1/z per quantisation step: rel = 8 steps
    quant = np.clip(np.round(inv / step), 0, 32767).astype(np.int16)  # (H, W)
    quant[known & (quant == 0)] = 1  # 0 is "unknown" for filterSpeckles
    filtered, _ = cv2.filterSpeckles(quant.copy(), 0, int(max_px), 8)
    return known & (filtered == 0)


def superpixels(image: np.ndarray, spacing: int) -> np.ndarray:
    """``(H, W)`` int32 labels ``0..S-1`` of watershed superpixels of ``image (H, W, 3)`` uint8.

    Seeds on a grid ``spacing`` pixels apart flood the colour gradient (``cv2.watershed``), so
    segment borders follow colour edges; watershed lines join their neighbouring segment.
    """
    h, w = image.shape[:2]
    markers = np.zeros((h, w), np.int32)
    ys = np.arange(spacing // 2, h, spacing)
    xs = np.arange(spacing // 2, w, spacing)
    grid = np.arange(1, 1 + len(ys) * len(xs), dtype=np.int32).reshape(len(ys), len(xs))
    markers[np.ix_(ys, xs)] = grid
    bgr = np.ascontiguousarray(image[..., ::-1])
    cv2.watershed(cv2.GaussianBlur(bgr, (3, 3), 0), markers)
    lines = markers <= 0  # (H, W) watershed lines (-1)
    if lines.any():
        grown = cv2.dilate(markers.astype(np.float32), np.ones((3, 3), np.uint8))  # (H, W)
        markers = np.where(lines, grown.astype(np.int32), markers)
        markers[markers <= 0] = 1  # a line pixel with only line neighbours (thin corners)
    return markers - 1


def _fit_planes(
    coords: np.ndarray,
    inv: np.ndarray,
    labels: np.ndarray,
    weight: np.ndarray,
    num: int,
) -> np.ndarray:
    """Least-squares ``1/z = a x + b y + c`` per label; ``(S, 3)`` (NaN where singular).

    ``coords (P, 2)`` normalised image coordinates, ``inv (P,)`` inverse depth, ``labels (P,)``,
    ``weight (P,)`` 0/1 which pixels take part. A small ridge on ``a, b`` keeps segments whose
    measured pixels lie on a line solvable (it leans them towards fronto-parallel).
    """
    x, y = coords[:, 0], coords[:, 1]
    feats = np.stack([x, y, np.ones_like(x)], axis=1)  # (P, 3)
    ata = np.zeros((num, 3, 3))
    atb = np.zeros((num, 3))
    for i in range(3):
        atb[:, i] = np.bincount(labels, weight * feats[:, i] * inv, minlength=num)
        for j in range(i, 3):
            ata[:, i, j] = ata[:, j, i] = np.bincount(
                labels, weight * feats[:, i] * feats[:, j], minlength=num
            )
    count = ata[:, 2, 2]  # (S,)
    ata[:, 0, 0] += RIDGE * count + 1e-12
    ata[:, 1, 1] += RIDGE * count + 1e-12
    ata[:, 2, 2] += 1e-12
    planes = np.full((num, 3), np.nan)
    ok = count >= 3
    planes[ok] = np.linalg.solve(ata[ok], atb[ok][..., None])[..., 0]
    return planes


def _segment_medians(
    values: np.ndarray, labels: np.ndarray, use: np.ndarray, num: int
) -> np.ndarray:
    """``(S,)`` median of ``values (P,)`` over the ``use (P,)`` pixels of each label (NaN: none)."""
    idx = np.flatnonzero(use)
    lab, val = labels[idx], values[idx]
    order = np.lexsort((val, lab))
    counts = np.bincount(lab, minlength=num)  # (S,)
    starts = np.cumsum(counts) - counts
    med = np.full(num, np.nan)
    has = counts > 0
    med[has] = val[order][starts[has] + counts[has] // 2]
    return med


def _robust_planes(
    coords: np.ndarray,
    inv: np.ndarray,
    labels: np.ndarray,
    measured: np.ndarray,
    num: int,
    p: DensifyParams,
) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel plane prediction of ``1/z`` ``(P,)`` and the measured plane inliers ``(P,)``.

    Starts from each segment's median inverse depth (so a segment straddling a step takes one
    side, never the average of both), then refits on the inliers within a shrinking tolerance
    (4x, 2x, 1x ``plane_tolerance``).
    """
    design = np.c_[coords, np.ones(len(coords))]  # (P, 3)
    planes = np.zeros((num, 3))
    planes[:, 2] = _segment_medians(inv, labels, measured, num)  # fronto-parallel start
    weight = measured.astype(np.float64)  # (P,)
    for scale in (4.0, 2.0, 1.0):
        pred = np.einsum("pk,pk->p", design, planes[labels])  # (P,)
        with np.errstate(invalid="ignore"):
            inlier = weight * (np.abs(inv - pred) <= scale * p.plane_tolerance * inv)
        planes = _fit_planes(coords, inv, labels, inlier, num)
    pred = np.einsum("pk,pk->p", design, planes[labels])  # (P,)
    with np.errstate(invalid="ignore"):
        inlier = weight * (np.abs(inv - pred) <= p.plane_tolerance * inv)
    return pred, inlier


def densify_depth(
    depth: np.ndarray,
    image: np.ndarray,
    intrinsics: np.ndarray,
    confidence: np.ndarray | None = None,
    exclude: np.ndarray | None = None,
    unmeasured: np.ndarray | None = None,
    params: DensifyParams | None = None,
    fill: bool = True,
) -> DenseDepth:
    """Dense depth of one frame (see the module docstring).

    ``depth (H, W)`` metres (0 = unknown), ``image (H, W, 3)`` uint8 RGB (the guide),
    ``intrinsics (fx, fy, cx, cy)``, ``confidence (H, W)`` in [0, 1] or None (all known depth is
    measured), ``exclude (H, W)`` pixels to leave out altogether (e.g. hands), ``unmeasured
    (H, W)`` pixels whose depth must be filled rather than trusted (e.g. under inpainted hands).
    ``fill=False`` stops after step 2: only measured pixels keep depth.
    """
    p = params or DensifyParams()
    h, w = depth.shape
    depth = np.asarray(depth, dtype=np.float64)
    keep = np.ones((h, w), bool) if exclude is None else np.asarray(exclude) == 0  # (H, W)
    measured = (depth > 0) & keep  # (H, W)
    conf = np.ones((h, w)) if confidence is None else np.asarray(confidence, dtype=np.float64)
    if confidence is not None:
        measured &= conf >= p.min_confidence
    if unmeasured is not None:
        measured &= ~np.asarray(unmeasured, dtype=bool)
    before = int(measured.sum())
    if p.edge_threshold > 0:
        flying = flying_pixel_mask(np.where(measured, depth, 0.0), p.edge_threshold, p.drop_edges)
        measured &= ~flying
        if p.drop_edges:
            keep &= ~flying
    if confidence is not None:  # estimated depth: its isolated blobs are matching errors
        measured &= ~speckle_mask(np.where(measured, depth, 0.0), p.speckle_px, p.speckle_rel)
    num_flying = before - int(measured.sum())
    source = np.where(measured, MEASURED, EXCLUDED).astype(np.uint8)  # (H, W)
    out_conf = np.where(measured, conf, 0.0)  # (H, W)
    inv = np.where(measured, 1.0 / np.where(measured, depth, 1.0), 0.0)  # (H, W)
    todo = keep & ~measured  # (H, W)
    if not fill or not measured.any() or not todo.any():
        sparse = np.where(measured, depth, 0.0).astype(np.float32)  # (H, W)
        return DenseDepth(sparse, source, out_conf.astype(np.float32), num_flying)
    # 3. segment planes
    fx, fy, cx, cy = np.asarray(intrinsics, dtype=np.float64)
    coords = (pixel_grid(h, w).reshape(-1, 2) - [cx, cy]) / [fx, fy]  # (P, 2) at z = 1
    lo, hi = inv[measured].min(), inv[measured].max()
    num_outliers = 0
    inv_measured = inv.ravel().copy()  # (P,) planes are fitted to measurements only
    left = todo.ravel().copy()  # (P,) still without depth
    for level, spacing in enumerate(p.segment_px):  # fine superpixels first, then coarser
        labels = superpixels(image, spacing).ravel()  # (P,)
        num = int(labels.max()) + 1
        pred, inlier = _robust_planes(coords, inv_measured, labels, measured.ravel(), num, p)
        support = np.bincount(labels, inlier, minlength=num)  # (S,)
        size = np.bincount(labels, minlength=num).astype(np.float64)  # (S,)
        good = (support >= p.min_plane_support) & (support >= p.min_plane_fraction * size)
        with np.errstate(invalid="ignore"):
            plausible = (pred >= 0.5 * lo) & (pred <= 2.0 * hi)  # (P,) in front, not far out
        by_plane = left & good[labels] & plausible  # (P,)
        if p.outlier_factor > 0 and level == 0:  # measurements far off a well-supported plane
            with np.errstate(invalid="ignore"):
                off = np.abs(inv_measured - pred) > p.outlier_factor * p.plane_tolerance * pred
            outliers = measured.ravel() & off & good[labels] & plausible  # (P,)
            by_plane |= outliers
            num_outliers = int(outliers.sum())
        flat = inv.ravel()  # (P,) view of inv
        flat[by_plane] = pred[by_plane]
        if p.snap_to_planes and level == 0:  # measured inliers take their plane's value
            snap = (inlier > 0) & good[labels] & plausible  # (P,)
            flat[snap] = pred[snap]
        source.ravel()[by_plane] = PLANE
        share = np.minimum(support / np.maximum(size, 1.0), 1.0)  # (S,) inlier share
        out_conf.ravel()[by_plane] = PLANE_CONFIDENCE * share[labels][by_plane]
        left &= ~by_plane
    by_plane = todo & ~left.reshape(h, w)  # (H, W)
    # 4. inpainting for what no plane reached
    rest = todo & ~by_plane  # (H, W)
    if rest.any():
        unknown = (inv <= 0).astype(np.uint8)  # (H, W) excluded pixels are no source either
        guess = cv2.inpaint(inv.astype(np.float32), unknown, p.inpaint_radius, cv2.INPAINT_NS)
        guess = np.clip(guess, 0.5 * lo, 2.0 * hi)  # (H, W)
        inv = np.where(rest, guess, inv)
        source[rest] = INPAINTED
        out_conf = np.where(rest, INPAINT_CONFIDENCE, out_conf)
    dense = np.where(keep, 1.0 / np.where(inv > 0, inv, 1.0), 0.0)  # (H, W)
    return DenseDepth(
        dense.astype(np.float32), source, out_conf.astype(np.float32), num_flying, num_outliers
    )
