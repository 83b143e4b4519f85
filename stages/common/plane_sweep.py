"""Plane-sweep multi-view stereo with known poses: OpenCV on the CPU, torch on a GPU.

``depth_camera`` sweeps frame 0 (:func:`first_frame_depth`); ``state_fusion`` sweeps every
``stride``-th frame of a clip whose cameras are known (:func:`clip_depth`).

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

Two implementations of the same algorithm (``PlaneSweepParams.backend``):

- ``opencv`` (the CPU default): one plane at a time, each source warped by the plane-induced
  homography ``H = K (R + t n^T / d) K^-1`` with ``cv2.warpPerspective`` and scored with box
  filters, while running winners (best score, its plane, and the scores of the planes on either
  side for the parabola) are kept per source and for the aggregate. Memory is ``O(S H W)`` instead
  of the ``O(S D H W)`` cost volume; horizontal bands of the image run on ``threads`` worker
  threads. Hand masks are burnt into the source images as a sentinel value, so one warp per
  plane and source carries both the image and its mask.
- ``torch``: the whole cost volume with ``grid_sample`` and ``avg_pool2d``; the default on a GPU
  (``device`` other than ``cpu``), and the reference the OpenCV path is tested against.

Both share the window semantics: a window at the image border averages the pixels inside the
image only, and counts as seen by a source when every one of those pixels samples (bilinearly)
valid pixels of the source only, in front of its camera: pixels whose value would blend in a
hand, or the zeros beyond the source image, are not seen.
"""

from __future__ import annotations

import itertools
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import cv2
import numpy as np
import torch
import torch.nn.functional as nnf

from egosim.pipeline.geometry import intrinsics_matrix

BACKENDS = ("auto", "opencv", "torch")


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
    device: str = "cpu"  # torch device (torch backend only)
    backend: str = "auto"  # "opencv", "torch", or "auto" = opencv on device "cpu", else torch
    threads: int = 0  # worker threads of the opencv backend; 0 = torch.get_num_threads()

    def __post_init__(self) -> None:
        """Raise :class:`PlaneSweepError` naming every bad field at once."""
        problems: list[str] = []
        if self.num_planes < 3:
            problems.append(f"num_planes must be >= 3, got {self.num_planes}")
        if self.window < 1 or self.window % 2 == 0:
            problems.append(f"window must be odd and >= 1, got {self.window}")
        if self.top_k < 1:
            problems.append(f"top_k must be >= 1, got {self.top_k}")
        if not self.max_zncc > self.min_zncc:
            problems.append(
                f"max_zncc must exceed min_zncc, got {self.min_zncc} and {self.max_zncc}"
            )
        if self.backend not in BACKENDS:
            problems.append(f"backend must be one of {list(BACKENDS)}, got {self.backend!r}")
        if self.threads < 0:
            problems.append(f"threads must be >= 0, got {self.threads}")
        if problems:
            raise PlaneSweepError("; ".join(problems))

    def resolved_backend(self) -> str:
        """``opencv`` or ``torch``: the backend ``auto`` stands for on this ``device``."""
        if self.backend != "auto":
            return self.backend
        return "opencv" if torch.device(self.device).type == "cpu" else "torch"


@dataclass(frozen=True)
class PlaneSweepResult:
    """Depth and confidence of the reference frame at the working resolution."""

    depth: np.ndarray  # (H, W) float32 z-depth in the poses' scale
    confidence: np.ndarray  # (H, W) float32 in [0, 1]
    zncc: np.ndarray  # (H, W) float32 winning aggregated ZNCC
    agreement: np.ndarray  # (H, W) bool, at least ``min_support`` sources agree
    support: np.ndarray  # (H, W) int, sources that see the pixel and agree with its depth
    visible: np.ndarray  # (H, W) int, sources that see the pixel at its depth


@dataclass(frozen=True)
class _Winners:
    """What both backends hand to :func:`_finish`: the sweep's winners, as numpy arrays."""

    inv: np.ndarray  # (H, W) float32 refined inverse depth of the aggregate winner
    best: np.ndarray  # (H, W) float32 winning aggregated ZNCC
    arg: np.ndarray  # (H, W) int winning plane index
    per_src_inv: np.ndarray  # (S, H, W) float32 refined inverse depth of each source's winner
    seen: np.ndarray  # (S, H, W) bool, source sees the pixel at the aggregate winner's plane
    ref_std: np.ndarray  # (H, W) float32 reference window standard deviation


def _finish(
    won: _Winners,
    ref_valid: np.ndarray,
    step: float,
    far: float,
    p: PlaneSweepParams,
) -> PlaneSweepResult:
    """Depth, visibility-aware agreement and confidence from the winners of either backend."""
    # a winner on the first or last plane is no peak: the surface may lie outside the range
    interior = (won.arg > 0) & (won.arg < p.num_planes - 1)  # (H, W)
    # Visibility-aware cross-check: every source that sees the pixel at the chosen depth (window
    # inside its image and off its hands) votes with its own winner; sources that do not see it
    # (out of view, or a hand covers the scene later in the clip) neither support nor veto.
    close = np.abs(won.per_src_inv - won.inv[None]) <= np.float32(p.agreement_planes * step)
    agrees = won.seen & close  # (S, H, W)
    support = agrees.sum(0)  # (H, W)
    visible = won.seen.sum(0)  # (H, W)
    agree = support >= p.min_support
    span = np.float32(p.max_zncc - p.min_zncc)
    photometric = np.clip((won.best - np.float32(p.min_zncc)) / span, 0.0, 1.0)
    textured = won.ref_std >= p.min_texture
    ok = agree & interior & textured & (np.asarray(ref_valid) > 0.5) & (won.best > -1.0)
    conf = np.where(ok, photometric, np.float32(0.0))
    depth = 1.0 / np.maximum(won.inv, np.float32(1.0 / (far * 4.0)))
    return PlaneSweepResult(
        depth=depth.astype(np.float32),
        confidence=conf.astype(np.float32),
        zncc=won.best.astype(np.float32),
        agreement=agree,
        support=support,
        visible=visible,
    )


# --- torch backend: the whole cost volume ------------------------------------------------------


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
        mode="bilinear",
        padding_mode="zeros",
        align_corners=False,
    )  # (D, 1, H, W), < 1 where the sample blends in the outside or a hand
    valid = (valid > 0.999).float()  # weights under 1/1024 do not count (as in OpenCV's warps)
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


def _sweep_torch(
    ref_image: np.ndarray,
    src_images: np.ndarray,
    intrinsics: np.ndarray,
    src_from_ref: np.ndarray,
    inv_depths: np.ndarray,
    src_valid: np.ndarray,
    p: PlaneSweepParams,
) -> _Winners:
    """Winners of the sweep from the full ``(S, D, H, W)`` cost volume on ``p.device``.

    ``ref_image (H, W)``, ``src_images (S, H, W)``, ``src_from_ref (S, 4, 4)``, ``inv_depths
    (D,)`` increasing, ``src_valid (S, H, W)`` 1 where source pixels may be matched.
    """
    dev = p.device
    s = len(src_images)
    h, w = ref_image.shape
    inv_t = torch.as_tensor(inv_depths, dtype=torch.float32, device=dev)  # (D,)
    ref = torch.as_tensor(ref_image, device=dev)[None, None]  # (1, 1, H, W)
    ref_mean = _box(ref, p.window)
    ref_std = (_box(ref * ref, p.window) - ref_mean * ref_mean).clamp_min(0.0).sqrt()
    scores = []
    for j in range(s):
        grid = _grids(intrinsics, src_from_ref[j], inv_t, h, w, dev)  # (D, H, W, 2)
        src = torch.as_tensor(src_images[j], device=dev)[None, None]
        valid = torch.as_tensor(np.asarray(src_valid[j], np.float32), device=dev)[None, None]
        scores.append(_zncc_volume(ref, ref_mean, ref_std, src, valid, grid, p.window))
        del grid
    vol = torch.stack(scores)  # (S, D, H, W)
    del scores
    k = max(1, min(p.top_k, s))
    agg = vol.topk(k, dim=0).values.mean(0)  # (D, H, W)
    inv, best, arg = _winner(agg, inv_t)
    at_final = vol.gather(1, arg[None, None].expand(s, 1, -1, -1))[:, 0]  # (S, H, W)
    per_src = torch.stack([_winner(vol[j], inv_t)[0] for j in range(s)])  # (S, H, W)
    return _Winners(
        inv=inv.cpu().numpy(),
        best=best.cpu().numpy(),
        arg=arg.cpu().numpy(),
        per_src_inv=per_src.cpu().numpy(),
        seen=(at_final > -1.0).cpu().numpy(),
        ref_std=ref_std[0, 0].cpu().numpy(),
    )


# --- OpenCV backend: one plane at a time, running winners ------------------------------------


class _RunningWinner:
    """Winner-take-all over planes fed one at a time, with what the parabola needs.

    Equivalent to :func:`_winner` over the stacked scores: the first maximum wins, and the scores
    of the planes just before and after it are kept. All arrays have the pixel grid's ``shape``;
    the caller must keep the previous plane's scores unchanged until the next update.
    """

    def __init__(self, shape: tuple[int, int]) -> None:
        self.best = np.full(shape, -np.inf, np.float32)  # best score so far
        self.idx = np.zeros(shape, np.int32)  # plane of the best score
        self.lo = np.zeros(shape, np.float32)  # score of the plane before the best
        self.hi = np.zeros(shape, np.float32)  # score of the plane after the best
        # where each plane won (uint8 255/0, by plane parity): masks for cv2.copyTo, which is
        # an order of magnitude faster than a masked np.copyto
        self._better = [np.zeros(shape, np.uint8), np.zeros(shape, np.uint8)]
        self._prev: np.ndarray | None = None  # scores of the previous plane

    def update(self, score: np.ndarray, plane: np.ndarray) -> np.ndarray:
        """Feed ``score`` of the next plane, whose index fills the int32 array ``plane``.

        Planes come in order from 0. Returns where this plane now wins (uint8 255/0), a mask that
        stays valid until the update after next.
        """
        d = int(plane.flat[0])
        better = self._better[d % 2]
        if self._prev is not None:  # pixels won by the previous plane: this is their "after"
            cv2.copyTo(score, self._better[(d - 1) % 2], self.hi)
        cv2.compare(score, self.best, cv2.CMP_GT, dst=better)
        cv2.copyTo(score if self._prev is None else self._prev, better, self.lo)
        np.maximum(self.best, score, out=self.best)
        cv2.copyTo(plane, better, self.idx)
        self._prev = score
        return better

    def refined(self, inv_depths: np.ndarray) -> np.ndarray:
        """Inverse depth of the winner, refined by a parabola through its neighbours."""
        d = len(inv_depths)
        np.copyto(self.hi, self.best, where=self.idx == d - 1)  # the clamp of :func:`_winner`
        denom = self.lo - 2.0 * self.best + self.hi
        peak = (self.idx > 0) & (self.idx < d - 1) & (denom < -1e-6)
        with np.errstate(divide="ignore", invalid="ignore"):
            offset = np.where(peak, 0.5 * (self.lo - self.hi) / denom, 0.0)
        offset = np.clip(offset, -0.5, 0.5).astype(np.float32)
        inv_f32 = inv_depths.astype(np.float32)
        step = inv_f32[1] - inv_f32[0]
        return inv_f32[self.idx] + offset * step


def _plane_homographies(
    intrinsics: np.ndarray, src_from_ref: np.ndarray, inv_depths: np.ndarray
) -> np.ndarray:
    """Ref-to-source pixel-index homographies ``(S, D, 3, 3)`` of fronto-parallel planes.

    The plane ``z = 1/q`` of the reference camera maps by ``H = K (R + t n^T q) K^-1`` with
    ``n = (0, 0, 1)``; the half-pixel shifts move between the pixel-centre convention of the
    intrinsics (centres at integer + 0.5) and OpenCV's integer pixel indices.
    """
    k = intrinsics_matrix(intrinsics)  # (3, 3)
    k_inv = np.linalg.inv(k)
    rot = src_from_ref[:, None, :3, :3]  # (S, 1, 3, 3)
    trans = src_from_ref[:, None, :3, 3]  # (S, 1, 3)
    n_q = np.zeros((len(inv_depths), 3))  # (D, 3): n^T q
    n_q[:, 2] = inv_depths
    hom = k @ (rot + trans[..., :, None] * n_q[None, :, None, :]) @ k_inv  # (S, D, 3, 3)
    to_centre = np.array([[1.0, 0.0, 0.5], [0.0, 1.0, 0.5], [0.0, 0.0, 1.0]])
    to_index = np.array([[1.0, 0.0, -0.5], [0.0, 1.0, -0.5], [0.0, 0.0, 1.0]])
    return to_index @ hom @ to_centre


class _RefWindows:
    """Window statistics of the reference image that every source's ZNCC needs."""

    def __init__(self, ref: np.ndarray, window: int) -> None:
        h, w = ref.shape
        self.window = window
        self.image = np.ascontiguousarray(ref, dtype=np.float32)  # (H, W)
        self.count = _box_sum(np.ones((h, w), np.float32), window)  # (H, W) in-image pixels
        inv_count = 1.0 / self.count
        self.mean = _box_sum(self.image, window) * inv_count  # (H, W)
        var = _box_sum(self.image * self.image, window) * inv_count - self.mean * self.mean
        self.std = np.sqrt(np.maximum(var, 0.0)).astype(np.float32)  # (H, W)
        self.eps = (self.count * 1e-6).astype(np.float32)  # (H, W) n * eps of the ZNCC


def _box_sum(x: np.ndarray, window: int, out: np.ndarray | None = None) -> np.ndarray:
    """Sum over a ``window x window`` box of ``x (H, W)`` float32, zero outside the image."""
    return cv2.boxFilter(
        x, -1, (window, window), dst=out, normalize=False, borderType=cv2.BORDER_CONSTANT
    )


def _top_k_mean(
    scores: np.ndarray, k: int, top: np.ndarray, carry: np.ndarray, tmp: np.ndarray
) -> np.ndarray:
    """Mean of the ``k`` largest of ``scores (S, H, W)`` per pixel, as ``torch.topk(...).mean``.

    Running insertion, largest first, into the scratch ``top (k, H, W)`` with the scratch
    ``carry`` and ``tmp (H, W)``: about ``2 k S`` elementwise passes and no sort.
    """
    s = len(scores)
    if k == 1:
        return scores.max(0)
    if k == s:
        return scores.mean(0)
    top.fill(-np.inf)
    for j in range(s):
        np.minimum(top[0], scores[j], out=carry)  # what drops out of place 0 moves down
        np.maximum(top[0], scores[j], out=top[0])
        for i in range(1, k):
            if i < k - 1:
                np.minimum(top[i], carry, out=tmp)
            np.maximum(top[i], carry, out=top[i])
            carry, tmp = tmp, carry
    agg = top[0] + top[1]
    for i in range(2, k):
        agg += top[i]
    return agg / np.float32(k)


class _Source:
    """One source frame of the OpenCV sweep: grey image with its hand mask burnt in.

    Invalid (hand) pixels, and the border beyond the image, take a sentinel value far below the
    image's range, so that any warped pixel whose bilinear footprint touches one of them comes out
    below ``lowest``: the warp of the image also warps the mask. OpenCV's bilinear weights are
    multiples of 1/1024, and ``sentinel`` is low enough that the smallest of them pulls a sample
    below ``lowest``; box sums over windows free of sentinels keep their precision (OpenCV's box
    filter sums in double).
    """

    def __init__(self, image: np.ndarray, valid: np.ndarray) -> None:
        image = np.asarray(image, dtype=np.float32)  # (H, W) grey
        invalid = (np.asarray(valid) <= 0.5).astype(np.uint8)  # (H, W) 1 = hand
        values = image[invalid == 0]
        lo, hi = (float(values.min()), float(values.max())) if values.size else (0.0, 1.0)
        self.lowest = lo  # warped values below this touched an invalid pixel
        self.sentinel = lo - 4096.0 * (hi - lo + 1.0)  # the smallest weight, 1/1024, still tells
        self.image = np.where(invalid > 0, np.float32(self.sentinel), image)  # (H, W) float32
        self.invalid_sum = cv2.integral(invalid)  # (H + 1, W + 1) int32
        self.any_invalid = bool(invalid.any())

    def sees_all(self, corners: np.ndarray) -> bool:
        """Whether every pixel of a warped rectangle is valid, from its mapped ``corners (4, 3)``.

        True when the corners are in front of the camera and their bounding box (which holds the
        whole convex image of the rectangle, with the bilinear footprints) lies inside the image
        and off the hand mask: then no pixel needs checking. False = look closer.
        """
        if corners[:, 2].min() <= 1e-6:
            return False
        x = corners[:, 0] / corners[:, 2]
        y = corners[:, 1] / corners[:, 2]
        h, w = self.image.shape
        if x.min() < 0.0 or y.min() < 0.0 or x.max() > w - 1 or y.max() > h - 1:
            return False
        if not self.any_invalid:
            return True
        x0, y0 = int(np.floor(x.min())), int(np.floor(y.min()))
        x1, y1 = int(np.ceil(x.max())) + 1, int(np.ceil(y.max())) + 1  # exclusive
        total = self.invalid_sum
        return int(total[y1, x1] - total[y0, x1] - total[y1, x0] + total[y0, x0]) == 0


class _Band:
    """Rows ``[y0, y1)`` of the reference image, swept over every plane and source.

    Bands are independent (every state is per pixel), so they run on separate threads. Sources
    are warped over the band plus a halo of ``window // 2`` rows on each side, so that window sums
    inside the band cover the same pixels as over the whole image (their rounding differs).
    """

    def __init__(self, y0: int, y1: int, ref: _RefWindows, num_sources: int, top_k: int) -> None:
        h, w = ref.image.shape
        r = ref.window // 2
        self.ref = ref
        self.y0, self.y1 = y0, y1
        self.a, self.b = max(0, y0 - r), min(h, y1 + r)  # rows warped: the band and its halo
        rows, n = self.b - self.a, y1 - y0
        self.inner = slice(y0 - self.a, y1 - self.a)  # the band's rows among the warped ones
        # homographies take band row indices: warped row i is image row i + a
        self.shift = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, self.a], [0.0, 0.0, 1.0]])
        self.ref_rows = ref.image[self.a : self.b]  # (rows, W)
        self.count, self.neg_mean = ref.count[y0:y1], -ref.mean[y0:y1]  # (n, W)
        self.std, self.eps = ref.std[y0:y1], ref.eps[y0:y1]  # (n, W)
        # x, x^2 and x * ref stacked with r zero rows between, for one box filter call
        self.stack = np.zeros((3 * rows + 2 * r, w), np.float32)  # (3 rows + 2r, W)
        self.sums = np.empty_like(self.stack)
        starts = [i * (rows + r) for i in range(3)]
        self.x, self.xx, self.xr = (self.stack[s : s + rows] for s in starts)  # (rows, W)
        self.s1, self.s2, self.s3 = (self.sums[s : s + rows][self.inner] for s in starts)  # (n, W)
        self.bad = np.empty((rows, w), np.uint8)  # warped invalid mask
        self.bad_window = np.empty((rows, w), np.uint8)  # window touches an invalid pixel
        self.den, self.var = np.empty((n, w), np.float32), np.empty((n, w), np.float32)
        self.kernel = np.ones((ref.window, ref.window), np.uint8)
        self.corners = np.array(
            [[0.0, 0.0, 1.0], [w - 1, 0.0, 1.0], [0.0, rows - 1, 1.0], [w - 1, rows - 1, 1.0]]
        )
        self.k = max(1, min(top_k, num_sources))
        self.scores = np.empty((2, num_sources, n, w), np.float32)  # by plane parity
        self.top = np.empty((self.k, n, w), np.float32)
        self.carry, self.spare = np.empty((n, w), np.float32), np.empty((n, w), np.float32)
        self.per_src = [_RunningWinner((n, w)) for _ in range(num_sources)]
        self.agg = _RunningWinner((n, w))
        # each source's score at the aggregate winner's plane: -1 = does not see the pixel there
        self.at_winner = np.zeros((num_sources, n, w), np.float32)
        self.minus_one = np.full((n, w), -1.0, np.float32)
        self.plane = np.zeros((n, w), np.int32)  # the current plane's index

    def _score(self, src: _Source, hom: np.ndarray, out: np.ndarray) -> None:
        """ZNCC ``out (n, W)`` of one source warped by the ref-to-source ``hom (3, 3)``.

        -1 where the window is not seen: off the source image, on its hand, behind its camera.
        """
        w, rows = self.x.shape[1], self.x.shape[0]
        hom = hom @ self.shift
        inverse = cv2.WARP_INVERSE_MAP
        cv2.warpPerspective(
            src.image,
            hom,
            (w, rows),
            dst=self.x,
            flags=inverse | cv2.INTER_LINEAR,
            borderValue=src.sentinel,
        )
        masked = not src.sees_all(self.corners @ hom.T)
        if masked:
            cv2.compare(self.x, src.lowest, cv2.CMP_LT, dst=self.bad)  # 255: blends in invalid
            if (self.corners @ hom[2]).min() <= 1e-6:  # part of the plane is behind the camera
                ys, xs = np.mgrid[0:rows, 0:w]
                self.bad[hom[2, 0] * xs + hom[2, 1] * ys + hom[2, 2] <= 1e-6] = 255
            # a window is unseen when one of its in-image pixels is (outside the image is not)
            cv2.dilate(
                self.bad,
                self.kernel,
                dst=self.bad_window,
                borderType=cv2.BORDER_CONSTANT,
                borderValue=0,
            )
        np.multiply(self.x, self.x, out=self.xx)
        np.multiply(self.x, self.ref_rows, out=self.xr)
        _box_sum(self.stack, self.ref.window, out=self.sums)
        # window sums S1 = sum(x), S2 = sum(x^2), S3 = sum(x ref): n cov = S3 - S1 mean_ref and
        # n^2 var = n S2 - S1^2, so zncc = cov / (std_ref sqrt(var) + eps)
        #                                 = n cov / (std_ref sqrt(n^2 var) + n eps)
        cv2.accumulateProduct(self.s1, self.neg_mean, self.s3)  # s3 := n cov
        cv2.multiply(self.s1, self.s1, dst=self.var, scale=-1.0)
        cv2.accumulateProduct(self.s2, self.count, self.var)  # n^2 var
        np.maximum(self.var, 0.0, out=self.var)
        cv2.sqrt(self.var, dst=self.den)
        np.multiply(self.den, self.std, out=self.den)
        np.add(self.den, self.eps, out=self.den)
        np.divide(self.s3, self.den, out=out)
        np.clip(out, -1.0, 1.0, out=out)
        if masked:
            cv2.copyTo(self.minus_one, self.bad_window[self.inner], out)

    def run(self, sources: list[_Source], homs: np.ndarray) -> None:
        """Sweep every plane of ``homs (S, D, 3, 3)`` over ``sources``, feeding the winners."""
        for d in range(homs.shape[1]):
            self.plane.fill(d)
            scores = self.scores[d % 2]  # (S, n, W); the other parity holds plane d - 1
            for j, src in enumerate(sources):
                self._score(src, homs[j, d], scores[j])
                self.per_src[j].update(scores[j], self.plane)
            agg = _top_k_mean(scores, self.k, self.top, self.carry, self.spare)
            better = self.agg.update(agg, self.plane)
            for j in range(len(sources)):
                cv2.copyTo(scores[j], better, self.at_winner[j])


def _sweep_opencv(
    ref_image: np.ndarray,
    src_images: np.ndarray,
    intrinsics: np.ndarray,
    src_from_ref: np.ndarray,
    inv_depths: np.ndarray,
    src_valid: np.ndarray,
    p: PlaneSweepParams,
) -> _Winners:
    """Winners of the sweep, one plane at a time with OpenCV warps and box filters.

    Same arguments as :func:`_sweep_torch`. The image is cut into horizontal bands, swept on
    ``p.threads`` worker threads; in a band, per plane, each source is warped into the reference
    view, scored by ZNCC and fed to its own running winner, then the best ``top_k`` scores are
    averaged and fed to the aggregate winner, which also records which sources see the pixel at
    its plane.
    """
    s = len(src_images)
    h = ref_image.shape[0]
    ref = _RefWindows(ref_image, p.window)
    sources = [_Source(src_images[j], src_valid[j]) for j in range(s)]
    homs = _plane_homographies(intrinsics, src_from_ref, inv_depths)  # (S, D, 3, 3)
    threads = p.threads if p.threads > 0 else torch.get_num_threads()
    num_bands = max(1, min(threads, h // max(p.window, 8)))  # one band per thread
    edges = [int(e) for e in np.linspace(0, h, num_bands + 1).round()]
    bands = [_Band(y0, y1, ref, s, p.top_k) for y0, y1 in itertools.pairwise(edges)]

    def run(band: _Band) -> None:
        band.run(sources, homs)

    if threads > 1 and len(bands) > 1:
        with ThreadPoolExecutor(max_workers=threads) as pool:
            list(pool.map(run, bands))
    else:
        for band in bands:
            run(band)
    return _Winners(
        inv=np.concatenate([b.agg.refined(inv_depths) for b in bands]),
        best=np.concatenate([b.agg.best for b in bands]),
        arg=np.concatenate([b.agg.idx for b in bands]),
        per_src_inv=np.concatenate(
            [np.stack([win.refined(inv_depths) for win in b.per_src]) for b in bands], axis=1
        ),
        seen=np.concatenate([b.at_winner for b in bands], axis=1) > -1.0,
        ref_std=ref.std,
    )


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
    ``depth_range`` is ``(near, far)`` in the poses' scale. ``params.backend`` picks the OpenCV
    or the torch implementation of the same algorithm. Raises :class:`PlaneSweepError`.
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
    if ref_valid is None:
        ref_valid = np.ones((h, w), np.float32)
    if src_valid is None:
        src_valid = np.ones((s, h, w), np.float32)
    # float32 like torch.linspace, so that both backends sweep the very same planes
    inv_depths = torch.linspace(1.0 / far, 1.0 / near, p.num_planes).numpy()  # (D,)
    ref_from_world = np.asarray(ref_cam_from_world, dtype=np.float64)
    src_from_ref = np.asarray(src_cam_from_world, np.float64) @ np.linalg.inv(ref_from_world)
    sweep = _sweep_opencv if p.resolved_backend() == "opencv" else _sweep_torch
    won = sweep(ref_image, src_images, intrinsics, src_from_ref, inv_depths, src_valid, p)
    step = float(inv_depths[1] - inv_depths[0])
    return _finish(won, ref_valid, step, far, p)


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
    ref: int = 0,
) -> list[int]:
    """Pick source frames for frame ``ref`` (default 0) by triangulation angle and view overlap.

    ``cam_from_world (T, 4, 4)``, ``candidates (T,)`` bool (registered frames), ``points_world
    (P, 3)`` the SfM points frame ``ref`` sees (may be empty when ``median_depth`` is given:
    overlap is then taken as 1). A point counts as seen by frame ``j`` when it projects inside
    the image and, given ``usable (T, H, W)`` bool, onto a usable (non-hand) pixel: hands that
    later cover part of the scene make a frame a worse source. A frame scores
    ``overlap * min(a / target, target / a)`` for its angle ``a`` (baseline over the median
    scene depth); frames seeing less than
    ``min_overlap`` of the points are skipped; picks keep a minimum index gap so that they spread
    along the clip. Returns frame indices (may be fewer than ``num_sources``).
    """
    t = len(cam_from_world)
    h, w = image_size
    fx, fy, cx, cy = np.asarray(intrinsics, dtype=np.float64)
    world_from_cam0 = np.linalg.inv(cam_from_world[ref])
    pts_cam0 = points_world @ cam_from_world[ref, :3, :3].T + cam_from_world[ref, :3, 3]  # (P, 3)
    z_med = float(np.median(pts_cam0[:, 2])) if median_depth is None else float(median_depth)
    scores = np.full(t, -np.inf)
    for j in np.flatnonzero(candidates):
        if j == ref:
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
    """Grey float32 ``(h, w) = size`` of an RGB ``frame (H, W, 3)``, area-averaged."""
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
    """Depth and confidence ``(H, W)`` of ``frames[0]``: :func:`frame_depth` with ``ref`` 0."""
    return frame_depth(
        frames, usable, intrinsics, cam_from_world, 0, sources, depth_range, scale, params, edge_rel
    )


def frame_depth(
    frames: np.ndarray,
    usable: np.ndarray | None,
    intrinsics: np.ndarray,
    cam_from_world: np.ndarray,
    ref: int,
    sources: list[int],
    depth_range: tuple[float, float],
    scale: float,
    params: PlaneSweepParams,
    edge_rel: float = 0.1,
) -> tuple[np.ndarray, np.ndarray]:
    """Depth and confidence ``(H, W)`` of ``frames[ref]`` at full resolution.

    The sweep runs at ``scale`` times the frame size; inverse depth is upsampled bilinearly and
    confidence by nearest neighbour, after zeroing it where the working-resolution depth jumps by
    more than ``edge_rel`` within 3x3 pixels (upsampling there would blend two surfaces).
    ``usable (T, H, W)`` is True where pixels may be matched (not hand); None = everywhere.
    """
    from egosim.pipeline.geometry import scale_intrinsics

    big_h, big_w = frames.shape[1:3]
    h, w = max(8, round(big_h * scale)), max(8, round(big_w * scale))
    k_small = scale_intrinsics(intrinsics, w / big_w, h / big_h)
    idx = [ref, *sources]
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
        cam_from_world[ref],
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


@dataclass(frozen=True)
class ClipDepthParams:
    """Knobs of :func:`clip_depth` (per-frame depth of a clip from known poses)."""

    stride: int = 2  # every stride-th frame (and the last) is swept; the others stay 0 (unknown)
    num_sources: int = 6  # source frames per reference frame
    window_frames: int = 8  # sources are taken among frames at most this far from the reference
    scale: float = 0.5  # sweep resolution as a fraction of the frame size
    target_angle_deg: float = 8.0  # preferred triangulation angle of a source (select_sources)
    edge_rel: float = 0.1  # no confidence where depth jumps by more than this within 3x3 pixels
    min_confidence: float = 0.5  # depth kept where the sweep's confidence is at least this
    consistency_rel: float = 0.01  # a depth agrees with a neighbour's within this relative error
    min_consistent: int = 1  # swept neighbours (2 on each side) that must agree; 0 = no check
    sweep: PlaneSweepParams = PlaneSweepParams()  # the sweep itself

    def __post_init__(self) -> None:
        """Raise :class:`PlaneSweepError` naming every bad field at once."""
        problems: list[str] = []
        for name in ("stride", "window_frames"):
            if getattr(self, name) < 1:
                problems.append(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.num_sources < 2:
            problems.append(f"num_sources must be >= 2, got {self.num_sources}")
        if not 0.05 <= self.scale <= 1.0:
            problems.append(f"scale must be in [0.05, 1], got {self.scale}")
        if not 0.0 < self.target_angle_deg < 90.0:
            problems.append(f"target_angle_deg must be in (0, 90), got {self.target_angle_deg}")
        if not self.edge_rel > 0:
            problems.append(f"edge_rel must be > 0, got {self.edge_rel}")
        if not self.consistency_rel > 0:
            problems.append(f"consistency_rel must be > 0, got {self.consistency_rel}")
        if self.min_consistent < 0:
            problems.append(f"min_consistent must be >= 0, got {self.min_consistent}")
        if not 0.0 <= self.min_confidence <= 1.0:
            problems.append(f"min_confidence must be in [0, 1], got {self.min_confidence}")
        if problems:
            raise PlaneSweepError("; ".join(problems))


@dataclass(frozen=True)
class ClipDepth:
    """Per-frame depth of a clip: swept frames have depth where confident, the others zero."""

    depth: np.ndarray  # (T, H, W) float32 z-depth in the poses' scale, 0 = unknown
    confidence: np.ndarray  # (T, H, W) float32 in [0, 1], 0 on frames not swept
    swept: tuple[int, ...]  # frames that were swept
    skipped: tuple[int, ...]  # swept frames without 2 usable sources (depth 0)


def swept_frames(num_frames: int, stride: int) -> list[int]:
    """Frames :func:`clip_depth` sweeps: every ``stride``-th from 0, and the last."""
    frames = list(range(0, num_frames, stride))
    if frames[-1] != num_frames - 1:
        frames.append(num_frames - 1)
    return frames


def clip_depth(
    frames: np.ndarray,
    usable: np.ndarray | None,
    intrinsics: np.ndarray,
    cam_from_world: np.ndarray,
    depth_ranges: np.ndarray,
    params: ClipDepthParams | None = None,
) -> ClipDepth:
    """Depth of every ``params.stride``-th frame of ``frames (T, H, W, 3)`` from known poses.

    Each swept frame is the reference of a plane sweep (:func:`frame_depth`) against up to
    ``num_sources`` frames within ``window_frames`` of it (chosen by :func:`select_sources`:
    close in time, so that an object the hands move has moved little between them), over its
    own ``depth_ranges[k] = (near, far)``. ``usable (T, H, W)`` bool is False on hands (not
    matched); ``cam_from_world (T, 4, 4)``. Depth is kept where confidence reaches
    ``min_confidence`` and, unless ``min_consistent`` is 0, where neighbouring swept frames
    agree (:func:`consistent_depth`). A frame with fewer than 2 sources that move away from it
    keeps depth 0 and is listed in ``skipped``. Raises :class:`PlaneSweepError` on bad shapes.
    """
    p = params if params is not None else ClipDepthParams()
    frames = np.asarray(frames)
    t, h, w = frames.shape[:3]
    cam_from_world = np.asarray(cam_from_world, np.float64)
    depth_ranges = np.asarray(depth_ranges, np.float64)
    if cam_from_world.shape != (t, 4, 4) or depth_ranges.shape != (t, 2):
        raise PlaneSweepError(
            f"need poses ({t}, 4, 4) and depth ranges ({t}, 2) for {t} frames, got "
            f"{cam_from_world.shape} and {depth_ranges.shape}"
        )
    if usable is not None and np.shape(usable) != (t, h, w):
        raise PlaneSweepError(f"usable must be ({t}, {h}, {w}), got {np.shape(usable)}")
    depth = np.zeros((t, h, w), np.float32)
    conf = np.zeros((t, h, w), np.float32)
    swept, skipped = swept_frames(t, p.stride), []
    for ref in swept:
        near, far = (float(x) for x in depth_ranges[ref])
        window = np.abs(np.arange(t) - ref) <= p.window_frames
        sources = select_sources(
            cam_from_world,
            window,
            np.zeros((0, 3)),
            intrinsics,
            (h, w),
            p.num_sources,
            median_depth=float(np.sqrt(near * far)),
            target_angle_deg=p.target_angle_deg,
            ref=ref,
        )
        if len(sources) < 2:
            skipped.append(ref)
            continue
        d, c = frame_depth(
            frames,
            usable,
            intrinsics,
            cam_from_world,
            ref,
            sources,
            (near, far),
            p.scale,
            p.sweep,
            p.edge_rel,
        )
        keep = c >= p.min_confidence
        depth[ref] = np.where(keep, d, 0.0)
        conf[ref] = c
    if p.min_consistent > 0:
        depth = consistent_depth(
            depth, intrinsics, cam_from_world, swept, p.consistency_rel, p.min_consistent
        )
    return ClipDepth(depth, conf, tuple(swept), tuple(skipped))


def consistent_depth(
    depth: np.ndarray,
    intrinsics: np.ndarray,
    cam_from_world: np.ndarray,
    swept: list[int],
    rel: float,
    min_consistent: int,
) -> np.ndarray:
    """``depth (T, H, W)`` kept where at least ``min_consistent`` neighbouring swept frames agree.

    A pixel of frame ``k`` is lifted to 3D and projected into each of the two swept frames
    before and after it; a neighbour agrees when its own depth at that pixel (nearest) is within
    ``rel`` (relative) of the projected depth. Isolated sweep errors disagree, and so does an
    object while the hands move it; the scene at rest agrees.
    """
    from egosim.pipeline.geometry import unproject_depth

    h, w = depth.shape[1:]
    fx, fy, cx, cy = np.asarray(intrinsics, np.float64)
    out = np.zeros_like(depth)
    for i, k in enumerate(swept):
        sel = depth[k] > 0
        if not sel.any():
            continue
        pts = unproject_depth(depth[k], intrinsics)[sel].astype(np.float64)  # (n, 3) camera k
        votes = np.zeros(len(pts), np.int32)
        for j in [*swept[max(0, i - 2) : i], *swept[i + 1 : i + 3]]:
            j_from_k = cam_from_world[j] @ np.linalg.inv(cam_from_world[k])
            q = pts @ j_from_k[:3, :3].T + j_from_k[:3, 3]  # (n, 3) camera j
            z = q[:, 2]
            with np.errstate(divide="ignore", invalid="ignore"):
                u = np.floor(fx * q[:, 0] / z + cx)
                v = np.floor(fy * q[:, 1] / z + cy)
            inside = (z > 0) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
            dj = np.zeros(len(pts), np.float32)
            dj[inside] = depth[j][v[inside].astype(int), u[inside].astype(int)]
            votes += (inside & (dj > 0) & (np.abs(dj - z) <= rel * z)).astype(np.int32)
        kept = np.zeros((h, w), bool)
        kept[sel] = votes >= min_consistent
        out[k] = np.where(kept, depth[k], 0.0)
    return out
