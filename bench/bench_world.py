"""Synthetic world rendering speed at 480x832 on one core."""

from __future__ import annotations

import os
import time

from egosim.pipeline.geometry import intrinsics_from_fov
from egosim.world import WorldConfig, render_clip
from egosim.world.camera_path import camera_path
from egosim.world.render import WorldRenderer
from egosim.world.scene import build_scene


def _one_core() -> set[int] | None:
    """Pin this process to one core (returns the previous affinity to restore)."""
    if not hasattr(os, "sched_setaffinity"):
        return None
    previous = os.sched_getaffinity(0)
    os.sched_setaffinity(0, {min(previous)})
    return previous


def bench_world_render() -> list[dict]:
    """Frames/s of whole clips (interaction + static video + ground truth) vs one static layer."""
    previous = _one_core()
    try:
        frames = 16
        cfg = WorldConfig(seed=3, num_frames=frames)
        render_clip(WorldConfig(seed=3, num_frames=2, height=64, width=112))  # warm up imports
        t0 = time.perf_counter()
        render_clip(cfg)
        clip_fps = frames / (time.perf_counter() - t0)

        scene = build_scene(3, False)
        renderer = WorldRenderer(scene, intrinsics_from_fov(832, 480, 75.0), 480, 832)
        poses = camera_path(3, "tabletop", frames, 16.0)
        renderer.render_static(poses[0], scene.initial_object_poses)  # builds the BVH
        t0 = time.perf_counter()
        for pose in poses:
            renderer.render_static(pose, scene.initial_object_poses)
        layer_fps = frames / (time.perf_counter() - t0)
    finally:
        if previous is not None:
            os.sched_setaffinity(0, previous)
    return [
        {
            "name": "world clip render 480x832 (1 core)",
            "value": clip_fps,
            "unit": "frames/s",
            "baseline": "static layer only (raycast + texture)",
            "baseline_value": layer_fps,
        },
        {
            "name": "world clip render target",
            "value": clip_fps / 10.0,
            "unit": "x target",
            "baseline": "10 frames/s",
            "baseline_value": None,
        },
    ]
