"""Which camera a stage uses: cleaned poses beat estimated cameras beat the clip's own.

Stages that need intrinsics, poses or the first frame's depth declare the optional input roles
below and call :func:`resolve_cameras` / :func:`first_frame_depth` with the rows they were given:

- ``poses`` (schema ``poses``, from ``pose_clean``): cleaned ``world_from_cam``;
- ``cameras`` (schema ``depth_camera``): estimated intrinsics, poses and frame-0 depth;
- ``clips``: the source's own intrinsics, poses and depth (synthetic world, EgoDex, MCAP).

One rule for every stage, so the scene condition and the hand condition always use the same
intrinsics and poses.
"""

from __future__ import annotations

from collections.abc import Mapping, Sized
from dataclasses import dataclass
from typing import Any

import numpy as np

from egosim.pipeline import media
from egosim.pipeline.records import CameraRecord, ClipsRecord, DepthCameraRecord, PosesRecord
from egosim.pipeline.stage import ClipRejected
from egosim.schemas import ShardSchema
from egosim.schemas.depth_camera import DEPTH_CAMERA
from egosim.schemas.poses import POSES

CAMERA_ROLES: dict[str, ShardSchema] = {"poses": POSES, "cameras": DEPTH_CAMERA}

# The columns resolve_cameras reads, per role: add them to a stage's ``columns`` declaration
# (``pipeline.stage.join_columns``) when the stage calls it.
CAMERA_COLUMNS: dict[str, tuple[str, ...]] = {
    "clips": ("clip_id", "num_frames", "intrinsics", "world_from_cam"),
    "poses": ("world_from_cam",),
    "cameras": ("intrinsics", "world_from_cam"),
}
# The columns first_frame_depth and depth_is_unknown_by_model read, per role.
DEPTH0_COLUMNS: dict[str, tuple[str, ...]] = {
    "clips": ("clip_id", "static_depth", "depth", "depth_unit_m"),
    "cameras": ("depth0", "depth_unit_m", "static_camera", "camera_model"),
}

# The column camera_is_static reads.
STATIC_COLUMNS: dict[str, tuple[str, ...]] = {"cameras": ("static_camera",)}


@dataclass(frozen=True)
class Cameras:
    """The intrinsics and trajectory a stage should use for one clip."""

    intrinsics: np.ndarray  # (4,) fx, fy, cx, cy in pixels of the stored frames
    world_from_cam: np.ndarray | None  # (T, 4, 4) camera-to-world, None when nobody has poses
    source: str  # role the poses came from: "poses", "cameras" or "clips"


# The record class each role's row is read through (a plain mapping is wrapped in it).
_CAMERA_RECORDS: dict[str, type[CameraRecord]] = {
    "clips": ClipsRecord,
    "poses": PosesRecord,
    "cameras": DepthCameraRecord,
}


def _poses(row: CameraRecord, t: int, clip_id: str, role: str) -> np.ndarray:
    """``role``'s poses ``(T, 4, 4)`` float64, checked against the clip's ``t`` frames.

    Parsed once by the record (the stage holding it reads the same parse); a copy is returned
    so a caller changing it in place cannot change the record's value.
    """
    value = row["world_from_cam"]
    if isinstance(value, Sized) and len(value) == t:
        try:
            return np.array(row.array("world_from_cam", np.float64, (t, 4, 4)))
        except ClipRejected:
            pass  # worded below, as for a wrong frame count
    shape = np.asarray(value, dtype=np.float64).shape
    raise ClipRejected(f"clip {clip_id!r}: {role} has poses of shape {shape}, expected ({t}, 16)")


def _camera_records(rows: Mapping[str, Mapping[str, Any]]) -> dict[str, CameraRecord]:
    """Each camera role's row in ``rows`` typed as its record (``Record.of``: a record as it is,
    a plain mapping wrapped)."""
    return {
        role: record.of(rows[role])
        for role, record in _CAMERA_RECORDS.items()
        if rows.get(role) is not None
    }


def resolve_cameras(rows: Mapping[str, Mapping[str, Any]]) -> Cameras:
    """Intrinsics from ``cameras`` else ``clips``; poses from ``poses``, ``cameras``, ``clips``.

    ``rows`` are the records a stage's ``process`` was handed, or plain mappings (wrapped in
    the role's record class); values are read through the records' accessors, parsed once.
    """
    records = _camera_records(rows)
    clip = records["clips"]
    cid, t = clip["clip_id"], clip.num_frames
    cams = records.get("cameras")
    intrinsics = np.array((cams or clip).intrinsics)  # (4,) a copy: see _poses
    for role in ("poses", "cameras", "clips"):
        row = records.get(role)
        if row is not None and row.get("world_from_cam") is not None:
            return Cameras(intrinsics, _poses(row, t, cid, role), role)
    return Cameras(intrinsics, None, "none")


def camera_is_static(rows: Mapping[str, Mapping[str, Any]]) -> bool:
    """Whether the connected ``cameras`` row says the clip's camera is fixed (``static_camera``;
    the schema keeps it equal to ``camera_model == "static"``); False without a cameras row."""
    cams = rows.get("cameras")
    return cams is not None and bool(cams.get("static_camera"))


def depth_is_unknown_by_model(rows: Mapping[str, Mapping[str, Any]]) -> bool:
    """True when the ``cameras`` row says depth cannot exist: a static or rotation-only camera.

    Such a camera sees no parallax, so any depth gives the same picture from its poses; stages
    stand frame 0 in on a fronto-parallel plane (DWM's fixed-camera recipe) instead of
    rejecting the clip.
    """
    cams = rows.get("cameras")
    if cams is None or cams.get("depth0") is not None:
        return False
    return bool(cams.get("static_camera")) or cams.get("camera_model") in ("static", "rotation")


def first_frame_confidence(
    rows: Mapping[str, Mapping[str, Any]], shape: tuple[int, ...]
) -> np.ndarray | None:
    """``(H, W)`` float32 in [0, 1]: the ``cameras`` row's ``confidence0``, the confidence of its
    ``depth0`` (None when there is no cameras row or it has none). A confidence whose size is not
    ``shape`` (depth0's) rejects the clip."""
    cams, cid = rows.get("cameras"), rows["clips"]["clip_id"]
    if cams is None or cams.get("confidence0") is None:
        return None
    conf = media.decode_lossless_video(cams["confidence0"], f"clip {cid} confidence0", 1)[0]
    if conf.shape != shape:
        raise ClipRejected(f"clip {cid!r}: confidence0 {conf.shape} != depth0 {shape}")
    return conf.astype(np.float32) / 255.0


def first_frame_depth(rows: Mapping[str, Mapping[str, Any]]) -> np.ndarray | None:
    """Frame-0 z-depth ``(H, W)`` float32 (0 = unknown): ``cameras`` depth0, else the clip's.

    The clip's static depth (ground truth without hands) is preferred over its plain depth.
    Returns None when no role has depth. Read through the roles' records (``depth0``,
    ``first_depth``: one frame decoded, kept on the record; plain mappings are wrapped); a copy
    is returned, as in :func:`resolve_cameras`.
    """
    cams = rows.get("cameras")
    depth = None if cams is None else DepthCameraRecord.of(cams).depth0
    if depth is None:
        clip = ClipsRecord.of(rows["clips"])
        key = next((k for k in ("static_depth", "depth") if clip.get(k) is not None), None)
        depth = None if key is None else clip.first_depth(key)
    return None if depth is None else np.array(depth)
