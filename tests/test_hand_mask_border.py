"""The clip's black border (``hand_mask.border``): found per clip, never masked (hand_mask v23)."""

from __future__ import annotations

import numpy as np

from egosim.stages.hand_mask.border import BorderParams, not_image
from egosim.stages.hand_mask.stage import HandMaskConfig, masks_from_keypoints
from egosim.world import WorldConfig, render_clip
from tests.test_hand_mask import _drawn_hand, _moving_hand_frames


def _bordered(frames: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(frames, border (H, W))``: ``frames (T, H, W, 3)`` with HOT3D's kind of black border:
    a bar of 0 along the bottom, above it rows of 3-6 (compression ringing, which the per-frame
    ``padding`` test, at most 2, does not count as bar), and a black fisheye corner."""
    out = frames.copy()
    t, h, w = out.shape[:3]
    border = np.zeros((h, w), bool)
    border[h - 16 :] = True
    yy, xx = np.mgrid[:h, :w]
    border |= (xx + (h - yy)) < 14  # the bottom-left corner outside the "circle"
    rng = np.random.default_rng(1)
    out[:, border] = 0
    ringing = np.zeros((h, w), bool)
    ringing[h - 16 : h - 10] = True
    out[:, ringing] = rng.integers(3, 7, (t, int(ringing.sum()), 3), dtype=np.uint8)
    return out, border


def test_not_image_finds_the_border_only() -> None:
    """The bar, its ringing rows and the corner are found, exactly; a world clip without a
    border gives nothing, nor does a black object inside a still view (it touches no edge), nor
    a dark corner that some frame lights (the head moved: it is picture)."""
    clip = render_clip(WorldConfig(seed=0, mode="tabletop", height=96, width=128, num_frames=6))
    assert not not_image(clip.frames).any()
    frames, border = _bordered(clip.frames)
    found = not_image(frames)
    np.testing.assert_array_equal(found, border)
    still = np.repeat(clip.frames[:1], 6, axis=0)
    still[:, 40:60, 50:80] = 0  # a black object in the middle of a still view
    assert not not_image(still).any()
    lit = frames.copy()
    lit[2, 80:, :40] = 90  # one frame shows picture in the corner: that part is no border
    assert not not_image(lit)[80:, :40].any() and not_image(lit)[80:, 40:].all()
    # A few black pixels at the edge are no border (less than min_fraction of the frame).
    speck = clip.frames.copy()
    speck[:, :2, :3] = 0
    assert not not_image(speck, BorderParams(min_fraction=0.002)).any()


def test_border_is_never_masked() -> None:
    """A hand whose arm runs down into the border: v22 masked the ringing rows above the bar
    (the arm's certain strip reaches them, and ``padding`` only clears rows of at most 2); v23
    masks nothing of the border and is v22's mask everywhere else."""
    frames, border = _bordered(_moving_hand_frames([(0, 0)] * 5))  # min_frames frames
    kp = np.tile(_drawn_hand((40.5, 70.5)), (5, 1, 1, 1))  # (5, 1, 21, 2) arm runs down
    valid = np.ones((5, 1), bool)
    v22 = masks_from_keypoints(frames, kp, valid, HandMaskConfig(border=False))
    v23 = masks_from_keypoints(frames, kp, valid, HandMaskConfig())
    assert v22[:, border].any(), "v22 masks some of the border (the test would not fail)"
    assert not v23[:, border].any()
    assert v23[:, ~border].sum() > 0
    np.testing.assert_array_equal(v23[:, ~border], v22[:, ~border])


def test_too_few_frames_find_no_border() -> None:
    """One frame cannot tell a black border from dark picture (a dark real clip's edge: review11d
    measured 2.9% of one darkened DWM frame, 213 hand pixels, taken as border): under
    ``min_frames`` frames nothing is found; the same frames repeated to ``min_frames`` are."""
    clip = render_clip(WorldConfig(seed=0, mode="tabletop", height=96, width=128, num_frames=6))
    frames, border = _bordered(clip.frames)
    p = BorderParams()
    assert not not_image(frames[: p.min_frames - 1]).any()
    np.testing.assert_array_equal(not_image(frames[: p.min_frames]), border)
    np.testing.assert_array_equal(not_image(frames[:1], BorderParams(min_frames=1)), border)
