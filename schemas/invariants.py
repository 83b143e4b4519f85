"""Numeric invariants shared by row validators and by the geometry module."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np


def se3_problems(transform: np.ndarray, tol: float = 1e-4) -> list[str]:
    """Describe why ``transform (..., 4, 4)`` is not a valid rigid transform; empty when it is."""
    transform = np.asarray(transform, dtype=np.float64)
    problems: list[str] = []
    if transform.shape[-2:] != (4, 4):
        return [f"expected (..., 4, 4), got shape {transform.shape}"]
    if not np.all(np.isfinite(transform)):
        return ["contains NaN or infinite values"]
    rot = transform[..., :3, :3]
    ortho_err = np.abs(np.swapaxes(rot, -1, -2) @ rot - np.eye(3)).max(initial=0.0)
    if ortho_err > tol:
        problems.append(f"rotation is not orthonormal (max |R^T R - I| = {ortho_err:.2e})")
    det = np.linalg.det(rot)
    if np.any(np.abs(det - 1.0) > tol):
        problems.append(f"rotation determinant is not +1 (got {float(np.min(det)):.4f})")
    bottom = transform[..., 3, :]
    if np.abs(bottom - np.array([0.0, 0.0, 0.0, 1.0])).max(initial=0.0) > tol:
        problems.append("last row is not [0, 0, 0, 1]")
    return problems


def frame_count_problems(row: Mapping[str, Any], per_frame: tuple[str, ...] = ()) -> list[str]:
    """``num_frames >= 1`` and each ``per_frame`` column (when not null) has that many entries."""
    t = row["num_frames"]
    if t is None or t < 1:
        return [f"num_frames must be >= 1, got {t}"]
    return [
        f"{name} has {len(row[name])} entries, num_frames is {t}"
        for name in per_frame
        if row.get(name) is not None and len(row[name]) != t
    ]


def frame_size_problems(row: Mapping[str, Any]) -> list[str]:
    """``width`` and ``height`` are positive."""
    if row["width"] < 1 or row["height"] < 1:
        return [f"width and height must be positive, got {row['width']}x{row['height']}"]
    return []
