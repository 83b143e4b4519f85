"""The ``keypoints`` schema: 2D hand keypoints, their visibility and the skeleton video.

Keypoints are the ``hands`` joints projected with the clip's own intrinsics and poses (the same
camera model as the scene render). Pixel coordinates use the project convention: pixel centres
at integer + 0.5, so a point at ``(u, v)`` lies in pixel ``(floor(u), floor(v))``.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import pyarrow as pa

from egosim.schemas.base import Column, ShardSchema
from egosim.schemas.invariants import frame_count_problems

NUM_KEYPOINTS = 2 * 21  # both hands


def _check_keypoints(row: Mapping[str, Any]) -> list[str]:
    problems = frame_count_problems(row, ("keypoints_2d", "keypoint_depth", "keypoint_visible"))
    t = row["num_frames"]
    if problems:
        return problems
    uv = np.asarray(row["keypoints_2d"], dtype=np.float64).reshape(t, NUM_KEYPOINTS, 2)
    depth = np.asarray(row["keypoint_depth"], dtype=np.float64)  # (T, 42)
    vis = np.asarray(row["keypoint_visible"], dtype=bool)  # (T, 42)
    if not np.all(np.isfinite(uv[vis])) or not np.all(depth[vis] > 0):
        problems.append("visible keypoints need finite pixels and positive depth")
    w, h = row["width"], row["height"]
    inside = (uv[..., 0] >= 0) & (uv[..., 0] < w) & (uv[..., 1] >= 0) & (uv[..., 1] < h)
    if np.any(vis & ~inside):
        problems.append("visible keypoints must lie inside the image")
    if row["variant"] not in ("hand", "gripper"):
        problems.append(f"variant must be 'hand' or 'gripper', got {row['variant']!r}")
    return problems


KEYPOINTS = ShardSchema(
    name="keypoints",
    version=1,
    doc="Projected 2D hand keypoints with visibility, and the skeleton video drawn from them.",
    columns=(
        Column("clip_id", pa.string(), "Clip id, joins with the clips shard."),
        Column("num_frames", pa.int32(), "Number of frames T (same as the clip)."),
        Column("width", pa.int32(), "Frame width W in pixels (same as the clip)."),
        Column("height", pa.int32(), "Frame height H in pixels (same as the clip)."),
        Column("fps", pa.float64(), "Frames per second (same as the clip)."),
        Column("variant", pa.string(), "'hand' (21 joints) or 'gripper' (thumb + index chains)."),
        Column(
            "keypoints_2d",
            pa.list_(pa.list_(pa.float32(), NUM_KEYPOINTS * 2)),
            "(T, 2*21*2) float32 pixel (u, v) per joint, hand-major; NaN for invalid hands and "
            "joints at or behind the camera.",
        ),
        Column(
            "keypoint_depth",
            pa.list_(pa.list_(pa.float32(), NUM_KEYPOINTS)),
            "(T, 2*21) float32 camera z in metres (NaN for invalid hands).",
        ),
        Column(
            "keypoint_visible",
            pa.list_(pa.list_(pa.bool_(), NUM_KEYPOINTS)),
            "(T, 2*21) True = valid hand, in front of the near plane and inside the image "
            "(not an occlusion test).",
        ),
        Column(
            "skeleton_video",
            pa.binary(),
            "(T, H, W, 3) skeleton on black, per-finger colours, H.264 MP4 bytes.",
        ),
    ),
    validators=(_check_keypoints,),
)
