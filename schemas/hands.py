"""The ``hands`` schema: cleaned 3D hand joints per frame, one row per clip.

Joints follow the project convention (MANO/OpenPose order, hand 0 = left, 1 = right, world
metres). A hand that the filters removed in a frame (duplicate or temporal outlier) or that was
never detected has ``hand_valid`` False and NaN joints, so it can never be drawn by mistake.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import pyarrow as pa

from egosim.schemas.base import Column, ShardSchema
from egosim.schemas.clips import HAND_JOINTS_PER_FRAME
from egosim.schemas.invariants import frame_count_problems


def _check_hands(row: Mapping[str, Any]) -> list[str]:
    problems = frame_count_problems(row, ("hand_joints", "hand_valid", "hand_confidence"))
    t = row["num_frames"]
    if problems:
        return problems
    joints = np.asarray(row["hand_joints"], dtype=np.float64).reshape(t, 2, 21 * 3)
    valid = np.asarray(row["hand_valid"], dtype=bool)  # (T, 2)
    if not np.all(np.isfinite(joints[valid])):
        problems.append("valid hands have NaN or infinite joints")
    if np.any(np.isfinite(joints[~valid])):
        problems.append("invalid hands must have NaN joints")
    conf = np.asarray(row["hand_confidence"], dtype=np.float64)
    if np.any((conf < 0) | (conf > 1)):
        problems.append("hand_confidence outside [0, 1]")
    for name in ("num_duplicates_removed", "num_outliers_removed"):
        if row[name] < 0:
            problems.append(f"{name} must be >= 0, got {row[name]}")
    return problems


HANDS = ShardSchema(
    name="hands",
    version=1,
    doc="Per-frame 3D hand joints after de-duplication and temporal outlier removal.",
    columns=(
        Column("clip_id", pa.string(), "Clip id, joins with the clips shard."),
        Column("num_frames", pa.int32(), "Number of frames T (same as the clip)."),
        Column(
            "backend",
            pa.string(),
            "Where the joints came from: given (clip labels), mediapipe, hamer.",
        ),
        Column(
            "hand_joints",
            pa.list_(HAND_JOINTS_PER_FRAME),
            "(T, 2*21*3) float32 world metres, hand 0 left, 1 right, MANO joint order; "
            "NaN where the hand is not valid.",
        ),
        Column("hand_valid", pa.list_(pa.list_(pa.bool_(), 2)), "(T, 2) hand kept in the frame."),
        Column(
            "hand_confidence",
            pa.list_(pa.list_(pa.float32(), 42)),
            "(T, 2*21) per-joint confidence in [0, 1]; 0 where the hand is not valid.",
        ),
        Column(
            "num_duplicates_removed",
            pa.int32(),
            "Detections dropped by the frame-wise de-duplication (all frames).",
        ),
        Column(
            "num_outliers_removed",
            pa.int32(),
            "Hand-frames dropped as temporal outliers (both velocities above the threshold).",
        ),
    ),
    validators=(_check_hands,),
)
