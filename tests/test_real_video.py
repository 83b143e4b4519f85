"""The real-video bench: registering a ground-truth video to the real one (bench/real_video)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from bench.real_video import _shift, truth_shift


@pytest.mark.parametrize("shift", [(-5.7, -5.1), (3.25, 0.0), (0.0, 7.5)])
def test_truth_shift_finds_a_principal_point_offset(shift: tuple[float, float]) -> None:
    """A truth rendered with another principal point is the real frame translated."""
    rng = np.random.default_rng(0)
    h, w = 120, 180
    texture = cv2.GaussianBlur(
        rng.uniform(0, 255, (h + 40, w + 40, 3)).astype(np.float32), (0, 0), 2
    )
    real = texture[20 : 20 + h, 20 : 20 + w]
    m = np.float32([[1, 0, -shift[0]], [0, 1, -shift[1]]])  # the truth: real moved by -shift
    truth = cv2.warpAffine(texture, m, (w + 40, h + 40), flags=cv2.INTER_LINEAR)[
        20 : 20 + h, 20 : 20 + w
    ]
    real, truth = real.astype(np.uint8), truth.astype(np.uint8)
    dx, dy = truth_shift(real, truth)
    assert (dx, dy) == pytest.approx(shift, abs=0.15)
    # shifting the truth by what truth_shift returns registers it to the real frame
    inner = (slice(12, -12), slice(12, -12))
    before = np.abs(truth.astype(float) - real)[inner].mean()
    after = np.abs(_shift(truth, dx, dy).astype(float) - real)[inner].mean()
    assert after < 0.2 * before
