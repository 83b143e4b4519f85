"""The ``depth_camera`` stage: intrinsics, per-frame poses and first-frame depth with confidence.

Backends (``backend`` parameter):

- ``sfm`` (default): a texture and background-motion pre-check (:mod:`.static_camera`), then
  pycolmap SfM on the clip's frames with hand pixels excluded from features (run in a
  subprocess, :mod:`.sfm`): incremental mapping from the clip's focal prior first (then
  ``sfm_focal_factors`` x width; the focal fixed at the prior when self-calibration leaves
  ``sfm_plausible_fov_deg``), and pycolmap's global mapper when no incremental model registers
  ``sfm_good_enough_fraction`` of the frames (``sfm_try_global``). The kept model: plausible
  focal first, then more registered frames, then lower mean reprojection error. Then PnP on
  the model's points tracked by KLT into the frames the mapper missed (:mod:`.tracking`), then
  a plane sweep (:mod:`.plane_sweep`) for frame 0's depth against neighbouring frames chosen
  by parallax, in the SfM model's frame and scale. Where SfM poses too few frames (or not
  frame 0), a rotation-only model (:mod:`.rotation_model`) is tried.
- ``given``: the source's own poses and intrinsics; depth from the source or by plane sweep.
- ``da3``: Depth Anything 3 from local weights (:mod:`.da3`).

Model choice (``camera_model``), in order:

1. ``static``: the background (the dominant homography-consistent set of corners tracked from
   frame 0) moves less than ``static_motion_px`` (median) in every checked frame. Every pose
   equals the first, ``static_camera`` true, no depth (DWM section 3.3: ``scene_render`` repeats
   the inpainted first frame).
2. ``sfm``: SfM + PnP tracking poses frame 0 and at least ``min_registered_fraction`` of the
   frames, frame 0 gets depth, and the motion determines the focal: the focal check (bundle
   adjustment of the kept model with its focal held at ``sfm_focal_check_factors`` x its own)
   raises the reprojection error by at least ``sfm_focal_min_rise`` at every factor. A model
   that fails only the focal check gives way to the rotation model when that poses the clip
   (its depth, like its focal, is not determined), and is kept otherwise.
3. ``rotation``: otherwise, when a pure rotation explains the frame-to-frame motion: per pair the
   RANSAC homography's inliers are at least ``rotation_min_h_inlier_ratio`` of the fundamental
   matrix's inliers and its median transfer residual on them is at most
   ``rotation_max_residual_px`` (parallax would leave more), for enough pairs that at least
   ``min_registered_fraction`` of the frames are posed. Poses are pure rotations (zero
   translation), depth is unknown (null); ``scene_cloud`` puts frame 0 on a plane.

Frames no model could pose are interpolated (SE(3)) and flagged (``posed_by`` 3,
``registered`` False); a clip with more than ``1 - min_registered_fraction`` of its frames
flagged is rejected. A textureless clip, or one neither SfM nor the rotation model explains, is a
reject that names the figures.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Mapping
from pathlib import Path
from typing import Any, ClassVar, Literal

import cv2
import numpy as np

from egosim.pipeline import media
from egosim.pipeline.geometry import invert_se3
from egosim.pipeline.records import ClipsRecord
from egosim.pipeline.stage import ClipRejected, ClipStage, ConfigError, StageConfig
from egosim.schemas.base import ShardSchema
from egosim.schemas.clips import CLIPS
from egosim.schemas.depth_camera import (
    BACKENDS,
    DEPTH_CAMERA,
    POSED_BY_INTERPOLATION,
    POSED_BY_MAPPER,
    POSED_BY_MOTION_MODEL,
    POSED_BY_SOURCE,
)
from egosim.stages.common.hand_landmarks import (
    RawLandmarks,
    detect_hand_landmarks,
)
from egosim.stages.common.plane_sweep import (
    PlaneSweepParams,
    first_frame_depth,
    select_sources,
)
from egosim.stages.depth_camera import da3, given
from egosim.stages.depth_camera.hand_region import landmark_hand_mask
from egosim.stages.depth_camera.metric_scale import (
    MetricScaleParams,
    estimate_metric_scale,
    pooled_metric_scale,
)
from egosim.stages.depth_camera.rotation_model import (
    RotationEstimate,
    RotationParams,
    estimate_rotations,
)
from egosim.stages.depth_camera.sfm import (
    SfmError,
    SfmOptions,
    SfmResult,
    fill_unregistered,
    keyframe_indices,
    run_sfm,
    spread_to_frames,
)
from egosim.stages.depth_camera.source_track import (
    SourceTrack,
    SourceTrackError,
    estimate_track,
    read_track_frames,
    thumbnail,
)
from egosim.stages.depth_camera.static_camera import check_motion
from egosim.stages.depth_camera.tracking import NOT_POSED, TrackingParams, register_from_sfm

Backend = Literal["sfm", "given", "da3", "auto"]
log = logging.getLogger(__name__)


@dataclasses.dataclass(frozen=True)
class DepthCameraConfig(StageConfig):
    """Parameters of ``depth_camera``."""

    backend: Backend = (
        "sfm"  # sfm, given (source poses), da3, or auto (given if the clip has poses)
    )
    hand_dilate_px: int = 8  # hand mask grows by this many pixels before excluding features
    # a clip with no hand_mask input (the dataset workflow's cameras step) whose frame 0 shows a
    # hand: True keeps hands and forearms, masked from MediaPipe's landmarks (hand_region; the
    # detections are the metric scale's), out of SfM's features and its PnP tracking only (not
    # the plane sweep, static check or rotation model). Mends clips that start with the arms in
    # view (DWM 00013 from frame 8); clips whose hands come in later are posed as with it off
    mask_hands: bool = True
    min_corners: int = 50  # fewer Shi-Tomasi corners in frame 0 than this = textureless reject
    static_motion_px: float = 1.0  # background's median motion never above this = static camera
    sfm_max_image_size: int = 640  # SIFT runs on frames downscaled to this longest side
    sfm_max_features: int = 1024  # SIFT features per frame
    sfm_overlap: int = 6  # sequential matching: neighbours per frame (plus 2^k jumps)
    sfm_focal_factors: tuple[float, ...] = (0.5,)  # focal priors x width, after the clip's focal
    sfm_init_min_tri_angle: float = 4.0  # degrees; COLMAP's 16 fails on small head motion
    sfm_max_mapping_seconds: int = 60  # mapping time cap per focal prior
    sfm_timeout_s: float = 600.0  # the SfM subprocess is killed after this many seconds
    sfm_threads: int = 1  # threads of the SfM subprocess; 1 is reproducible (more was not)
    sfm_keyframe_stride: int = 1  # SfM on every k-th frame (and the last); PnP tracking the rest
    sfm_good_enough_fraction: float = 0.95  # stop trying focal priors once this many keyframes ...
    sfm_good_max_reprojection_px: float = 1.0  # ... register with at most this error (plausible f)
    sfm_plausible_fov_deg: tuple[float, ...] = (40.0, 110.0)  # horizontal FOV of a believable model
    sfm_try_global: bool = True  # also try pycolmap's global mapper when incremental is not good
    sfm_focal_check_factors: tuple[float, ...] = (0.7, 1.4)  # focal check: the kept model is
    # bundle-adjusted again with its focal held at these x its own (() = no check)
    sfm_focal_min_rise: float = 0.1  # focal check: a model whose reprojection error rises less
    # than this (relative) at any factor has an undetermined focal and depth: rotation model
    sfm_focal_check_points: int = 400  # focal check: at most this many of the model's points
    min_registered_fraction: float = 0.8  # fewer frames posed by estimation than this = reject
    track_ransac_px: float = 3.0  # PnP tracking: RANSAC inlier threshold, pixels
    track_min_inliers: int = 20  # PnP tracking: fewer inliers = the frame stays unposed
    rotation_max_residual_px: float = 1.0  # rotation model: median H residual on F inliers
    rotation_min_h_inlier_ratio: float = 0.6  # rotation model: H inliers / F inliers at least
    rotation_self_calibrate: bool = True  # rotation model: refine the focal from homographies
    depth_scale: float = 0.5  # plane sweep resolution as a fraction of the frame size
    depth_planes: int = 64  # inverse-depth planes of the sweep
    depth_sources: int = 8  # source frames matched against frame 0
    depth_window: int = 7  # ZNCC window side, pixels at the sweep resolution (odd)
    depth_top_k: int = 2  # best sources averaged per plane
    depth_min_support: int = 2  # sources that see a pixel and agree on its depth, for confidence
    depth_target_angle_deg: float = 8.0  # preferred triangulation angle of a source frame
    depth_edge_rel: float = 0.1  # no confidence where depth jumps by more within 3x3 pixels
    depth_margin: float = 0.3  # depth range = SfM points' 1-99 percentiles widened by this
    confidence_threshold: float = 0.5  # confidence at or above = confident pixel (figures)
    given_depth_range: tuple[float, ...] = (0.2, 20.0)  # given backend without depth: near, far
    device: str = "cpu"  # torch device of the plane sweep and of da3
    da3_weights: str = ""  # da3: local folder of the Depth Anything 3 weights
    da3_process_res: int = 504  # da3: processing resolution
    metric_scale: Literal["hand_size", "none"] = "hand_size"  # sfm: put poses and depth in
    # metres from the hands' size prior (:mod:`.metric_scale`); none: keep SfM's units
    source_track: Literal["auto", "off"] = "auto"  # sfm: windows of a longer video or frame
    # folder share one camera track of the whole source (:mod:`.source_track`); off: per window
    track_keyframe_stride: int = 2  # source track: SfM on every k-th track frame, PnP the rest
    track_max_frames: int = 360  # source track: track frames per chunk (held in memory)

    def __post_init__(self) -> None:
        problems: list[str] = []
        if self.backend not in (*BACKENDS, "auto"):
            problems.append(f"backend must be one of {[*BACKENDS, 'auto']}, got {self.backend!r}")
        for name in (
            "min_corners",
            "sfm_max_image_size",
            "sfm_max_features",
            "sfm_overlap",
            "sfm_max_mapping_seconds",
            "sfm_threads",
            "sfm_keyframe_stride",
            "track_keyframe_stride",
            "track_max_frames",
            "track_min_inliers",
            "sfm_focal_check_points",
            "depth_sources",
            "depth_top_k",
            "depth_min_support",
            "da3_process_res",
        ):
            if getattr(self, name) < 1:
                problems.append(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.hand_dilate_px < 0:
            problems.append(f"hand_dilate_px must be >= 0, got {self.hand_dilate_px}")
        if self.depth_sources < 2:
            problems.append(f"depth_sources must be >= 2, got {self.depth_sources}")
        if self.depth_planes < 3:
            problems.append(f"depth_planes must be >= 3, got {self.depth_planes}")
        if self.depth_window < 3 or self.depth_window % 2 == 0:
            problems.append(f"depth_window must be odd and >= 3, got {self.depth_window}")
        if not self.sfm_focal_factors or any(
            not (np.isfinite(f) and 0.1 <= f <= 10.0) for f in self.sfm_focal_factors
        ):
            problems.append(f"sfm_focal_factors must be in [0.1, 10], got {self.sfm_focal_factors}")
        if any(
            not (np.isfinite(f) and 0.1 <= f <= 10.0 and f != 1.0)
            for f in self.sfm_focal_check_factors
        ):
            problems.append(
                "sfm_focal_check_factors must be in [0.1, 10] and not 1, got "
                f"{self.sfm_focal_check_factors}"
            )
        if not (np.isfinite(self.sfm_focal_min_rise) and self.sfm_focal_min_rise >= 0):
            problems.append(f"sfm_focal_min_rise must be >= 0, got {self.sfm_focal_min_rise}")
        fov = self.sfm_plausible_fov_deg
        if len(fov) != 2 or not (0 < fov[0] < fov[1] < 180):
            problems.append(f"sfm_plausible_fov_deg must be (low, high) in (0, 180), got {fov}")
        if not 0.0 < self.sfm_good_enough_fraction <= 1.0:
            problems.append(
                f"sfm_good_enough_fraction must be in (0, 1], got {self.sfm_good_enough_fraction}"
            )
        if not 0.0 < self.rotation_min_h_inlier_ratio <= 1.0:
            problems.append(
                "rotation_min_h_inlier_ratio must be in (0, 1], got "
                f"{self.rotation_min_h_inlier_ratio}"
            )
        for name in (
            "static_motion_px",
            "sfm_init_min_tri_angle",
            "sfm_timeout_s",
            "track_ransac_px",
            "rotation_max_residual_px",
        ):
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0):
                problems.append(f"{name} must be > 0, got {value}")
        if not 0.0 < self.min_registered_fraction <= 1.0:
            problems.append(
                f"min_registered_fraction must be in (0, 1], got {self.min_registered_fraction}"
            )
        if not 0.05 <= self.depth_scale <= 1.0:
            problems.append(f"depth_scale must be in [0.05, 1], got {self.depth_scale}")
        if not 0.0 < self.depth_target_angle_deg < 90.0:
            problems.append(
                f"depth_target_angle_deg must be in (0, 90), got {self.depth_target_angle_deg}"
            )
        if not self.depth_edge_rel > 0:
            problems.append(f"depth_edge_rel must be > 0, got {self.depth_edge_rel}")
        if not 0.0 <= self.depth_margin < 1.0:
            problems.append(f"depth_margin must be in [0, 1), got {self.depth_margin}")
        if not 0.0 <= self.confidence_threshold <= 1.0:
            problems.append(
                f"confidence_threshold must be in [0, 1], got {self.confidence_threshold}"
            )
        rng = self.given_depth_range
        if len(rng) != 2 or not (0 < rng[0] < rng[1] and np.isfinite(rng[1])):
            problems.append(f"given_depth_range must be (near, far) with 0 < near < far, got {rng}")
        if self.metric_scale not in ("hand_size", "none"):
            problems.append(
                f"metric_scale must be 'hand_size' or 'none', got {self.metric_scale!r}"
            )
        if self.source_track not in ("auto", "off"):
            problems.append(f"source_track must be 'auto' or 'off', got {self.source_track!r}")
        if problems:
            raise ConfigError("; ".join(problems))

    def sweep_params(self) -> PlaneSweepParams:
        """The plane-sweep knobs of this config."""
        return PlaneSweepParams(
            num_planes=self.depth_planes,
            window=self.depth_window,
            top_k=self.depth_top_k,
            min_support=self.depth_min_support,
            device=self.device,
        )

    def tracking_params(self) -> TrackingParams:
        """The PnP tracking knobs of this config."""
        return TrackingParams(ransac_px=self.track_ransac_px, min_inliers=self.track_min_inliers)

    def rotation_params(self) -> RotationParams:
        """The rotation-model knobs of this config."""
        return RotationParams(
            max_h_residual_px=self.rotation_max_residual_px,
            min_h_inlier_ratio=self.rotation_min_h_inlier_ratio,
        )

    def sfm_options(self, prior_focal: float = 0.0) -> SfmOptions:
        """The SfM worker settings of this config; ``prior_focal`` pixels is tried first."""
        return SfmOptions(
            prior_focal=prior_focal,
            plausible_fov_deg=(self.sfm_plausible_fov_deg[0], self.sfm_plausible_fov_deg[1]),
            try_global=self.sfm_try_global,
            good_enough_fraction=self.sfm_good_enough_fraction,
            good_max_reprojection_px=self.sfm_good_max_reprojection_px,
            max_image_size=self.sfm_max_image_size,
            max_num_features=self.sfm_max_features,
            sequential_overlap=self.sfm_overlap,
            focal_factors=tuple(self.sfm_focal_factors),
            init_min_tri_angle=self.sfm_init_min_tri_angle,
            max_mapping_seconds=self.sfm_max_mapping_seconds,
            num_threads=self.sfm_threads,
            mask_dilate_px=self.hand_dilate_px,
            timeout_s=self.sfm_timeout_s,
            focal_check_factors=tuple(self.sfm_focal_check_factors),
            focal_check_points=self.sfm_focal_check_points,
        )


@dataclasses.dataclass(frozen=True)
class CameraEstimate:
    """Everything one backend found for one clip (before encoding as a row)."""

    intrinsics: np.ndarray  # (4,) fx, fy, cx, cy
    world_from_cam: np.ndarray  # (T, 4, 4)
    registered: np.ndarray  # (T,) bool, posed by estimation (not interpolated)
    static: bool  # static camera: every pose equals the first, no depth
    depth0: np.ndarray | None  # (H, W) float32 in the poses' scale
    confidence0: np.ndarray | None  # (H, W) float32 in [0, 1]
    backend: str  # backend name
    reprojection_error_px: float | None = None  # SfM only
    num_points3d: int | None = None  # SfM only
    sources: tuple[int, ...] = ()  # plane-sweep source frames
    camera_model: str = "sfm"  # sfm, rotation, static, given or da3
    posed_by: np.ndarray | None = None  # (T,) int8 schema codes; None: 0 / 3 from registered
    focal_prior_px: float | None = None  # focal prior the estimate was checked against
    metric_scale: float | None = None  # metres per unit, already applied; None = unknown
    scale_source: str | None = None  # source, hand_size, hand_size_wide or none
    scale_spread: float | None = None  # relative spread of the scale estimate

    def posed_by_codes(self) -> np.ndarray:
        """``(T,)`` int8 ``posed_by`` (mapper where registered, interpolated elsewhere if unset)."""
        if self.posed_by is not None:
            return np.asarray(self.posed_by, dtype=np.int8)
        reg = np.asarray(self.registered, dtype=bool)
        return np.where(reg, POSED_BY_MAPPER, POSED_BY_INTERPOLATION).astype(np.int8)

    def with_scale(self, scale: float, source: str, spread: float | None) -> CameraEstimate:
        """A copy in metres: translations and depth0 multiplied by ``scale`` (metres per unit).

        For an estimate whose scale is not applied yet; records ``scale``, ``source``, ``spread``.
        """
        if not (np.isfinite(scale) and scale > 0):
            raise ValueError(f"scale must be finite and > 0, got {scale}")
        poses = np.array(self.world_from_cam, dtype=np.float64)  # (T, 4, 4)
        poses[:, :3, 3] *= scale
        depth0 = None if self.depth0 is None else (self.depth0 * scale).astype(np.float32)
        return dataclasses.replace(
            self,
            world_from_cam=poses,
            depth0=depth0,
            metric_scale=float(scale),
            scale_source=source,
            scale_spread=spread,
        )


def with_hand_size_scale(
    est: CameraEstimate, frames: np.ndarray, found: RawLandmarks | None = None
) -> CameraEstimate:
    """``est`` in metres by :func:`.metric_scale.estimate_metric_scale`, when it finds a scale.

    Static and rotation-only estimates (no depth, no translation) and clips where the hands give
    no usable estimate are returned unchanged (``scale_source`` ``none``). ``found``: the
    clip's detections when already made (:func:`hand_mask_from_landmarks`), else detected here.
    """
    if est.depth0 is None or est.metric_scale is not None:
        return est
    scale = estimate_metric_scale(
        frames, est.intrinsics, est.world_from_cam, est.depth0, est.confidence0, found=found
    )
    if scale.scale is None:
        return est
    return est.with_scale(scale.scale, scale.source, scale.spread)


def hand_mask_from_landmarks(frames: np.ndarray) -> tuple[np.ndarray, RawLandmarks]:
    """``(mask (T, H, W) uint8, detections)``: the clip's hands and forearms from the metric
    scale's detector (:func:`.hand_region.landmark_hand_mask`). Asked for by ``mask_hands``, so
    a missing MediaPipe or TFLite runtime raises (naming the install) rather than silently
    leaving the arms in SfM."""
    found = detect_hand_landmarks(frames, MetricScaleParams().detector)
    return landmark_hand_mask(found, frames.shape[1:3]), found


def usable_pixels(hand_mask: np.ndarray | None, dilate_px: int) -> np.ndarray | None:
    """``(T, H, W)`` bool, True where a pixel is not (near) a hand; None without a mask."""
    if hand_mask is None:
        return None
    if dilate_px == 0:
        return hand_mask == 0
    side = 2 * dilate_px + 1
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (side, side))
    return np.stack([cv2.dilate(m.astype(np.uint8), kernel) == 0 for m in hand_mask])


def static_estimate(
    intrinsics: np.ndarray, num_frames: int, backend: str, focal_prior_px: float | None = None
) -> CameraEstimate:
    """A static camera: identity poses (every pose = the first), no depth."""
    metric = backend == "given"  # a static source camera keeps the source's (metric) frame
    return CameraEstimate(
        intrinsics=np.asarray(intrinsics, dtype=np.float64),
        world_from_cam=np.tile(np.eye(4), (num_frames, 1, 1)),
        registered=np.ones(num_frames, dtype=bool),
        static=True,
        depth0=None,
        confidence0=None,
        backend=backend,
        camera_model="static",
        posed_by=np.full(num_frames, POSED_BY_SOURCE if metric else POSED_BY_MOTION_MODEL, np.int8),
        focal_prior_px=focal_prior_px,
        metric_scale=1.0 if metric else None,
        scale_source="source" if metric else "none",
        scale_spread=0.0 if metric else None,
    )


def _plausible_focal(focal: float, width: int, fov_range: tuple[float, ...]) -> bool:
    """True when ``focal`` (pixels) gives a horizontal FOV inside ``fov_range`` degrees."""
    fov = 2.0 * np.degrees(np.arctan(0.5 * width / focal))
    return bool(fov_range[0] <= fov <= fov_range[1])


def window_depth(
    frames: np.ndarray,
    usable: np.ndarray | None,
    intrinsics: np.ndarray,
    cam_from_world: np.ndarray,
    posed: np.ndarray,
    points0: np.ndarray,
    config: DepthCameraConfig,
) -> tuple[np.ndarray, np.ndarray, list[int]] | str:
    """Frame 0's depth and confidence ``(H, W)`` by plane sweep, and its source frames.

    ``frames (T, H, W, 3)``, ``cam_from_world (T, 4, 4)`` (unposed frames filled), ``posed (T,)``,
    ``points0 (P, 3)`` model points frame 0 sees (they set the depth range and pick the
    sources). Returns why not (a string starting with ``; ``) when there is too little to sweep.
    """
    h, w = frames.shape[1:3]
    pts_cam0 = points0 @ cam_from_world[0, :3, :3].T + cam_from_world[0, :3, 3]
    z = pts_cam0[:, 2][pts_cam0[:, 2] > 0]  # (P,)
    if len(z) < 20:
        return f"; only {len(z)} model points in front of frame 0, need 20"
    near = float(np.percentile(z, 1)) * (1.0 - config.depth_margin)
    far = float(np.percentile(z, 99)) * (1.0 + config.depth_margin)
    sources = select_sources(
        cam_from_world,
        posed,
        points0,
        intrinsics,
        (h, w),
        config.depth_sources,
        target_angle_deg=config.depth_target_angle_deg,
        usable=usable,
    )
    if len(sources) < 2:
        return f"; only {len(sources)} posed frames overlap frame 0 with parallax: need 2 for depth"
    depth0, conf0 = first_frame_depth(
        frames,
        usable,
        intrinsics,
        cam_from_world,
        sources,
        (near, far),
        config.depth_scale,
        config.sweep_params(),
        edge_rel=config.depth_edge_rel,
    )
    return depth0, conf0, sources


def focal_undetermined(sfm: SfmResult, min_rise: float) -> str | None:
    """Why the motion of ``sfm``'s frames does not determine its focal, or None when it does.

    The worker's focal check (``sfm_worker.focal_rise``) held the model's focal at a few factors
    of its own and bundle-adjusted the same frames and tracks again; when the reprojection error
    rises by less than ``min_rise`` at any of them, another focal fits the frames as well, and the
    model's depth (which scales with the focal along the camera's motion) is not determined
    either. A rise that is not a number (a bundle adjustment that diverged) counts as under
    ``min_rise``. No check run: None.
    """
    rise = np.asarray(sfm.focal_rise, dtype=np.float64)
    if not len(rise) or float(rise.min()) >= min_rise:
        return None
    figures = ", ".join(
        f"{r:+.0%} at {k:g}x" for k, r in zip(sfm.focal_check_factors, rise, strict=True)
    )
    return (
        f"focal not determined by the motion (reprojection error with the focal held: "
        f"{figures}; a rise under {min_rise:.0%} at any factor means undetermined)"
    )


def sfm_camera(
    frames: np.ndarray,
    usable: np.ndarray | None,
    sfm: SfmResult,
    config: DepthCameraConfig,
    focal_prior_px: float,
    sweep_usable: np.ndarray | None,
) -> tuple[CameraEstimate | None, str]:
    """SfM + PnP tracking + frame-0 depth, or ``(None, why not)`` when the model falls short.

    ``usable (T, H, W)`` bool (False on hands) keeps the PnP tracking off the hands;
    ``sweep_usable`` does so for the plane sweep (None: every pixel)."""
    t = frames.shape[0]
    reg = np.asarray(sfm.registered, dtype=bool)
    posed_by = np.where(reg, POSED_BY_MAPPER, NOT_POSED).astype(np.int8)
    cam_from_world = sfm.cam_from_world
    points0 = sfm.points3d  # (P, 3) model points seen in frame 0
    if not reg.all() and len(sfm.all_points3d):
        tracked = register_from_sfm(frames, usable, sfm, config.tracking_params())
        posed_by, cam_from_world = tracked.posed_by.copy(), tracked.cam_from_world
        if not reg[0] and 0 in tracked.frame_points:
            points0 = tracked.frame_points[0]
    posed = posed_by != NOT_POSED
    frac = float(posed.mean())
    what = (
        f"SfM ({sfm.mapper} mapper, f {sfm.intrinsics[0]:.0f} px) posed {int(posed.sum())}/{t} "
        f"frames ({int(reg.sum())} mapper, {int(posed.sum() - reg.sum())} PnP)"
    )
    if frac < config.min_registered_fraction:
        return None, f"{what}: {frac:.0%}, need {config.min_registered_fraction:.0%}"
    if not posed[0]:
        return None, f"{what}, not frame 0, so it has no depth"
    if len(points0) < 20:
        return None, f"{what}; only {len(points0)} model points seen in frame 0, need 20"
    cam_from_world = fill_unregistered(cam_from_world, posed)  # (T, 4, 4)
    posed_by[~posed] = POSED_BY_INTERPOLATION
    depth = window_depth(
        frames, sweep_usable, sfm.intrinsics, cam_from_world, posed, points0, config
    )
    if isinstance(depth, str):
        return None, f"{what}{depth}"
    est = sfm_estimate(sfm.intrinsics, cam_from_world, posed, posed_by, depth, sfm, focal_prior_px)
    return est, what


def sfm_estimate(
    intrinsics: np.ndarray,
    cam_from_world: np.ndarray,
    posed: np.ndarray,
    posed_by: np.ndarray,
    depth: tuple[np.ndarray, np.ndarray, list[int]],
    model: SfmResult | SourceTrack,
    focal_prior_px: float,
) -> CameraEstimate:
    """The SfM model's :class:`CameraEstimate` (no scale yet) of a window's ``cam_from_world
    (T, 4, 4)``, ``posed (T,)``, ``posed_by (T,)`` and frame-0 ``depth`` (:func:`window_depth`);
    ``model`` gives the reprojection error and point count."""
    depth0, conf0, sources = depth
    return CameraEstimate(
        intrinsics=intrinsics,
        world_from_cam=invert_se3(cam_from_world),
        registered=posed,
        static=False,
        depth0=depth0,
        confidence0=conf0,
        backend="sfm",
        reprojection_error_px=model.reprojection_error_px,
        num_points3d=model.num_points3d,
        sources=tuple(int(v) for v in sources),
        camera_model="sfm",
        posed_by=posed_by,
        focal_prior_px=focal_prior_px,
        scale_source="none",
    )


def rotation_camera(rot: RotationEstimate, focal_prior_px: float) -> CameraEstimate:
    """A rotation-only estimate: pure rotations about frame 0's centre, no depth."""
    posed = rot.posed
    cam_from_world = np.tile(np.eye(4), (len(posed), 1, 1))  # (T, 4, 4), world = camera 0
    cam_from_world[:, :3, :3] = rot.cam_from_cam0
    cam_from_world = fill_unregistered(cam_from_world, posed)
    posed_by = np.where(posed, POSED_BY_MOTION_MODEL, POSED_BY_INTERPOLATION).astype(np.int8)
    world_from_cam = invert_se3(cam_from_world)
    world_from_cam[:, :3, 3] = 0.0  # interpolation between zero centres keeps zero: make it exact
    return CameraEstimate(
        intrinsics=rot.intrinsics,
        world_from_cam=world_from_cam,
        registered=posed,
        static=False,
        depth0=None,
        confidence0=None,
        backend="sfm",
        camera_model="rotation",
        posed_by=posed_by,
        focal_prior_px=focal_prior_px,
        scale_source="none",
    )


def static_check(
    clip_id: str,
    frames: np.ndarray,
    hand_mask: np.ndarray | None,
    intrinsics: np.ndarray,
    config: DepthCameraConfig,
) -> CameraEstimate | None:
    """The static estimate when the background holds still, else None; raises
    :class:`ClipRejected` for a textureless scene."""
    check = check_motion(frames, hand_mask, config.min_corners, config.static_motion_px)
    if check.textureless:
        raise ClipRejected(
            f"clip {clip_id}: textureless scene: {check.num_corners} corners outside the hands "
            f"in frame 0, need {config.min_corners} for SfM"
        )
    if check.static:
        intrinsics = np.asarray(intrinsics, dtype=np.float64)
        return static_estimate(intrinsics, len(frames), "sfm", float(intrinsics[0]))
    return None


def estimate_sfm(
    clip_id: str,
    frames: np.ndarray,
    hand_mask: np.ndarray | None,
    intrinsics: np.ndarray,
    config: DepthCameraConfig,
    worker_command: list[str] | None = None,
    checked: bool = False,
    pose_mask: np.ndarray | None = None,
) -> CameraEstimate:
    """The ``sfm`` backend on decoded ``frames (T, H, W, 3)``; raises :class:`ClipRejected`.

    ``intrinsics`` (the clip's, from metadata or a field-of-view guess) are the focal prior and
    the camera of a static or rotation-only clip. See the module docstring for the model choice.
    ``checked``: :func:`static_check` already ran (and found a textured, moving camera).
    ``hand_mask (T, H, W)`` (1 = hand) is kept out of everything: the static check, SfM's
    features, PnP tracking, the rotation model and the plane sweep. ``pose_mask (T, H, W)``
    (1 = hand, joined to ``hand_mask``) is kept out of SfM's features and its PnP tracking
    only (``mask_hands``' landmark mask, depth_camera v16): not out of the plane sweep, whose
    frame-0 depth the metric scale compares the hands with, nor out of the static check and
    the rotation model (with it there, the EgoDex sample's rotation-model focal went from +7.4%
    to +15.4% of its true one).
    """
    t, w = frames.shape[0], frames.shape[2]
    intrinsics = np.asarray(intrinsics, dtype=np.float64)
    prior = float(intrinsics[0])
    if not checked:
        static = static_check(clip_id, frames, hand_mask, intrinsics, config)
        if static is not None:
            return static
    usable = usable_pixels(hand_mask, config.hand_dilate_px)  # (T, H, W) or None
    sfm_mask, sfm_usable = hand_mask, usable  # what SfM and its PnP tracking keep out
    if pose_mask is not None:
        sfm_mask = pose_mask if hand_mask is None else np.maximum(hand_mask, pose_mask)
        sfm_usable = usable_pixels(sfm_mask, config.hand_dilate_px)
    rot_intrinsics = intrinsics
    sfm_est: CameraEstimate | None = None
    key = keyframe_indices(t, config.sfm_keyframe_stride)  # (K,)
    try:
        sfm = run_sfm(
            frames[key],
            None if sfm_mask is None else sfm_mask[key],
            config.sfm_options(prior),
            worker_command,
        )
        sfm = spread_to_frames(sfm, key, t)
    except SfmError as exc:
        sfm_why = str(exc)
    else:
        est, sfm_why = sfm_camera(frames, sfm_usable, sfm, config, prior, usable)
        undetermined = focal_undetermined(sfm, config.sfm_focal_min_rise)
        if est is not None and undetermined is None:
            rise = ", ".join(f"{r:+.0%}" for r in sfm.focal_rise)
            log.info("clip %s: %s; focal check %s: sfm", clip_id, sfm_why, rise or "off")
            return est
        if est is not None:  # SfM posed the clip, but its focal and depth are not determined
            sfm_est, sfm_why = est, f"{sfm_why}, but its {undetermined}"
        if _plausible_focal(float(sfm.intrinsics[0]), w, config.sfm_plausible_fov_deg):
            rot_intrinsics = sfm.intrinsics
    rot = estimate_rotations(
        frames, usable, rot_intrinsics, config.rotation_params(), config.rotation_self_calibrate
    )
    frac = float(rot.posed.mean())
    rot_what = f"the rotation model posed {int(rot.posed.sum())}/{t} frames"
    if frac >= config.min_registered_fraction:
        if sfm_est is not None:
            log.info("clip %s: %s; %s: rotation model, no depth", clip_id, sfm_why, rot_what)
        return rotation_camera(rot, prior)
    if sfm_est is not None:  # nothing better: the SfM model, as before the focal check
        log.info("clip %s: %s; %s: SfM model kept", clip_id, sfm_why, rot_what)
        return sfm_est
    residuals = [p.h_residual_px for p in rot.pairs if np.isfinite(p.h_residual_px)]
    raise ClipRejected(
        f"clip {clip_id}: {sfm_why}; rotation-only model: a homography explains "
        f"{rot.explained_fraction:.0%} of frame pairs (median residual "
        f"{np.median(residuals) if residuals else float('nan'):.2f} px), posing "
        f"{int(rot.posed.sum())}/{t} frames, need {config.min_registered_fraction:.0%}"
    )


TRACK_SOURCES = ("video", "frames")  # clip sources whose source_uri the track can read again
TRACK_CLIP_KINDS = ("full", "tail")  # clip_policy kinds cut from a source longer than a clip
# A window whose frame 0 differs from the re-read source's frame by more than this mean grey
# level (0-255, on 64x36 thumbnails) is not from that source any more (ingest's H.264 encode
# differs by well under 2): the window takes the per-window path.
TRACK_FRAME_MAX_DIFF = 8.0


@dataclasses.dataclass(frozen=True)
class TrackRequest:
    """What a window row says about its source's track (:func:`track_request`)."""

    kind: str  # the clip's source: video or frames
    uri: str  # the source file or folder
    fps: float  # the clip rate (track frames are picked at it)
    source_fps: float | None  # the source's rate
    size: tuple[int, int]  # (H, W) of the clip's frames
    intrinsics: tuple[float, ...]  # the clip's (prior) intrinsics
    source_indices: np.ndarray  # (T,) the window's source frames
    first_target: int  # the window's first track position, from its timestamps
    source_crop: tuple[float, ...] | None = None  # the clip's crop (x0, y0, x1, y1 source
    # pixels); None = ingest's centre crop (rows written before clips v5)

    def key(self, chunk: int) -> tuple:
        """Cache key of chunk ``chunk`` of this source's track (file size and time included)."""
        path = Path(self.uri)
        try:
            stat = path.stat()
            stamp = (stat.st_size, stat.st_mtime_ns)
        except OSError:
            stamp = (-1, -1)
        return (self.kind, str(path), stamp, self.fps, self.source_fps, self.size,
                self.intrinsics, self.source_crop, chunk)  # fmt: skip


def track_request(row: ClipsRecord) -> TrackRequest | None:
    """The window's :class:`TrackRequest` when its source is longer than it and readable again
    (a ``full`` or ``tail`` window of a video file or frame folder with frames outside it);
    None for a short clip, a one-window source or another source kind."""
    policy = row.get("clip_policy") or ""
    idx = row.get("source_frame_indices")
    if (
        row.get("source") not in TRACK_SOURCES
        or not row.get("source_uri")
        or policy.split(":")[0] not in TRACK_CLIP_KINDS
        or idx is None
        or len(idx) == 0
    ):
        return None
    idx = np.asarray(idx, dtype=np.int64)
    fps = float(row["fps"])
    source_fps = row.get("source_fps")
    n = row.get("source_num_frames")
    step = 1 if not source_fps else max(1, int(np.ceil(float(source_fps) / fps)))
    if idx[0] == 0 and n is not None and idx[-1] >= n - 1 - step:
        return None  # the window holds the whole source
    keep_rate = source_fps is not None and 0 < source_fps < fps * (1 - 1e-6)
    ts = np.asarray(row["timestamps"], dtype=np.float64)
    crop = row.get("source_crop")
    first_target = int(idx[0]) if keep_rate else round(float(ts[0]) * fps)
    return TrackRequest(
        kind=row["source"],
        uri=row["source_uri"],
        fps=fps,
        source_fps=None if source_fps is None else float(source_fps),
        size=(row.height, row.width),
        intrinsics=tuple(float(v) for v in row.intrinsics),
        source_indices=idx,
        first_target=first_target,
        source_crop=None if crop is None else tuple(float(v) for v in crop),
    )


def build_source_track(
    req: TrackRequest, segment: int, chunk: int, config: DepthCameraConfig
) -> SourceTrack:
    """The track of chunk ``chunk`` of a source: SfM + PnP over its track frames, one plane-sweep
    depth per segment of ``segment`` frames, and the scale pooled over the segments. Raises
    :class:`SourceTrackError` when the source cannot be read or tracked."""
    length = max(1, config.track_max_frames // segment) * segment
    picks, frames = read_track_frames(
        req.kind,
        req.uri,
        req.fps,
        req.source_fps,
        req.size,
        chunk * length,
        length,
        source_crop=req.source_crop,
    )
    prior = req.intrinsics[0]
    intrinsics, cam_from_world, posed_by, points, sfm = estimate_track(
        frames,
        prior,
        config.sfm_options(prior),
        config.track_keyframe_stride,
        config.tracking_params(),
    )
    posed = posed_by != POSED_BY_INTERPOLATION
    log.info(
        "source %s, chunk %d: %d track frames; SfM (%s mapper, f %.0f px, features %.0f s, "
        "mapping %.0f s, focal check %.0f s) and PnP posed %d",
        req.uri,
        chunk,
        len(frames),
        sfm.mapper,
        intrinsics[0],
        sfm.seconds_features,
        sfm.seconds_mapping,
        sfm.seconds_focal_check,
        int(posed.sum()),
    )
    undetermined = focal_undetermined(sfm, config.sfm_focal_min_rise)
    if undetermined is not None:  # each window decides between SfM and rotation on its own
        raise SourceTrackError(f"SfM on the source's keyframes: its {undetermined}")
    depths: dict[int, tuple[np.ndarray, np.ndarray, tuple[int, ...]]] = {}
    segments = []
    for start in range(0, len(frames), segment):
        end = min(start + segment, len(frames))
        if end - start < 2 or not posed[start] or start not in points:
            continue
        depth = window_depth(
            frames[start:end],
            None,
            intrinsics,
            cam_from_world[start:end],
            posed[start:end],
            points[start],
            config,
        )
        if isinstance(depth, str):
            continue
        depths[start] = (depth[0], depth[1], tuple(depth[2]))
        segments.append(
            (frames[start:end], invert_se3(cam_from_world[start:end]), depth[0], depth[1])
        )
    track = SourceTrack(
        thumbnails=np.stack([thumbnail(f) for f in frames]),
        picks=picks,
        first=chunk * length,
        intrinsics=intrinsics,
        cam_from_world=cam_from_world,
        posed_by=posed_by,
        frame_points=points,
        reprojection_error_px=sfm.reprojection_error_px,
        num_points3d=sfm.num_points3d,
        mapper=sfm.mapper,
        depths=depths,
    )
    if config.metric_scale != "hand_size" or not segments:
        return track
    scale = pooled_metric_scale(segments, intrinsics)
    if scale.scale is None:
        return dataclasses.replace(track, scale_reason=scale.reason)
    return dataclasses.replace(
        track, metric_scale=scale.scale, scale_source=scale.source, scale_spread=scale.spread
    )


def estimate_from_track(
    track: SourceTrack,
    req: TrackRequest,
    frames: np.ndarray,
    hand_mask: np.ndarray | None,
    config: DepthCameraConfig,
) -> tuple[CameraEstimate | None, str]:
    """A window's cameras sampled from its source's ``track``, or ``(None, why not)``."""
    pos = track.positions(req.source_indices, req.first_target)
    if pos is None:
        return None, "the window's frames are not consecutive frames of the track's chunk"
    diff = track.frame_difference(int(pos[0]), frames[0])
    if diff > TRACK_FRAME_MAX_DIFF:
        return None, (
            f"the source {req.uri!r} no longer shows this window's frame 0 (mean grey difference "
            f"{diff:.1f} > {TRACK_FRAME_MAX_DIFF}): it changed since ingest"
        )
    posed_by = track.posed_by[pos].copy()  # (T,)
    posed = posed_by != POSED_BY_INTERPOLATION
    frac = float(posed.mean())
    what = f"source track ({track.mapper} mapper) posed {int(posed.sum())}/{len(pos)} frames"
    if frac < config.min_registered_fraction:
        return None, f"{what}: {frac:.0%}, need {config.min_registered_fraction:.0%}"
    if not posed[0]:
        return None, f"{what}, not frame 0"
    cam_from_world = track.cam_from_world[pos]  # (T, 4, 4)
    saved = track.depths.get(int(pos[0]))
    if saved is not None and max(saved[2]) < len(pos):
        depth = (saved[0], saved[1], list(saved[2]))
    else:
        points0 = track.frame_points.get(int(pos[0]), np.zeros((0, 3)))
        usable = usable_pixels(hand_mask, config.hand_dilate_px)
        depth = window_depth(
            frames, usable, track.intrinsics, cam_from_world, posed, points0, config
        )
        if isinstance(depth, str):
            return None, f"{what}{depth}"
    est = sfm_estimate(
        track.intrinsics, cam_from_world, posed, posed_by, depth, track, req.intrinsics[0]
    )
    if track.metric_scale is not None:
        est = est.with_scale(track.metric_scale, track.scale_source, track.scale_spread)
    return est, what


def estimate_given(
    clip_id: str,
    frames: np.ndarray,
    hand_mask: np.ndarray | None,
    row: Mapping[str, Any],
    config: DepthCameraConfig,
) -> CameraEstimate:
    """The ``given`` backend on one clips ``row`` (a :class:`ClipsRecord` or a plain mapping,
    wrapped in one); raises :class:`ClipRejected`."""
    row = ClipsRecord.of(row)
    t = row.num_frames
    poses = row.world_from_cam  # (T, 4, 4)
    if poses is None:
        raise ClipRejected(f"clip {clip_id}: backend 'given' needs the source's world_from_cam")
    depth0 = None
    # The static (hand-free) depth when the source has it: the scene behind the hands.
    key = "static_depth" if row.get("static_depth") is not None else "depth"
    if row.get(key) is not None and row.get("depth_unit_m"):
        depth0 = media.decode_lossless_video(row[key], f"clip {clip_id} {key}", 1)[0]
        depth0 = depth0.astype(np.float32) * float(row["depth_unit_m"])
    try:
        res = given.given_camera(
            frames,
            usable_pixels(hand_mask, config.hand_dilate_px),
            row.intrinsics,
            poses,
            depth0,
            (config.given_depth_range[0], config.given_depth_range[1]),
            config.depth_sources,
            config.depth_scale,
            dataclasses.replace(config.sweep_params(), num_planes=max(config.depth_planes, 96)),
        )
    except ValueError as exc:
        raise ClipRejected(f"clip {clip_id}: {exc}") from exc
    if res.static:
        return static_estimate(res.intrinsics, t, "given")
    return CameraEstimate(
        intrinsics=res.intrinsics,
        world_from_cam=res.world_from_cam,
        registered=np.ones(t, dtype=bool),
        static=False,
        depth0=res.depth0,
        confidence0=res.confidence0,
        backend="given",
        sources=tuple(res.sources),
        camera_model="given",
        posed_by=np.full(t, POSED_BY_SOURCE, np.int8),
        metric_scale=1.0,
        scale_source="source",
        scale_spread=0.0,
    )


def estimate_da3(clip_id: str, frames: np.ndarray, config: DepthCameraConfig) -> CameraEstimate:
    """The ``da3`` backend; raises :class:`ClipRejected` when the package or weights are absent."""
    try:
        res = da3.run_da3(frames, config.da3_weights, config.device, config.da3_process_res)
    except da3.Da3Error as exc:
        raise ClipRejected(f"clip {clip_id}: {exc}") from exc
    return CameraEstimate(
        intrinsics=res.intrinsics,
        world_from_cam=res.world_from_cam,
        registered=np.ones(len(frames), dtype=bool),
        static=False,
        depth0=res.depth0,
        confidence0=res.confidence0,
        backend="da3",
        camera_model="da3",
        posed_by=np.full(len(frames), POSED_BY_SOURCE, np.int8),
        scale_source="none",
    )


def row_from_estimate(
    clip_id: str, est: CameraEstimate, height: int, width: int, threshold: float
) -> dict[str, Any]:
    """Encode a :class:`CameraEstimate` as one ``depth_camera`` row."""
    t = len(est.world_from_cam)
    depth_bytes = conf_bytes = unit = frac = None
    if est.depth0 is not None and est.confidence0 is not None:
        depth = np.where(np.isfinite(est.depth0) & (est.depth0 > 0), est.depth0, 0.0)[None]
        unit = media.depth_unit_for(depth)
        depth_bytes = media.encode_depth_video(depth, unit)
        conf_u8 = np.round(np.clip(est.confidence0, 0.0, 1.0) * 255).astype(np.uint8)
        conf_bytes = media.encode_mask_video(conf_u8[None])
        frac = float(np.mean(conf_u8 >= round(threshold * 255)))
    return {
        "clip_id": clip_id,
        "num_frames": t,
        "width": width,
        "height": height,
        "intrinsics": np.asarray(est.intrinsics, dtype=np.float64).tolist(),
        "world_from_cam": np.asarray(est.world_from_cam).reshape(t, 16).tolist(),
        "registered": np.asarray(est.registered, dtype=bool).tolist(),
        "static_camera": bool(est.static),
        "depth0": depth_bytes,
        "depth_unit_m": unit,
        "confidence0": conf_bytes,
        "backend": est.backend,
        "reprojection_error_px": est.reprojection_error_px,
        "num_points3d": est.num_points3d,
        "confident_fraction": frac,
        "depth_source_frames": list(est.sources) if est.sources else None,
        "camera_model": est.camera_model,
        "posed_by": est.posed_by_codes().tolist(),
        "focal_prior_px": est.focal_prior_px,
        "metric_scale": est.metric_scale,
        "scale_source": est.scale_source,
        "scale_spread": est.scale_spread,
    }


class DepthCameraStage(ClipStage):
    """Estimate intrinsics, per-frame poses and first-frame depth with confidence."""

    name = "depth_camera"
    description = "intrinsics, poses, frame-0 depth, metric scale: static/SfM/rotation, or given"
    # 8: the metric scale measures the hands stage's own detections (tiles, hands followed
    # through misses by the v4 tracker), not a plainer detector of its own
    # 7: the metric scale places hands with the hands stage's palm-PnP lift (was a
    # translation-only fit: real hands sat 1.5x deeper than the surfaces they touch)
    # 6: metric scale falls back to a wide surface window (scale_source hand_size_wide) when
    # the strict one finds too few hand detections
    # 5: sfm poses and depth in metres from the hands' size prior (metric_scale); static test
    # takes still corners as the background, skips occluded frames, tolerates an end bump
    # 4: schema v2, background-motion static test, PnP tracking, rotation model, focal prior
    # 3: one SfM thread (reproducible); 2: visibility-aware depth confidence
    # 9: windows of a longer video share one camera track, world frame and metric scale per
    # source (source_track auto)
    # 10: focal check after SfM: a model whose focal (and so depth) the motion does not
    # determine gives way to the rotation model when that poses the clip (the EgoDex sample)
    # 11: the metric scale's palm lift is the hands stage v8's (refined palm poses, MediaPipe's
    # proximal phalanges taken 1/0.70 longer; hand_lift.palm_pnp_pose's defaults)
    # 12: the metric scale leaves out per-detection estimates more than 5 scaled MADs above
    # their median before its contact quantile (a misfit MediaPipe track made tabletop 1 +46%)
    # 13: the palm lift's fingers are bent to fit their 2D (hand_lift.fit_finger_bends, hands
    # v13); the joints the scale reads move, palm and wrist do not (scale within 1.1 points)
    # 14: the scale's hand detector also runs the palm detector on contrast-stretched dim frames
    # while a side has no palm detection in the clip (hand_landmarks.stretch_gain, hands16): a
    # dim clip may give the scale more detections; well-exposed clips are unchanged
    # 15: the scale's hand tracker reads a lost hand's predicted ROI once more mirrored
    # (roi_landmarks.TrackParams.mirror_retry, hands v17): more tracked hand-frames on some clips;
    # mask_hands (off by default) masks hands from landmarks before SfM
    # 16: mask_hands on by default, and its landmark mask only where frame 0 shows a hand and
    # only for SfM's features and PnP tracking (not the plane sweep, static check or rotation
    # model): clips without a hand in frame 0 are as in 15 with it off
    # 17: the scale's hand tracker refuses a reading more than TrackParams.max_drift (1.6) off the
    # size of its last trusted reading (roi_landmarks, hands v19): a hand whose low-presence
    # readings spread over its sleeve step by step is searched for again; detections can change
    # 18: the scale's wide-window fallback leaves out frame-0 depths far off their neighbourhood
    # (metric_scale.drop_depth_outliers) and a detection's joints off its main surface
    # (on_main_surface, 0.25): DWM 00017's wide-window scale no longer follows a few wrong sweep
    # depths under the hand; clips whose scale comes from the strict window are unchanged
    # 19: the scale's and mask_hands' hand tracker checks a reading found only in its wider ROIs
    # against the hand it was followed from (roi_landmarks.TrackParams.confirm_wider, hands v20):
    # a tracked "hand" on scenery next to an entering hand is not followed; detections can change
    # 20: the same tracker's mirrored reads (hands v22: every predicted ROI, kept only when steady)
    version = 20
    config_class = DepthCameraConfig
    inputs: ClassVar[Mapping[str, ShardSchema]] = {"clips": CLIPS}
    output = DEPTH_CAMERA
    backends = BACKENDS
    # What estimate() reads of the clip (the executor decodes nothing else): frames, hand
    # masks (features there are ignored), the source's own camera and depth (backend given).
    columns: ClassVar[Mapping[str, tuple[str, ...]]] = {
        "clips": (
            "num_frames",
            "height",
            "width",
            "video",
            "hand_mask",
            "intrinsics",
            "world_from_cam",
            "static_depth",
            "depth",
            "depth_unit_m",
            # the source track (source_track auto): where the window sits in its source
            "source",
            "source_uri",
            "fps",
            "timestamps",
            "source_fps",
            "source_num_frames",
            "source_frame_indices",
            "clip_policy",
            "source_crop",
        )
    }
    config: DepthCameraConfig
    # Source tracks built in this task (all windows of a source are in one shard): cache key
    # (TrackRequest.key) -> the track, or the reason it could not be built.
    _tracks: dict[tuple, tuple[SourceTrack | str, int]]

    def estimate(self, row: Mapping[str, Any]) -> CameraEstimate:
        """Run the configured backend on one clips row (a :class:`ClipsRecord` or a plain
        mapping, wrapped in one); raises :class:`ClipRejected`."""
        row = ClipsRecord.of(row)
        clip_id = row.clip_id
        try:
            frames = row.frames  # (T, H, W, 3)
            hand_mask = row.mask_video("hand_mask", f"clip {clip_id} hands")  # (T, H, W) or None
        except media.MediaError as exc:
            raise ClipRejected(f"clip {clip_id}: {exc}") from exc
        backend = self.config.backend
        if backend == "auto":
            backend = "given" if row.get("world_from_cam") is not None else "sfm"
        if backend == "given":
            return estimate_given(clip_id, frames, hand_mask, row, self.config)
        if backend == "da3":
            return estimate_da3(clip_id, frames, self.config)
        static = static_check(clip_id, frames, hand_mask, row.intrinsics, self.config)
        if static is not None:
            return static
        req = track_request(row) if self.config.source_track == "auto" else None
        if req is not None:
            est, why = self._from_track(req, row.num_frames, frames, hand_mask)
            log.info("clip %s: %s", clip_id, why)
            if est is not None:
                return est
        # mask_hands: where frame 0 shows a hand, the landmark mask keeps the hands out of SfM's
        # features and PnP tracking (not the plane sweep, whose frame-0 depth the metric scale
        # compares the hands with); a clip whose hands come in later is posed as without it.
        # Detected only here, where SfM runs: a static clip or a window posed from its source's
        # track does not use it (the detections are the metric scale's, so no second detection)
        found = pose_mask = None
        if hand_mask is None and self.config.mask_hands:
            landmark_mask, found = hand_mask_from_landmarks(frames)
            if landmark_mask[0].any():
                pose_mask = landmark_mask
        est = estimate_sfm(
            clip_id,
            frames,
            hand_mask,
            row.intrinsics,
            self.config,
            checked=True,
            pose_mask=pose_mask,
        )
        if self.config.metric_scale == "hand_size":
            est = with_hand_size_scale(est, frames, found)
        return est

    def _from_track(
        self, req: TrackRequest, segment: int, frames: np.ndarray, hand_mask: np.ndarray | None
    ) -> tuple[CameraEstimate | None, str]:
        """The window's cameras from its source's track (built once per source and chunk), or
        ``(None, why)`` to fall back to the per-window path."""
        if not hasattr(self, "_tracks"):
            self._tracks = {}
        # The chunk: by the segment length of whichever window built the source's first chunk.
        seg = next(
            (
                v[1]
                for k, v in self._tracks.items()
                if k[:-1] == req.key(0)[:-1] and isinstance(v, tuple)
            ),
            segment,
        )
        length = max(1, self.config.track_max_frames // seg) * seg
        chunk = req.first_target // length
        key = req.key(chunk)
        if key not in self._tracks:
            try:
                track: SourceTrack | str = build_source_track(req, seg, chunk, self.config)
            except SourceTrackError as exc:
                track = str(exc)
            self._tracks[key] = (track, seg)
        track, _ = self._tracks[key]
        if isinstance(track, str):
            return None, f"no source track ({track}): cameras per window"
        est, why = estimate_from_track(track, req, frames, hand_mask, self.config)
        if est is None:
            return None, f"{why}: cameras per window"
        scale = (
            f"scale {track.metric_scale:.4g} ({track.scale_source})"
            if track.metric_scale is not None
            else f"no scale ({track.scale_reason})"
        )
        return est, f"{why}; one {scale} for the source"

    def process(self, rows: Mapping[str, Mapping[str, Any]]) -> dict[str, Any]:
        """Return the ``depth_camera`` row of one clips row."""
        row = ClipsRecord.of(rows["clips"])
        est = self.estimate(row)
        return row_from_estimate(
            row["clip_id"], est, row.height, row.width, self.config.confidence_threshold
        )
