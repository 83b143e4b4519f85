"""The ``depth_camera`` stage: intrinsics, per-frame poses and first-frame depth with confidence.

Backends (``backend`` parameter):

- ``sfm`` (default): a texture and motion pre-check (:mod:`.static_camera`), then pycolmap
  incremental SfM on the clip's frames with hand pixels excluded from features (run in a
  subprocess, :mod:`.sfm`), then a plane sweep (:mod:`.plane_sweep`) for frame 0's depth against
  neighbouring frames chosen by parallax, in the SfM model's frame and scale.
- ``given``: the source's own poses and intrinsics; depth from the source or by plane sweep.
- ``da3``: Depth Anything 3 from local weights (:mod:`.da3`).

A static camera (no feature motion) gets every pose equal to the first, ``static_camera`` true
and no depth (DWM section 3.3: ``scene_render`` repeats the inpainted first frame). A textureless
clip, a failed or aborted SfM run, or too few registered frames are rejects that name the reason.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Mapping
from typing import Any, ClassVar, Literal

import cv2
import numpy as np

from egosim.pipeline import media
from egosim.pipeline.geometry import invert_se3
from egosim.pipeline.stage import ClipRejected, ClipStage, ConfigError, StageConfig
from egosim.schemas.base import ShardSchema
from egosim.schemas.clips import CLIPS
from egosim.schemas.depth_camera import BACKENDS, DEPTH_CAMERA
from egosim.stages.depth_camera import da3, given
from egosim.stages.depth_camera.plane_sweep import (
    PlaneSweepParams,
    first_frame_depth,
    select_sources,
)
from egosim.stages.depth_camera.sfm import SfmError, SfmOptions, run_sfm
from egosim.stages.depth_camera.static_camera import check_motion

Backend = Literal["sfm", "given", "da3", "auto"]


@dataclasses.dataclass(frozen=True)
class DepthCameraConfig(StageConfig):
    """Parameters of ``depth_camera``."""

    backend: Backend = (
        "sfm"  # sfm, given (source poses), da3, or auto (given if the clip has poses)
    )
    hand_dilate_px: int = 8  # hand mask grows by this many pixels before excluding features
    min_corners: int = 50  # fewer Shi-Tomasi corners in frame 0 than this = textureless reject
    static_motion_px: float = 1.0  # median corner motion never above this = static camera
    sfm_max_image_size: int = 640  # SIFT runs on frames downscaled to this longest side
    sfm_max_features: int = 1024  # SIFT features per frame
    sfm_overlap: int = 6  # sequential matching: neighbours per frame (plus 2^k jumps)
    sfm_focal_factors: tuple[float, ...] = (0.7, 1.0, 0.5)  # focal priors x width, tried in order
    sfm_init_min_tri_angle: float = 4.0  # degrees; COLMAP's 16 fails on small head motion
    sfm_max_mapping_seconds: int = 60  # mapping time cap per focal prior
    sfm_timeout_s: float = 600.0  # the SfM subprocess is killed after this many seconds
    sfm_threads: int = 1  # threads of the SfM subprocess; 1 is reproducible (more was not)
    min_registered_fraction: float = 0.8  # fewer registered frames than this = reject
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
        for name in ("static_motion_px", "sfm_init_min_tri_angle", "sfm_timeout_s"):
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

    def sfm_options(self) -> SfmOptions:
        """The SfM worker settings of this config."""
        return SfmOptions(
            max_image_size=self.sfm_max_image_size,
            max_num_features=self.sfm_max_features,
            sequential_overlap=self.sfm_overlap,
            focal_factors=tuple(self.sfm_focal_factors),
            init_min_tri_angle=self.sfm_init_min_tri_angle,
            max_mapping_seconds=self.sfm_max_mapping_seconds,
            num_threads=self.sfm_threads,
            mask_dilate_px=self.hand_dilate_px,
            timeout_s=self.sfm_timeout_s,
        )


@dataclasses.dataclass(frozen=True)
class CameraEstimate:
    """Everything one backend found for one clip (before encoding as a row)."""

    intrinsics: np.ndarray  # (4,) fx, fy, cx, cy
    world_from_cam: np.ndarray  # (T, 4, 4)
    registered: np.ndarray  # (T,) bool
    static: bool  # static camera: every pose equals the first, no depth
    depth0: np.ndarray | None  # (H, W) float32 in the poses' scale
    confidence0: np.ndarray | None  # (H, W) float32 in [0, 1]
    backend: str  # backend name
    reprojection_error_px: float | None = None  # SfM only
    num_points3d: int | None = None  # SfM only
    sources: tuple[int, ...] = ()  # plane-sweep source frames


def usable_pixels(hand_mask: np.ndarray | None, dilate_px: int) -> np.ndarray | None:
    """``(T, H, W)`` bool, True where a pixel is not (near) a hand; None without a mask."""
    if hand_mask is None:
        return None
    if dilate_px == 0:
        return hand_mask == 0
    side = 2 * dilate_px + 1
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (side, side))
    return np.stack([cv2.dilate(m.astype(np.uint8), kernel) == 0 for m in hand_mask])


def static_estimate(intrinsics: np.ndarray, num_frames: int, backend: str) -> CameraEstimate:
    """A static camera: identity poses (every pose = the first), no depth."""
    return CameraEstimate(
        intrinsics=np.asarray(intrinsics, dtype=np.float64),
        world_from_cam=np.tile(np.eye(4), (num_frames, 1, 1)),
        registered=np.ones(num_frames, dtype=bool),
        static=True,
        depth0=None,
        confidence0=None,
        backend=backend,
    )


def estimate_sfm(
    clip_id: str,
    frames: np.ndarray,
    hand_mask: np.ndarray | None,
    intrinsics: np.ndarray,
    config: DepthCameraConfig,
    worker_command: list[str] | None = None,
) -> CameraEstimate:
    """The ``sfm`` backend on decoded ``frames (T, H, W, 3)``; raises :class:`ClipRejected`.

    ``intrinsics`` (the source's) are only used for a static camera, where SfM cannot run.
    """
    t, h, w = frames.shape[:3]
    check = check_motion(frames, hand_mask, config.min_corners, config.static_motion_px)
    if check.textureless:
        raise ClipRejected(
            f"clip {clip_id}: textureless scene: {check.num_corners} corners outside the hands "
            f"in frame 0, need {config.min_corners} for SfM"
        )
    if check.static:
        return static_estimate(intrinsics, t, "sfm")
    try:
        sfm = run_sfm(frames, hand_mask, config.sfm_options(), worker_command)
    except SfmError as exc:
        raise ClipRejected(f"clip {clip_id}: {exc}") from exc
    frac = float(sfm.registered.mean())
    if frac < config.min_registered_fraction:
        raise ClipRejected(
            f"clip {clip_id}: SfM registered {int(sfm.registered.sum())}/{t} frames "
            f"({frac:.0%}), need {config.min_registered_fraction:.0%}"
        )
    if not sfm.registered[0]:
        raise ClipRejected(f"clip {clip_id}: SfM did not register frame 0, so it has no depth")
    if len(sfm.points3d) < 20:
        raise ClipRejected(
            f"clip {clip_id}: only {len(sfm.points3d)} SfM points seen in frame 0, need 20"
        )
    pts_cam0 = sfm.points3d @ sfm.cam_from_world[0, :3, :3].T + sfm.cam_from_world[0, :3, 3]
    z = pts_cam0[:, 2][pts_cam0[:, 2] > 0]  # (P,)
    near = float(np.percentile(z, 1)) * (1.0 - config.depth_margin)
    far = float(np.percentile(z, 99)) * (1.0 + config.depth_margin)
    usable = usable_pixels(hand_mask, config.hand_dilate_px)
    sources = select_sources(
        sfm.cam_from_world,
        sfm.registered,
        sfm.points3d,
        sfm.intrinsics,
        (h, w),
        config.depth_sources,
        target_angle_deg=config.depth_target_angle_deg,
        usable=usable,
    )
    if len(sources) < 2:
        raise ClipRejected(
            f"clip {clip_id}: only {len(sources)} registered frames overlap frame 0 with "
            "parallax: need 2 for depth"
        )
    depth0, conf0 = first_frame_depth(
        frames,
        usable,
        sfm.intrinsics,
        sfm.cam_from_world,
        sources,
        (near, far),
        config.depth_scale,
        config.sweep_params(),
        edge_rel=config.depth_edge_rel,
    )
    return CameraEstimate(
        intrinsics=sfm.intrinsics,
        world_from_cam=invert_se3(sfm.cam_from_world),
        registered=sfm.registered,
        static=False,
        depth0=depth0,
        confidence0=conf0,
        backend="sfm",
        reprojection_error_px=sfm.reprojection_error_px,
        num_points3d=sfm.num_points3d,
        sources=tuple(sources),
    )


def estimate_given(
    clip_id: str,
    frames: np.ndarray,
    hand_mask: np.ndarray | None,
    row: Mapping[str, Any],
    config: DepthCameraConfig,
) -> CameraEstimate:
    """The ``given`` backend on one clips ``row``; raises :class:`ClipRejected`."""
    t = int(row["num_frames"])
    if row.get("world_from_cam") is None:
        raise ClipRejected(f"clip {clip_id}: backend 'given' needs the source's world_from_cam")
    poses = np.asarray(row["world_from_cam"], dtype=np.float64).reshape(t, 4, 4)
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
            np.asarray(row["intrinsics"], dtype=np.float64),
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
    )


def row_from_estimate(
    clip_id: str, est: CameraEstimate, height: int, width: int, threshold: float, seconds: float
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
        "seconds": seconds,
    }


class DepthCameraStage(ClipStage):
    """Estimate intrinsics, per-frame poses and first-frame depth with confidence."""

    name = "depth_camera"
    description = "intrinsics, poses and first-frame depth: pycolmap SfM + plane sweep, or given"
    version = 3  # 3: one SfM thread (reproducible); 2: visibility-aware depth confidence
    config_class = DepthCameraConfig
    inputs: ClassVar[Mapping[str, ShardSchema]] = {"clips": CLIPS}
    output = DEPTH_CAMERA
    backends = BACKENDS
    config: DepthCameraConfig

    def estimate(self, row: Mapping[str, Any]) -> CameraEstimate:
        """Run the configured backend on one clips row; raises :class:`ClipRejected`."""
        clip_id = row["clip_id"]
        h, w = int(row["height"]), int(row["width"])
        try:
            frames = media.decode_rgb_video(row["video"], h, w, f"clip {clip_id} video")
            hand_mask = None
            if row.get("hand_mask") is not None:
                hand_mask = media.decode_lossless_video(row["hand_mask"], f"clip {clip_id} hands")
        except media.MediaError as exc:
            raise ClipRejected(f"clip {clip_id}: {exc}") from exc
        backend = self.config.backend
        if backend == "auto":
            backend = "given" if row.get("world_from_cam") is not None else "sfm"
        if backend == "given":
            return estimate_given(clip_id, frames, hand_mask, row, self.config)
        if backend == "da3":
            return estimate_da3(clip_id, frames, self.config)
        intrinsics = np.asarray(row["intrinsics"], dtype=np.float64)
        return estimate_sfm(clip_id, frames, hand_mask, intrinsics, self.config)

    def process(self, rows: Mapping[str, Mapping[str, Any]]) -> dict[str, Any]:
        """Return the ``depth_camera`` row of one clips row."""
        start = time.perf_counter()
        row = rows["clips"]
        est = self.estimate(row)
        return row_from_estimate(
            row["clip_id"],
            est,
            int(row["height"]),
            int(row["width"]),
            self.config.confidence_threshold,
            time.perf_counter() - start,
        )
