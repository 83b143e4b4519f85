"""Fill the hand pixels of frame 0 from later frames reprojected through depth and pose.

Method (backward warping, needs depth of frame 0 only):

1. The surface behind the hand in frame 0 is unknown, so frame 0's depth inside the (dilated)
   hand mask is replaced by an OpenCV (Navier-Stokes) inpainting of the depth around it: a
   smooth continuation of the table and objects the hand covers. Only measured depth feeds it
   (``measured``: an estimated depth's confident pixels): a plane sweep of a frame with a
   moving hand in it is wrong in a band round the hand (it matches the hand too), and that
   band is inpainted with the hole (measured on DWM 00013: faceted pieces of floor pasted).
2. Each masked pixel is lifted to 3D with that depth and projected into every later frame
   (``world_from_cam`` and the intrinsics, with the shared geometry). A frame may fill a pixel
   when the projection lands inside the image on a pixel that is not hand in that frame (its own
   mask, dilated). When that frame's depth is known, the depth found there must also agree with
   the predicted depth within ``depth_tolerance`` (relative): a moved object or an occluder is
   rejected.
3. Near each hole pixel the frame must also show frame 0's ring (the pixels just outside the
   hole, lifted with frame 0's measured depth where it is measured, else with the depth
   inpainted in step 1) within ``local_residual`` grey levels (mean
   absolute difference, :func:`ring_residual`): where the pose, the depth or the scene (a held
   object that moved) is wrong near the hole, that frame does not fill that side of it.
   With ``shift_px`` the frame's reprojection is first moved by the whole-pixel shift that best
   aligns the ring (:func:`ring_shift`): estimated poses drift by a few pixels.
4. Frames are tried by increasing time gap (closest first: least object motion and lighting
   change); a pixel takes the per-channel median of the colours (bilinear) of the first
   ``candidates`` frames that may fill it (1 = the closest frame alone). The median leaves no
   ghost of a hand or arm that one frame's mask missed.
5. What no frame saw is filled by :func:`unseen_fill` (OpenCV Telea or Navier-Stokes).

The result records, per pixel, the fill source (0 original, 1 reprojected, 2 OpenCV) and the
frame index its colour came from.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np

from egosim.pipeline.geometry import (
    invert_se3,
    project_points,
    transform_points,
    unproject_depth,
)
from egosim.schemas.inpaint import FILL_OPENCV, FILL_ORIGINAL, FILL_REPROJECTED


class InpaintInputError(ValueError):
    """Frames, masks, depth or poses given to the fill disagree in shape or values."""


@dataclass(frozen=True)
class FillResult:
    """A hand-free frame and where each pixel came from."""

    image: np.ndarray  # (H, W, 3) uint8 RGB
    fill_source: np.ndarray  # (H, W) uint8 codes FILL_* (0 original, 1 reprojected, 2 OpenCV)
    source_frame: np.ndarray  # (H, W) uint16 frame index of each pixel's colour
    filled: np.ndarray  # (H, W) bool pixels that were replaced (the dilated hand mask)


def dilate(mask: np.ndarray, pixels: int) -> np.ndarray:
    """Dilate a ``(H, W)`` or ``(T, H, W)`` 0/1 mask by a disk of radius ``pixels``."""
    if pixels <= 0:
        return mask.astype(np.uint8)
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * pixels + 1, 2 * pixels + 1))
    if mask.ndim == 3:
        return np.stack([cv2.dilate(m.astype(np.uint8), kernel) for m in mask])
    return cv2.dilate(mask.astype(np.uint8), kernel)


def opencv_fill(image: np.ndarray, mask: np.ndarray, radius: float = 5.0) -> np.ndarray:
    """OpenCV Telea inpainting of ``image (H, W, 3)`` RGB where ``mask (H, W)`` is 1."""
    return unseen_fill(image, mask, radius, "telea")


UNSEEN_METHODS = {"telea": cv2.INPAINT_TELEA, "ns": cv2.INPAINT_NS}  # OpenCV inpainting flags


def unseen_fill(
    image: np.ndarray, mask: np.ndarray, radius: float = 5.0, method: str = "telea"
) -> np.ndarray:
    """OpenCV inpainting (``method`` "telea" or "ns") of ``image (H, W, 3)`` RGB where ``mask``."""
    if method not in UNSEEN_METHODS:
        raise InpaintInputError(
            f"unseen method must be one of {sorted(UNSEEN_METHODS)}, got {method!r}"
        )
    bgr = cv2.cvtColor(image, cv2.COLOR_RGB2BGR)
    out = cv2.inpaint(bgr, mask.astype(np.uint8), radius, UNSEEN_METHODS[method])
    return cv2.cvtColor(out, cv2.COLOR_BGR2RGB)


def pushpull_fill(image: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """``image (H, W[, C])`` with the ``mask (H, W)`` pixels from a pyramid of masked averages.

    Pull: each level halves the image, averaging only known pixels (weights carried along);
    push: from the coarsest level down, a pixel takes its own average where its weight is full
    and the upsampled coarser level for the rest, in proportion to the missing weight.
    """
    hole = mask > 0
    weight = (~hole).astype(np.float32)  # (H, W)
    colour = image.astype(np.float32).reshape(*hole.shape, -1) * weight[..., None]  # (H, W, C)
    levels = [(colour, weight)]
    while min(levels[-1][1].shape) > 2 and levels[-1][1].min() < 1e-3:
        c, wt = levels[-1]
        down = cv2.pyrDown(c)
        levels.append((down.reshape(*down.shape[:2], -1), cv2.pyrDown(wt)))
    c, wt = levels[-1]
    filled = c / np.maximum(wt, 1e-6)[..., None]
    for c, wt in reversed(levels[:-1]):
        up = cv2.pyrUp(filled, dstsize=(wt.shape[1], wt.shape[0])).reshape(c.shape)
        alpha = np.clip(wt, 0, 1)[..., None]  # (h, w, 1) how much of its own average is known
        filled = alpha * (c / np.maximum(wt, 1e-6)[..., None]) + (1 - alpha) * up
    out = image.copy()
    got = filled.reshape(image.shape)[hole]
    if np.issubdtype(image.dtype, np.integer):
        got = np.clip(np.round(got), 0, 255)
    out[hole] = got.astype(image.dtype)
    return out


def local_residual_map(
    diff: np.ndarray, known: np.ndarray, hole: np.ndarray, window: int = 15
) -> np.ndarray:
    """``(H, W)`` float32: the alignment residual ``diff`` near each pixel, carried into ``hole``.

    ``diff (H, W)``: absolute grey difference of an aligned frame and frame 0, trusted on
    ``known (H, W)`` (the ring round the hole); its mean over a ``window`` box of known pixels
    is spread into the ``hole (H, W)`` (and wherever no known pixel is near) by
    :func:`pushpull_fill`.
    """
    k = known.astype(np.float32)
    num = cv2.boxFilter(diff.astype(np.float32) * k, -1, (window, window), normalize=False)
    den = cv2.boxFilter(k, -1, (window, window), normalize=False)
    local = np.where(den > 0.5, num / np.maximum(den, 1e-6), 0).astype(np.float32)  # (H, W)
    return pushpull_fill(local, (den <= 0.5) | (hole > 0))  # (H, W)


MIN_SHIFT_EVIDENCE = 20  # ring points a frame must show before a shift is looked for
MAX_SHIFT_EVIDENCE = 4000  # ring points a shift is scored on (an even subsample of more): the
# mean residual of 4,000 points is sure enough (the shift chosen was the same on every clip
# measured, design.md "Inpaint v14"), and each of the (2 radius + 1)^2 shifts samples them all
# (a large HOT3D hole's ring: 45k points, 6 s of 19 s a clip)


def evidence(count: int) -> slice:
    """The even subsample (a slice) of ``count`` ring points that a shift is scored on: all of
    them up to ``MAX_SHIFT_EVIDENCE``, else every n-th."""
    return slice(None, None, max(1, -(-count // MAX_SHIFT_EVIDENCE)))


def ring_shift(
    ring_check: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],
    frame: np.ndarray,
    mask: np.ndarray,
    cam_from_world: np.ndarray,
    intrinsics: np.ndarray,
    radius: int,
    min_gain: float,
) -> tuple[float, float]:
    """The image shift ``(dx, dy)`` (whole pixels, ``|dx|, |dy| < radius``) that best aligns
    ``frame (H, W, 3)`` with frame 0 on the reprojected ring, or ``(0, 0)``.

    Estimated poses drift: a frame's reprojection lands a few pixels off. Every shift within
    ``radius`` of the reprojected ring points (``ring_check``, see :func:`ring_residual`; ones
    off ``frame``, within ``radius`` of its border or on its ``mask (H, W)`` are left out) is
    scored by the ring's mean absolute grey difference to frame 0. The best is kept only when it
    lowers that by at least ``min_gain`` (a fraction) and lies inside the window (a best on the
    window's edge is no minimum: the frame is off by more, or the ring does not tell).
    """
    _, _, world, grey0 = ring_check
    h, w = mask.shape
    uv, _ = project_points(transform_points(cam_from_world, world), intrinsics)  # (R, 2)
    x, y = uv[:, 0] - 0.5, uv[:, 1] - 0.5
    inner = (x >= radius) & (x <= w - 1 - radius) & (y >= radius) & (y <= h - 1 - radius)
    seen = np.isfinite(x) & np.isfinite(y) & inner
    xi = np.clip(np.round(np.nan_to_num(x)).astype(int), 0, w - 1)
    yi = np.clip(np.round(np.nan_to_num(y)).astype(int), 0, h - 1)
    seen &= mask[yi, xi] == 0
    if seen.sum() < MIN_SHIFT_EVIDENCE:
        return (0.0, 0.0)
    grey = cv2.cvtColor(frame, cv2.COLOR_RGB2GRAY)[..., None]  # (H, W, 1)
    x, y, ref = x[seen], y[seen], grey0[seen]  # (R',)
    keep = evidence(len(x))
    x, y, ref = x[keep], y[keep], ref[keep]  # (R'',) at most MAX_SHIFT_EVIDENCE
    dx, dy = best_shift(
        lambda dx, dy: np.mean(np.abs(sample_bilinear(grey, x + dx, y + dy)[:, 0] - ref)),
        radius,
        min_gain,
    )
    return (float(dx), float(dy))


def best_shift(error: Callable[[int, int], float], radius: int, min_gain: float) -> tuple[int, int]:
    """The whole-pixel shift ``(dx, dy)`` of least ``error(dx, dy)`` (a float) over the window
    ``|dx|, |dy| <= radius``, or ``(0, 0)`` unless it lowers the unshifted error by at least
    ``min_gain`` (a fraction) and lies inside the window, ``|dx|, |dy| < radius`` (a best on the
    window's edge is no minimum)."""
    steps = range(-radius, radius + 1)
    errors = np.array([[error(dx, dy) for dx in steps] for dy in steps])  # rows dy, columns dx
    iy, ix = np.unravel_index(int(np.argmin(errors)), errors.shape)
    on_edge = iy in (0, 2 * radius) or ix in (0, 2 * radius)
    if on_edge or errors[iy, ix] >= (1.0 - min_gain) * errors[radius, radius]:
        return (0, 0)  # no better than unshifted (ties and a zero error included)
    return (int(ix - radius), int(iy - radius))


def ring_residual(
    ring_check: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],
    frame: np.ndarray,
    mask: np.ndarray,
    cam_from_world: np.ndarray,
    intrinsics: np.ndarray,
    hole: np.ndarray,
    shift: tuple[float, float] = (0.0, 0.0),
) -> np.ndarray:
    """``(H, W)`` float32: how far ``frame (H, W, 3)`` reprojected disagrees with frame 0 near
    each ``hole (H, W)`` pixel (:func:`local_residual_map` of the ring's grey differences).
    ``shift``: ``(dx, dy)`` pixels added to the reprojection (:func:`ring_shift`).

    ``ring_check``: the ring's pixel rows, columns ``(R,)``, world points ``(R, 3)`` and frame-0
    grey levels ``(R,)``. Ring points that land outside ``frame``, behind it or on its ``mask (H,
    W)`` (dilated hands) are not evidence; when no ring point is evidence the map is 0 everywhere,
    so the frame is not held back (nothing shows it wrong).
    """
    ry, rx, world, grey0 = ring_check
    h, w = hole.shape
    uv, _ = project_points(transform_points(cam_from_world, world), intrinsics)  # (R, 2)
    x, y = uv[:, 0] - 0.5 + shift[0], uv[:, 1] - 0.5 + shift[1]
    seen = np.isfinite(x) & np.isfinite(y) & (x >= 0) & (x <= w - 1) & (y >= 0) & (y <= h - 1)
    xi = np.clip(np.round(np.nan_to_num(x)).astype(int), 0, w - 1)
    yi = np.clip(np.round(np.nan_to_num(y)).astype(int), 0, h - 1)
    seen &= mask[yi, xi] == 0
    diff = np.zeros((h, w), np.float32)
    known = np.zeros((h, w), bool)
    if seen.any():
        grey = cv2.cvtColor(frame, cv2.COLOR_RGB2GRAY)[..., None]  # (H, W, 1)
        got = sample_bilinear(grey, x[seen], y[seen])[:, 0].astype(np.float32)  # (R',)
        diff[ry[seen], rx[seen]] = np.abs(got - grey0[seen])
        known[ry[seen], rx[seen]] = True
    return local_residual_map(diff, known, hole)


class OccluderColours:
    """Tells samples that look like frame 0's hands and arms from ones that look like background.

    Two small palettes (k-means in RGB) are learned from frame 0 ``image (H, W, 3)``: one from
    the pixels under its ``hand (H, W)`` mask, one from a ring of ``ring_px`` round ``target
    (H, W)`` (the dilated mask, so the ring holds background only). A sample is hand-like when
    its nearest hand colour is closer than ``ratio`` times its nearest background colour: another
    frame
    whose mask missed a sleeve would otherwise paste that sleeve into the hole (a ghost), and a
    median over frames does not remove an arm that stays in place for most of the clip.
    """

    def __init__(
        self,
        image: np.ndarray,
        hand: np.ndarray,
        target: np.ndarray,
        ratio: float = 0.6,
        ring_px: int = 15,
    ) -> None:
        self.ratio = ratio
        ring = (dilate(target, ring_px) > 0) & ~(target > 0)  # (H, W)
        self.hand = _palette(image[hand > 0], 4)  # (k, 3)
        self.background = _palette(image[ring], 6)  # (k', 3)

    def hand_like(self, colours: np.ndarray) -> np.ndarray:
        """``(N,)`` bool: which of ``colours (N, 3)`` look like a hand or arm of frame 0."""
        if self.ratio <= 0 or self.hand is None or self.background is None or not len(colours):
            return np.zeros(len(colours), bool)
        c = colours.astype(np.float32)[:, None]  # (N, 1, 3)
        to_hand = np.linalg.norm(c - self.hand[None], axis=2).min(axis=1)  # (N,)
        to_background = np.linalg.norm(c - self.background[None], axis=2).min(axis=1)  # (N,)
        return to_hand < self.ratio * to_background


def _palette(colours: np.ndarray, k: int) -> np.ndarray | None:
    """``(k, 3)`` float32 k-means centres of ``colours (N, 3)`` (deterministic), or None if few."""
    if len(colours) < 4 * k:
        return None
    data = colours.astype(np.float32)
    if len(data) > 20000:  # a fixed, even subsample keeps it fast and deterministic
        data = data[:: len(data) // 20000 + 1]
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 20, 1.0)
    cv2.setRNGSeed(0)
    _, _, centres = cv2.kmeans(data, k, None, criteria, 2, cv2.KMEANS_PP_CENTERS)
    return centres


def slot_median(samples: np.ndarray, count: np.ndarray) -> np.ndarray:
    """Per-pixel median ``(M, 3)`` float32 of the first ``count (M,)`` of ``samples (S, M, 3)``.

    Pixels with no sample (count 0) are 0.
    """
    out = np.zeros(samples.shape[1:], np.float32)  # (M, 3)
    for n in range(1, len(samples) + 1):
        sel = count == n
        if sel.any():
            out[sel] = np.median(samples[:n, sel], axis=0)
    return out


REMAP_CHUNK = 32000  # cv2.remap refuses maps with SHRT_MAX (32767) or more rows


def sample_bilinear(image: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Bilinear samples ``(N, C)`` of ``image (H, W, C)`` at OpenCV pixel coordinates ``x, y (N,)``.

    Borders replicate. Done in chunks: ``cv2.remap`` asserts on maps of 32767 or more rows.
    """
    out = np.empty((len(x), image.shape[2]), dtype=image.dtype)
    for start in range(0, len(x), REMAP_CHUNK):
        part = slice(start, start + REMAP_CHUNK)
        map_x = x[part].astype(np.float32).reshape(-1, 1)
        map_y = y[part].astype(np.float32).reshape(-1, 1)
        got = cv2.remap(image, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        out[part] = got.reshape(-1, image.shape[2])
    return out


def reproject_fill(
    frames: np.ndarray,
    hand_mask: np.ndarray,
    depth0: np.ndarray,
    world_from_cam: np.ndarray,
    intrinsics: np.ndarray,
    depth: np.ndarray | None = None,
    dilate_px: int = 2,
    depth_tolerance: float = 0.05,
    inpaint_radius: float = 5.0,
    candidates: int = 1,
    unseen_method: str = "telea",
    occluder_ratio: float = 0.0,
    local_residual: float = 0.0,
    ring_px: int = 15,
    measured: np.ndarray | None = None,
    shift_px: int = 0,
    shift_gain: float = 0.2,
) -> FillResult:
    """Remove the hand from ``frames[0]``; see the module docstring.

    ``frames (T, H, W, 3)`` uint8 RGB, ``hand_mask (T, H, W)`` 1 = hand, ``depth0 (H, W)``
    metres (0 = unknown), ``world_from_cam (T, 4, 4)``, ``intrinsics (4,)``, optional
    ``depth (T, H, W)`` of every frame for the agreement test. ``local_residual``: a frame
    fills only the hole pixels whose nearby ring (``ring_px`` round the hole, reprojected with
    frame 0's measured depth, or the inpainted one where it is not measured) it shows within
    this many grey levels of frame 0 (mean absolute difference; 0: off): a moved object or a
    wrong pose near the hole does not fill it.
    ``measured (H, W)``: where ``depth0`` is measured (an estimated depth's confident pixels);
    the rest is inpainted with the hole's depth (step 1) and lifts the ring with it (None: all
    known depth counts; also when no pixel outside the hole is measured). ``shift_px > 0``
    (with the ring check): each frame's reprojection is moved by :func:`ring_shift` (less than
    ``shift_px`` pixels, kept when it lowers the ring's residual by ``shift_gain``) before the
    check and sampling.
    """
    t, h, w = frames.shape[:3]
    if hand_mask.shape != (t, h, w) or depth0.shape != (h, w) or world_from_cam.shape != (t, 4, 4):
        raise InpaintInputError(
            f"shapes disagree: frames {frames.shape}, hand_mask {hand_mask.shape}, depth0 "
            f"{depth0.shape}, world_from_cam {world_from_cam.shape}"
        )
    masks = dilate(hand_mask > 0, dilate_px)  # (T, H, W)
    target = masks[0] > 0  # (H, W) pixels to fill
    image = frames[0].copy()
    fill_source = np.zeros((h, w), np.uint8)
    source_frame = np.zeros((h, w), np.uint16)
    if not target.any():
        return FillResult(image, fill_source, source_frame, target)
    # 1. Depth behind the hand: inpaint frame 0's depth over the hand and unknown pixels.
    trusted = depth0 > 0  # (H, W)
    if measured is not None and (trusted & measured & ~target).any():
        trusted &= measured  # else nothing is sure: all known depth counts, as without it
    unknown = (target | ~trusted).astype(np.uint8)
    known_depth = depth0[unknown == 0]
    if known_depth.size == 0:
        raise InpaintInputError("frame 0 has no known depth outside the hand")
    d0 = np.where(unknown > 0, 0.0, depth0).astype(np.float32)
    # Navier-Stokes: OpenCV 5's Telea returns noise on float32 images (measured: a smooth slope
    # came back between 0.06 and 2.9); NS continues it within 3% here.
    d0 = cv2.inpaint(d0, unknown, inpaint_radius, cv2.INPAINT_NS)  # (H, W)
    d0 = np.where(d0 > 0, d0, float(np.median(known_depth)))
    # 2. Lift the masked pixels of frame 0 to the world.
    ys, xs = np.nonzero(target)  # (M,)
    points_cam0 = unproject_depth(d0, intrinsics)[ys, xs]  # (M, 3)
    points_world = transform_points(world_from_cam[0], points_cam0)  # (M, 3)
    candidates = max(1, int(candidates))
    occluders = None
    if occluder_ratio > 0:
        occluders = OccluderColours(frames[0], hand_mask[0] > 0, target, occluder_ratio)
    samples = np.zeros((candidates, len(ys), 3), np.float32)  # colours per candidate slot
    count = np.zeros(len(ys), np.int32)  # (M,) slots each pixel filled
    ring_check = None
    if local_residual > 0:  # 3. the ring round the hole, where frame 0 has a depth
        ring = (dilate(target, ring_px) > 0) & ~target & (depth0 > 0)  # (H, W)
        ry, rx = np.nonzero(ring)  # (R,)
        ring_depth = np.where(trusted, depth0, d0)  # (H, W) measured, else as the hole's
        ring_world = transform_points(
            world_from_cam[0], unproject_depth(ring_depth, intrinsics)[ry, rx]
        )
        grey0 = cv2.cvtColor(frames[0], cv2.COLOR_RGB2GRAY).astype(np.float32)  # (H, W)
        ring_check = (ry, rx, ring_world, grey0[ry, rx])
    for k in range(1, t):  # 4. closest frames first
        todo = count < candidates
        if not todo.any():
            break
        idx = np.nonzero(todo)[0]
        cam_from_world = invert_se3(world_from_cam[k])
        uv, z = project_points(transform_points(cam_from_world, points_world[idx]), intrinsics)
        shift = (0.0, 0.0)  # (dx, dy) pixels: the pose's drift seen on the ring
        if ring_check is not None and shift_px > 0:
            shift = ring_shift(
                ring_check, frames[k], masks[k], cam_from_world, intrinsics, shift_px, shift_gain
            )
        x = uv[:, 0] - 0.5 + shift[0]  # (m,) OpenCV coordinates: pixel centre of column 0 is 0
        y = uv[:, 1] - 0.5 + shift[1]
        ok = np.isfinite(x) & np.isfinite(y) & (x >= 0) & (x <= w - 1) & (y >= 0) & (y <= h - 1)
        xi = np.clip(np.round(np.nan_to_num(x)).astype(int), 0, w - 1)
        yi = np.clip(np.round(np.nan_to_num(y)).astype(int), 0, h - 1)
        ok &= masks[k][yi, xi] == 0
        if depth is not None:
            seen = depth[k][yi, xi].astype(np.float64)
            ok &= (seen <= 0) | (np.abs(seen - z) <= depth_tolerance * np.maximum(z, 1e-6))
        if ring_check is not None and ok.any():
            near = ring_residual(
                ring_check, frames[k], masks[k], cam_from_world, intrinsics, target, shift
            )
            ok &= near[ys[idx], xs[idx]] <= local_residual
        if not ok.any():
            continue
        sampled = sample_bilinear(frames[k], x[ok], y[ok])  # (m_ok, 3)
        got = idx[ok]
        if occluders is not None:  # not another frame's missed hand or arm
            keep = ~occluders.hand_like(sampled)
            got, sampled = got[keep], sampled[keep]
        samples[count[got], got] = sampled
        first = got[count[got] == 0]
        source_frame[ys[first], xs[first]] = k
        count[got] += 1
    done = count > 0
    colours = slot_median(samples, count)  # (M, 3)
    todo = ~done
    image[ys[done], xs[done]] = np.clip(np.round(colours[done]), 0, 255).astype(np.uint8)
    fill_source[ys[done], xs[done]] = FILL_REPROJECTED
    # 5. OpenCV for what no frame saw.
    unseen = np.zeros((h, w), np.uint8)
    unseen[ys[todo], xs[todo]] = 1
    if unseen.any():
        image = unseen_fill(image, unseen, inpaint_radius, unseen_method)
        fill_source[unseen > 0] = FILL_OPENCV
    fill_source[~target] = FILL_ORIGINAL
    return FillResult(image, fill_source, source_frame, target)
