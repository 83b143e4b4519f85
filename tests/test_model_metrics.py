"""Metrics against hand-computed values."""

from __future__ import annotations

import numpy as np
import pytest

from egosim.model.metrics import lpips_distance, psnr, ssim
from egosim.pipeline.geometry import camera_error, look_at, plucker_rays


def test_psnr_known_value() -> None:
    a = np.zeros((2, 4, 4, 3), np.uint8)
    b = a.copy()
    assert psnr(a, b) == float("inf")
    b[:] = 10  # mse 100 -> 10 log10(255^2 / 100)
    assert psnr(a, b) == pytest.approx(10 * np.log10(255**2 / 100))


def test_ssim_identity_and_degradation() -> None:
    rng = np.random.default_rng(0)
    a = rng.integers(0, 256, (2, 24, 24, 3)).astype(np.uint8)
    assert ssim(a, a) == pytest.approx(1.0)
    noisy = np.clip(a + rng.normal(0, 40, a.shape), 0, 255).astype(np.uint8)
    assert ssim(a, noisy) < 0.9
    # constant images: luminance term only, (2 mu_a mu_b + c1) / (mu_a^2 + mu_b^2 + c1)
    c1 = (0.01 * 255) ** 2
    x, y = np.full((16, 16), 100.0), np.full((16, 16), 120.0)
    assert ssim(x, y) == pytest.approx((2 * 100 * 120 + c1) / (100**2 + 120**2 + c1))


def test_plucker_rays_by_hand() -> None:
    k = np.array([10.0, 10.0, 2.0, 2.0])  # 4x4 image, principal point at the centre
    pose = np.eye(4)
    pose[:3, 3] = [1.0, 0.0, 0.0]
    rays = plucker_rays(k, pose[None], 4, 4)
    assert rays.shape == (1, 4, 4, 6)
    d = np.array([0.05, 0.05, 1.0]) / np.linalg.norm([0.05, 0.05, 1.0])  # pixel (2, 2) centre
    np.testing.assert_allclose(rays[0, 2, 2, :3], d)
    np.testing.assert_allclose(rays[0, 2, 2, 3:], np.cross([1.0, 0, 0], d))


def test_camera_error() -> None:
    k = np.array([20.0, 20.0, 8.0, 8.0])
    poses = np.stack([look_at([0.1 * i, -1.0, 0.5], [0, 0, 0]) for i in range(3)])
    assert camera_error(k, poses, poses, 16, 16) == 0.0
    moved = poses.copy()
    moved[:, :3, 3] += [0.0, 0.0, 0.2]  # a pure translation changes only the moments
    err = camera_error(k, poses, moved, 16, 16)
    d = plucker_rays(k, poses, 16, 16)[..., :3]
    expected = np.linalg.norm(np.cross([0.0, 0.0, 0.2], d), axis=-1).mean()
    assert err == pytest.approx(expected)


def test_lpips_is_skipped_without_local_weights() -> None:
    a = np.zeros((1, 16, 16, 3), np.uint8)
    assert lpips_distance(a, a, weights=None) is None
