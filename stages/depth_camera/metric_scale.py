"""Metric scale of a reconstruction from the size of the hands in it (issue 17).

SfM gives poses and frame-0 depth in arbitrary units; MediaPipe's world landmarks carry an
average-hand size prior (wrist to middle knuckle 8-10 cm), so a hand placed in the camera by PnP
has a metric depth. Hands touch or hover in front of the surfaces behind them, so along the ray of
a joint its metric depth ``z_m`` plus the distance from the joint to the surface it rests on is at
most ``s * z_s``, where ``z_s`` is the depth of the scene surface under the joint in
reconstruction units and ``s`` the wanted scale in metres per unit, with equality at contact.

Method, for one clip (:func:`estimate_metric_scale`):

1. **Landmarks**: the hands stage's detector (:mod:`egosim.stages.common.hand_landmarks`: MediaPipe
   Hands in video mode plus zoomed tiles, found hands followed through misses, overlapping
   detections dropped): per detection 21 pixel landmarks and 21 metric world landmarks.
   (depth_camera v7 and before ran a plainer detector of its own: 6 usable detections on DWM
   00013 where this one gives 22, none on a HOT3D window where the hands stage found hands.)
2. **Metric joints**: the hands stage's own lift (:mod:`egosim.stages.common.hand_lift`, the
   ``lift`` field): an average metric palm placed by planar PnP onto the palm landmarks, every
   joint on its pixel's ray at the depth the posed landmarks give it; so the scene ends up in
   metres where the hands stage puts the hands (those whose 3D it trusts: since hands v10 it
   withholds the 3D of palms turning off their track, which this per-detection rule does not
   link into tracks and so still uses; step 5's cut drops such a tail where it is large).
   Detections without a palm pose in front of the camera, or smaller than ``min_hand_px``, are
   skipped. (``lift="translation"``, depth_camera
   v6: MediaPipe's world landmarks translated only; on real clips that sits 6-67% nearer than
   the palm lift, and real hands came out 1.5x deeper than the surfaces they touch.)
3. **Scene depth under each joint**: frame 0's depth is lifted to world points with
   ``world_from_cam[0]`` and splatted into frame ``t`` with a z-buffer (frame 0 uses ``depth0``
   itself). ``z_s`` is the median of the known depths within ``window_px`` of the joint's pixel
   (this also bridges the splat's pinholes); a window that spans a depth edge (max/min above
   ``1 + max_edge_rel``) or has fewer than ``min_window_pixels`` known depths gives no sample.
   A joint where frame ``t`` shows frame 0's scene colour (the splatted colour differs by less
   than ``min_colour_diff``) is hidden behind the scene, not in front of it, and is dropped.
4. **Per detection**: ``r = (z_m + contact_offset_m) / z_s`` per joint; the detection's estimate
   is the ``joint_quantile`` (0.75) quantile of its joints' ``r``: the part of the hand nearest
   its surface, but not the single highest joint (fingers curled behind an object and hidden by
   the back of the hand itself have ``r > s``; no colour test sees them).
5. **Rule**: estimates more than ``outlier_mads`` (5) scaled MADs (1.4826 x the median
   absolute deviation) above their median are left out (depth_camera v12); the scale is the
   ``contact_quantile`` (0.9) quantile of the rest: hands at rest or touching sit at the top of
   the distribution, reaching/hovering ones below it, and the top decile is left out as
   outliers. Why the quantile and not the median: a hovering hand's joints lie nearer than the
   surface behind them, so its ``r`` is below the scale; the median of a clip where the hands
   often reach is low by their hover gap (oracle landmarks, default world: median -5% to -10%,
   0.9 quantile -2% to +4%). Why the cut: the top decile is all the quantile drops, and a
   misfit detection can make more of the clip than that (tabletop 1: a MediaPipe hand followed
   through misses onto a box, 8 of 61 detections at 1.43-2.82 x the scale, so the 0.9
   quantile landed in them: +46%); only the upper tail is cut, so at least half the estimates
   stay, and a clip whose hands mostly reach has a wide MAD, so nothing is cut there (DWM
   00013). ``spread`` is the MAD / median of the kept estimates at or above their median (how
   well the contact half agrees). Fewer than ``min_detections`` usable detections: ``scale``
   is None and ``reason`` says why (``num_samples`` counts the left-out ones too).
6. **Wide-window fallback** (``source`` ``hand_size_wide``): when step 5 finds too few
   detections, steps 3-5 run again with ``z_s`` the median of the known depths within
   ``wide_window_px`` of the joint, and a window counted as spanning a depth edge when its 75th
   depth percentile exceeds its 25th by more than ``wide_max_spread_rel``. A low-texture surface
   (a plain drawer front, a wall) has confident plane-sweep depth only at its edges and marks,
   rarely right under a joint; the wider window reaches them. The result is less local (a
   neighbouring surface can answer for the touched one), so it is used only when the strict
   window fails, and the row says which one it came from. Both failing: ``scale`` None, the
   reason names both. ``wide_window_px`` and ``wide_max_spread_rel`` were checked on the tuning
   clips with the wide window forced (oracle landmarks, tabletop 0 / 1): -2.0% / -4.1%, and
   -0.8% / -1.3% with depth known on a random 5% of pixels only (the strict window then finds
   2 / 6 detections). The first look at the problem was DWM 00017 (a plain drawer front, plane
   sweep confident on 19% of frame 0, 2 usable detections of 47), which now gets 0.018 m/unit
   from 15 detections; held out, MediaPipe: default tabletop 4 (strict: no scale) -9.1%, wild 1
   still none (0 usable detections in either window).
   **Outliers** (depth_camera v18): before the splat, a frame-0 depth more than
   ``wide_outlier_rel`` (0.2, as a ratio) off the median of the known depths in its
   ``wide_window_px`` block and the 8 around it is left out (:func:`drop_depth_outliers`), and
   per detection, joints whose wide-window depth is more than ``wide_joint_rel`` (0.25) off the
   median of its joints' depths are left out (:func:`on_main_surface`: the hand rests on the
   surface most of it lies over). Why: on DWM 00017 the plane sweep is confident on a handful of
   pixels just under a gap line between two drawers at 0.55 x the depth of the drawer front
   around them (a horizontal edge matched at the wrong plane); the drawer front has almost no
   other confident depth, so those pixels were all the 25 px window held under the hand at
   frames 17-20 (and half of it at 10-12 in another SfM), and which of them the sweep kept
   confident changed with any change to the SfM: v17 gave 0.0297, 0.0441 or 0.0522 m/unit on
   three SfM results of the same frames (v18: 0.0297, 0.0298, 0.0315). Limit: outliers that are
   the majority of their 75 px neighbourhood are kept (a thicker line on a plainer surface);
   sparse depths beside a dense nearer object go too (fewer samples there, not wrong ones).

``contact_offset_m`` (3 cm), ``joint_quantile`` and ``contact_quantile`` were tuned on the
synthetic world, tabletop seeds 0-1 (61 frames, 480x832, poses and depth scaled by 0.37 and 2.9,
frame-0 depth masked under the hands), with the translation lift. Scale error (estimate / truth -
1) with the palm lift and the hands stage's detector (depth_camera v8), from
``.venv/bin/python tests/test_metric_scale.py MODE:SEED ...``:

- tuned on: tabletop 0 oracle +0.8%, MediaPipe +14.0%; tabletop 1 oracle +7.2%, MediaPipe +19.8%.
- held out: default wild 0 oracle +0.3%, MediaPipe +34.5%; alt tabletop 0 / 1 / 2 oracle -4.6% /
  -6.3% / +1.2%, MediaPipe +14.6% / +11.5% / +17.0%; alt wild 0 oracle -1.6%, MediaPipe +34.9%.
- The MediaPipe path is high because MediaPipe's 2D palm on the world's drawn hands is 0.74
  (default) / 0.85 (alt) of the true joints' projected palm (median over 300 / 324 hand-frames),
  so the metric palm fitted to it lands further away; the hands stage places those hands at the
  same depth, so hands and scene agree. On real hands with 3D truth (InterHand fixture, landmarks
  on each true hand's ROI) the ratio is 0.90-1.11, median 0.97 of 6 hands. With the translation
  lift the MediaPipe path gave -6.3% / +0.5% tuned and -1.9% to +14.3% held out, but disagreed
  with the hands stage.
- Real clips (``python -m bench.real_video``, hand/surface ratio at contact against the scene
  cloud; against its measured points only in brackets), v6 -> v8: DWM 00013 1.53 (1.59) -> 1.08
  (1.13), scale 0.094 -> 0.133 m/unit; DWM 00017 1.50 (1.57) -> 0.91 (0.95), scale 0.018 ->
  0.030; EgoDex 1.04 (0.35) -> 0.97 (0.32), scale 0.022 -> 0.024. EgoDex's all-points figure
  follows the fill of the depth under the hands (0.48 in a v7 run with the same hands and a 7%
  different scale): the plane sweep is confident on 8.5% of its frame 0, a nearly still head over
  a plain table, and its measured figure says the geometry, not the lift, is off there.
- Filling frame-0 depth holes before measuring (Telea up to 50 px, or the scene cloud's
  superpixel plane fill) was measured and dropped (depth_camera v5): it cost usable detections
  on the synthetic world and moved the EgoDex clip's scale by +10% to +35%.
- Real hands with 3D truth (InterHand fixture, ``python -m bench.hands_real``): lifted depth /
  true depth, median of 5 hands, palm lift 0.87, translation fit 0.57.
- depth_camera v11 (the hands stage v8's lift: refined palm poses, MediaPipe's proximal
  phalanges 1/0.70 longer, also applied to the oracle landmarks), v8 -> v11 figures above:
  tabletop 0 oracle +0.6 -> +3.3%, MediaPipe +13.8 -> +14.6%; tabletop 1 oracle +6.9 -> +2.9%,
  MediaPipe +19.4 -> +46.2% (its per-detection median 1.05 -> 1.09, but 8 estimates (was 6) at
  1.25 or more, where the 0.9 quantile now lands); wild 0 MediaPipe +34.5 -> +31.6%; alt
  tabletop 0 / 1 / 2 MediaPipe +14.7 / +11.4 / +16.8 -> +14.7 / +13.3 / +13.9%; alt wild 0
  +35.3 -> +24.7%; InterHand palm lift 0.87 -> 0.98. Real clips (``bench.real_video``):
  hand/surface DWM 00013 1.10 -> 1.06, 00017 0.92 -> 0.91, HOT3D 0.95 -> 0.99; HOT3D scale
  0.0843 -> 0.0864 m/unit.

- depth_camera v12 (``outlier_mads`` 5, chosen on the default world: tabletop 0-3, wild 0-2;
  held out: alt tabletop 0-3, wild 0-1; the tests' oracle now lifts true joints with
  ``proximal_ratio`` 1.0), MediaPipe path v11 -> v12: tabletop 1 +46.2 -> +15.0%, every other
  default clip unchanged (tabletop 0 +14.6, wild 0 +31.6, tabletop 3 +17.4, wild 1 +21.1;
  tabletop 2, wild 2: no scale either way); held out unchanged (alt tabletop 0-3 +14.7 /
  +13.3 / +13.9 / +10.2, wild 0 +24.7) but alt wild 1 +15.5 -> +14.6%. What is left is the
  lift's depth on the drawn hands: divided by each clip's median lifted / true hand depth,
  the MediaPipe path's mean |error| is 7.6 -> 3.5% (default; tabletop 1 +23.5 -> -2.9%) and
  2.2 -> 2.1% (alt). Oracle (true joints, ``proximal_ratio`` 1.0): tabletop 1 +2.6 -> -0.3%,
  the others unchanged, mean |error| default 1.9 -> 1.5%, alt 2.4% both. Other cuts measured
  on the same samples: the 0.8 quantile (oracle default -1.7% to -4.5%), a cut at 1.15 x the
  median (default MediaPipe net 2.3%, but on real clips it cut contact hands: DWM 00013 scale
  0.142 -> 0.113, HOT3D 0.086 -> 0.068), 4 MADs (oracle tabletop 1 -5.4%), a density mode of
  the upper half (oracle -4% to -10%), a cut at the first 5% gap above the median (MediaPipe
  wild 1 net +2.7 -> -7.5%). Real clips
  (the last stop's cameras, samples recomputed; HOT3D pooled over its windows' depth0):
  DWM 00013 0.142 and 00017 0.0293 m/unit unchanged; HOT3D 0.0864 -> 0.0848 (5 of 135
  estimates at 1.8-2.6 x the scale left out; hand/surface 0.99 -> 1.01 expected).

The error is the same for both factors (the method is scale-equivariant). Known biases: the size
prior (MediaPipe's hands came out 3% near on median, +-8% per detection), hands that never
touch a visible surface (the estimate is then low by their hover gap), and moving objects (frame
0's depth shows them where they were).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from egosim.pipeline.geometry import invert_se3, project_points, transform_points, unproject_depth
from egosim.stages.common.hand_landmarks import (
    HandLandmarkParams,
    RawLandmarks,
    detect_hand_landmarks,
    drop_overlapping,
    place_in_camera,
)
from egosim.stages.common.hand_lift import MEDIAPIPE_PROXIMAL_RATIO, MIN_POSE_DEPTH, palm_pnp_pose

SOURCE_HAND_SIZE = "hand_size"  # ScaleEstimate.source: strict window (steps 1-5)
SOURCE_HAND_SIZE_WIDE = "hand_size_wide"  # ScaleEstimate.source: wide-window fallback (step 6)
ALL_JOINTS = tuple(range(21))  # MANO/MediaPipe joint indices
LIFTS = ("palm_pnp", "translation")  # MetricScaleParams.lift


class MetricScaleParamsError(ValueError):
    """A :class:`MetricScaleParams` field holds an invalid value; names every bad one."""


class MetricScaleInputError(ValueError):
    """The inputs of :func:`estimate_metric_scale` disagree in shape; names every problem."""


@dataclass(frozen=True)
class MetricScaleParams:
    """Knobs of :func:`estimate_metric_scale`."""

    detector: HandLandmarkParams = field(default_factory=HandLandmarkParams)  # MediaPipe, the
    # hands stage's detector (same defaults), so the scale measures the hands that stage places
    joints: tuple[int, ...] = ALL_JOINTS  # joints that give samples (MediaPipe order)
    lift: str = "palm_pnp"  # how a detection is placed in the camera: "palm_pnp", the hands
    # stage's own lift (:mod:`egosim.stages.common.hand_lift`; a detection without a palm pose in
    # front of the camera gives no sample), so the scale puts the scene where the hands stage puts
    # the hands; "translation": MediaPipe's world landmarks translated only (depth_camera v6)
    proximal_ratio: float = MEDIAPIPE_PROXIMAL_RATIO  # palm lift: how short the landmarks'
    # proximal phalanges are (hand_lift.landmark_bone_lengths): MediaPipe's 0.70; 1.0 for true
    # joints (an oracle's landmarks, in tests)
    contact_offset_m: float = 0.03  # depth from a resting hand's joint centres to the surface it
    # rests on, metres (half a hand's thickness, longer along oblique rays); tuned, tabletop 0-1
    window_px: int = 3  # z_s: median of known depths within this many pixels of the joint
    min_window_pixels: int = 5  # fewer known depths in the window: no sample
    max_edge_rel: float = 0.15  # window max/min depth above 1 + this: a depth edge, no sample
    min_confidence: float = 0.5  # depth0 pixels with confidence0 below this count as unknown
    min_colour_diff: float = 20.0  # joint hidden by the scene: frame t matches frame 0's splat
    # there (mean over the window of the max channel difference below this, 0..255); 0 = no test
    colour_window_px: int = 1  # window half size of the colour test, pixels
    min_hand_px: float = 24.0  # detections whose landmark box diagonal is smaller are skipped
    min_joint_samples: int = 5  # a detection needs this many joint samples to count
    joint_quantile: float = 0.75  # per detection: this quantile of its joints' ratios (tuned)
    contact_quantile: float = 0.9  # per clip: this quantile of the per-detection estimates (tuned)
    outlier_mads: float | None = 5.0  # per clip, before the contact quantile: estimates more than
    # this many scaled MADs (1.4826 x MAD) above their median are left out (misfit detections,
    # e.g. MediaPipe landmarks off any hand); None keeps all (v11). Chosen on the default world
    spread_from_quantile: float = 0.5  # spread: MAD/median of the estimates above this quantile
    min_detections: int = 5  # fewer usable detections: no scale
    wide_window_px: int = 25  # fallback (step 6): z_s from the known depths within this many
    # pixels when the strict window gives fewer than min_detections; 0 = no fallback
    wide_max_spread_rel: float = 0.3  # fallback: window's depth 75th/25th percentile above
    # 1 + this = a depth edge, no sample (the strict max/min test fails on noisy wide windows)
    wide_min_window_pixels: int = 10  # fallback: fewer known depths in the window = no sample
    wide_outlier_rel: float | None = 0.2  # fallback: a frame-0 depth more than this off (as a
    # ratio) the median of the known depths around it (3 x 3 blocks of wide_window_px) is left
    # out before splatting: an isolated confident outlier of the plane sweep (DWM 00017: a
    # drawer's edge line at 0.55 x its front's depth) would otherwise be the wide window's only
    # depth under a hand; None keeps all (v17). Set on DWM 00017 (depth_camera v18)
    wide_joint_rel: float | None = 0.25  # fallback: a detection's joints whose surface depth is
    # more than this off (as a ratio) the median of its joints' surface depths are left out:
    # the hand rests on the surface most of its joints lie over; None keeps all (v17). DWM
    # 00017's split joints: 1.35 apart; 0.15 cost 2 points on synthetic tabletop 0 (wide forced)

    def __post_init__(self) -> None:
        problems: list[str] = []
        if not self.joints or any(not 0 <= j < 21 for j in self.joints):
            problems.append(f"joints must be a non-empty tuple of indices 0..20, got {self.joints}")
        for name in ("joint_quantile", "contact_quantile", "spread_from_quantile"):
            value = getattr(self, name)
            if not 0.0 <= value <= 1.0:
                problems.append(f"{name} must be in [0, 1], got {value!r}")
        if not (np.isfinite(self.proximal_ratio) and 0.0 < self.proximal_ratio <= 2.0):
            problems.append(f"proximal_ratio must be in (0, 2], got {self.proximal_ratio!r}")
        for name in (
            "contact_offset_m",
            "max_edge_rel",
            "min_confidence",
            "min_hand_px",
            "wide_max_spread_rel",
        ):
            value = getattr(self, name)
            if not (np.isfinite(value) and value >= 0):
                problems.append(f"{name} must be finite and >= 0, got {value!r}")
        for name in ("wide_outlier_rel", "wide_joint_rel"):
            value = getattr(self, name)
            if value is not None and not (np.isfinite(value) and value > 0):
                problems.append(f"{name} must be None or finite and > 0, got {value!r}")
        if self.outlier_mads is not None and not (
            np.isfinite(self.outlier_mads) and self.outlier_mads > 0
        ):
            problems.append(
                f"outlier_mads must be None or finite and > 0, got {self.outlier_mads!r}"
            )
        for name in ("window_px", "colour_window_px", "wide_window_px"):
            if getattr(self, name) < 0:
                problems.append(f"{name} must be >= 0, got {getattr(self, name)!r}")
        if self.lift not in LIFTS:
            problems.append(f"lift must be one of {LIFTS}, got {self.lift!r}")
        if not 0.0 <= self.min_colour_diff <= 255.0:
            problems.append(f"min_colour_diff must be in [0, 255], got {self.min_colour_diff!r}")
        for name in (
            "min_window_pixels",
            "min_joint_samples",
            "min_detections",
            "wide_min_window_pixels",
        ):
            if getattr(self, name) < 1:
                problems.append(f"{name} must be >= 1, got {getattr(self, name)!r}")
        if problems:
            raise MetricScaleParamsError("invalid MetricScaleParams: " + "; ".join(problems))


@dataclass(frozen=True)
class ScaleEstimate:
    """Metric scale of a reconstruction and how well its samples agree."""

    scale: float | None  # metres per reconstruction unit; None when it could not be estimated
    spread: float | None  # MAD / median of the contact estimates (relative); None with no scale
    num_samples: int  # usable detections (frame, hand) that gave an estimate
    source: str = SOURCE_HAND_SIZE  # metric cue the scale comes from
    reason: str = ""  # why scale is None ("" when it is set)


def splat_depth(
    depth0: np.ndarray,
    intrinsics: np.ndarray,
    world_from_cam0: np.ndarray,
    world_from_cam_t: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Frame 0's depth ``(H, W)`` seen from camera ``t``, z-buffered.

    Each known pixel of ``depth0`` is lifted to the world with ``world_from_cam0 (4, 4)``, moved
    into camera ``t`` (``world_from_cam_t (4, 4)``) and written to the pixel it projects into;
    where several land on one pixel the nearest wins. Returns ``depth (H, W)`` (0 = unknown) and
    ``source (H, W)`` int64, the flat frame-0 pixel index each pixel came from (-1 = none).
    """
    h, w = depth0.shape
    known = np.isfinite(depth0) & (depth0 > 0)  # (H, W)
    points_cam0 = unproject_depth(np.where(known, depth0, 0.0), intrinsics)[known]  # (P, 3)
    src = np.flatnonzero(known)  # (P,) flat frame-0 pixel of each point
    t_from_0 = invert_se3(world_from_cam_t) @ world_from_cam0  # (4, 4)
    points_t = transform_points(t_from_0, points_cam0)  # (P, 3)
    uv, z = project_points(points_t, intrinsics)  # (P, 2), (P,)
    ok = np.isfinite(uv).all(axis=1) & (z > 0)
    cols = np.floor(uv[ok, 0]).astype(np.int64)  # (Q,)
    rows = np.floor(uv[ok, 1]).astype(np.int64)  # (Q,)
    z, src = z[ok], src[ok]
    inside = (cols >= 0) & (cols < w) & (rows >= 0) & (rows < h)
    flat = rows[inside] * w + cols[inside]  # (Q',)
    z, src = z[inside], src[inside]
    order = np.argsort(z, kind="stable")  # nearest first
    uniq, first = np.unique(flat[order], return_index=True)
    depth = np.zeros(h * w)
    depth[uniq] = z[order][first]
    source = np.full(h * w, -1, dtype=np.int64)
    source[uniq] = src[order][first]
    return depth.reshape(h, w), source.reshape(h, w)


def drop_depth_outliers(depth: np.ndarray, block_px: int, rel: float) -> np.ndarray:
    """``depth (H, W)`` (0 or NaN = unknown) with its isolated outliers set to 0.

    The image is cut into square blocks of ``block_px``; a known depth more than ``rel`` off (as
    a ratio, either way) the median of the known depths in its block and the 8 around it is left
    out. A confident plane-sweep depth that disagrees with most of its neighbourhood is an
    outlier (a thin line matched at the wrong plane) or a thin object; either way not the
    surface a hand rests on (step 6 of the module docstring).
    """
    h, w = depth.shape
    known = np.isfinite(depth) & (depth > 0)  # (H, W)
    rows, cols = -(-h // block_px), -(-w // block_px)
    median = np.full((rows, cols), np.nan)
    for i in range(rows):
        for j in range(cols):
            win = (
                slice(max(0, (i - 1) * block_px), (i + 2) * block_px),
                slice(max(0, (j - 1) * block_px), (j + 2) * block_px),
            )
            values = depth[win][known[win]]
            if values.size:
                median[i, j] = np.median(values)
    around = np.repeat(np.repeat(median, block_px, axis=0), block_px, axis=1)[:h, :w]  # (H, W)
    ratio = np.where(known, depth, 1.0) / np.where(known, around, 1.0)  # (H, W)
    bad = known & ((ratio > 1.0 + rel) | (ratio < 1.0 / (1.0 + rel)))
    return np.where(known & ~bad, depth, 0.0)


def surface_depth(
    depth: np.ndarray, uv: np.ndarray, params: MetricScaleParams, wide: bool = False
) -> np.ndarray:
    """Scene depth ``(N,)`` under pixels ``uv (N, 2)`` of ``depth (H, W)``; NaN = no sample.

    Strict (``wide`` False): the median of the known depths within ``window_px``; NaN where
    fewer than ``min_window_pixels`` are known or the window spans a depth edge (max/min above
    ``1 + max_edge_rel``). Wide (step 6 of the module docstring): the median within
    ``wide_window_px``; NaN where fewer than ``wide_min_window_pixels`` are known or the 75th
    percentile exceeds the 25th by more than ``wide_max_spread_rel``.
    """
    h, w = depth.shape
    r = params.wide_window_px if wide else params.window_px
    min_pixels = params.wide_min_window_pixels if wide else params.min_window_pixels
    out = np.full(len(uv), np.nan)
    for n, (u, v) in enumerate(uv):
        if not (np.isfinite(u) and np.isfinite(v)):
            continue
        col, row = int(np.floor(u)), int(np.floor(v))
        if not (0 <= col < w and 0 <= row < h):
            continue
        patch = depth[max(0, row - r) : row + r + 1, max(0, col - r) : col + r + 1]
        values = patch[np.isfinite(patch) & (patch > 0)]  # (M,)
        if values.size < min_pixels:
            continue
        if wide:
            low, high = np.quantile(values, [0.25, 0.75])
            if high > (1.0 + params.wide_max_spread_rel) * low:
                continue
        elif values.max() > (1.0 + params.max_edge_rel) * values.min():
            continue
        out[n] = float(np.median(values))
    return out


def scene_visible(
    frame_t: np.ndarray,
    scene_t: np.ndarray,
    known: np.ndarray,
    uv: np.ndarray,
    params: MetricScaleParams,
) -> np.ndarray:
    """Per pixel ``uv (N, 2)``: does frame ``t`` show frame 0's scene there (the joint is hidden)?

    ``frame_t (H, W, 3)`` uint8, ``scene_t (H, W, 3)`` frame 0's colours splatted into view ``t``,
    ``known (H, W)`` bool where the splat has a value. True where the mean over the window of
    the per-pixel max channel difference is below ``min_colour_diff``: the hand is not in front
    of that surface there, so the joint lies behind it (e.g. fingers around an object). ``(N,)``.
    """
    h, w = known.shape
    r = params.colour_window_px
    out = np.zeros(len(uv), dtype=bool)
    diff = np.abs(frame_t.astype(np.int16) - scene_t.astype(np.int16)).max(axis=-1)  # (H, W)
    for n, (u, v) in enumerate(uv):
        col, row = int(np.floor(u)), int(np.floor(v))
        if not (0 <= col < w and 0 <= row < h):
            continue
        win = (slice(max(0, row - r), row + r + 1), slice(max(0, col - r), col + r + 1))
        ok = known[win]
        if ok.any():
            out[n] = float(diff[win][ok].mean()) < params.min_colour_diff
    return out


def place_detection(
    uv: np.ndarray,
    world: np.ndarray,
    intrinsics: np.ndarray,
    lift: str,
    proximal_ratio: float = MEDIAPIPE_PROXIMAL_RATIO,
) -> np.ndarray | None:
    """Metric camera joints ``(21, 3)`` of one detection (``uv (21, 2)`` pixels, MediaPipe's
    ``world (21, 3)`` metres) by ``lift`` (:attr:`MetricScaleParams.lift`); None when the palm
    PnP finds no pose with every joint :data:`MIN_POSE_DEPTH` or more in front of the camera.
    ``proximal_ratio``: :attr:`MetricScaleParams.proximal_ratio` (palm lift only)."""
    if lift == "translation":
        return place_in_camera(uv, world, intrinsics)
    # The side does not change the placed points.
    pose = palm_pnp_pose(uv, world, intrinsics, proximal_ratio=proximal_ratio)
    if pose is None or float(pose[0][:, 2].min()) < MIN_POSE_DEPTH:
        return None
    return pose[0]


def detection_samples(
    landmarks: RawLandmarks,
    frames: np.ndarray,
    intrinsics: np.ndarray,
    world_from_cam: np.ndarray,
    depth0: np.ndarray,
    params: MetricScaleParams,
    wide: bool = False,
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per usable detection, its joints' metric and surface depths: ``(z_m (J,), z_s (J,))``.

    ``landmarks`` holds ``uv (T, K, 21, 2)`` pixels and metric ``world (T, K, 21, 3)``;
    ``frames (T, H, W, 3)`` uint8 RGB; ``depth0 (H, W)`` is frame 0's depth in reconstruction
    units (0 or NaN = unknown). Joints hidden behind the scene (:func:`scene_visible`) are
    dropped from frames after the first. ``wide``: surface depths from the wide window
    (:func:`surface_depth`).
    """
    joints = np.asarray(params.joints)
    out: list[tuple[np.ndarray, np.ndarray]] = []
    t_count = landmarks.present.shape[0]
    if wide and params.wide_outlier_rel is not None and params.wide_window_px > 0:
        depth0 = drop_depth_outliers(depth0, params.wide_window_px, params.wide_outlier_rel)
    for t in range(t_count):
        slots = [k for k in np.flatnonzero(landmarks.present[t])]
        if not slots:
            continue
        scene_t = None
        if t == 0:
            depth_t = np.where(np.isfinite(depth0), depth0, 0.0)
        else:
            depth_t, source = splat_depth(depth0, intrinsics, world_from_cam[0], world_from_cam[t])
            if params.min_colour_diff > 0:
                scene_t = frames[0].reshape(-1, 3)[np.maximum(source, 0)]  # (H*W, 3)
                scene_t = scene_t.reshape(frames.shape[1:])  # (H, W, 3)
        for k in slots:
            uv, world = landmarks.uv[t, k], landmarks.world[t, k]  # (21, 2), (21, 3)
            if not (np.isfinite(uv).all() and np.isfinite(world).all()):
                continue
            if np.linalg.norm(uv.max(axis=0) - uv.min(axis=0)) < params.min_hand_px:
                continue
            points_cam = place_detection(
                uv, world, intrinsics, params.lift, params.proximal_ratio
            )  # (21, 3) metres
            if points_cam is None:
                continue
            z_m = points_cam[joints, 2]  # (J,)
            z_s = surface_depth(depth_t, uv[joints], params, wide)  # (J,)
            ok = np.isfinite(z_s) & (z_m > 0)
            if scene_t is not None:
                seen = source >= 0  # (H, W) a known frame-0 pixel landed here
                ok &= ~scene_visible(frames[t], scene_t, seen, uv[joints], params)
            if wide and params.wide_joint_rel is not None and ok.any():
                ok &= on_main_surface(z_s, ok, params.wide_joint_rel)
            if ok.sum() < params.min_joint_samples:
                continue
            out.append((z_m[ok], z_s[ok]))
    return out


def on_main_surface(z_s: np.ndarray, ok: np.ndarray, rel: float) -> np.ndarray:
    """``(J,)`` bool: the joints whose surface depth ``z_s (J,)`` lies within ``rel`` (as a ratio,
    either way) of the median of the ``ok (J,)`` joints' depths (step 6 of the module
    docstring): a wide window that reached another surface than the one most of the hand lies
    over gives no sample."""
    median = float(np.median(z_s[ok]))
    with np.errstate(invalid="ignore"):
        return ok & (z_s <= (1.0 + rel) * median) & (z_s >= median / (1.0 + rel))


def without_outliers(estimates: np.ndarray, outlier_mads: float | None) -> np.ndarray:
    """``estimates (N,)`` less those more than ``outlier_mads`` scaled MADs (1.4826 x the median
    absolute deviation) above their median (step 5 of the module docstring); None keeps all.
    Only the upper tail is cut (hovering hands below the median are the contact rule's to
    skip), so at least half the estimates stay; with no spread (a MAD of 0) nothing is cut."""
    if outlier_mads is None or len(estimates) == 0:
        return estimates
    median = float(np.median(estimates))
    mad = 1.4826 * float(np.median(np.abs(estimates - median)))
    if mad <= 0.0:  # over half the estimates equal: no spread to measure a tail by
        return estimates
    return estimates[estimates <= median + outlier_mads * mad]


def scale_from_samples(
    samples: list[tuple[np.ndarray, np.ndarray]],
    params: MetricScaleParams,
    source: str = SOURCE_HAND_SIZE,
) -> ScaleEstimate:
    """Apply the contact rule (module docstring, steps 4-5) to :func:`detection_samples`.

    ``source`` names the cue in the returned :class:`ScaleEstimate`.
    """
    per_detection = np.array(
        [
            np.quantile((z_m + params.contact_offset_m) / z_s, params.joint_quantile)
            for z_m, z_s in samples
        ]
    )
    n = len(per_detection)
    if n < params.min_detections:
        return ScaleEstimate(
            scale=None,
            spread=None,
            num_samples=n,
            source=source,
            reason=f"{n} usable hand detections, need {params.min_detections}",
        )
    kept = without_outliers(per_detection, params.outlier_mads)  # (M,) M >= N / 2
    scale = float(np.quantile(kept, params.contact_quantile))
    top = kept[kept >= np.quantile(kept, params.spread_from_quantile)]
    median = float(np.median(top))
    spread = float(np.median(np.abs(top - median)) / median)
    return ScaleEstimate(scale=scale, spread=spread, num_samples=n, source=source)


def _check_inputs(
    landmarks: RawLandmarks,
    frames: np.ndarray,
    intrinsics: np.ndarray,
    world_from_cam: np.ndarray,
    depth0: np.ndarray | None,
    confidence0: np.ndarray | None,
) -> None:
    """Raise :class:`MetricScaleInputError` listing every shape disagreement."""
    problems: list[str] = []
    t = landmarks.present.shape[0]
    if frames.ndim != 4 or frames.shape[0] != t or frames.shape[-1] != 3:
        problems.append(f"frames must be (T={t}, H, W, 3), got {frames.shape}")
    if np.shape(intrinsics) != (4,):
        problems.append(f"intrinsics must be (4,), got {np.shape(intrinsics)}")
    if np.shape(world_from_cam) != (t, 4, 4):
        problems.append(f"world_from_cam must be (T={t}, 4, 4), got {np.shape(world_from_cam)}")
    for name, image in (("depth0", depth0), ("confidence0", confidence0)):
        if image is not None and np.shape(image) != frames.shape[1:3]:
            problems.append(f"{name} must be (H, W) = {frames.shape[1:3]}, got {np.shape(image)}")
    if problems:
        raise MetricScaleInputError("; ".join(problems))


def scale_from_landmarks(
    landmarks: RawLandmarks,
    frames: np.ndarray,
    intrinsics: np.ndarray,
    world_from_cam: np.ndarray,
    depth0: np.ndarray | None,
    confidence0: np.ndarray | None,
    params: MetricScaleParams | None = None,
) -> ScaleEstimate:
    """Steps 2-6 of the module docstring on given landmarks (MediaPipe's, or an oracle's).

    Shapes as :func:`estimate_metric_scale`; ``landmarks`` has ``T`` frames. Raises
    :class:`MetricScaleInputError` when the shapes disagree.
    """
    params = params or MetricScaleParams()
    _check_inputs(landmarks, frames, intrinsics, world_from_cam, depth0, confidence0)
    if depth0 is None:
        return ScaleEstimate(None, None, 0, reason="no frame-0 depth (static camera?)")
    depth0 = np.asarray(depth0, dtype=np.float64)
    if confidence0 is not None:
        depth0 = np.where(np.asarray(confidence0) >= params.min_confidence, depth0, 0.0)
    if not np.any(np.isfinite(depth0) & (depth0 > 0)):
        return ScaleEstimate(None, None, 0, reason="frame-0 depth has no known pixel")
    if not landmarks.present.any():
        return ScaleEstimate(None, None, 0, reason="no hand detected")
    return window_cascade([(landmarks, frames, intrinsics, world_from_cam, depth0, params)], params)


def estimate_metric_scale(
    frames: np.ndarray,
    intrinsics: np.ndarray,
    world_from_cam: np.ndarray,
    depth0: np.ndarray | None,
    confidence0: np.ndarray | None,
    params: MetricScaleParams | None = None,
    found: RawLandmarks | None = None,
) -> ScaleEstimate:
    """Metres per reconstruction unit of a clip, from the hands' metric size prior.

    ``frames (T, H, W, 3)`` uint8 RGB; ``intrinsics (4,)`` fx, fy, cx, cy in pixels;
    ``world_from_cam (T, 4, 4)`` in reconstruction units; ``depth0 (H, W)`` frame-0 z-depth in
    the same units, 0 = unknown (None: no scale); ``confidence0 (H, W)`` in [0, 1] or None.
    Raises :class:`~egosim.stages.common.hand_landmarks.MediaPipeUnavailableError` without
    MediaPipe, and :class:`~egosim.stages.common.roi_landmarks.LandmarkRuntimeUnavailableError`
    without ai-edge-litert when ``params.detector.track_misses`` (the default) and a hand is found.
    ``found``: the clip's detections by ``params.detector`` when the caller already has them.
    """
    params = params or MetricScaleParams()
    if depth0 is None:  # no detection needed
        return ScaleEstimate(None, None, 0, reason="no frame-0 depth (static camera?)")
    if found is None:
        found = detect_hand_landmarks(frames, params.detector)
    landmarks = drop_overlapping(found, params.detector.duplicate_distance)  # as the hands stage
    return scale_from_landmarks(
        landmarks, frames, intrinsics, world_from_cam, depth0, confidence0, params
    )


def pooled_metric_scale(
    segments: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]],
    intrinsics: np.ndarray,
    params: MetricScaleParams | None = None,
    landmarks: list[RawLandmarks] | None = None,
) -> ScaleEstimate:
    """One scale for several segments of one reconstruction (a source's track, depth_camera v9).

    Each segment is ``(frames (T, H, W, 3), world_from_cam (T, 4, 4), depth0 (H, W),
    confidence0 (H, W) or None)`` with ``depth0`` the depth of the segment's first frame, all in
    the same reconstruction units. Hands are detected per segment as in
    :func:`estimate_metric_scale`; the per-detection samples of every segment are pooled and the
    contact rule (steps 4-6: strict window, else wide) applied once. ``landmarks``, one per
    segment, replaces the detector (an oracle's, in tests).
    """
    params = params or MetricScaleParams()
    prepared = []
    for i, (frames, poses, depth0, confidence0) in enumerate(segments):
        depth = np.asarray(depth0, dtype=np.float64)
        if confidence0 is not None:
            depth = np.where(np.asarray(confidence0) >= params.min_confidence, depth, 0.0)
        if not np.any(np.isfinite(depth) & (depth > 0)):
            continue
        if landmarks is not None:
            found = landmarks[i]
        else:
            found = detect_hand_landmarks(frames, params.detector)
            found = drop_overlapping(found, params.detector.duplicate_distance)
        if found.present.any():
            prepared.append((found, frames, intrinsics, poses, depth, params))
    if not prepared:
        return ScaleEstimate(None, None, 0, reason="no segment with depth and a hand detected")
    return window_cascade(prepared, params)


def window_cascade(prepared: list[tuple], params: MetricScaleParams) -> ScaleEstimate:
    """Steps 4-6 on the pooled samples of ``prepared`` (:func:`detection_samples` argument
    tuples, one per segment): the strict window, else the wide one; both failing gives no
    scale with both reasons."""
    strict = scale_from_samples([s for args in prepared for s in detection_samples(*args)], params)
    if strict.scale is not None or params.wide_window_px == 0:
        return strict
    wide_samples = [s for args in prepared for s in detection_samples(*args, wide=True)]
    wide = scale_from_samples(wide_samples, params, SOURCE_HAND_SIZE_WIDE)
    if wide.scale is not None:
        return wide
    return ScaleEstimate(
        None,
        None,
        wide.num_samples,
        source=SOURCE_HAND_SIZE_WIDE,
        reason=f"strict window: {strict.reason}; wide window: {wide.reason}",
    )
