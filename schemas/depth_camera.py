"""The ``depth_camera`` schema: what ``depth_camera`` writes, one row per clip.

Camera intrinsics, a pose per frame and a dense depth map of the first frame with a per-pixel
confidence. Poses and depth share one frame and one scale: metric when the backend is ``given``
with metric source poses, SfM's arbitrary (but consistent) scale for ``sfm``. A clip filmed by a
static camera (no parallax) gets every pose equal to the first, ``static_camera`` true and no
depth (DWM's fixed-camera recipe: ``scene_render`` repeats the inpainted first frame).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import pyarrow as pa

from egosim.schemas.base import Column, ShardSchema
from egosim.schemas.clips import POSE
from egosim.schemas.invariants import frame_count_problems, frame_size_problems, se3_problems

BACKENDS = ("sfm", "given", "da3")


def _check_counts(row: Mapping[str, Any]) -> list[str]:
    problems = frame_count_problems(row, ("world_from_cam", "registered"))
    return problems + frame_size_problems(row)


def _check_camera(row: Mapping[str, Any]) -> list[str]:
    problems: list[str] = []
    w, h = row["width"], row["height"]
    fx, fy, cx, cy = row["intrinsics"]
    if not np.all(np.isfinite([fx, fy, cx, cy])) or fx <= 0 or fy <= 0:
        problems.append(f"intrinsics must be finite with fx, fy > 0, got {[fx, fy, cx, cy]}")
    elif not (0 < cx < w and 0 < cy < h):
        problems.append(f"principal point ({cx}, {cy}) lies outside the {w}x{h} image")
    mats = np.asarray(row["world_from_cam"], dtype=np.float64).reshape(-1, 4, 4)
    problems.extend(f"world_from_cam: {p}" for p in se3_problems(mats))
    return problems


def _check_depth(row: Mapping[str, Any]) -> list[str]:
    problems: list[str] = []
    has_depth = row.get("depth0") is not None
    if row["static_camera"]:
        if has_depth:
            problems.append("a static-camera clip must have no depth0 (depth needs parallax)")
        poses = np.asarray(row["world_from_cam"], dtype=np.float64).reshape(-1, 16)
        if len(poses) and np.abs(poses - poses[0]).max() > 1e-9:
            problems.append("a static-camera clip must have every pose equal to the first")
    else:
        for name in ("depth0", "confidence0", "depth_unit_m"):
            if row.get(name) is None:
                problems.append(f"{name} is null but the camera is not static")
    unit = row.get("depth_unit_m")
    if unit is not None and not (np.isfinite(unit) and unit > 0):
        problems.append(f"depth_unit_m must be > 0, got {unit}")
    if row.get("confidence0") is not None and not has_depth:
        problems.append("confidence0 is set but depth0 is null")
    if row["backend"] not in BACKENDS:
        problems.append(f"backend must be one of {list(BACKENDS)}, got {row['backend']!r}")
    return problems


def _check_figures(row: Mapping[str, Any]) -> list[str]:
    problems: list[str] = []
    for name in ("reprojection_error_px", "confident_fraction", "seconds"):
        value = row.get(name)
        if value is not None and not (np.isfinite(value) and value >= 0):
            problems.append(f"{name} must be finite and >= 0, got {value}")
    frac = row.get("confident_fraction")
    if frac is not None and frac > 1:
        problems.append(f"confident_fraction must be <= 1, got {frac}")
    if row.get("num_points3d") is not None and row["num_points3d"] < 0:
        problems.append(f"num_points3d must be >= 0, got {row['num_points3d']}")
    return problems


DEPTH_CAMERA = ShardSchema(
    name="depth_camera",
    version=1,
    doc="Intrinsics, per-frame camera-to-world poses and first-frame depth with confidence.",
    columns=(
        Column("clip_id", pa.string(), "Clip id, as in the clips shard."),
        Column("num_frames", pa.int32(), "Number of frames T."),
        Column("width", pa.int32(), "Frame width W in pixels (of the clip's stored frames)."),
        Column("height", pa.int32(), "Frame height H in pixels."),
        Column(
            "intrinsics",
            pa.list_(pa.float64(), 4),
            "fx, fy, cx, cy in pixels of the stored frames (estimated by sfm, else the source's).",
        ),
        Column(
            "world_from_cam",
            pa.list_(POSE),
            "(T, 16) camera-to-world, row-major 4x4, OpenCV axes, in the depth's scale. Frames "
            "that are not registered are interpolated from their registered neighbours.",
        ),
        Column(
            "registered",
            pa.list_(pa.bool_()),
            "(T,) True where the backend estimated the frame's pose (False: interpolated).",
        ),
        Column(
            "static_camera",
            pa.bool_(),
            "True when the camera did not move (no parallax): every pose equals the first and "
            "depth0 is null; downstream repeats the inpainted first frame.",
        ),
        Column(
            "depth0",
            pa.binary(),
            "(1, H, W) z-depth of frame 0 in the poses' scale, lossless FFV1 uint16 video in "
            "steps of depth_unit_m; 0 = unknown. Null for a static camera.",
            True,
        ),
        Column(
            "depth_unit_m",
            pa.float64(),
            "Depth units (poses' scale) per uint16 step of depth0. Null when depth0 is null.",
            True,
        ),
        Column(
            "confidence0",
            pa.binary(),
            "(1, H, W) uint8 confidence of depth0, 0 (none) .. 255 (sure), lossless FFV1 video. "
            "Null when depth0 is null.",
            True,
        ),
        Column("backend", pa.string(), "Backend that made the row: sfm, given or da3."),
        Column(
            "reprojection_error_px",
            pa.float64(),
            "Mean reprojection error of the SfM model in pixels; null for other backends.",
            True,
        ),
        Column(
            "num_points3d",
            pa.int64(),
            "Number of triangulated SfM points; null for other backends.",
            True,
        ),
        Column(
            "confident_fraction",
            pa.float64(),
            "Fraction of depth0 pixels whose confidence reaches the stage's threshold.",
            True,
        ),
        Column(
            "depth_source_frames",
            pa.list_(pa.int32()),
            "Frame indices the first-frame depth was matched against (plane sweep).",
            True,
        ),
        Column("seconds", pa.float64(), "Wall-clock seconds the stage spent on the clip.", True),
    ),
    validators=(_check_counts, _check_camera, _check_depth, _check_figures),
)
