"""Benchmark of hand_mask and inpaint on a default-size synthetic clip (61 x 480 x 832)."""

from __future__ import annotations

import time

from egosim.stages.hand_mask.stage import HandMaskStage
from egosim.stages.inpaint.reproject_fill import dilate, opencv_fill, reproject_fill
from egosim.world import WorldConfig, render_clip


def bench_hand_mask_inpaint() -> list[dict]:
    """Seconds per clip: hand_mask (capsules + colour), inpaint (reprojection) vs cv2 alone."""
    clip = render_clip(WorldConfig(seed=0))  # 61 x 480 x 832
    start = time.perf_counter()
    masks = HandMaskStage().masks_for_clip(clip)
    mask_s = time.perf_counter() - start
    start = time.perf_counter()
    reproject_fill(clip.frames, masks, clip.depth[0], clip.world_from_cam, clip.intrinsics)
    inpaint_s = time.perf_counter() - start
    start = time.perf_counter()
    opencv_fill(clip.frames[0], dilate(masks[0], 2))
    cv_s = time.perf_counter() - start
    return [
        {
            "name": "hand_mask_seconds_per_clip",
            "value": mask_s,
            "unit": "s",
            "baseline": "capsules only (no colour model)",
            "baseline_value": _capsules_only(clip),
        },
        {
            "name": "inpaint_seconds_per_clip",
            "value": inpaint_s,
            "unit": "s",
            "baseline": "cv2.inpaint (Telea) alone",
            "baseline_value": cv_s,
        },
    ]


def _capsules_only(clip: object) -> float:
    from egosim.stages.hand_mask.stage import HandMaskConfig

    start = time.perf_counter()
    HandMaskStage(HandMaskConfig(colour_refine=False)).masks_for_clip(clip)  # type: ignore[arg-type]
    return time.perf_counter() - start
