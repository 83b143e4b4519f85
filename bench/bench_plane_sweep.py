"""Benchmark of the first-frame plane sweep at 240x416, 64 planes, 6 sources (issue 17).

Times :func:`plane_sweep` with its default parameters (the OpenCV backend on the CPU), the same
with one worker thread, and the torch backend, each against a numpy + OpenCV reference of the
same cost (per-plane ``cv2.warpPerspective`` and ``cv2.boxFilter`` ZNCC, top-2 average,
winner-take-all) measured in the same run. The reference skips the visibility-aware cross-check,
the parabolic refinement and the hand masks, so it does less work than the sweep it is compared
with. Rendering the synthetic clip (about 20 s on 2 cores) is not timed.

Call :func:`bench_plane_sweep`; the harness prints or stores the figures it returns.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable

import cv2
import numpy as np

from egosim.pipeline.geometry import intrinsics_matrix, invert_se3
from egosim.stages.common.plane_sweep import PlaneSweepParams, plane_sweep
from egosim.world import WorldConfig, render_clip

HEIGHT, WIDTH = 240, 416  # working resolution of the sweep (the stage's default at 480x832)
NUM_PLANES = 64  # inverse-depth planes
WINDOW = 7  # ZNCC window side
SOURCES = [10, 20, 30, 40, 50, 60]  # source frames of the 61-frame clip
REPEATS = 3  # the fast runs are timed this many times, interleaved; the best time counts


def numpy_plane_sweep(
    ref: np.ndarray,
    srcs: np.ndarray,
    intrinsics: np.ndarray,
    ref_cam_from_world: np.ndarray,
    src_cam_from_world: np.ndarray,
    depth_range: tuple[float, float],
    num_planes: int,
    window: int,
) -> np.ndarray:
    """Reference: ZNCC plane sweep one plane and one source at a time with numpy and OpenCV.

    ``ref (H, W)`` and ``srcs (S, H, W)`` float32 grey, poses world-to-camera ``(4, 4)`` /
    ``(S, 4, 4)``. Per plane the two best sources are averaged and the winner takes all; returns
    the depth ``(H, W)`` of the winning plane (no refinement, no confidence).
    """
    k = intrinsics_matrix(intrinsics)
    k_inv = np.linalg.inv(k)
    h, w = ref.shape
    box = (window, window)
    mean_i = cv2.boxFilter(ref, -1, box)
    std_i = np.sqrt(np.maximum(cv2.boxFilter(ref * ref, -1, box) - mean_i**2, 0))
    inv_depths = np.linspace(1 / depth_range[1], 1 / depth_range[0], num_planes)
    best = np.full((h, w), -2.0, np.float32)
    best_inv = np.zeros((h, w), np.float32)
    for inv_d in inv_depths:
        scores = []
        for src, cfw in zip(srcs, src_cam_from_world, strict=True):
            rel = cfw @ np.linalg.inv(ref_cam_from_world)  # (4, 4) source from reference
            hom = k @ (rel[:3, :3] + np.outer(rel[:3, 3], [0, 0, 1]) * inv_d) @ k_inv
            warped = cv2.warpPerspective(src, hom, (w, h), flags=cv2.WARP_INVERSE_MAP)
            mean_j = cv2.boxFilter(warped, -1, box)
            var_j = np.maximum(cv2.boxFilter(warped * warped, -1, box) - mean_j**2, 0)
            cov = cv2.boxFilter(warped * ref, -1, box) - mean_i * mean_j
            scores.append(cov / (std_i * np.sqrt(var_j) + 1e-6))
        agg = np.sort(np.stack(scores), axis=0)[-2:].mean(0)  # (H, W) top-2 average
        better = agg > best
        best = np.where(better, agg, best)
        best_inv = np.where(better, inv_d, best_inv)
    return 1.0 / np.maximum(best_inv, 1e-6)


def _seconds(fn: Callable[[], object]) -> float:
    """Wall-clock seconds of one call of ``fn``."""
    start = time.perf_counter()
    fn()
    return time.perf_counter() - start


def bench_plane_sweep() -> list[dict]:
    """Seconds of the default, single-thread and torch plane sweeps vs the numpy reference."""
    clip = render_clip(WorldConfig(seed=0, mode="wild", height=HEIGHT, width=WIDTH, num_frames=61))
    grey = np.stack([cv2.cvtColor(f, cv2.COLOR_RGB2GRAY) for f in clip.frames]).astype(np.float32)
    cfw = invert_se3(clip.world_from_cam)  # (T, 4, 4) world-to-camera
    near, far = np.percentile(clip.depth[0], [1, 99]) * np.array([0.7, 1.3])
    args = (grey[0], grey[SOURCES], clip.intrinsics, cfw[0], cfw[SOURCES], (near, far))
    base = PlaneSweepParams(num_planes=NUM_PLANES, window=WINDOW, top_k=2)
    runs: dict[str, Callable[[], object]] = {
        "reference": lambda: numpy_plane_sweep(*args, NUM_PLANES, WINDOW),
        "default": lambda: plane_sweep(*args, params=base),
        "one_thread": lambda: plane_sweep(
            *args, params=dataclasses.replace(base, backend="opencv", threads=1)
        ),
    }
    times: dict[str, float] = {name: np.inf for name in runs}
    for _ in range(REPEATS):
        for name, fn in runs.items():
            times[name] = min(times[name], _seconds(fn))
    torch_params = dataclasses.replace(base, backend="torch")
    torch_s = _seconds(lambda: plane_sweep(*args, params=torch_params))
    what = f"{HEIGHT}x{WIDTH}_{NUM_PLANES}planes_{len(SOURCES)}src"
    reference = "numpy/OpenCV sweep, same cost, same run"
    return [
        {
            "name": f"plane_sweep_default_seconds_{what}",
            "value": times["default"],
            "unit": "s",
            "baseline": reference,
            "baseline_value": times["reference"],
        },
        {
            "name": f"plane_sweep_opencv_1thread_seconds_{what}",
            "value": times["one_thread"],
            "unit": "s",
            "baseline": reference,
            "baseline_value": times["reference"],
        },
        {
            "name": f"plane_sweep_torch_cpu_seconds_{what}",
            "value": torch_s,
            "unit": "s",
            "baseline": reference,
            "baseline_value": times["reference"],
        },
    ]
