"""The ``poses`` schema: what ``pose_clean`` writes, one row per clip.

Cleaned camera trajectories (outliers repaired, jitter smoothed) with the per-clip figures of the
cleaning: which frames were outliers and how much jitter there was before and after.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import pyarrow as pa

from egosim.schemas.base import Column, ShardSchema
from egosim.schemas.clips import POSE
from egosim.schemas.invariants import se3_problems

JITTER_DOC = (
    "Jitter = RMS over frames 1..T-2 of the norm of the second difference {what}; 0 when T < 3."
)
MILLI_UNITS = (
    "in thousandths of the poses' length unit: millimetres only when the poses are metric (a "
    "clip's own poses, or cameras with metric_scale set), else thousandths of an SfM unit"
)


def _check_counts(row: Mapping[str, Any]) -> list[str]:
    t = row["num_frames"]
    if t is None or t < 1:
        return [f"num_frames must be >= 1, got {t}"]
    problems: list[str] = []
    poses = row["world_from_cam"]
    if len(poses) != t:
        problems.append(f"world_from_cam has {len(poses)} entries, num_frames is {t}")
    bad = [int(i) for i in row["outlier_frames"] if not 0 <= int(i) < t]
    if bad:
        problems.append(f"outlier_frames outside [0, {t}): {bad}")
    if len(set(row["outlier_frames"])) != len(row["outlier_frames"]):
        problems.append("outlier_frames has repeated frame indices")
    return problems


def _check_poses(row: Mapping[str, Any]) -> list[str]:
    mats = np.asarray(row["world_from_cam"], dtype=np.float64).reshape(-1, 4, 4)
    return [f"world_from_cam: {p}" for p in se3_problems(mats)]


def _check_jitter(row: Mapping[str, Any]) -> list[str]:
    names = ("jitter_before_mm", "jitter_after_mm", "jitter_before_deg", "jitter_after_deg")
    return [
        f"{n} must be finite and >= 0, got {row[n]}"
        for n in names
        if not (np.isfinite(row[n]) and row[n] >= 0)
    ]


POSES = ShardSchema(
    name="poses",
    version=1,
    doc="Cleaned camera trajectories (Eq. 4 outlier repair + smoothing), one clip per row.",
    columns=(
        Column("clip_id", pa.string(), "Clip id, as in the clips shard."),
        Column("num_frames", pa.int32(), "Number of frames T."),
        Column(
            "world_from_cam",
            pa.list_(POSE),
            "(T, 16) cleaned camera-to-world, row-major 4x4, OpenCV axes, in the input poses' "
            "units (metres when they are metric).",
        ),
        Column(
            "outlier_frames",
            pa.list_(pa.int32()),
            "Ascending indices of the frames flagged by the jump test and repaired.",
        ),
        Column("method", pa.string(), "Cleaning method: kalman_rts, kalman_causal or egocap."),
        Column(
            "jitter_before_mm",
            pa.float64(),
            JITTER_DOC.format(what=f"of the input camera centre, {MILLI_UNITS}"),
        ),
        Column(
            "jitter_after_mm",
            pa.float64(),
            JITTER_DOC.format(what=f"of the cleaned camera centre, {MILLI_UNITS}"),
        ),
        Column(
            "jitter_before_deg",
            pa.float64(),
            JITTER_DOC.format(
                what="of the input rotation (angle between consecutive relative rotations), degrees"
            ),
        ),
        Column(
            "jitter_after_deg",
            pa.float64(),
            JITTER_DOC.format(
                what="of the cleaned rotation (angle between consecutive relative rotations), "
                "degrees"
            ),
        ),
    ),
    validators=(_check_counts, _check_poses, _check_jitter),
)
