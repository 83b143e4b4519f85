"""The ``scene_cloud`` and ``scene_render`` schemas: the static scene condition of a clip.

``scene_cloud`` holds the world point cloud unprojected from the clip's hand-free first frame.
Point arrays are little-endian binary blobs (``np.ndarray.tobytes()``; read them back with
``np.frombuffer``): compact, and one Parquet value per clip however many points it has.

``scene_render`` holds that cloud rendered along the clip's trajectory: an RGB scene video and
a visibility mask video (1 = a scene point landed on the pixel, or a small crack was closed).
The model's inpainting mask is derived from ``visible`` by
``egosim.stages.scene_render.splat.inpaint_mask_from_visible`` only.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
import pyarrow as pa

from egosim.schemas.base import Column, ShardSchema
from egosim.schemas.invariants import frame_count_problems, frame_size_problems


def _check_cloud(row: Mapping[str, Any]) -> list[str]:
    problems: list[str] = []
    n = row["num_points"]
    if n is None or n < 1:
        return [f"num_points must be >= 1, got {n}"]
    sizes = {"points_xyz": 12 * n, "points_rgb": 3 * n, "point_size": 4 * n, "point_confidence": n}
    for name, expected in sizes.items():
        if len(row[name]) != expected:
            problems.append(
                f"{name} has {len(row[name])} bytes, expected {expected} for {n} points"
            )
    if problems:
        return problems
    xyz = np.frombuffer(row["points_xyz"], dtype="<f4")
    if not np.all(np.isfinite(xyz)):
        problems.append("points_xyz contains NaN or infinite values")
    size = np.frombuffer(row["point_size"], dtype="<f4")
    if not np.all(size > 0):
        problems.append("point_size must be > 0 for every point")
    if not 0.0 < row["kept_fraction"] <= 1.0:
        problems.append(f"kept_fraction must be in (0, 1], got {row['kept_fraction']}")
    return problems


SCENE_CLOUD = ShardSchema(
    name="scene_cloud",
    version=2,  # 2: point_confidence (measured or filled depth)
    doc="World point cloud of each clip's hand-free first frame, with colours, one per row.",
    columns=(
        Column("clip_id", pa.string(), "Clip id, joins with the clips shard."),
        Column("num_points", pa.int64(), "Number of points N (>= 1)."),
        Column(
            "points_xyz",
            pa.binary(),
            "(N, 3) float32 little-endian world coordinates in metres, row-major bytes.",
        ),
        Column("points_rgb", pa.binary(), "(N, 3) uint8 RGB colour of each point, row-major."),
        Column(
            "point_size",
            pa.binary(),
            "(N,) float32 little-endian side in metres of the pixel each point came from "
            "(depth / fx); renderers widen near points' splats with it.",
        ),
        Column("source_frame", pa.int32(), "Frame index the cloud was unprojected from (0)."),
        Column(
            "image_source",
            pa.string(),
            "Where colour and depth came from, as '<image>+<depth>[-hand_mask]': image one of "
            "inpaint, first_frame_clean, frames; depth one of depth0 (depth_camera), "
            "static_depth, depth, static_plane (static camera); '-hand_mask' when hand pixels "
            "were left out.",
        ),
        Column(
            "kept_fraction",
            pa.float64(),
            "Points kept / pixels of the frame, in (0, 1]: the rest were hands (or, without the "
            "depth fill, had unknown depth or were flying pixels at depth edges).",
        ),
        Column(
            "num_flying_removed",
            pa.int64(),
            "Measured pixels dropped as flying pixels at depth edges or speckles (then filled).",
        ),
        Column(
            "point_confidence",
            pa.binary(),
            "(N,) uint8 per point: 255 = depth measured (confident multi-view depth or the "
            "source's own); 1..254 = depth filled (superpixel plane or inpainting), "
            "1 + round(253 x fill confidence).",
        ),
    ),
    validators=(_check_cloud,),
)


def _check_render(row: Mapping[str, Any]) -> list[str]:
    problems = frame_count_problems(row)
    if problems:
        return problems
    t = row["num_frames"]
    problems += frame_size_problems(row)
    frac = np.asarray(row["visible_fraction"], dtype=np.float64)
    if frac.shape != (t,):
        problems.append(f"visible_fraction has {frac.size} entries, num_frames is {t}")
    elif np.any((frac < 0) | (frac > 1)) or not np.all(np.isfinite(frac)):
        problems.append("visible_fraction must be finite and in [0, 1]")
    if not len(row["scene_video"]) or not len(row["visible"]):
        problems.append("scene_video and visible must be non-empty encoded videos")
    if row["surface_quads"] < 0:
        problems.append(f"surface_quads must be >= 0, got {row['surface_quads']}")
    return problems


SCENE_RENDER = ShardSchema(
    name="scene_render",
    # 2: visible also marks the small cracks the renderer closed
    # 3: surface_quads (how many surface quads the render drew from the cloud's depth grid)
    version=3,
    doc="The scene cloud rendered along each clip's trajectory: scene video and visibility mask.",
    columns=(
        Column("clip_id", pa.string(), "Clip id, joins with the clips shard."),
        Column("num_frames", pa.int32(), "Number of frames T (same as the clip)."),
        Column("width", pa.int32(), "Frame width W in pixels (same as the clip)."),
        Column("height", pa.int32(), "Frame height H in pixels (same as the clip)."),
        Column("fps", pa.float64(), "Frames per second (same as the clip)."),
        Column(
            "scene_video",
            pa.binary(),
            "(T, H, W, 3) RGB render of the scene cloud, H.264 MP4 bytes; black where no "
            "point landed.",
        ),
        Column(
            "visible",
            pa.binary(),
            "(T, H, W) uint8 visibility mask, 1 = a scene point landed on the pixel or the "
            "pixel is in a small crack between landed points that the renderer closed, 0 = none; "
            "lossless FFV1 video.",
        ),
        Column("visible_fraction", pa.list_(pa.float32()), "(T,) fraction of pixels visible."),
        Column("splat_radius", pa.int32(), "Largest splat radius in pixels used for near points."),
        Column(
            "surface_quads",
            pa.int64(),
            "Surface quads linked from the cloud's depth grid (>= 0), drawn in frames away from "
            "its source pose (those over mesh_max_px in a frame skipped). 0: splats only: "
            "a state row (closed loop), mesh_max_step 0, or a cloud whose source pixels the "
            "render's pose at source_frame does not recover (a pose not exactly the cloud's).",
        ),
    ),
    validators=(_check_render,),
)


@dataclass(frozen=True)
class SceneCloud:
    """A coloured world point cloud and what was removed to make it."""

    points: np.ndarray  # (N, 3) float32 world metres
    colours: np.ndarray  # (N, 3) uint8 RGB
    point_size: np.ndarray  # (N,) float32 side in metres of each point's source pixel (z / fx)
    num_flying_removed: int  # measured pixels dropped at depth edges (left out or filled), speckles
    kept_fraction: float  # N / (H * W)
    confidence: np.ndarray  # (N,) uint8 255 = depth measured; 1..254 filled: 1 + 253 x confidence


def cloud_from_row(row: Mapping[str, Any]) -> SceneCloud:
    """Decode one ``scene_cloud`` row into a :class:`SceneCloud`."""
    n = int(row["num_points"])
    return SceneCloud(
        points=np.frombuffer(row["points_xyz"], dtype="<f4").reshape(n, 3),
        colours=np.frombuffer(row["points_rgb"], dtype=np.uint8).reshape(n, 3),
        point_size=np.frombuffer(row["point_size"], dtype="<f4").reshape(n),
        num_flying_removed=int(row["num_flying_removed"]),
        kept_fraction=float(row["kept_fraction"]),
        confidence=np.frombuffer(row["point_confidence"], dtype=np.uint8).reshape(n),
    )
