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
true depth. Pixels with unknown depth (0) are skipped;
negative or non-finite depth rejects the clip. Flying pixels (depth interpolated across an
occlusion edge by estimators and codecs) are removed where inverse depth breaks planarity: the
second difference of ``1/z`` along a row, a column or a diagonal, relative to ``1/z``, exceeds
``edge_threshold``. Inverse depth is affine in pixel coordinates on any plane, so slanted
surfaces (a table seen at a grazing angle) keep every pixel while both sides of a depth edge go.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any, ClassVar

import cv2
import numpy as np

from egosim.pipeline import media
from egosim.pipeline.geometry import se3_problems, transform_points, unproject_depth
from egosim.pipeline.stage import ClipRejected, ClipStage, ConfigError, StageConfig
from egosim.schemas import CLIPS, ShardSchema
from egosim.schemas.inpaint import INPAINT
from egosim.schemas.scene import SCENE_CLOUD
from egosim.stages.common.cameras import (
    CAMERA_ROLES,
    depth_is_unknown_by_model,
    first_frame_depth,
    resolve_cameras,
)

STATIC_PLANE_DEPTH = 1.0  # depth of the plane standing in for a static / rotating camera's scene


class SceneCloudError(ValueError):
    """The inputs of a cloud cannot give a correct cloud (shapes, depth, pose, empty result)."""


@dataclasses.dataclass(frozen=True)
class SceneCloud:
    """A coloured world point cloud and what was removed to make it."""

    points: np.ndarray  # (N, 3) float32 world metres
    colours: np.ndarray  # (N, 3) uint8 RGB
    point_size: np.ndarray  # (N,) float32 side in metres of each point's source pixel (z / fx)
    num_flying_removed: int  # pixels dropped by the depth-edge test
    kept_fraction: float  # N / (H * W)


def flying_pixel_mask(depth: np.ndarray, edge_threshold: float) -> np.ndarray:
    """``(H, W)`` bool, True where a pixel sits on a depth edge (a flying pixel candidate).

    ``depth (H, W)`` metres, 0 = unknown. A pixel is flagged when, along any of the four
    directions (row, column, two diagonals), ``|d(p-1) - 2 d(p) + d(p+1)| / d(p)`` exceeds
    ``edge_threshold`` with ``d = 1/z``; neighbours of unknown depth or outside the image are
    ignored.
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
        flagged |= np.nan_to_num(second, nan=0.0) > edge_threshold
    return flagged & known


def build_scene_cloud(
    image: np.ndarray,
    depth: np.ndarray,
    world_from_cam: np.ndarray,
    intrinsics: np.ndarray,
    exclude: np.ndarray | None = None,
    edge_threshold: float = 0.05,
) -> SceneCloud:
    """Unproject ``image (H, W, 3)`` uint8 with ``depth (H, W)`` metres through one camera.

    ``world_from_cam (4, 4)``, ``intrinsics (fx, fy, cx, cy)``; ``exclude (H, W)`` marks pixels
    to leave out (1 = hand). Depth 0 means unknown and is skipped; ``edge_threshold <= 0``
    disables the flying-pixel filter. Raises :class:`SceneCloudError` for shapes that disagree,
    negative or non-finite depth, an invalid pose and an empty result.
    """
    image = np.asarray(image)
    depth = np.asarray(depth, dtype=np.float64)
    problems: list[str] = []
    if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
        problems.append(f"image must be (H, W, 3) uint8, got {image.shape} {image.dtype}")
    elif depth.shape != image.shape[:2]:
        problems.append(f"depth shape {depth.shape} != image shape {image.shape[:2]}")
    if exclude is not None and np.shape(exclude) != depth.shape:
        problems.append(f"exclude shape {np.shape(exclude)} != depth shape {depth.shape}")
    if not np.all(np.isfinite(depth)):
        problems.append("depth contains NaN or infinite values")
    elif np.any(depth < 0):
        problems.append(f"depth has {int((depth < 0).sum())} negative values")
    problems += [f"world_from_cam: {p}" for p in se3_problems(world_from_cam)]
    if problems:
        raise SceneCloudError("; ".join(problems))
    keep = depth > 0  # (H, W)
    if exclude is not None:
        keep &= np.asarray(exclude) == 0
    masked = np.where(keep, depth, 0.0)  # (H, W) hands count as unknown depth for the edge test
    flying = (
        flying_pixel_mask(masked, edge_threshold) if edge_threshold > 0 else np.zeros_like(keep)
    )
    keep &= ~flying
    if not keep.any():
        raise SceneCloudError("empty point cloud: no pixel has known depth outside the masks")
    points_cam = unproject_depth(masked, intrinsics)[keep]  # (N, 3)
    points_world = transform_points(world_from_cam, points_cam).astype(np.float32)  # (N, 3)
    fx = float(np.asarray(intrinsics, dtype=np.float64)[0])
    return SceneCloud(
        points=points_world,
        colours=np.ascontiguousarray(image[keep]),  # (N, 3)
        point_size=(masked[keep] / fx).astype(np.float32),  # (N,)
        num_flying_removed=int(flying.sum()),
        kept_fraction=float(keep.sum()) / keep.size,
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
    }


def cloud_from_row(row: Mapping[str, Any]) -> SceneCloud:
    """Decode one ``scene_cloud`` row into a :class:`SceneCloud`."""
    n = int(row["num_points"])
    return SceneCloud(
        points=np.frombuffer(row["points_xyz"], dtype="<f4").reshape(n, 3),
        colours=np.frombuffer(row["points_rgb"], dtype=np.uint8).reshape(n, 3),
        point_size=np.frombuffer(row["point_size"], dtype="<f4").reshape(n),
        num_flying_removed=int(row["num_flying_removed"]),
        kept_fraction=float(row["kept_fraction"]),
    )


@dataclasses.dataclass(frozen=True)
class SceneCloudConfig(StageConfig):
    """Parameters of ``scene_cloud``."""

    edge_threshold: float = (
        0.05  # flying pixel: |2nd difference of 1/z| / (1/z) above this; 0 = off
    )

    def __post_init__(self) -> None:
        if not (np.isfinite(self.edge_threshold) and self.edge_threshold >= 0):
            raise ConfigError(f"edge_threshold must be finite and >= 0, got {self.edge_threshold}")


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
    # 2: static_depth beats depth for frames+hand_mask; image_source names the depth
    # 3: a static camera gets a plane at STATIC_PLANE_DEPTH instead of a reject
    # 4: so does a rotation-only camera (depth_camera camera_model "rotation")
    version = 4
    config: SceneCloudConfig

    def process(self, rows: Mapping[str, Mapping[str, Any]]) -> dict[str, Any]:
        """Build the cloud of one clip from its rows (see the module docstring)."""
        cid = rows["clips"]["clip_id"]
        cams = resolve_cameras(rows)
        if cams.world_from_cam is None:
            raise ClipRejected(f"clip {cid!r}: no camera poses (world_from_cam is null)")
        image, depth, exclude, source = _first_frame(rows)
        try:
            cloud = build_scene_cloud(
                image,
                depth,
                cams.world_from_cam[0],
                cams.intrinsics,
                exclude,
                self.config.edge_threshold,
            )
        except SceneCloudError as exc:
            raise ClipRejected(f"clip {cid!r}: {exc}") from exc
        return cloud_row(cid, cloud, source)


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


def _first_frame(
    rows: Mapping[str, Mapping[str, Any]],
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, str]:
    """``(image (H, W, 3), depth (H, W), exclude (H, W) or None, source name)`` of frame 0."""
    row, inpaint = rows["clips"], rows.get("inpaint")
    cid, h, w = row["clip_id"], row["height"], row["width"]
    depth = first_frame_depth(rows)  # (H, W)
    depth_name = _depth_name(rows)
    if depth is None:
        if not depth_is_unknown_by_model(rows):
            raise ClipRejected(f"clip {cid!r}: no depth (needs depth0, static_depth or depth)")
        # A static or rotating camera has no parallax, hence no depth (DWM's fixed-camera
        # recipe): a fronto-parallel plane seen from pure rotations about frame 0's centre makes
        # scene_render warp frame 0 by the rotation's homography (repeat it when static).
        depth = np.full((h, w), STATIC_PLANE_DEPTH, np.float32)
        depth_name = "static_plane"
    hand_free = depth_name in ("static_depth", "static_plane")
    if inpaint is not None:
        image = media.decode_png(inpaint["first_frame"], f"clip {cid} inpaint first_frame")
        if not hand_free:
            filled = media.decode_png(inpaint["fill_source"], f"clip {cid} fill_source") > 0
            if filled.shape != depth.shape:
                raise ClipRejected(
                    f"clip {cid!r}: inpaint fill_source {filled.shape} != depth {depth.shape}"
                )
            depth = fill_depth_under(depth, filled)
        return image, depth, None, f"inpaint+{depth_name}"
    if row.get("first_frame_clean") is not None and hand_free:
        image = media.decode_png(row["first_frame_clean"], f"clip {cid} first_frame_clean")
        return image, depth, None, f"first_frame_clean+{depth_name}"
    if row.get("hand_mask") is None:
        raise ClipRejected(
            f"clip {cid!r}: no inpaint, first_frame_clean or hand_mask: the cloud would "
            "contain hands"
        )
    image = media.decode_rgb_video(row["video"], h, w, f"clip {cid} video")[0]
    hands = media.decode_lossless_video(row["hand_mask"], f"clip {cid} hand_mask", 1)[0]
    return image, depth, hands, f"frames+{depth_name}-hand_mask"
