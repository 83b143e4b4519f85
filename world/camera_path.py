"""Head-camera trajectories: smooth low-frequency motion plus a small high-frequency jitter."""

from __future__ import annotations

import numpy as np

from egosim.pipeline.geometry import look_at
from egosim.world.scene import TABLE_TOP_Z


def view_directions(to_focus: np.ndarray, yaw: np.ndarray, pitch: np.ndarray) -> np.ndarray:
    """Unit view directions ``(T, 3)`` (world z up): ``yaw (T,)`` radians about the bearing of
    ``to_focus (3,)`` in the ground plane, ``pitch (T,)`` radians above the horizon."""
    base_yaw = np.arctan2(to_focus[1], to_focus[0])
    return np.stack(
        [
            np.cos(base_yaw + yaw) * np.cos(pitch),
            np.sin(base_yaw + yaw) * np.cos(pitch),
            np.sin(pitch),
        ],
        axis=1,
    )  # (T, 3)


def _wobble(rng: np.random.Generator, times: np.ndarray, amp: float, freqs: tuple) -> np.ndarray:
    """Sum of sinusoids ``(T, 3)`` with random phases, amplitudes up to ``amp`` per axis."""
    out = np.zeros((len(times), 3))
    for f in freqs:
        a = amp * rng.uniform(0.3, 1.0, 3) / len(freqs)
        phase = rng.uniform(0.0, 2.0 * np.pi, 3)
        out += a * np.sin(2.0 * np.pi * f * times[:, None] + phase)
    return out


def camera_path(seed: int, mode: str, num_frames: int, fps: float) -> np.ndarray:
    """``(T, 4, 4)`` world_from_cam of a head camera looking at the table.

    ``tabletop``: seated, ~0.6 m from the table centre, a few cm of motion (EgoDex-like).
    ``wild``: standing, tens of cm of motion and a yaw sweep of 30-50 degrees each way.
    """
    rng = np.random.default_rng([seed, 2])
    times = np.arange(num_frames) / fps  # (T,)
    jitter = _wobble(rng, times, 0.003, (2.3, 3.7))  # (T, 3) millimetre-scale head tremor
    focus = np.array([0.09, 0.0, TABLE_TOP_Z])
    if mode == "tabletop":
        eye0 = np.array([-0.40 + rng.uniform(-0.04, 0.04), rng.uniform(-0.05, 0.05), 0.0])
        eye0[2] = TABLE_TOP_Z + rng.uniform(0.50, 0.62)
        eyes = eye0 + _wobble(rng, times, 0.04, (0.15, 0.35)) + jitter  # (T, 3)
        targets = focus + _wobble(rng, times, 0.04, (0.1, 0.25))  # (T, 3)
    else:
        eye0 = np.array([-0.62, rng.uniform(-0.1, 0.1), TABLE_TOP_Z + rng.uniform(0.7, 0.85)])
        eyes = eye0 + _wobble(rng, times, 0.3, (0.12, 0.3)) + jitter  # (T, 3)
        yaw_amp = np.deg2rad(rng.uniform(30.0, 50.0))
        duration = max(num_frames / fps, 1.0)
        yaw = yaw_amp * np.sin(2.0 * np.pi * times / duration + rng.uniform(0, 2 * np.pi))  # (T,)
        pitch = np.deg2rad(-40.0 + 12.0 * np.sin(2.0 * np.pi * 0.2 * times + rng.uniform(0, 6)))
        targets = eyes + view_directions(focus - eye0, yaw, pitch)  # (T, 3)
    return np.stack([look_at(e, t) for e, t in zip(eyes, targets, strict=True)])  # (T, 4, 4)
