"""The "alt" variant's camera set-up: per-seed field of view, a higher, steeper, rolled head.

Against the default (:mod:`egosim.world.camera_path`): the head sits higher and closer to
the table, so it looks down more steeply; it rolls by a few degrees; it aims at a different spot;
its motion has other amplitudes and frequencies; the field of view changes with the seed.
"""

from __future__ import annotations

import numpy as np

from egosim.pipeline.geometry import look_at
from egosim.world.camera_path import _wobble, view_directions
from egosim.world.scene import TABLE_TOP_Z

FOV_SPREAD_DEG = 15.0  # the alt FOV is the configured one plus an offset in +-FOV_SPREAD_DEG


def alt_fov_deg(seed: int, horizontal_fov_deg: float) -> float:
    """Horizontal FOV (degrees) of ``seed``: the configured value plus a per-seed offset."""
    rng = np.random.default_rng([seed, 13])
    offset = rng.uniform(-FOV_SPREAD_DEG, FOV_SPREAD_DEG)
    return float(np.clip(horizontal_fov_deg + offset, 10.0, 150.0))


def _roll(world_from_cam: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """``world_from_cam (T, 4, 4)`` turned about each camera's own z axis by ``angle (T,)``."""
    c, s = np.cos(angle), np.sin(angle)
    rz = np.zeros((len(angle), 4, 4))
    rz[:, 0, 0], rz[:, 0, 1], rz[:, 1, 0], rz[:, 1, 1] = c, -s, s, c
    rz[:, 2, 2] = rz[:, 3, 3] = 1.0
    return world_from_cam @ rz


def camera_path_alt(seed: int, mode: str, num_frames: int, fps: float) -> np.ndarray:
    """``(T, 4, 4)`` world_from_cam of the alt head camera.

    ``tabletop``: 0.62-0.74 m above the table, ~0.3 m behind the near objects, a few cm of motion.
    ``wild``: standing tall, tens of cm of motion, yaw sweeps of 25-45 degrees each way.
    """
    rng = np.random.default_rng([seed, 12])
    times = np.arange(num_frames) / fps  # (T,)
    jitter = _wobble(rng, times, 0.004, (1.9, 3.1))  # (T, 3)
    focus = np.array([rng.uniform(-0.02, 0.06), rng.uniform(-0.05, 0.05), TABLE_TOP_Z])
    roll = np.deg2rad(rng.uniform(-7.0, 7.0) + 2.0 * np.sin(2 * np.pi * 0.2 * times))  # (T,)
    if mode == "tabletop":
        eye0 = np.array([-0.34 + rng.uniform(-0.03, 0.03), rng.uniform(-0.06, 0.06), 0.0])
        eye0[2] = TABLE_TOP_Z + rng.uniform(0.62, 0.74)
        eyes = eye0 + _wobble(rng, times, 0.05, (0.12, 0.3)) + jitter  # (T, 3)
        targets = focus + _wobble(rng, times, 0.05, (0.08, 0.2))  # (T, 3)
    else:
        eye0 = np.array([-0.5, rng.uniform(-0.12, 0.12), TABLE_TOP_Z + rng.uniform(0.88, 0.98)])
        eyes = eye0 + _wobble(rng, times, 0.25, (0.1, 0.25)) + jitter  # (T, 3)
        yaw_amp = np.deg2rad(rng.uniform(25.0, 45.0))
        duration = max(num_frames / fps, 1.0)
        yaw = yaw_amp * np.sin(2.0 * np.pi * times / duration + rng.uniform(0, 2 * np.pi))  # (T,)
        pitch = np.deg2rad(-52.0 + 10.0 * np.sin(2.0 * np.pi * 0.15 * times + rng.uniform(0, 6)))
        targets = eyes + view_directions(focus - eye0, yaw, pitch)  # (T, 3)
    cams = np.stack([look_at(e, t) for e, t in zip(eyes, targets, strict=True)])  # (T, 4, 4)
    return _roll(cams, roll)
