"""Backend ``given``: hand joints that the clip carries as labels (synthetic world, EgoDex)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from egosim.stages.hands.filters import Detections


class NoHandLabelsError(ValueError):
    """The clip has no hand labels for the ``given`` backend."""


def given_detections(row: Mapping[str, Any]) -> Detections:
    """Detections ``K = 2`` (slot = side) from a clips row's ``hand_*`` columns."""
    if row.get("hand_joints") is None:
        raise NoHandLabelsError("the clip has no hand_joints labels")
    t = int(row["num_frames"])
    joints = np.asarray(row["hand_joints"], dtype=np.float64).reshape(-1, 2, 21, 3)  # (T, 2, 21, 3)
    if row.get("hand_valid") is not None:
        present = np.asarray(row["hand_valid"], dtype=bool).reshape(-1, 2)  # (T, 2)
    else:
        present = np.all(np.isfinite(joints), axis=(2, 3))
    if row.get("hand_confidence") is not None:
        conf = np.asarray(row["hand_confidence"], dtype=np.float64).reshape(-1, 2, 21)
    else:
        conf = np.ones((len(joints), 2, 21))
    if not (len(joints) == len(present) == len(conf) == t):
        raise NoHandLabelsError(
            f"hand labels cover {len(joints)}/{len(present)}/{len(conf)} frames, clip has {t}"
        )
    bad = present & ~np.all(np.isfinite(joints), axis=(2, 3))  # (T, 2)
    if bad.any():
        raise NoHandLabelsError(
            f"{int(bad.sum())} hand-frames are marked valid but have NaN joints"
        )
    side = np.tile(np.array([0, 1]), (t, 1))  # (T, 2)
    return Detections(joints=joints, side=side, confidence=conf, present=present)
