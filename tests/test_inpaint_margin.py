"""Tests of bench.inpaint_margin's mask cache: masks of another hand_mask version are not read."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from bench.inpaint_margin import world_masks
from egosim.stages.hand_mask.stage import HandMaskStage

CASE, SIZE, FRAMES = "tabletop:0", (96, 160), 4


def test_cache_name_carries_mask_version_and_is_read(tmp_path: Path) -> None:
    clip, masks = world_masks(CASE, SIZE, FRAMES, tmp_path)
    files = [p.name for p in tmp_path.iterdir()]
    assert files == [f"world_default_tabletop_0_96x160x4_hm{HandMaskStage.version}.npz"]
    assert masks.shape == clip.hand_mask.shape and masks.any()
    # the stage's masks from the true joints cover most of the true hand of frame 0
    truth = clip.hand_mask[0] > 0
    assert (masks[0] > 0)[truth].mean() > 0.8
    # a cached file of this version is what is read back (no recomputation)
    marked = np.zeros_like(masks)
    marked[:, :2, :2] = 1
    np.savez_compressed(tmp_path / files[0], masks=marked)
    _, again = world_masks(CASE, SIZE, FRAMES, tmp_path)
    assert np.array_equal(again, marked)


def test_cache_of_another_version_is_not_read(tmp_path: Path) -> None:
    stale = np.ones((FRAMES, *SIZE), np.uint8)  # what an unversioned (pre-v13) cache held
    np.savez_compressed(tmp_path / "world_default_tabletop_0_96x160x4.npz", masks=stale)
    old = HandMaskStage.version - 1
    np.savez_compressed(tmp_path / f"world_default_tabletop_0_96x160x4_hm{old}.npz", masks=stale)
    _, masks = world_masks(CASE, SIZE, FRAMES, tmp_path)
    assert not np.array_equal(masks, stale)
    assert (masks == 0).mean() > 0.5  # computed afresh: most of the frame is not hand
