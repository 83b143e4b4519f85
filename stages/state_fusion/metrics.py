"""Figures of a state against ground truth: Chamfer distance, centroid error, stray points."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree


def nearest_distance(points: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """Distance ``(N,)`` from each of ``points (N, 3)`` to its nearest in ``reference (M, 3)``."""
    if len(reference) == 0:
        return np.full(len(points), np.inf)
    if len(points) == 0:
        return np.zeros(0)
    dist, _ = cKDTree(reference).query(points)
    return dist


def chamfer(a: np.ndarray, b: np.ndarray) -> float:
    """Symmetric Chamfer distance in metres: the mean of both directions' mean NN distances.

    Infinite when exactly one of the sets is empty, 0 when both are.
    """
    if len(a) == 0 and len(b) == 0:
        return 0.0
    if len(a) == 0 or len(b) == 0:
        return float("inf")
    return 0.5 * float(nearest_distance(a, b).mean() + nearest_distance(b, a).mean())


def centroid_error(points: np.ndarray, truth: np.ndarray) -> float:
    """Distance in metres between the centroids of ``points`` and ``truth`` (inf if empty)."""
    if len(points) == 0 or len(truth) == 0:
        return float("inf")
    return float(np.linalg.norm(points.mean(0) - truth.mean(0)))


def stray_points(
    points: np.ndarray, stray: np.ndarray, scene: np.ndarray, radius: float = 0.01
) -> np.ndarray:
    """``(N,)`` bool: points within ``radius`` of ``stray`` (e.g. hand surface points) and
    farther than ``radius`` from the true ``scene`` (so table points under a hand do not count).
    """
    near_stray = nearest_distance(points, stray) <= radius
    off_scene = nearest_distance(points, scene) > radius
    return near_stray & off_scene
