"""stages.common.klt: forward-backward Lucas-Kanade tracking against known shifts."""

from __future__ import annotations

import cv2
import numpy as np

from egosim.stages.common.klt import track_forward_backward


def _texture(height: int = 120, width: int = 160) -> np.ndarray:
    """A smooth random grey texture ``(H, W)`` uint8 that Lucas-Kanade can lock onto."""
    rng = np.random.default_rng(3)
    noise = np.clip(rng.normal(128, 50, (height, width)), 0, 255).astype(np.uint8)
    return cv2.GaussianBlur(noise, (7, 7), 0)


def test_points_follow_a_known_shift_and_return() -> None:
    """The second frame is the first shifted by (+3, -2) px: every point away from the border
    lands within 0.1 px of its shifted place and its backward track within 0.1 px of its start."""
    a = _texture()
    b = cv2.warpAffine(a, np.float32([[1, 0, 3], [0, 1, -2]]), (160, 120))
    uv = np.stack(np.meshgrid(np.arange(50, 111, 10), np.arange(40, 81, 10)), -1).reshape(-1, 2)
    track = track_forward_backward(a, b, uv.astype(np.float32))
    assert track.converged.all()
    np.testing.assert_allclose(track.uv_b, uv + np.array([3, -2]), atol=0.1)
    assert track.fb_px.max() < 0.1 and track.error.max() < 5.0
    assert track.uv_b.shape == (len(uv), 2) and track.fb_px.shape == (len(uv),)


def test_lost_points_are_flagged() -> None:
    """Points outside the image do not converge; a point whose surroundings are wiped flat in
    the second frame is flagged by its status or by its backward track."""
    a = _texture()
    b = cv2.warpAffine(a, np.float32([[1, 0, 3], [0, 1, -2]]), (160, 120))
    b[40:80, 60:100] = 128  # the neighbourhood of (80, 60) is gone
    uv = np.array([[-100.0, 50.0], [500.0, 50.0], [80.0, 60.0]], np.float32)
    track = track_forward_backward(a, b, uv)
    assert not track.converged[:2].any()
    assert not track.converged[2] or track.fb_px[2] > 1.0


def test_no_points() -> None:
    """No points in, empty arrays of the documented shapes out."""
    a = _texture()
    track = track_forward_backward(a, a, np.zeros((0, 2)))
    assert track.uv_b.shape == (0, 2) and track.fb_px.shape == (0,)
    assert track.converged.shape == (0,) and track.error.shape == (0,)
