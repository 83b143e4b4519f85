"""bench.hand_free_real's split of a mask's misses into background- and hand-coloured pixels."""

from __future__ import annotations

import numpy as np

from bench.hand_free_real import background_like_misses

SKIN = (200, 150, 120)
FLOOR = (60, 90, 160)


def test_background_like_misses_counts_only_misses_of_background_colour() -> None:
    """A truth hand of skin colour on a blue floor: the mask holds most of it and misses a
    10x4 skin strip (visible hand) and the 40x6 strip the truth draws over the floor (a render
    off the hand); only the floor strip's 240 pixels count."""
    frame = np.zeros((1, 80, 80, 3), np.uint8)
    frame[:] = FLOOR
    frame[0, 20:60, 20:50] = SKIN  # the real hand
    truth = np.zeros((1, 80, 80), bool)
    truth[0, 20:60, 20:56] = True  # the hand plus 6 columns of floor
    mask = np.zeros((1, 80, 80), bool)
    mask[0, 20:60, 20:50] = True
    mask[0, 20:30, 46:50] = False  # a missed skin strip
    missed_floor = 40 * 6
    assert int((truth & ~mask).sum()) == missed_floor + 40
    assert background_like_misses(frame, mask, truth) == missed_floor


def test_background_like_misses_zero_without_misses() -> None:
    """A mask that holds the whole truth misses nothing; a missed colour seen neither on the
    masked hand nor round it is not counted as background."""
    frame = np.full((2, 40, 40, 3), 128, np.uint8)
    truth = np.zeros((2, 40, 40), bool)
    truth[:, 10:20, 10:20] = True
    assert background_like_misses(frame, truth | False, truth) == 0
    mask = truth.copy()
    mask[:, 10:12, 10:20] = False  # missed ...
    frame[:, 10:12, 10:20] = (250, 20, 250)  # ... in a colour found nowhere else
    assert background_like_misses(frame, mask, truth) == 0
