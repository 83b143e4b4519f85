"""The ``hand_mask`` schema: per-frame hand-and-arm masks of a clip, one row per clip."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import pyarrow as pa

from egosim.schemas.base import Column, ShardSchema
from egosim.schemas.invariants import frame_count_problems, frame_size_problems

HAND_MASK_BACKENDS = ("keypoints", "sam")


def _check_hand_mask(row: Mapping[str, Any]) -> list[str]:
    problems = frame_count_problems(row)
    if problems:
        return problems
    t = row["num_frames"]
    problems += frame_size_problems(row)
    coverage = np.asarray(row["coverage"], dtype=np.float64)
    if coverage.shape != (t,):
        problems.append(f"coverage has {coverage.size} entries, num_frames is {t}")
    elif not np.all(np.isfinite(coverage)) or np.any((coverage < 0) | (coverage > 1)):
        problems.append("coverage must be finite and in [0, 1]")
    if not len(row["hand_mask"]):
        problems.append("hand_mask must be a non-empty encoded video")
    if row["backend"] not in HAND_MASK_BACKENDS:
        problems.append(f"backend must be one of {HAND_MASK_BACKENDS}, got {row['backend']!r}")
    return problems


HAND_MASK = ShardSchema(
    name="hand_mask",
    version=1,
    doc="Hand-and-arm masks of every frame of each clip, with per-frame coverage, one per row.",
    columns=(
        Column("clip_id", pa.string(), "Clip id, joins with the clips shard."),
        Column("num_frames", pa.int32(), "Number of frames T (same as the clip)."),
        Column("width", pa.int32(), "Frame width W in pixels (same as the clip)."),
        Column("height", pa.int32(), "Frame height H in pixels (same as the clip)."),
        Column(
            "hand_mask",
            pa.binary(),
            "(T, H, W) uint8, 1 = hand or arm pixel, 0 = not; lossless FFV1 video bytes.",
        ),
        Column("coverage", pa.list_(pa.float64()), "(T,) fraction of each frame's pixels masked."),
        Column("backend", pa.string(), "Backend that made the masks: 'keypoints' or 'sam'."),
    ),
    validators=(_check_hand_mask,),
)
