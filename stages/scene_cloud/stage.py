"""The ``scene_cloud`` stage: unproject the hand-free first frame into a coloured world cloud.

Depth is :func:`egosim.stages.common.cameras.first_frame_depth` (the optional ``cameras``
input's depth0, else the clip's ``static_depth[0]``, else its ``depth[0]``); the pose of frame 0
and the intrinsics come from :func:`egosim.stages.common.cameras.resolve_cameras`. Colour:

- the optional ``inpaint`` input's ``first_frame`` when connected; where the depth may show the
  hands (it is not the clip's hand-free ``static_depth``), the depth under the inpainted pixels
  is filled by OpenCV inpainting of the depth around them (a smooth continuation of the
  surfaces the hand covered, as ``inpaint`` assumes);
- else the clip's ``first_frame_clean`` when the depth is its ``static_depth``;
- else ``video[0]`` with the ``hand_mask[0]`` pixels removed.

A static camera (a ``cameras`` row with ``static_camera`` and no depth0) or a rotation-only
camera (``camera_model`` ``rotation``, no depth0): without parallax there is no depth, so frame 0
is placed on a fronto-parallel plane at ``STATIC_PLANE_DEPTH``; rendered from the one pose, that
repeats the (inpainted) first frame in every frame, the fixed-camera recipe of DWM; rendered from
pure rotations about frame 0's centre, it is the homography warp of frame 0, exact whatever the
true depth. Negative or non-finite depth rejects the clip.

Depth is made dense by :func:`egosim.stages.scene_cloud.densify.densify_depth`: pixels whose
depth was measured (the ``cameras`` row's ``confidence0`` at or above ``min_confidence``; every
known pixel of a source's own depth) are kept, flying pixels at depth edges (inverse depth breaks
planarity: both sides of an occlusion edge) and, optionally, small islands are dropped, and
every other pixel (unconfident, flying, under the inpainted hands) is filled edge-aware: by the
plane of its colour superpixel fitted to the measured inverse depth, else by inpainting the
inverse depth. Each point records whether its depth was measured or filled
(``point_confidence``). ``fill=False`` keeps the measured pixels only.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any, ClassVar

import cv2
import numpy as np

from egosim.pipeline import media
from egosim.pipeline.geometry import se3_problems, transform_points, unproject_depth
from egosim.pipeline.records import ClipsRecord, require_camera_poses
from egosim.pipeline.stage import ClipRejected, ClipStage, ConfigError, StageConfig, join_columns
from egosim.schemas import CLIPS, ShardSchema
from egosim.schemas.inpaint import INPAINT
from egosim.schemas.scene import SCENE_CLOUD, SceneCloud, cloud_from_row  # noqa: F401 (re-exported)
from egosim.stages.common.cameras import (
    CAMERA_COLUMNS,
    CAMERA_ROLES,
    DEPTH0_COLUMNS,
    depth_is_unknown_by_model,
    first_frame_confidence,
    first_frame_depth,
    resolve_cameras,
)
from egosim.stages.scene_cloud.densify import MEASURED, DensifyParams, densify_depth

STATIC_PLANE_DEPTH = 1.0  # depth of the plane standing in for a static / rotating camera's scene


class SceneCloudError(ValueError):
    """The inputs of a cloud cannot give a correct cloud (shapes, depth, pose, empty result)."""


def point_confidence(source: np.ndarray, confidence: np.ndarray) -> np.ndarray:
    """Per-pixel uint8 code of :class:`SceneCloud`'s ``confidence`` from a densified depth.

    ``source (...)`` a :mod:`~egosim.stages.scene_cloud.densify` source code, ``confidence
    (...)`` in [0, 1]: 255 where the depth was measured, else ``1 + round(253 x confidence)``.
    """
    filled = 1 + np.round(253.0 * np.clip(confidence, 0.0, 1.0)).astype(np.uint8)
    return np.where(source == MEASURED, np.uint8(255), filled).astype(np.uint8)


def build_scene_cloud(
    image: np.ndarray,
    depth: np.ndarray,
    world_from_cam: np.ndarray,
    intrinsics: np.ndarray,
    exclude: np.ndarray | None = None,
    *,
    confidence: np.ndarray | None = None,
    unmeasured: np.ndarray | None = None,
    params: DensifyParams | None = None,
    fill: bool = True,
) -> SceneCloud:
    """Unproject ``image (H, W, 3)`` uint8 with ``depth (H, W)`` metres through one camera.

    ``world_from_cam (4, 4)``, ``intrinsics (fx, fy, cx, cy)``; ``exclude (H, W)`` marks pixels
    to leave out (1 = hand); ``confidence (H, W)`` in [0, 1] of the depth (None: every known
    pixel is measured); ``unmeasured (H, W)`` pixels whose depth is to be filled, not trusted.
    The depth is densified by :func:`densify_depth` with ``params``; ``fill=False`` keeps only
    the measured pixels (depth 0 = unknown, flying pixels and speckles dropped). Raises
    :class:`SceneCloudError` for shapes that disagree, negative or non-finite depth, an invalid
    pose and an empty result.
    """
    image = np.asarray(image)
    depth = np.asarray(depth, dtype=np.float64)
    problems: list[str] = []
    if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
        problems.append(f"image must be (H, W, 3) uint8, got {image.shape} {image.dtype}")
    elif depth.shape != image.shape[:2]:
        problems.append(f"depth shape {depth.shape} != image shape {image.shape[:2]}")
    for name, extra in (
        ("exclude", exclude),
        ("confidence", confidence),
        ("unmeasured", unmeasured),
    ):
        if extra is not None and np.shape(extra) != depth.shape:
            problems.append(f"{name} shape {np.shape(extra)} != depth shape {depth.shape}")
    if not np.all(np.isfinite(depth)):
        problems.append("depth contains NaN or infinite values")
    elif np.any(depth < 0):
        problems.append(f"depth has {int((depth < 0).sum())} negative values")
    problems += [f"world_from_cam: {p}" for p in se3_problems(world_from_cam)]
    if problems:
        raise SceneCloudError("; ".join(problems))
    dense = densify_depth(
        depth,
        image,
        intrinsics,
        confidence=confidence,
        exclude=exclude,
        unmeasured=unmeasured,
        params=params,
        fill=fill,
    )
    keep = dense.depth > 0  # (H, W)
    if not keep.any():
        raise SceneCloudError("empty point cloud: no pixel has known depth outside the masks")
    points_cam = unproject_depth(dense.depth, intrinsics)[keep]  # (N, 3)
    points_world = transform_points(world_from_cam, points_cam).astype(np.float32)  # (N, 3)
    fx = float(np.asarray(intrinsics, dtype=np.float64)[0])
    return SceneCloud(
        points=points_world,
        colours=np.ascontiguousarray(image[keep]),  # (N, 3)
        point_size=(dense.depth[keep] / fx).astype(np.float32),  # (N,)
        num_flying_removed=dense.num_flying,
        kept_fraction=float(keep.sum()) / keep.size,
        confidence=point_confidence(dense.source[keep], dense.confidence[keep]),  # (N,)
    )


def cloud_row(clip_id: str, cloud: SceneCloud, image_source: str) -> dict[str, Any]:
    """Encode a :class:`SceneCloud` as one ``scene_cloud`` row."""
    return {
        "clip_id": clip_id,
        "num_points": len(cloud.points),
        "points_xyz": cloud.points.astype("<f4").tobytes(),
        "points_rgb": cloud.colours.astype(np.uint8).tobytes(),
        "point_size": cloud.point_size.astype("<f4").tobytes(),
        "source_frame": 0,
        "image_source": image_source,
        "kept_fraction": cloud.kept_fraction,
        "num_flying_removed": cloud.num_flying_removed,
        "point_confidence": cloud.confidence.astype(np.uint8).tobytes(),
    }


@dataclasses.dataclass(frozen=True)
class SceneCloudConfig(StageConfig):
    """Parameters of ``scene_cloud`` (the depth fill: see :class:`DensifyParams`)."""

    fill: bool = True  # fill unmeasured depth edge-aware; False = keep measured pixels only
    min_confidence: float = 0.5  # depth_camera confidence at or above = measured depth (0..1)
    edge_threshold: float = 0.05  # flying pixel: |2nd difference of 1/z| / (1/z) above; 0 = off
    drop_edges: bool = True  # True: both sides of a depth edge left out; False: refill them
    speckle_px: int = 50  # islands of estimated depth up to this many pixels ... (0 = off)
    speckle_rel: float = 0.03  # ... whose neighbours differ by at most this (relative 1/z) go
    segment_px: tuple[int, ...] = (20,)  # colour superpixel seed spacings, fine to coarse
    plane_tolerance: float = 0.03  # plane inlier: |1/z - plane| / (1/z) at most this
    snap_to_planes: bool = False  # measured plane inliers take the plane's depth (denoising)
    outlier_factor: float = 3.0  # measured pixels off their superpixel plane by more than this
    # x plane_tolerance take the plane's depth (confident matching errors); 0 = keep them
    min_plane_support: int = 12  # a superpixel plane needs this many inlier pixels ...
    min_plane_fraction: float = 0.05  # ... and this share of the superpixel
    inpaint_radius: float = 5.0  # radius (pixels) of the inpainting fill for what planes miss

    def __post_init__(self) -> None:
        problems: list[str] = []
        for name in ("fill", "drop_edges", "snap_to_planes"):
            if not isinstance(getattr(self, name), bool):
                problems.append(f"{name} must be a bool, got {getattr(self, name)!r}")
        for name in ("min_confidence", "min_plane_fraction"):
            value = getattr(self, name)
            if not (np.isfinite(value) and 0.0 <= value <= 1.0):
                problems.append(f"{name} must be in [0, 1], got {value}")
        for name in ("edge_threshold", "speckle_rel", "outlier_factor"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value >= 0):
                problems.append(f"{name} must be finite and >= 0, got {value}")
        for name in ("plane_tolerance", "inpaint_radius"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0):
                problems.append(f"{name} must be > 0, got {value}")
        if self.speckle_px < 0:
            problems.append(f"speckle_px must be >= 0, got {self.speckle_px}")
        if not self.segment_px or any(int(s) < 2 for s in self.segment_px):
            problems.append(f"segment_px must be spacings >= 2 pixels, got {self.segment_px}")
        if self.min_plane_support < 3:
            problems.append(f"min_plane_support must be >= 3, got {self.min_plane_support}")
        if problems:
            raise ConfigError("; ".join(problems))

    def densify_params(self) -> DensifyParams:
        """The :class:`DensifyParams` these settings describe."""
        return DensifyParams(
            min_confidence=self.min_confidence,
            edge_threshold=self.edge_threshold,
            drop_edges=self.drop_edges,
            speckle_px=self.speckle_px,
            speckle_rel=self.speckle_rel,
            segment_px=tuple(int(s) for s in self.segment_px),
            plane_tolerance=self.plane_tolerance,
            snap_to_planes=self.snap_to_planes,
            outlier_factor=self.outlier_factor,
            min_plane_support=self.min_plane_support,
            min_plane_fraction=self.min_plane_fraction,
            inpaint_radius=self.inpaint_radius,
        )


class SceneCloudStage(ClipStage):
    """Unproject each clip's hand-free first frame into a coloured world point cloud."""

    name = "scene_cloud"
    description = "unproject the hand-free first frame with its depth and pose into a world cloud"
    config_class = SceneCloudConfig
    inputs: ClassVar[Mapping[str, ShardSchema]] = {"clips": CLIPS}
    # replacement camera and depth, and the inpainted first frame (see the module docstring)
    optional_inputs: ClassVar[Mapping[str, ShardSchema]] = {**CAMERA_ROLES, "inpaint": INPAINT}
    output = SCENE_CLOUD
    backends = ("first_frame",)
    # What process reads (the executor decodes nothing else): frame 0's image (inpainted, clean
    # or masked), its depth and confidence, the camera.
    columns: ClassVar[Mapping[str, tuple[str, ...]]] = join_columns(
        {
            "clips": ("height", "width", "first_frame_clean", "hand_mask", "video"),
            "cameras": ("confidence0",),
            "inpaint": ("first_frame", "fill_source"),
        },
        CAMERA_COLUMNS,
        DEPTH0_COLUMNS,
    )
    # 2: static_depth beats depth for frames+hand_mask; image_source names the depth
    # 3: a static camera gets a plane at STATIC_PLANE_DEPTH instead of a reject
    # 4: so does a rotation-only camera (depth_camera camera_model "rotation")
    # 5: dense depth (measured where confident, filled by superpixel planes / inpainting),
    #    flying pixels only at depth edges; point_confidence (scene_cloud schema v2)
    version = 5
    config: SceneCloudConfig

    def process(self, rows: Mapping[str, Mapping[str, Any]]) -> dict[str, Any]:
        """Build the cloud of one clip from its rows (see the module docstring)."""
        cid = ClipsRecord.of(rows["clips"]).clip_id
        cams = resolve_cameras(rows)
        world_from_cam = require_camera_poses(cams.world_from_cam, cid)
        first = _first_frame(rows, self.config.fill)
        try:
            cloud = build_scene_cloud(
                first.image,
                first.depth,
                world_from_cam[0],
                cams.intrinsics,
                first.exclude,
                confidence=first.confidence,
                unmeasured=first.unmeasured,
                params=self.config.densify_params(),
                fill=self.config.fill,
            )
        except SceneCloudError as exc:
            raise ClipRejected(f"clip {cid!r}: {exc}") from exc
        return cloud_row(cid, cloud, first.source)


def _depth_name(rows: Mapping[str, Mapping[str, Any]]) -> str:
    """Which column :func:`first_frame_depth` reads: ``depth0``, ``static_depth`` or ``depth``."""
    cams, clip = rows.get("cameras"), rows["clips"]
    if cams is not None and cams.get("depth0") is not None:
        return "depth0"
    return "static_depth" if clip.get("static_depth") is not None else "depth"


def fill_depth_under(depth: np.ndarray, filled: np.ndarray, radius: float = 5.0) -> np.ndarray:
    """``depth (H, W)`` with the ``filled (H, W)`` pixels replaced by inpainted depth.

    Unknown depth (0) outside ``filled`` stays unknown; it is not used as a source. Navier-Stokes
    inpainting: OpenCV's Telea returns noise on float32 images (seen with OpenCV 5.0).
    """
    unknown = (filled | ~(depth > 0)).astype(np.uint8)  # (H, W)
    if not filled.any() or unknown.all():
        return depth
    guess = cv2.inpaint(
        np.where(unknown > 0, 0.0, depth).astype(np.float32), unknown, radius, cv2.INPAINT_NS
    )  # (H, W)
    return np.where(filled, guess, depth).astype(np.float32)


@dataclasses.dataclass(frozen=True)
class FirstFrame:
    """What frame 0 gives the cloud: colour, depth and which pixels to trust or leave out."""

    image: np.ndarray  # (H, W, 3) uint8 RGB
    depth: np.ndarray  # (H, W) float32 metres, 0 = unknown
    confidence: np.ndarray | None  # (H, W) float32 in [0, 1] of depth0, None = all measured
    exclude: np.ndarray | None  # (H, W) bool pixels left out (hands), None = none
    unmeasured: np.ndarray | None  # (H, W) bool pixels whose depth is filled (under inpainting)
    source: str  # image_source column value


def _first_frame(rows: Mapping[str, Mapping[str, Any]], fill: bool = True) -> FirstFrame:
    """Frame 0's image, depth, depth confidence, pixels to leave out or fill (module docstring)."""
    row, inpaint = ClipsRecord.of(rows["clips"]), rows.get("inpaint")
    cid, h, w = row.clip_id, row.height, row.width
    depth = first_frame_depth(rows)  # (H, W)
    depth_name = _depth_name(rows)
    confidence = None
    if depth is None:
        if not depth_is_unknown_by_model(rows):
            raise ClipRejected(f"clip {cid!r}: no depth (needs depth0, static_depth or depth)")
        # A static or rotating camera has no parallax, hence no depth (DWM's fixed-camera
        # recipe): a fronto-parallel plane seen from pure rotations about frame 0's centre makes
        # scene_render warp frame 0 by the rotation's homography (repeat it when static).
        depth = np.full((h, w), STATIC_PLANE_DEPTH, np.float32)
        depth_name = "static_plane"
    elif depth_name == "depth0":
        confidence = first_frame_confidence(rows, depth.shape)
    hand_free = depth_name in ("static_depth", "static_plane")
    if inpaint is not None:
        image = media.decode_png(inpaint["first_frame"], f"clip {cid} inpaint first_frame")
        unmeasured = None
        if not hand_free:
            filled = media.decode_png(inpaint["fill_source"], f"clip {cid} fill_source") > 0
            if filled.shape != depth.shape:
                raise ClipRejected(
                    f"clip {cid!r}: inpaint fill_source {filled.shape} != depth {depth.shape}"
                )
            if fill:
                unmeasured = filled
            else:
                depth = fill_depth_under(depth, filled)
        return FirstFrame(image, depth, confidence, None, unmeasured, f"inpaint+{depth_name}")
    if row.get("first_frame_clean") is not None and hand_free:
        image = media.decode_png(row["first_frame_clean"], f"clip {cid} first_frame_clean")
        return FirstFrame(image, depth, confidence, None, None, f"first_frame_clean+{depth_name}")
    if row.get("hand_mask") is None:
        raise ClipRejected(
            f"clip {cid!r}: no inpaint, first_frame_clean or hand_mask: the cloud would "
            "contain hands"
        )
    image = media.decode_rgb_video(row["video"], h, w, f"clip {cid} video")[0]
    hands = media.decode_lossless_video(row["hand_mask"], f"clip {cid} hand_mask", 1)[0]
    return FirstFrame(image, depth, confidence, hands > 0, None, f"frames+{depth_name}-hand_mask")
