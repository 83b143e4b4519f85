"""Ground-truth scene state of the synthetic world: what ``state_fusion`` should reconstruct.

:func:`scene_truth` renders the static scene (no hands) with the objects at given poses from
given cameras and unprojects every hit into world points labelled by object, so the state
after a clip is compared with the scene after its interaction (objects at their last poses),
seen from the same cameras as the clip (the same surfaces a fusion of the clip can know).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from egosim.pipeline.geometry import transform_points, unproject_depth
from egosim.pipeline.records import Clip
from egosim.world.clip import _setup, world_cameras
from egosim.world.config import WorldConfig
from egosim.world.render import WorldRenderer, to_uint8


@dataclass
class SceneTruth:
    """Ground-truth world points of the static scene, labelled by object."""

    points: np.ndarray  # (N, 3) float32 world metres, one per occupied voxel
    colours: np.ndarray  # (N, 3) uint8 RGB as rendered
    object_id: np.ndarray  # (N,) int32 object index + 1 (as in clips' object_mask), 0 = background

    def object_points(self, object_id: int) -> np.ndarray:
        """``(n, 3)`` points of one object (``object_id`` = object index + 1)."""
        return self.points[self.object_id == object_id]


def scene_truth(
    config: WorldConfig,
    object_poses: np.ndarray,
    world_from_cam: np.ndarray,
    voxel_size: float = 0.005,
) -> SceneTruth:
    """Points of ``config``'s scene with objects at ``object_poses (N, 4, 4)``, seen by cameras.

    Every pixel of every camera in ``world_from_cam (K, 4, 4)`` that hits a surface becomes a
    world point; points are thinned to one per ``voxel_size`` voxel (the first one rendered).
    """
    scene, intrinsics, _ = _setup(config)
    renderer = WorldRenderer(scene, intrinsics, config.height, config.width)
    n_bg = len(scene.background)
    pts, rgb, ids = [], [], []
    for cam in np.asarray(world_from_cam, dtype=np.float64):
        layer = renderer.render_static(cam, object_poses)
        hit = np.isfinite(layer.depth)  # (H, W)
        cam_pts = unproject_depth(np.where(hit, layer.depth, 0.0), intrinsics)[hit]  # (n, 3)
        pts.append(transform_points(cam, cam_pts).astype(np.float32))
        rgb.append(to_uint8(layer.rgb)[hit])
        body = layer.ids[hit].astype(np.int32)
        ids.append(np.where(body >= n_bg, body - n_bg + 1, 0).astype(np.int32))
    points = np.concatenate(pts)
    keys = np.floor(points / voxel_size).astype(np.int64)
    _, first = np.unique(keys, axis=0, return_index=True)
    first = np.sort(first)
    return SceneTruth(points[first], np.concatenate(rgb)[first], np.concatenate(ids)[first])


def moved_objects(object_poses: np.ndarray, min_shift: float = 0.005) -> np.ndarray:
    """Object ids (index + 1) whose pose ``(T, N, 4, 4)`` changed by more than ``min_shift``.

    The change is the largest displacement of the object's origin or of a point 10 cm along
    any of its axes between the first and the last frame (so a lid turning on its hinge counts).
    """
    first, last = object_poses[0], object_poses[-1]  # (N, 4, 4)
    probes = np.concatenate([np.zeros((1, 3)), 0.1 * np.eye(3)])  # (4, 3) object frame
    shift = np.zeros(len(first))
    for n in range(len(first)):
        a = transform_points(first[n], probes)
        b = transform_points(last[n], probes)
        shift[n] = np.linalg.norm(a - b, axis=1).max()
    return np.flatnonzero(shift > min_shift) + 1


def render_views(
    config: WorldConfig, object_poses: np.ndarray, world_from_cam: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Static renders (no hands) with objects at ``object_poses (N, 4, 4)`` from cameras.

    Returns ``rgb (K, H, W, 3)`` uint8 and ``depth (K, H, W)`` float32 metres (0 = no hit), the
    ground truth a scene render of the state along those cameras is compared with.
    """
    scene, intrinsics, _ = _setup(config)
    renderer = WorldRenderer(scene, intrinsics, config.height, config.width)
    k = len(world_from_cam)
    rgb = np.zeros((k, config.height, config.width, 3), np.uint8)
    depth = np.zeros((k, config.height, config.width), np.float32)
    for i, cam in enumerate(np.asarray(world_from_cam, dtype=np.float64)):
        layer = renderer.render_static(cam, object_poses)
        rgb[i] = to_uint8(layer.rgb)
        depth[i] = np.where(np.isfinite(layer.depth), layer.depth, 0.0)
    return rgb, depth


def look_back_path(config: WorldConfig, offset: int = 1000) -> np.ndarray:
    """``(T, 4, 4)`` a second head path over the same table (another seed's path, same mode).

    Stands in for segment 2 of a task: the camera comes back to the table after the
    interaction of ``config``'s clip, along a different path.
    """
    other = WorldConfig(**{**config.__dict__, "seed": config.seed + offset})
    return world_cameras(other)[1]  # the path only: building the other seed's scene is wasted


def look_back_clip(config: WorldConfig, clip: Clip) -> Clip:
    """Segment 2 of a task: the static scene after ``clip``'s interaction along another head path.

    No hands: the true static render (objects at their last poses) along
    :func:`look_back_path`, named ``<clip_id>-seg2``.
    """
    poses = look_back_path(config)
    rgb, depth = render_views(config, clip.object_poses[-1], poses)
    t = len(poses)
    return Clip(
        clip_id=f"{clip.clip_id}-seg2",
        source="synthetic",
        source_uri="",
        fps=clip.fps,
        timestamps=np.arange(t) / clip.fps,
        intrinsics=clip.intrinsics,
        frames=rgb,
        world_from_cam=poses,
        depth=depth,
        hand_joints=np.full((t, 2, 21, 3), np.nan, np.float32),
        hand_valid=np.zeros((t, 2), bool),
        hand_confidence=np.zeros((t, 2, 21), np.float32),
        hand_mask=np.zeros((t, *depth.shape[1:]), np.uint8),
    )
