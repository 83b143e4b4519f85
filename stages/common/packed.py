"""Decode ``pack`` rows into the model's :class:`~egosim.model.TrainingSample` (shared reader).

``pack`` writes the rows; ``train`` (through :class:`~.pack_dataset.PackDataset`),
``simulate`` and ``evaluate`` read them with :func:`sample_from_pack_row`, so one function decides
what a packed sample is. Every disagreement between the row's columns (frame counts, sizes,
missing conditions) is reported at once in a :class:`PackRowError` naming the columns.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from egosim.model.conditioning import TrainingSample
from egosim.pipeline import media

CONDITION_COLUMNS = ("target_video", "scene_video", "visible", "skeleton_video", "first_frame")


class PackRowError(ValueError):
    """A pack row is missing a condition or its videos disagree in frame count or size."""


def decode_pack_row(row: Mapping[str, Any]) -> dict[str, np.ndarray]:
    """Decode a pack row's videos, checked against its ``num_frames`` x ``height`` x ``width``.

    Returns ``target`` / ``scene`` / ``skeleton`` (T, H, W, 3) uint8, ``visible`` (T, H, W)
    uint8 {0, 1}, ``first_frame`` (H, W, 3) uint8 and ``hand_mask`` (T, H, W) uint8 when present.
    """
    cid = row.get("clip_id", "?")
    missing = [c for c in (*CONDITION_COLUMNS, "prompt") if row.get(c) is None]
    if missing:
        raise PackRowError(f"pack row {cid!r}: missing conditions {missing}")
    t, h, w = int(row["num_frames"]), int(row["height"]), int(row["width"])
    what = f"pack row {cid!r}"
    out = {
        "target": media.decode_rgb_video(row["target_video"], h, w, f"{what} target_video"),
        "scene": media.decode_rgb_video(row["scene_video"], h, w, f"{what} scene_video"),
        "skeleton": media.decode_rgb_video(row["skeleton_video"], h, w, f"{what} skeleton_video"),
        "visible": media.decode_lossless_video(row["visible"], f"{what} visible"),
        "first_frame": media.decode_png(row["first_frame"], f"{what} first_frame"),
    }
    if row.get("hand_mask") is not None:
        out["hand_mask"] = media.decode_lossless_video(row["hand_mask"], f"{what} hand_mask")
    want = {
        "target": (t, h, w, 3),
        "scene": (t, h, w, 3),
        "skeleton": (t, h, w, 3),
        "visible": (t, h, w),
        "first_frame": (h, w, 3),
        "hand_mask": (t, h, w),
    }
    problems = [
        f"{name} is {tuple(arr.shape)}, expected {want[name]} (num_frames x height x width)"
        for name, arr in out.items()
        if tuple(arr.shape) != want[name]
    ]
    if problems:
        raise PackRowError(f"{what}: " + "; ".join(problems))
    out["visible"] = (out["visible"] > 0).astype(np.uint8)
    return out


def sample_from_pack_row(row: Mapping[str, Any]) -> TrainingSample:
    """The model's training sample (conditions + target) of one pack row."""
    videos = decode_pack_row(row)
    return TrainingSample(
        target_video=videos["target"],
        scene_video=videos["scene"],
        visibility=videos["visible"],
        skeleton_video=videos["skeleton"],
        first_frame=videos["first_frame"],
        prompt=str(row["prompt"]),
    )
