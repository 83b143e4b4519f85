"""The ``clips`` schema: what ``ingest`` writes, one row per clip.

Per-frame arrays are list columns with one entry per frame; images, masks, depth and videos are
encoded bytes (see :mod:`egosim.pipeline.media`): RGB video as H.264 MP4, masks and depth as
lossless FFV1 video, single images as PNG. Optional columns hold ground truth when the source has
it (the synthetic world, EgoDex) and are null otherwise.

Version 2 adds what ingest's clip policy did (``source_fps``, ``source_num_frames``,
``source_frame_indices``, ``clip_policy``; see ``docs/design.md``, "Clip policy / clips v2").
Version 1 shards have none of these and are refused by readers (``SchemaCompatibilityError``):
re-run ``ingest`` to rewrite them.

Version 3 adds ``gripper_opening`` (robot clips: the opening of the gripper in each hand slot; see
``docs/design.md``, "Robot embodiments"). Version 2 shards are refused the same way.

Version 4 adds ``embodiment_mask`` (robot clips: the arm's silhouette derived at ingest from the
log's URDF and joint states; ``hand_mask`` unions it into its output). Version 3 shards are
refused the same way: re-run ``ingest``.

Version 5 adds ``source_crop`` (the region of the source frame the clip's frames show, source
pixels: ingest's cover crop, placed by its crop anchor, over the hands for portrait footage; see
``docs/design.md``, "Crop anchor"); ``depth_camera``'s source track rebuilds the crop from it.
Version 4 shards are refused the same way: re-run ``ingest``.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import pyarrow as pa

from egosim.schemas.base import Column, ShardSchema
from egosim.schemas.invariants import se3_problems

POSE = pa.list_(pa.float64(), 16)  # row-major 4x4
HAND_JOINTS_PER_FRAME = pa.list_(pa.float32(), 2 * 21 * 3)


def _check_counts(row: Mapping[str, Any]) -> list[str]:
    problems: list[str] = []
    t = row["num_frames"]
    if t is None or t < 1:
        return [f"num_frames must be >= 1, got {t}"]
    for name in ("timestamps", "world_from_cam", "hand_joints", "hand_valid", "hand_confidence"):
        value = row.get(name)
        if value is not None and len(value) != t:
            problems.append(f"{name} has {len(value)} entries, num_frames is {t}")
    poses = row.get("object_poses")
    if poses is not None:
        n = row.get("num_objects") or 0
        if len(poses) != t * n:
            problems.append(f"object_poses has {len(poses)} entries, expected {t} x {n}")
    ts = np.asarray(row["timestamps"], dtype=np.float64)
    if len(ts) > 1 and not np.all(np.diff(ts) > 0):
        problems.append("timestamps are not strictly increasing")
    if not np.all(np.isfinite(ts)):
        problems.append("timestamps contain NaN or infinite values")
    return problems


def _check_camera(row: Mapping[str, Any]) -> list[str]:
    problems: list[str] = []
    w, h, fps = row["width"], row["height"], row["fps"]
    if w < 1 or h < 1:
        problems.append(f"width and height must be positive, got {w}x{h}")
    if not (np.isfinite(fps) and fps > 0):
        problems.append(f"fps must be positive, got {fps}")
    fx, fy, cx, cy = row["intrinsics"]
    if not np.all(np.isfinite([fx, fy, cx, cy])) or fx <= 0 or fy <= 0:
        problems.append(f"intrinsics must be finite with fx, fy > 0, got {[fx, fy, cx, cy]}")
    elif not (0 < cx < w and 0 < cy < h) and not _in_source(row, cx, cy):
        crop = row.get("source_crop")
        where = f"the {w}x{h} image" + ("" if crop is None else f" and its source crop {crop}")
        problems.append(f"principal point ({cx}, {cy}) lies outside {where}")
    return problems


def _in_source(row: Mapping[str, Any], cx: float, cy: float) -> bool:
    """Whether the principal point ``(cx, cy)`` (clip pixels) lies in the source frame that the
    row's ``source_crop`` was cut from. An off-centre crop (a band low in a portrait frame) puts
    the source's principal point outside the clip's image; the source's far edges are not
    recorded, so only its left and top edges bound it."""
    crop = row.get("source_crop")
    c = np.asarray(crop if crop is not None else [], dtype=np.float64)
    if c.shape != (4,) or not np.all(np.isfinite(c)):
        return False  # no crop, or a bad one (_check_crop names it)
    x0, y0, x1, y1 = c
    u = x0 + cx * (x1 - x0) / row["width"]  # source pixels
    v = y0 + cy * (y1 - y0) / row["height"]
    return u > 0 and v > 0


def _check_poses(row: Mapping[str, Any]) -> list[str]:
    poses = row.get("world_from_cam")
    if poses is None:
        return []
    mats = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
    return [f"world_from_cam: {p}" for p in se3_problems(mats)]


def _check_hands(row: Mapping[str, Any]) -> list[str]:
    joints = row.get("hand_joints")
    problems: list[str] = []
    if joints is not None:
        arr = np.asarray(joints, dtype=np.float64)
        valid = row.get("hand_valid")
        if valid is not None:
            mask = np.repeat(np.asarray(valid, dtype=bool), 21 * 3, axis=1)  # (T, 126)
            arr = arr[mask]
        if not np.all(np.isfinite(arr)):
            problems.append("hand_joints of valid hands contain NaN or infinite values")
    conf = row.get("hand_confidence")
    if conf is not None:
        c = np.asarray(conf, dtype=np.float64)
        if np.any((c < 0) | (c > 1)):
            problems.append("hand_confidence outside [0, 1]")
    return problems


def source_crop_problems(value: Any) -> list[str]:
    """What is wrong with a ``source_crop`` (``x0, y0, x1, y1`` source pixels; None: none
    recorded, fine). The clips schema and ``Clip.problems`` (pipeline/records.py) share it."""
    if value is None:
        return []
    c = np.asarray(value, dtype=np.float64)
    if c.shape != (4,) or not np.all(np.isfinite(c)) or not (0 <= c[0] < c[2] and 0 <= c[1] < c[3]):
        return [
            f"source_crop must be x0, y0, x1, y1 with 0 <= x0 < x1, 0 <= y0 < y1, got {c.tolist()}"
        ]
    return []


def _check_crop(row: Mapping[str, Any]) -> list[str]:
    return source_crop_problems(row.get("source_crop"))


def _check_gripper(row: Mapping[str, Any]) -> list[str]:
    value = row.get("gripper_opening")
    if value is None:
        return []
    t = row["num_frames"]
    arr = np.asarray(value, dtype=np.float64)
    if arr.shape != (t, 2):
        return [f"gripper_opening must be ({t}, 2), got shape {arr.shape}"]
    finite = arr[np.isfinite(arr)]
    if np.isinf(arr).any() or (finite < 0).any():
        return [f"gripper_opening must be NaN or >= 0 metres, got min {np.nanmin(arr)}"]
    valid = row.get("hand_valid")
    if valid is not None and np.isnan(arr[np.asarray(valid, dtype=bool)]).any():
        return ["gripper_opening is NaN for a valid hand"]
    return []


CLIP_POLICY_KINDS = ("full", "short", "tail")  # first part of the clip_policy column
RATE_TOLERANCE = 1e-6  # relative: fps may exceed source_fps by this much (float rounding)


def _check_policy(row: Mapping[str, Any]) -> list[str]:
    problems: list[str] = []
    t = row["num_frames"]
    idx = row.get("source_frame_indices")
    if idx is not None:
        arr = np.asarray(idx, dtype=np.int64)
        if len(arr) != t:
            problems.append(f"source_frame_indices has {len(arr)} entries, num_frames is {t}")
        elif len(arr) and (arr.min() < 0 or np.any(np.diff(arr) < 0)):
            problems.append(f"source_frame_indices must be >= 0 and non-decreasing, got {arr[:8]}")
    source_fps, fps = row.get("source_fps"), row["fps"]
    if source_fps is not None:
        if not (np.isfinite(source_fps) and source_fps > 0):
            problems.append(f"source_fps must be positive, got {source_fps}")
        elif fps > source_fps * (1 + RATE_TOLERANCE):
            problems.append(f"fps {fps} exceeds source_fps {source_fps}: clips are never upsampled")
    n = row.get("source_num_frames")
    if n is not None and n < 1:
        problems.append(f"source_num_frames must be >= 1, got {n}")
    policy = row.get("clip_policy")
    if policy is not None and policy.split(":")[0] not in CLIP_POLICY_KINDS:
        problems.append(
            f"clip_policy must start with one of {list(CLIP_POLICY_KINDS)}, got {policy!r}"
        )
    return problems


CLIPS = ShardSchema(
    name="clips",
    version=5,
    doc="Standardised clips: video, timing, intrinsics and optional ground truth, one per row.",
    columns=(
        Column("clip_id", pa.string(), "Unique clip id within the dataset."),
        Column("source", pa.string(), "Ingest source: video, frames, synthetic, egodex, mcap."),
        Column("source_uri", pa.string(), "File or recording the clip came from; '' if generated."),
        Column("fps", pa.float64(), "Frames per second of the stored frames."),
        Column("num_frames", pa.int32(), "Number of frames T."),
        Column("width", pa.int32(), "Frame width W in pixels."),
        Column("height", pa.int32(), "Frame height H in pixels."),
        Column("timestamps", pa.list_(pa.float64()), "(T,) seconds from the source's start."),
        Column(
            "intrinsics", pa.list_(pa.float64(), 4), "fx, fy, cx, cy in pixels of stored frames."
        ),
        Column("video", pa.binary(), "RGB frames as H.264 MP4 bytes (yuv420p)."),
        Column("world_from_cam", pa.list_(POSE), "(T, 16) camera-to-world, OpenCV axes.", True),
        Column("depth", pa.binary(), "(T, H, W) z-depth, lossless FFV1 uint16 video.", True),
        Column(
            "depth_unit_m",
            pa.float64(),
            "Metres per uint16 step of the depth columns; 0 means unknown depth.",
            True,
        ),
        Column("static_video", pa.binary(), "Same camera path, no hands, H.264 MP4.", True),
        Column("static_depth", pa.binary(), "Depth of the static scene, FFV1 uint16.", True),
        Column("first_frame_clean", pa.binary(), "Hand-free first frame, RGB PNG.", True),
        Column(
            "hand_joints",
            pa.list_(HAND_JOINTS_PER_FRAME),
            "(T, 2*21*3) world metres, hand 0 left, 1 right, MANO joint order.",
            True,
        ),
        Column("hand_valid", pa.list_(pa.list_(pa.bool_(), 2)), "(T, 2) hand present.", True),
        Column(
            "hand_confidence",
            pa.list_(pa.list_(pa.float32(), 42)),
            "(T, 2*21) per-joint confidence in [0, 1].",
            True,
        ),
        Column("hand_mask", pa.binary(), "(T, H, W) 1 = hand/arm, lossless FFV1 video.", True),
        Column("object_mask", pa.binary(), "(T, H, W) object instance id, lossless FFV1.", True),
        Column("num_objects", pa.int32(), "Number of tracked objects N.", True),
        Column("object_poses", pa.list_(POSE), "(T*N, 16) world_from_object, frame-major.", True),
        Column("text", pa.string(), "Text description of the interaction.", True),
        Column(
            "source_fps",
            pa.float64(),
            "Frame rate of the source; fps equals it when the source was slower than the target "
            "(never upsampled). Null when unknown.",
            True,
        ),
        Column(
            "source_num_frames",
            pa.int32(),
            "Frames in the source (a video file's declared count); null when unknown.",
            True,
        ),
        Column(
            "source_frame_indices",
            pa.list_(pa.int32()),
            "(T,) index of each stored frame in the source, non-decreasing.",
            True,
        ),
        Column(
            "clip_policy",
            pa.string(),
            "What ingest's clip policy made: 'full' (a num_frames window), 'short' (the longest "
            "1+4k frames of a source shorter than one clip) or 'tail' (the remainder after the "
            "last full window), then ':' and the ingest preset, e.g. 'short:egosim'.",
            True,
        ),
        Column(
            "gripper_opening",
            pa.list_(pa.list_(pa.float32(), 2)),
            "(T, 2) metres between the gripper's finger faces per hand slot (robot clips; the "
            "hand columns hold its skeleton); NaN where the slot holds no gripper; null for "
            "human clips.",
            True,
        ),
        Column(
            "embodiment_mask",
            pa.binary(),
            "(T, H, W) 1 = robot arm, lossless FFV1 video: derived at ingest from the log's URDF "
            "and joint states (not ground truth); null for human clips and logs without them.",
            True,
        ),
        Column(
            "source_crop",
            pa.list_(pa.float64(), 4),
            "x0, y0, x1, y1: the region of the source frame the stored frames show, source pixels "
            "(ingest scaled it to width x height; edges, so a whole W x H frame is 0, 0, W, H). "
            "Null in rows written without it (read as the centre crop).",
            True,
        ),
    ),
    validators=(
        _check_counts,
        _check_camera,
        _check_poses,
        _check_hands,
        _check_policy,
        _check_gripper,
        _check_crop,
    ),
)
