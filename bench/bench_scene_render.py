"""Benchmark of the torch z-buffer splat renderer against a straightforward numpy z-buffer.

:func:`bench_scene_render` renders a 400k-point cloud at 480x832 on one CPU thread and returns
frames per second for the torch renderer (one-pixel splats, and with the wide-splat hole fill)
and for a numpy z-buffer (``np.lexsort`` by pixel then depth) measured in the same run. A third
figure renders a depth-grid cloud (one point per pixel of a 480x832 frame, as ``scene_cloud``
writes) as scene_render v4 does: splats (radius 2) and the surface quads (:func:`surface_frame`,
quads linked once by :func:`grid_quads`), against the same numpy baseline.
"""

from __future__ import annotations

import time

import numpy as np
import torch

from egosim.pipeline.geometry import (
    intrinsics_from_fov,
    invert_se3,
    look_at,
    project_world_points,
    transform_points,
    unproject_depth,
)
from egosim.stages.scene_render.splat import (
    grid_quads,
    shade,
    splat_frame,
    surface_frame,
    to_device_cloud,
)

HEIGHT, WIDTH = 480, 832  # default clip size
NUM_POINTS = 400_000  # cloud size of the benchmark
NUM_FRAMES = 12  # frames timed per measurement


def _scene(seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A tabletop-like cloud (points, colours, sizes), intrinsics and a short camera path."""
    rng = np.random.default_rng(seed)
    n = NUM_POINTS
    pts = np.stack(
        [rng.uniform(-0.8, 0.8, n), rng.uniform(-0.5, 0.5, n), rng.uniform(0.0, 0.15, n)], axis=1
    )  # (N, 3)
    colours = rng.integers(0, 256, (n, 3), dtype=np.uint8)
    k = intrinsics_from_fov(WIDTH, HEIGHT, 75.0)
    poses = np.stack(
        [look_at([0.01 * i, -0.5 + 0.005 * i, 0.7], [0.0, 0.0, 0.0]) for i in range(NUM_FRAMES)]
    )  # (T, 4, 4)
    sizes = np.full(n, 0.7 / k[0], dtype=np.float32)  # (N,) about one pixel at the start
    return pts, colours, sizes, k, poses


def _grid_scene(
    poses: np.ndarray, k: np.ndarray, seed: int = 0
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A depth-grid cloud unprojected at ``poses[0]``: a tilted plane with 5 mm noise, one point
    per pixel; returns points ``(H*W, 3)``, colours, sizes ``(H*W,)`` and quads ``(Q, 4)``."""
    rng = np.random.default_rng(seed)
    rows = np.arange(HEIGHT, dtype=np.float64)[:, None] / HEIGHT  # (H, 1)
    depth = 0.9 - 0.3 * rows + rng.normal(0.0, 0.005, (HEIGHT, WIDTH))  # (H, W) metres
    pts = transform_points(poses[0], unproject_depth(depth, k)).reshape(-1, 3)  # (H*W, 3)
    colours = rng.integers(0, 256, (HEIGHT * WIDTH, 3), dtype=np.uint8)
    sizes = (depth / k[0]).reshape(-1).astype(np.float32)  # (H*W,)
    quads = grid_quads(pts, poses[0], k, HEIGHT, WIDTH, max_step=0.3)  # (Q, 4), built once
    return pts, colours, sizes, quads


def numpy_zbuffer(
    points: np.ndarray, colours: np.ndarray, pose: np.ndarray, k: np.ndarray
) -> np.ndarray:
    """Reference numpy z-buffer of one frame: lexsort by (pixel, depth), first per pixel wins."""
    uv, z = project_world_points(points, pose, k)  # (N, 2), (N,)
    with np.errstate(invalid="ignore"):
        u, v = np.floor(uv[:, 0]), np.floor(uv[:, 1])
        ok = (z > 1e-3) & (u >= 0) & (u < WIDTH) & (v >= 0) & (v < HEIGHT)
    pix = (v[ok] * WIDTH + u[ok]).astype(np.int64)  # (M,)
    order = np.lexsort((z[ok], pix))  # by pixel, then depth
    first = np.ones(len(order), dtype=bool)
    first[1:] = pix[order][1:] != pix[order][:-1]
    image = np.zeros((HEIGHT * WIDTH, 3), dtype=np.uint8)
    image[pix[order][first]] = colours[ok][order][first]
    return image.reshape(HEIGHT, WIDTH, 3)


def _fps(fn, frames: int, repeats: int = 3) -> float:
    """Frames/s over ``frames`` calls, best of ``repeats`` runs (shared machines are noisy)."""
    fn(0)  # warm-up
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        for i in range(frames):
            fn(i)
        best = min(best, time.perf_counter() - start)
    return frames / best


def bench_scene_render() -> list[dict]:
    """Frames/s of the torch splatter and of a numpy z-buffer: 400k points, 480x832, 1 thread."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        pts, colours, sizes, k, poses = _scene()
        cloud = to_device_cloud(pts, colours, sizes, "cpu")
        cam_from_world = torch.as_tensor(invert_se3(poses), dtype=torch.float32)

        def torch_frame(i: int, radius: int = 0) -> None:
            keys = splat_frame(cloud, cam_from_world[i % len(poses)], k, HEIGHT, WIDTH, radius)
            shade(cloud, keys)

        def numpy_frame(i: int) -> None:
            numpy_zbuffer(pts, colours, poses[i % len(poses)], k)

        numpy_fps = _fps(numpy_frame, 3, repeats=2)
        torch_fps = _fps(torch_frame, NUM_FRAMES)
        wide_fps = _fps(lambda i: torch_frame(i, 2), NUM_FRAMES)

        g_pts, g_colours, g_sizes, quads = _grid_scene(poses, k)
        grid = to_device_cloud(g_pts, g_colours, g_sizes, "cpu", quads)
        grid_splats = to_device_cloud(g_pts, g_colours, g_sizes, "cpu")  # no quads: splats only

        def surface_frame_(i: int) -> None:
            cam = cam_from_world[1 + i % (len(poses) - 1)]  # not the source pose (skipped there)
            shade(grid_splats, splat_frame(grid_splats, cam, k, HEIGHT, WIDTH, 2))
            surface_frame(grid, cam, k, HEIGHT, WIDTH)

        surface_fps = _fps(surface_frame_, 4, repeats=2)
    finally:
        torch.set_num_threads(threads)
    return [
        {
            "name": "scene_render splat 400k pts 480x832 1 thread",
            "value": round(torch_fps, 1),
            "unit": "frames/s",
            "baseline": "numpy lexsort z-buffer, same run",
            "baseline_value": round(numpy_fps, 1),
        },
        {
            "name": "scene_render splat + hole fill (radius 2) 400k pts 480x832 1 thread",
            "value": round(wide_fps, 1),
            "unit": "frames/s",
            "baseline": "numpy lexsort z-buffer, same run",
            "baseline_value": round(numpy_fps, 1),
        },
        {
            "name": f"scene_render splat + surface, depth grid 480x832 ({len(quads)} quads) "
            "1 thread",
            "value": round(surface_fps, 2),
            "unit": "frames/s",
            "baseline": "numpy lexsort z-buffer, same run",
            "baseline_value": round(numpy_fps, 1),
        },
    ]


if __name__ == "__main__":
    import json
    import sys

    json.dump(bench_scene_render(), sys.stdout, indent=1)
