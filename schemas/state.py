"""The ``state`` schema: the world state (a point cloud with instances) after one clip.

Written by ``state_fusion``, one row per clip: the scene as points in world metres (colour, size,
per-point instance id and per-point source), the instance table with the interaction test's
per-frame results, the cameras the state was built from and the Sim3 that registered the clip
to the previous state. Point arrays are little-endian binary blobs like ``scene_cloud``'s, so a
state row converts to a ``scene_cloud`` row by picking columns
(:func:`scene_cloud_row_from_state`).

Per-point ``source`` codes (``POINT_SOURCES``): 0 background fused by TSDF, 1 non-interacted
object fused by TSDF, 2 interacted object taken from its last observed frame, 3 carried over
from the previous state.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import pyarrow as pa

from egosim.schemas.base import Column, ShardSchema
from egosim.schemas.clips import POSE
from egosim.schemas.invariants import se3_problems
from egosim.schemas.scene import SCENE_CLOUD

POINT_SOURCES = ("background", "object", "last_observed", "previous")  # per-point source codes


def _blob(row: Mapping[str, Any], name: str, dtype: str, per_point: int) -> np.ndarray | None:
    """Decode one point blob, or None when its size is wrong (reported by the caller)."""
    data = row[name]
    n = row["num_points"]
    size = np.dtype(dtype).itemsize * per_point * n
    if len(data) != size:
        return None
    return np.frombuffer(data, dtype=dtype)


def _check_points(row: Mapping[str, Any]) -> list[str]:
    problems: list[str] = []
    n = row["num_points"]
    if n is None or n < 1:
        return [f"num_points must be >= 1, got {n}"]
    blobs = {
        "points_xyz": ("<f4", 3),
        "points_rgb": ("u1", 3),
        "point_size": ("<f4", 1),
        "point_instance": ("<i4", 1),
        "point_source": ("u1", 1),
    }
    arrays: dict[str, np.ndarray] = {}
    for name, (dtype, per_point) in blobs.items():
        arr = _blob(row, name, dtype, per_point)
        if arr is None:
            expected = np.dtype(dtype).itemsize * per_point * n
            problems.append(
                f"{name} has {len(row[name])} bytes, expected {expected} for {n} points"
            )
        else:
            arrays[name] = arr
    if "points_xyz" in arrays and not np.all(np.isfinite(arrays["points_xyz"])):
        problems.append("points_xyz contains NaN or infinite values")
    if "point_size" in arrays and not np.all(arrays["point_size"] > 0):
        problems.append("point_size must be > 0 for every point")
    if "point_source" in arrays:
        bad = np.unique(arrays["point_source"][arrays["point_source"] >= len(POINT_SOURCES)])
        if bad.size:
            problems.append(
                f"point_source codes must be < {len(POINT_SOURCES)}, got {bad[:5].tolist()}"
            )
    if "point_instance" in arrays:
        known = set(int(i) for i in row["instance_id"]) | {0}
        unknown = sorted(set(np.unique(arrays["point_instance"]).tolist()) - known)
        if unknown:
            problems.append(f"point_instance holds ids missing from instance_id: {unknown[:5]}")
    return problems


def _check_instances(row: Mapping[str, Any]) -> list[str]:
    problems: list[str] = []
    ids = list(row["instance_id"])
    m = len(ids)
    if len(set(ids)) != m:
        problems.append(f"instance_id has duplicates: {ids}")
    if any(i < 1 for i in ids):
        problems.append(f"instance ids must be >= 1 (0 is the background), got {ids}")
    names = (
        "instance_label",
        "instance_interactive",
        "instance_last_observed_frame",
        "instance_geometry_frame",
    )
    for name in names:
        if len(row[name]) != m:
            problems.append(f"{name} has {len(row[name])} entries, instance_id has {m}")
    if len(row["instance_centroid"]) != m:
        problems.append(
            f"instance_centroid has {len(row['instance_centroid'])} entries, expected {m}"
        )
    t = row["num_frames"]
    if t is None or t < 1:
        return [*problems, f"num_frames must be >= 1, got {t}"]
    for name in ("instance_interaction", "instance_depth_gap_m"):
        table = row[name]
        if len(table) != m:
            problems.append(f"{name} has {len(table)} rows, instance_id has {m}")
        elif any(len(r) != t for r in table):
            problems.append(f"{name} rows must each have num_frames={t} entries")
    for name in ("instance_last_observed_frame", "instance_geometry_frame"):
        frames = np.asarray(row[name], dtype=np.int64)
        if frames.size and (frames.min() < -1 or frames.max() >= t):
            problems.append(f"{name} must be in [-1, {t - 1}], got {frames.tolist()}")
    return problems


def _check_cameras(row: Mapping[str, Any]) -> list[str]:
    problems: list[str] = []
    poses = np.asarray(row["world_from_cam"], dtype=np.float64)
    k = len(row["camera_frames"])
    if poses.ndim != 2 or poses.shape[0] != k or poses.shape[0] < 1:
        problems.append(
            f"world_from_cam has {poses.shape[0] if poses.ndim else 0} poses, "
            f"camera_frames has {k} (need >= 1 and equal)"
        )
    else:
        problems += [f"world_from_cam: {p}" for p in se3_problems(poses.reshape(-1, 4, 4))]
    fx, fy, cx, cy = row["intrinsics"]
    if not np.all(np.isfinite([fx, fy, cx, cy])) or fx <= 0 or fy <= 0:
        problems.append(f"intrinsics must be finite with fx, fy > 0, got {[fx, fy, cx, cy]}")
    if row["width"] < 1 or row["height"] < 1:
        problems.append(f"width and height must be positive, got {row['width']}x{row['height']}")
    sim3 = np.asarray(row["previous_from_clip"], dtype=np.float64).reshape(4, 4)
    scale = row["sim3_scale"]
    if not (np.isfinite(scale) and scale > 0):
        problems.append(f"sim3_scale must be finite and > 0, got {scale}")
    else:
        rigid = sim3.copy()
        rigid[:3, :3] /= scale
        problems += [f"previous_from_clip (scale removed): {p}" for p in se3_problems(rigid)]
    return problems


STATE = ShardSchema(
    name="state",
    version=1,
    doc="World state after each clip: points with instances, instance table, cameras, Sim3.",
    columns=(
        Column(
            "clip_id",
            pa.string(),
            "Clip the row joins with: the clip the state was fused from, or, for a state given "
            "as a next clip's previous_state (state_for_clip), that next clip.",
        ),
        Column("state_clip_id", pa.string(), "Clip the state was fused from."),
        Column(
            "previous_clip_id",
            pa.string(),
            "Clip id of the previous state this one was fused onto; null for a first state.",
            True,
        ),
        Column(
            "world_frame",
            pa.string(),
            "Name of the world frame the points live in: the first clip of the chain of states.",
        ),
        Column("num_frames", pa.int32(), "Frames T of the fused clip (per-frame tables)."),
        Column("num_points", pa.int64(), "Number of points N (>= 1)."),
        Column("points_xyz", pa.binary(), "(N, 3) float32 little-endian world metres, row-major."),
        Column("points_rgb", pa.binary(), "(N, 3) uint8 RGB colour of each point, row-major."),
        Column(
            "point_size",
            pa.binary(),
            "(N,) float32 little-endian side in metres of the surface each point stands for "
            "(TSDF voxel size, or depth / fx for points taken from one frame).",
        ),
        Column(
            "point_instance",
            pa.binary(),
            "(N,) int32 little-endian instance id of each point, 0 = background.",
        ),
        Column(
            "point_source",
            pa.binary(),
            "(N,) uint8 where each point came from: 0 background (TSDF), 1 object not "
            "interacted with (TSDF), 2 interacted object from its last observed frame, 3 kept "
            "from the previous state.",
        ),
        Column("instance_id", pa.list_(pa.int32()), "(M,) instance ids, >= 1, unique."),
        Column(
            "instance_label",
            pa.list_(pa.string()),
            "(M,) label of each instance ('object' for geometric segmentation).",
        ),
        Column(
            "instance_interactive",
            pa.list_(pa.bool_()),
            "(M,) True when the hands interacted with the instance in this clip.",
        ),
        Column(
            "instance_last_observed_frame",
            pa.list_(pa.int32()),
            "(M,) last frame of this clip where the instance was seen; -1 = not seen (kept from "
            "the previous state).",
        ),
        Column(
            "instance_geometry_frame",
            pa.list_(pa.int32()),
            "(M,) frame an interacted instance's points were taken from (its last observed "
            "place, the frame seeing most of it there); -1 = points from TSDF or the previous "
            "state.",
        ),
        Column(
            "instance_interaction",
            pa.list_(pa.list_(pa.bool_())),
            "(M, T) interaction status per frame (box IoU and depth gap test, with the "
            "retrospective update of the last observed frame).",
        ),
        Column(
            "instance_depth_gap_m",
            pa.list_(pa.list_(pa.float32())),
            "(M, T) median depth gap in metres between the instance and the nearest hand; "
            "NaN where the instance or no hand box overlapping it was seen.",
        ),
        Column(
            "instance_centroid",
            pa.list_(pa.list_(pa.float64(), 3)),
            "(M, 3) centroid of each instance's points in world metres.",
        ),
        Column("width", pa.int32(), "Image width W of the cameras in pixels."),
        Column("height", pa.int32(), "Image height H of the cameras in pixels."),
        Column("intrinsics", pa.list_(pa.float64(), 4), "fx, fy, cx, cy of the cameras."),
        Column(
            "world_from_cam",
            pa.list_(POSE),
            "(K, 16) camera-to-world of every camera the state was built from (previous "
            "state's first), in the state's world frame, OpenCV axes.",
        ),
        Column(
            "camera_frames",
            pa.list_(pa.string()),
            "(K,) '<clip_id>:<frame>' naming each camera of world_from_cam.",
        ),
        Column(
            "previous_from_clip",
            pa.list_(pa.float64(), 16),
            "Row-major 4x4 Sim3 (scale times rotation, translation) taking the clip's camera "
            "frame to the state's world frame; identity when nothing needed registering.",
        ),
        Column("sim3_scale", pa.float64(), "Scale of previous_from_clip."),
        Column(
            "registration_rms_m",
            pa.float64(),
            "RMS residual in metres of the camera-pose registration; null when not registered.",
            True,
        ),
    ),
    validators=(_check_instances, _check_points, _check_cameras),
)


def state_for_clip(row: Mapping[str, Any], clip_id: str) -> dict[str, Any]:
    """``row`` keyed by ``clip_id``: the state a next clip starts from, joinable with it.

    Rows join on ``clip_id`` in a run, so the state a clip was generated from is given to
    ``state_fusion`` keyed by that clip; ``state_clip_id`` still names the clip it was fused
    from.
    """
    return {**row, "clip_id": clip_id}


def scene_cloud_row_from_state(
    row: Mapping[str, Any], clip_id: str | None = None
) -> dict[str, Any]:
    """A ``scene_cloud`` row holding a ``state`` row's points, for ``scene_render``.

    ``clip_id`` names the clip the cloud is rendered for (default: the state's own clip). The
    points, colours and sizes are the state's bytes unchanged; ``source_frame`` is -1 (a fused
    state, no single frame), ``kept_fraction`` 1.0 and
    every point's confidence is measured (255): fused points are observations.
    """
    n = int(row["num_points"])
    out = {
        "clip_id": row["clip_id"] if clip_id is None else clip_id,
        "num_points": n,
        "points_xyz": row["points_xyz"],
        "points_rgb": row["points_rgb"],
        "point_size": row["point_size"],
        "source_frame": -1,
        "image_source": f"state:{row['state_clip_id']}",
        "kept_fraction": 1.0,
        "num_flying_removed": 0,
        "point_confidence": np.full(n, 255, np.uint8).tobytes(),
    }
    missing = [c for c in SCENE_CLOUD.column_names if c not in out]
    if missing:
        raise KeyError(f"scene_cloud columns {missing} have no value from a state row")
    return out
