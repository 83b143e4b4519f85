"""The ``hands`` schema: cleaned 3D hand joints per frame, one row per clip.

Joints follow the project convention (MANO/OpenPose order, hand 0 = left, 1 = right, world
metres). A hand that the filters removed in a frame (duplicate or temporal outlier) or that was
never detected has ``hand_valid`` False and NaN joints, so it can never be drawn by mistake.
A valid hand whose ``hand_lifted`` is False is trusted in 2D only: its joints lie on the rays of
its image landmarks (so projecting them draws the hand where it is seen) at a depth that is a
guess; what needs the hand in 3D (depth, contact, exported state) skips it.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import pyarrow as pa

from egosim.schemas.base import Column, ShardSchema
from egosim.schemas.clips import HAND_JOINTS_PER_FRAME
from egosim.schemas.invariants import frame_count_problems

MANO_COLUMNS = ("mano_global_orient", "mano_hand_pose", "mano_transl", "mano_betas")
MANO_WIDTHS = {"mano_global_orient": 3, "mano_hand_pose": 45, "mano_transl": 3}  # per hand


def _check_mano(row: Mapping[str, Any], valid: np.ndarray) -> list[str]:
    """The ``mano_*`` columns: all null or all set, ``T`` rows of two hands' values, NaN where
    the hand is not valid, and each hand-frame's four groups all finite or all NaN."""
    given = [name for name in MANO_COLUMNS if row.get(name) is not None]
    if not given:
        return []
    if len(given) != len(MANO_COLUMNS):
        missing = sorted(set(MANO_COLUMNS) - set(given))
        return [f"mano columns must be all set or all null, missing {missing}"]
    t = len(valid)
    parts = []
    for name in MANO_COLUMNS:
        value = row[name]
        widths = {len(frame) for frame in value}
        if len(value) != t or len(widths) != 1:
            return [f"{name} must have {t} rows of one width, got {len(value)} rows {widths}"]
        width = widths.pop()
        want = 2 * MANO_WIDTHS.get(name, width // 2)
        if width != want or width == 0:
            return [f"{name} rows must hold 2 x {want // 2} values, got {width}"]
        parts.append(np.asarray(value, dtype=np.float64).reshape(t, 2, -1))
    params = np.concatenate(parts, axis=2)  # (T, 2, 51 + B)
    problems = []
    if np.any(np.isfinite(params[~valid])):
        problems.append("invalid hands must have NaN mano parameters")
    finite = np.isfinite(params)
    if np.any(finite.any(axis=2) != finite.all(axis=2)):
        problems.append("a hand-frame's mano parameters must be all finite or all NaN")
    return problems


def _check_hands(row: Mapping[str, Any]) -> list[str]:
    problems = frame_count_problems(
        row, ("hand_joints", "hand_valid", "hand_confidence", "hand_lifted")
    )
    t = row["num_frames"]
    if problems:
        return problems
    joints = np.asarray(row["hand_joints"], dtype=np.float64).reshape(t, 2, 21 * 3)
    valid = np.asarray(row["hand_valid"], dtype=bool)  # (T, 2)
    if not np.all(np.isfinite(joints[valid])):
        problems.append("valid hands have NaN or infinite joints")
    if np.any(np.isfinite(joints[~valid])):
        problems.append("invalid hands must have NaN joints")
    lifted = np.asarray(row["hand_lifted"], dtype=bool)
    if lifted.shape != valid.shape:
        problems.append(f"hand_lifted shape {lifted.shape}, expected {valid.shape}")
    elif np.any(lifted & ~valid):
        problems.append("hand_lifted True where hand_valid is False")
    conf = np.asarray(row["hand_confidence"], dtype=np.float64)
    if np.any((conf < 0) | (conf > 1)):
        problems.append("hand_confidence outside [0, 1]")
    for name in ("num_duplicates_removed", "num_outliers_removed"):
        if row[name] < 0:
            problems.append(f"{name} must be >= 0, got {row[name]}")
    return problems + _check_mano(row, valid)


MANO_DOC = (
    " World frame, per hand (0 left, 1 right); hand_joints = hand_joints_from_params(...) "
    "(egosim.stages.hands.mano): right hand MANO(...) + transl, left hand the mirrored model "
    "(rotation vectors flipped (x, -y, -z), joints mirrored in x). Null when the backend fits "
    "no MANO (given, mediapipe, hamer, regressor head joints); NaN where the hand has no fit."
)


def _mano_column(name: str, what: str) -> Column:
    """A nullable ``mano_*`` column: ``(T, 2 * width)`` float32 rows, the width per hand from
    :data:`MANO_WIDTHS` (``B``, any width, for the betas), so type and validator agree."""
    width = MANO_WIDTHS.get(name)
    row = pa.list_(pa.float32(), 2 * width) if width else pa.list_(pa.float32())
    shape = f"(T, 2*{width or 'B'})"
    return Column(name, pa.list_(row), f"{shape} float32 MANO {what}" + MANO_DOC, nullable=True)


HANDS = ShardSchema(
    name="hands",
    # 2: optional MANO fits (mano_global_orient, mano_hand_pose, mano_transl, mano_betas)
    # 3: hand_lifted (which valid hands' 3D is trusted; the rest are 2D only)
    version=3,
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
            "hand_lifted",
            pa.list_(pa.list_(pa.bool_(), 2)),
            "(T, 2) the valid hand's 3D joints are trusted; False where the hand is not valid and "
            "where only its 2D is (joints on its landmarks' rays at a guessed depth).",
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
        _mano_column("mano_global_orient", "wrist rotation vectors, radians."),
        _mano_column(
            "mano_hand_pose",
            "finger rotation vectors (15 joints, parent-relative, from the flat hand), radians.",
        ),
        _mano_column("mano_transl", "translation, world metres."),
        _mano_column("mano_betas", "shape coefficients (B = 10 for MANO's file)."),
    ),
    validators=(_check_hands,),
)
