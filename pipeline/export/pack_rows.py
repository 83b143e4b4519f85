"""Decode ``pack`` rows: the one decoder of a packed sample's media (moved from stages).

``egosim.stages.common.packed`` (train, simulate, evaluate) and the exporters of
:mod:`egosim.pipeline.export` both use :func:`decode_pack_row`, so one function decides what a
packed sample's videos are. Every disagreement between the row's columns (frame counts, sizes,
missing conditions) is reported at once in a :class:`PackRowError` naming the columns.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

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


class MaskError(ValueError):
    """A mask of the wrong shape or an invalid option; the message says which."""


def inpaint_mask_from_visible(visible: np.ndarray, dilate: int = 0) -> np.ndarray:
    """The model's inpainting mask from a visibility mask; the one place the polarity flips.

    Input ``visible (..., H, W)``: 1 = a scene point landed on the pixel (observed), 0 = none.
    Output ``(..., H, W)`` uint8: **1 = unobserved, the model must synthesise this pixel**,
    0 = the scene render is to be kept. This is the paper's "binary mask video that indicates the
    unobserved regions that require visual synthesis" and VideoX-Fun's ``mask_condition``
    polarity. ``dilate`` grows the synthesise region by that many pixels (a square
    neighbourhood), so thin seams around holes are regenerated too. (Moved here from
    ``stages/scene_render/splat.py``, which re-exports it, so that the exporters share it.)
    """
    visible = np.asarray(visible)
    if visible.ndim < 2:
        raise MaskError(f"visible must be (..., H, W), got shape {visible.shape}")
    if dilate < 0:
        raise MaskError(f"dilate must be >= 0, got {dilate}")
    mask = (visible == 0).astype(np.uint8)  # (..., H, W)
    if dilate > 0:
        from scipy.ndimage import maximum_filter

        size = [1] * (mask.ndim - 2) + [2 * dilate + 1, 2 * dilate + 1]
        mask = maximum_filter(mask, size=size)
    return mask
