"""Geometry against hand-computed answers (conventions in docs/design.md)."""

from __future__ import annotations

import numpy as np

from egosim.pipeline import geometry as g


def test_look_at_uses_opencv_axes() -> None:
    # Camera at the origin looking along +y with z up: x right = +x, y down = -z, z fwd = +y.
    pose = g.look_at([0, 0, 0], [0, 1, 0], up=[0, 0, 1])
    expected = np.array([[1, 0, 0, 0], [0, 0, 1, 0], [0, -1, 0, 0], [0, 0, 0, 1.0]])
    np.testing.assert_allclose(pose, expected, atol=1e-12)
    uv, z = g.project_world_points(np.array([0.0, 2.0, 0.5]), pose, [100, 100, 50, 40])
    np.testing.assert_allclose(uv, [50, 40 - 25])  # above the axis -> smaller v
    assert z == 2.0


def test_invert_and_transform_round_trip() -> None:
    rng = np.random.default_rng(1)
    rot = g.matrix_from_quat(rng.normal(size=4))
    pose = g.make_se3(rot, rng.normal(size=3))
    pts = rng.normal(size=(10, 3))
    back = g.transform_points(g.invert_se3(pose), g.transform_points(pose, pts))
    np.testing.assert_allclose(back, pts, atol=1e-12)
    np.testing.assert_allclose(g.invert_se3(pose) @ pose, np.eye(4), atol=1e-12)
    assert g.se3_problems(pose) == []
    bad = pose.copy()
    bad[0, 0] += 0.1
    assert any("orthonormal" in p for p in g.se3_problems(bad))
    assert g.se3_problems(np.full((4, 4), np.nan)) == ["contains NaN or infinite values"]


def test_unproject_then_project_lands_on_pixel_centres() -> None:
    intr = np.array([40.0, 42.0, 16.5, 11.0])
    depth = np.full((24, 32), 2.0)
    pts = g.unproject_depth(depth, intr)
    uv, z = g.project_points(pts, intr)
    np.testing.assert_allclose(uv, g.pixel_grid(24, 32), atol=1e-9)
    np.testing.assert_allclose(z, 2.0)


def test_resize_and_crop_keep_projection_consistent() -> None:
    intr = np.array([500.0, 500.0, 640.0, 360.0])
    point = np.array([0.3, -0.2, 2.0])
    uv, _ = g.project_points(point, intr)
    scaled = g.scale_intrinsics(intr, 0.5, 0.5)
    cropped = g.crop_intrinsics(scaled, 10, 20)
    uv2, _ = g.project_points(point, cropped)
    np.testing.assert_allclose(uv2, uv * 0.5 - [10, 20])


def test_quaternions_round_trip_and_hemisphere() -> None:
    rng = np.random.default_rng(2)
    q = rng.normal(size=(20, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    back = g.quat_from_matrix(g.matrix_from_quat(q))
    np.testing.assert_allclose(np.abs(np.sum(back * q, axis=1)), 1.0, atol=1e-9)
    flipped = q.copy()
    flipped[::2] *= -1
    aligned = g.quat_align_hemisphere(flipped)
    assert np.all(np.sum(aligned[1:] * aligned[:-1], axis=1) >= 0)


def test_umeyama_recovers_similarity() -> None:
    rng = np.random.default_rng(3)
    src = rng.normal(size=(50, 3))
    rot = g.matrix_from_quat([0.9, 0.1, -0.3, 0.2])
    dst = 2.5 * src @ rot.T + [1.0, -2.0, 0.5]
    s, r, t = g.umeyama(src, dst)
    assert abs(s - 2.5) < 1e-9
    np.testing.assert_allclose(r, rot, atol=1e-9)
    np.testing.assert_allclose(t, [1.0, -2.0, 0.5], atol=1e-9)
    assert g.rotation_angle_deg(r, rot) < 1e-5
