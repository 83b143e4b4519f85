"""hand_mask's colour growth (``grow``): a hand's mask grows into the band round it that has the
hand's colour, within a margin at the hand's scale, and not into the background beside it."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from egosim.pipeline.stage import ConfigError
from egosim.stages.hand_mask.capsules import CapsuleParams, draw_hand, hand_scale_px
from egosim.stages.hand_mask.grow import GrowParams, grow_masks
from egosim.stages.hand_mask.stage import HandMaskConfig
from tests.test_hand_mask import _drawn_hand as _open_hand  # an open hand pointing up


def _disk(r: int) -> np.ndarray:
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))


def _scene(band_px: int, skin_right: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(frame (96, 128, 3), mask (96, 128), hand (96, 128))``: a textured table; the hand is its
    capsules grown by ``band_px`` in skin (on its left half only unless ``skin_right``); the
    mask is the capsules alone. A skin patch lies 14 px right of the hand."""
    rng = np.random.default_rng(3)
    table = np.clip(rng.normal((90, 110, 140), 18, (96, 128, 3)), 0, 255).astype(np.uint8)
    skin = np.clip(rng.normal((205, 150, 120), 12, (96, 128, 3)), 0, 255).astype(np.uint8)
    kp = _open_hand((60.5, 85.5))
    capsule = draw_hand(kp, 0, 96, 128, CapsuleParams(forearm=False))[0]  # (H, W)
    hand = cv2.dilate(capsule, _disk(band_px)) > 0
    if not skin_right:
        hand[:, 61:] &= capsule[:, 61:] > 0
    patch = np.zeros((96, 128), bool)
    right = int(np.nonzero(hand.any(axis=0))[0].max())
    patch[40:60, right + 14 : right + 24] = True
    frame = table.copy()
    frame[hand | patch] = skin[hand | patch]
    return frame, capsule, hand


def test_grow_takes_the_hand_coloured_band_and_not_the_table() -> None:
    frame, mask, hand = _scene(band_px=3, skin_right=False)
    kp = _open_hand((60.5, 85.5))
    margin = 0.012 * hand_scale_px(kp)
    assert 3.0 < margin < 6.0  # the band lies inside the margin at this hand's scale
    out = grow_masks(frame[None], mask[None], kp[None, None], np.ones((1, 1), bool))[0] > 0
    band = hand & (mask == 0)  # skin the mask missed (left half only)
    recall = float(out[band].mean())
    false = int((out & ~hand).sum())
    # Measured: recall 1.000, no false pixel (the right half's band is table, the patch lies
    # 14 px off, beyond the margin).
    assert recall >= 0.9, f"band recall {recall:.3f}"
    assert false <= 0.05 * band.sum(), f"{false} false px for a band of {band.sum()}"


def test_grow_stays_within_the_margin() -> None:
    frame, mask, _ = _scene(band_px=12, skin_right=True)
    kp = _open_hand((60.5, 85.5))
    margin = 0.012 * hand_scale_px(kp)
    out = grow_masks(frame[None], mask[None], kp[None, None], np.ones((1, 1), bool))[0] > 0
    # Every added pixel lies within the margin of the mask (plus a pixel of rounding).
    dist = cv2.distanceTransform((mask == 0).astype(np.uint8), cv2.DIST_L2, 5)
    assert out.sum() > mask.sum()
    assert float(dist[out].max()) <= margin + 1.5


def test_grow_leaves_frames_without_hands_and_is_configurable() -> None:
    frame, mask, _ = _scene(band_px=3, skin_right=True)
    kp = _open_hand((60.5, 85.5))
    out = grow_masks(frame[None], mask[None], kp[None, None], np.zeros((1, 1), bool))
    assert np.array_equal(out[0], mask)
    with pytest.raises(ValueError, match="margin_m"):
        GrowParams(margin_m=0.05)
    with pytest.raises(ConfigError, match="grow_margin_m"):
        HandMaskConfig(grow_margin_m=-0.01)


def test_stage_grows_only_outwards_and_not_past_the_margin() -> None:
    from egosim.stages.hand_mask.stage import HandMaskStage, project_keypoints
    from egosim.world import WorldConfig, render_clip

    clip = render_clip(WorldConfig(seed=1, height=96, width=160, num_frames=6))
    off = HandMaskStage(HandMaskConfig(grow_margin_m=0.0)).masks_for_clip(clip) > 0
    on = HandMaskStage().masks_for_clip(clip) > 0
    kp = project_keypoints(clip)  # (T, 2, 21, 2)
    scales = [hand_scale_px(kp[t, k]) for t, k in zip(*np.nonzero(clip.hand_valid), strict=True)]
    margin = 0.012 * max(scales)  # measured: 3.1 px; 280 px added over 6 frames, none removed
    assert not (off & ~on).any()  # growth only adds pixels
    added = 0
    for a, b in zip(off, on, strict=True):
        if (b & ~a).any():
            added += int((b & ~a).sum())
            dist = cv2.distanceTransform((~a).astype(np.uint8), cv2.DIST_L2, 5)
            assert float(dist[b & ~a].max()) <= round(margin) + 1.5
    assert added > 0


def test_grow_follows_the_capsules_radius_scale() -> None:
    """With fat capsules (radius_scale 3.5) the hand's part of the mask is found round those
    capsules: the skin band round the whole mask is taken (with the default capsules the mask's
    outer edge lies beyond the margin and its band is left)."""
    rng = np.random.default_rng(3)
    table = np.clip(rng.normal((90, 110, 140), 18, (96, 128, 3)), 0, 255).astype(np.uint8)
    skin = np.clip(rng.normal((205, 150, 120), 12, (96, 128, 3)), 0, 255).astype(np.uint8)
    kp = _open_hand((60.5, 85.5))
    mask = draw_hand(kp, 0, 96, 128, CapsuleParams(3.5, forearm=False))[0]  # (H, W)
    hand = cv2.dilate(mask, _disk(3)) > 0
    frame = np.where(hand[..., None], skin, table)
    band = hand & (mask == 0)
    recalls = {}
    for scale in (1.0, 3.5):
        params = GrowParams(radius_scale=scale)
        out = grow_masks(frame[None], mask[None], kp[None, None], np.ones((1, 1), bool), params)
        recalls[scale] = float((out[0] > 0)[band].mean())
    # Measured: recall 1.000 with the capsules' scale, 0.000 with the default (no false px)
    assert recalls[3.5] >= 0.9, recalls
    assert recalls[1.0] < recalls[3.5] - 0.1, recalls
    with pytest.raises(ValueError, match="radius_scale"):
        GrowParams(radius_scale=0.0)
