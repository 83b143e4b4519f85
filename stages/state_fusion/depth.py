"""Per-frame depth for a clip that has none (issue 13, step 1).

A generated clip, and most real clips, carry depth for frame 0 at most (``depth_camera``'s plane
sweep). State fusion needs depth per frame, so :func:`estimate_clip_depth` runs the same plane
sweep (:func:`egosim.stages.common.plane_sweep.clip_depth`) on every ``sweep_stride``-th frame
with the clip's known cameras (in simulation the action's trajectory; on real video
``depth_camera``'s poses): only depth is estimated. Frames not swept, and pixels whose sweep
confidence is below ``sweep_min_confidence``, keep depth 0 (unknown), which fusion skips.

Hands move, so the sweep never gives their depth (hand pixels are not matched). The
interaction test compares an object's depth with the hand's, so :func:`fill_hand_depth` puts
on each hand's mask pixels inside its keypoint box the median camera depth of its 3D joints
(the ``hands`` row). Fusion leaves hand pixels out of the state, so this depth is used by the
interaction test only.
"""

from __future__ import annotations

import cv2
import numpy as np

from egosim.pipeline.geometry import invert_se3, project_world_points
from egosim.stages.common.plane_sweep import ClipDepthParams, PlaneSweepParams, clip_depth
from egosim.stages.state_fusion.config import StateFusionConfig


def sweep_params(config: StateFusionConfig, width: int) -> ClipDepthParams:
    """The :class:`ClipDepthParams` of ``config`` for frames ``width`` pixels wide."""
    return ClipDepthParams(
        stride=config.sweep_stride,
        num_sources=config.sweep_sources,
        window_frames=config.sweep_window_frames,
        scale=min(1.0, config.sweep_max_width / width),
        min_confidence=config.sweep_min_confidence,
        consistency_rel=config.sweep_consistency_rel,
        min_consistent=config.sweep_min_consistent,
        sweep=PlaneSweepParams(num_planes=config.sweep_planes, window=config.sweep_window),
    )


def prior_depth_range(
    prior_depth: np.ndarray | None, config: StateFusionConfig
) -> tuple[float, float]:
    """``(near, far)`` of the sweep: the prior depths' 1-99 percentiles widened by
    ``sweep_depth_margin``, or ``sweep_depth_range`` without a prior (fewer than 100 values)."""
    if prior_depth is None:
        return float(config.sweep_depth_range[0]), float(config.sweep_depth_range[1])
    z = np.asarray(prior_depth, np.float64).reshape(-1)
    z = z[np.isfinite(z) & (z > 0)]
    if z.size < 100:
        return float(config.sweep_depth_range[0]), float(config.sweep_depth_range[1])
    near = float(np.percentile(z, 1)) * (1.0 - config.sweep_depth_margin)
    far = float(np.percentile(z, 99)) * (1.0 + config.sweep_depth_margin)
    return near, far


def state_depths(
    points: np.ndarray, world_from_cam: np.ndarray, intrinsics: np.ndarray, size: tuple[int, int]
) -> np.ndarray:
    """Camera depths of the ``points (N, 3)`` that land in the image of any camera (a prior)."""
    h, w = size
    out = []
    for cam in world_from_cam[:: max(1, len(world_from_cam) // 8)]:  # a few cameras suffice
        uv, z = project_world_points(points, cam, intrinsics)
        inside = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
        out.append(z[inside])
    return np.concatenate(out) if out else np.zeros(0)


def estimate_clip_depth(
    frames: np.ndarray,
    hand_mask: np.ndarray,
    intrinsics: np.ndarray,
    world_from_cam: np.ndarray,
    depth_range: tuple[float, float],
    config: StateFusionConfig,
) -> np.ndarray:
    """``(T, H, W)`` float32 depth (0 = unknown) of ``frames`` by plane sweep from known poses.

    ``hand_mask (T, H, W)`` bool pixels (dilated by ``hand_dilation_px``) are not matched.
    Raises :class:`egosim.stages.common.plane_sweep.PlaneSweepError` on bad input.
    """
    r = config.hand_dilation_px
    kernel = np.ones((2 * r + 1, 2 * r + 1), np.uint8)
    t = len(frames)
    usable = np.stack([cv2.dilate(hand_mask[k].astype(np.uint8), kernel) == 0 for k in range(t)])
    ranges = np.tile(np.asarray(depth_range, np.float64), (t, 1))
    params = sweep_params(config, frames.shape[2])
    result = clip_depth(frames, usable, intrinsics, invert_se3(world_from_cam), ranges, params)
    return result.depth


def fill_hand_depth(
    depth: np.ndarray,
    hand_mask: np.ndarray,
    joints: np.ndarray,
    valid: np.ndarray,
    boxes: np.ndarray,
    world_from_cam: np.ndarray,
    intrinsics: np.ndarray,
) -> np.ndarray:
    """``depth`` with each valid hand's mask pixels inside its box set to its joints' depth.

    ``joints (T, 2, 21, 3)`` world, ``valid (T, 2)``, ``boxes (T, 2, 4)`` (:func:`hand_boxes`).
    The median camera depth of the hand's 21 joints stands for its surface (the interaction
    test takes the median over the hand's mask pixels in the same box).
    """
    out = np.array(depth, np.float32, copy=True)
    h, w = out.shape[1:]
    for k in range(len(out)):
        for hand in range(joints.shape[1]):
            box = boxes[k, hand]
            if not valid[k, hand] or not np.all(np.isfinite(box)):
                continue
            _, z = project_world_points(joints[k, hand], world_from_cam[k], intrinsics)
            x0, y0 = max(0, int(box[0])), max(0, int(box[1]))
            x1, y1 = min(w, int(np.ceil(box[2]))), min(h, int(np.ceil(box[3])))
            sub = out[k, y0:y1, x0:x1]
            sub[hand_mask[k, y0:y1, x0:x1]] = np.float32(np.median(z))
    return out
