"""Synthetic corruption of exact camera trajectories, shared by the tests and the benchmark.

:func:`corrupt` adds white Gaussian noise to the camera centre (in the trajectory's units) and to
the rotation (a random rotation vector, right-multiplied), then puts spikes on chosen frames:
a translation jump of fixed length in a random direction, or a rotation jump of fixed angle about
a random axis (the camera centre stays where it is, so only the orientation shows it).
:func:`spike_frames` picks spike frames as isolated spikes and as pairs one or two frames apart
(where spikes can hide each other). :func:`added_error` and :func:`pose_errors` measure the
results.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy.spatial.transform import Rotation

from egosim.pipeline.geometry import rotation_angle_deg


@dataclasses.dataclass(frozen=True)
class Corruption:
    """What :func:`corrupt` adds to a trajectory."""

    noise_translation: float = 0.005  # std. dev. per axis of the centre noise, trajectory units
    noise_rotation_deg: float = 0.5  # std. dev. per axis of the rotation-vector noise, degrees
    spike_translation: float = 0.10  # length of a translation spike, trajectory units
    spike_rotation_deg: float = 10.0  # angle of a rotation spike, degrees
    rotation_spike_share: float = 0.5  # probability that a spike is a rotation spike


def spike_frames(
    num_frames: int, rng: np.random.Generator, groups: int, gaps: tuple[int, ...] = (0, 1, 2)
) -> np.ndarray:
    """Ascending spike frames ``(K,)``: ``groups`` groups at interior frames ``2..T-3``.

    Each group is one spike (gap 0) or two spikes ``gap`` frames apart (gap 1: adjacent frames,
    gap 2: one good frame between), the gap drawn from ``gaps``. Groups keep at least 4 good
    frames between each other; fewer groups are placed when the trajectory is too short.
    """
    taken = np.zeros(num_frames, dtype=bool)
    out: list[int] = []
    for _ in range(groups):
        gap = int(rng.choice(gaps))
        starts = [
            s
            for s in range(2, num_frames - 2 - gap)
            if not taken[max(s - 4, 0) : s + gap + 5].any()
        ]
        if not starts:
            break
        s = int(rng.choice(starts))
        frames = [s] if gap == 0 else [s, s + gap]
        taken[frames] = True
        out.extend(frames)
    return np.array(sorted(out), dtype=int)


def corrupt(
    exact: np.ndarray,
    rng: np.random.Generator,
    spikes: np.ndarray,
    corruption: Corruption = Corruption(),
) -> tuple[np.ndarray, np.ndarray]:
    """``(noisy (T, 4, 4), noisy with spikes (T, 4, 4))`` of ``exact (T, 4, 4)``.

    ``spikes``: frame indices that get a spike (see :class:`Corruption`).
    """
    t = len(exact)
    noisy = np.array(exact, dtype=np.float64, copy=True)
    noisy[:, :3, 3] += rng.normal(0.0, corruption.noise_translation, (t, 3))
    rotvec = rng.normal(0.0, np.deg2rad(corruption.noise_rotation_deg), (t, 3))  # (T, 3)
    noisy[:, :3, :3] = noisy[:, :3, :3] @ Rotation.from_rotvec(rotvec).as_matrix()
    spiked = noisy.copy()
    for i in spikes:
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        if rng.random() < corruption.rotation_spike_share:
            jump = Rotation.from_rotvec(np.deg2rad(corruption.spike_rotation_deg) * axis)
            spiked[i, :3, :3] = spiked[i, :3, :3] @ jump.as_matrix()
        else:
            spiked[i, :3, 3] += corruption.spike_translation * axis
    return noisy, spiked


def pose_errors(est: np.ndarray, ref: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame centre distance (trajectory units) and rotation angle (deg); ``(T,)`` each."""
    return (
        np.linalg.norm(est[:, :3, 3] - ref[:, :3, 3], axis=1),
        rotation_angle_deg(est[:, :3, :3], ref[:, :3, :3]),
    )


def added_error(cleaned: np.ndarray, noisy: np.ndarray, exact: np.ndarray) -> tuple[float, float]:
    """``(translation, degrees)``: mean error of ``cleaned`` minus that of ``noisy`` to ``exact``.

    All ``(T, 4, 4)``. Positive when cleaning made the trajectory worse; for exact input
    (``noisy`` is ``exact``) it is the mean change the cleaning made.
    """
    et, er = pose_errors(cleaned, exact)
    nt, nr = pose_errors(noisy, exact)
    return float(et.mean() - nt.mean()), float(er.mean() - nr.mean())
