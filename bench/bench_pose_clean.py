"""Benchmark of ``pose_clean``: per-clip time of the stage's method against plain filterpy loops.

Call :func:`bench_pose_clean`; the harness prints or stores the figures it returns.
"""

from __future__ import annotations

import time

import numpy as np
from scipy.spatial.transform import Rotation

from egosim.pipeline.geometry import quat_align_hemisphere, quat_from_matrix
from egosim.stages.pose_clean import kalman
from egosim.stages.pose_clean.stage import PoseCleanConfig, clean_batch
from egosim.stages.world.camera_path import camera_path

FPS = 16.0


def _trajectories(count: int, num_frames: int = 61) -> list[np.ndarray]:
    """``count`` noisy ground-truth paths ``(T, 4, 4)`` (5 mm, 0.5 degree noise), both modes."""
    rng = np.random.default_rng(0)
    base = [camera_path(s, m, num_frames, FPS) for s in range(10) for m in ("tabletop", "wild")]
    out = []
    for i in range(count):
        poses = base[i % len(base)].copy()
        poses[:, :3, 3] += rng.normal(0.0, 0.005, (num_frames, 3))
        rotvec = rng.normal(0.0, np.deg2rad(0.5), (num_frames, 3))
        poses[:, :3, :3] = poses[:, :3, :3] @ Rotation.from_rotvec(rotvec).as_matrix()
        out.append(poses)
    return out


def _plain_filterpy(trajs: list[np.ndarray]) -> None:
    """The baseline: one filterpy 6-state CV Kalman + RTS on the centre and one 8-state on the
    quaternion per clip, fixed noise (no outlier test, no noise fit)."""
    dt = 1.0 / FPS
    for poses in trajs:
        kalman.filterpy_smooth(poses[:, :3, 3], dt, 1.0, 2.5e-5, True, False, 2)
        quats = quat_align_hemisphere(quat_from_matrix(poses[:, :3, :3]))
        kalman.filterpy_smooth(quats, dt, 1.0, 2e-5, True, True, 2)


def _per_clip(fn, trajs: list[np.ndarray], repeats: int = 1) -> float:
    """Best wall time per clip (ms) of ``fn(trajs)`` over ``repeats`` runs."""
    best = np.inf
    for _ in range(repeats):
        start = time.perf_counter()
        fn(trajs)
        best = min(best, time.perf_counter() - start)
    return best * 1e3 / len(trajs)


def bench_pose_clean(num_clips: int = 1000) -> list[dict]:
    """Figures ``{"name", "value", "unit", "baseline", "baseline_value"}`` measured now."""
    trajs = _trajectories(num_clips)
    few = trajs[:50]
    rts = PoseCleanConfig(method="kalman_rts")
    rts_filterpy = PoseCleanConfig(method="kalman_rts", engine="filterpy")
    baseline_ms = _per_clip(_plain_filterpy, few, 2)
    looped_ms = _per_clip(lambda ts: [clean_batch([t], rts, FPS) for t in ts], few, 2)
    filterpy_ms = _per_clip(lambda ts: clean_batch(ts, rts_filterpy, FPS), few[:20])
    batched_ms = _per_clip(lambda ts: clean_batch(ts, rts, FPS), trajs)
    egocap_ms = _per_clip(lambda ts: clean_batch(ts, PoseCleanConfig(method="egocap"), FPS), few)
    plain = "plain filterpy Kalman+RTS loop, fixed noise (translation + quaternion)"
    return [
        {
            "name": "pose_clean kalman_rts per clip, one clip per call (numpy)",
            "value": looped_ms,
            "unit": "ms/clip",
            "baseline": plain,
            "baseline_value": baseline_ms,
        },
        {
            "name": "pose_clean kalman_rts per clip, engine=filterpy (same method)",
            "value": filterpy_ms,
            "unit": "ms/clip",
            "baseline": plain,
            "baseline_value": baseline_ms,
        },
        {
            "name": f"pose_clean kalman_rts per clip, {num_clips} clips batched",
            "value": batched_ms,
            "unit": "ms/clip",
            "baseline": "same method, one clip per call",
            "baseline_value": looped_ms,
        },
        {
            "name": "pose_clean egocap per clip (spline + SLERP + Savitzky-Golay)",
            "value": egocap_ms,
            "unit": "ms/clip",
            "baseline": plain,
            "baseline_value": baseline_ms,
        },
    ]
