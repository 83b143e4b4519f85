"""Benchmark of ``pose_clean``: per-clip time of the stage's method against plain filterpy loops
(:func:`bench_pose_clean`) and its accuracy on synthetic-world paths
(:func:`bench_pose_clean_accuracy`: exact and near-exact poses, spike recall).

The harness prints or stores the figures these return.
"""

from __future__ import annotations

import time

import numpy as np
from scipy.spatial.transform import Rotation

from egosim.pipeline.geometry import quat_align_hemisphere, quat_from_matrix
from egosim.stages.pose_clean import kalman
from egosim.stages.pose_clean.harness import (
    Corruption,
    added_error,
    corrupt,
    pose_errors,
    spike_frames,
)
from egosim.stages.pose_clean.stage import PoseCleanConfig, clean_batch
from egosim.world.camera_path import camera_path

FPS = 16.0
MODES = ("tabletop", "wild")


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


def bench_pose_clean_accuracy(num_seeds: int = 25) -> list[dict]:
    """Accuracy figures of the default ``kalman_rts`` on synthetic-world camera paths.

    Exact paths (16 fps, 61 frames, both modes, seeds 100...): mean change the cleaning makes
    (mm, degrees). Near-exact paths (0.15 mm, 0.0125 degrees per axis): mean error before and
    after. Noisy paths (5 mm, 0.5 degrees) with 3 spike groups each (single spikes and pairs one
    or two frames apart; 10 cm or 10 degrees): spike recall and precision of the jump test.
    """
    cfg = PoseCleanConfig()
    exact = [camera_path(s, m, 61, FPS) for s in range(100, 100 + num_seeds) for m in MODES]
    out = [r.world_from_cam for r in clean_batch(exact, cfg, FPS)]
    added = np.array([added_error(o, e, e) for o, e in zip(out, exact, strict=True)])  # (N, 2)
    rng = np.random.default_rng(5)
    small = Corruption(noise_translation=0.15e-3, noise_rotation_deg=0.0125)
    near = [corrupt(e, rng, np.zeros(0, dtype=int), small)[0] for e in exact]
    out = [r.world_from_cam for r in clean_batch(near, cfg, FPS)]
    before = np.array(
        [[v.mean() for v in pose_errors(n, e)] for n, e in zip(near, exact, strict=True)]
    )
    after = np.array(
        [[v.mean() for v in pose_errors(o, e)] for o, e in zip(out, exact, strict=True)]
    )
    tp = fp = fn = 0
    for e in exact:
        spikes = spike_frames(len(e), rng, groups=3)
        truth = np.zeros(len(e), dtype=bool)
        truth[spikes] = True
        found = clean_batch([corrupt(e, rng, spikes)[1]], cfg, FPS)[0].outliers
        tp, fp, fn = (
            tp + np.sum(found & truth),
            fp + np.sum(found & ~truth),
            fn + np.sum(~found & truth),
        )
    exact_in = "exact input (0 by definition)"
    return [
        {
            "name": "pose_clean added error, exact poses",
            "value": 1e3 * added[:, 0].mean(),
            "unit": "mm",
            "baseline": exact_in,
            "baseline_value": 0.0,
        },
        {
            "name": "pose_clean added error, exact poses",
            "value": added[:, 1].mean(),
            "unit": "deg",
            "baseline": exact_in,
            "baseline_value": 0.0,
        },
        {
            "name": "pose_clean error, near-exact poses",
            "value": 1e3 * after[:, 0].mean(),
            "unit": "mm",
            "baseline": "input error",
            "baseline_value": 1e3 * before[:, 0].mean(),
        },
        {
            "name": "pose_clean error, near-exact poses",
            "value": after[:, 1].mean(),
            "unit": "deg",
            "baseline": "input error",
            "baseline_value": before[:, 1].mean(),
        },
        {
            "name": "pose_clean spike recall (incl. pairs 1-2 apart)",
            "value": tp / (tp + fn),
            "unit": "share",
            "baseline": "-",
            "baseline_value": None,
        },
        {
            "name": "pose_clean spike precision",
            "value": tp / max(tp + fp, 1),
            "unit": "share",
            "baseline": "-",
            "baseline_value": None,
        },
    ]
