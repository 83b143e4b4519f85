"""Backend ``given``: pass the source's own poses and intrinsics through.

First-frame depth comes from the source's depth column when it has one (confidence 1 where the
depth is known); otherwise it is estimated by plane sweep against the given poses over a
configured depth range. A trajectory whose poses are all equal is a static camera.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from egosim.pipeline.geometry import invert_se3
from egosim.stages.common.plane_sweep import (
    PlaneSweepParams,
    first_frame_depth,
    select_sources,
)

STATIC_CENTRE_TOL = 1e-6  # centre motion (poses' units) below which a trajectory is static
STATIC_ROT_TOL = 1e-6  # max |R_k - R_0| entry below which a trajectory is static


@dataclass(frozen=True)
class GivenResult:
    """Camera and first-frame depth taken from the source."""

    intrinsics: np.ndarray  # (4,) fx, fy, cx, cy
    world_from_cam: np.ndarray  # (T, 4, 4)
    static: bool  # every pose equals the first
    depth0: np.ndarray | None  # (H, W) float32, None when static
    confidence0: np.ndarray | None  # (H, W) float32 in [0, 1], None when static
    sources: list[int]  # frames the depth was matched against ([] for source depth)


def is_static(world_from_cam: np.ndarray) -> bool:
    """True when every pose of ``world_from_cam (T, 4, 4)`` equals the first (within tolerance)."""
    centre = np.abs(world_from_cam[:, :3, 3] - world_from_cam[0, :3, 3]).max(initial=0.0)
    rot = np.abs(world_from_cam[:, :3, :3] - world_from_cam[0, :3, :3]).max(initial=0.0)
    return bool(centre < STATIC_CENTRE_TOL and rot < STATIC_ROT_TOL)


def given_camera(
    frames: np.ndarray,
    usable: np.ndarray | None,
    intrinsics: np.ndarray,
    world_from_cam: np.ndarray,
    depth0: np.ndarray | None,
    depth_range: tuple[float, float],
    num_sources: int,
    scale: float,
    params: PlaneSweepParams,
) -> GivenResult:
    """Use the source's ``intrinsics (4,)`` and ``world_from_cam (T, 4, 4)``.

    ``depth0 (H, W)`` is the source's first-frame depth or None (then plane sweep over
    ``depth_range``). Raises :class:`ValueError` when no source frame sees frame 0's scene.
    """
    if is_static(world_from_cam):
        return GivenResult(intrinsics, world_from_cam, True, None, None, [])
    if depth0 is not None:
        depth = np.asarray(depth0, dtype=np.float32)
        conf = (np.isfinite(depth) & (depth > 0)).astype(np.float32)
        return GivenResult(intrinsics, world_from_cam, False, depth, conf, [])
    cam_from_world = invert_se3(world_from_cam)
    near, far = depth_range
    candidates = np.ones(len(world_from_cam), dtype=bool)
    sources = select_sources(
        cam_from_world,
        candidates,
        np.zeros((0, 3)),
        intrinsics,
        frames.shape[1:3],
        num_sources,
        median_depth=float(np.sqrt(near * far)),
    )
    if len(sources) < 2:
        raise ValueError(f"only {len(sources)} frames move away from frame 0: need 2 for depth")
    depth, conf = first_frame_depth(
        frames, usable, intrinsics, cam_from_world, sources, depth_range, scale, params
    )
    return GivenResult(intrinsics, world_from_cam, False, depth, conf, sources)
