"""Benchmark of the ``hands`` backend ``mediapipe``: seconds per standard 61-frame 480x832 clip.

The clip is the real egocentric HOT3D video's RGB view (../shared/data) scaled to cover 480x832
and centre-cropped, first 61 frames (since ingest v7 ingest itself puts this view's band lower,
over the hands; the timing clip keeps the centre band so figures stay comparable across stops).
Video (tracking) mode is the method; per-image mode is the baseline. Call
:func:`bench_hands_mediapipe`; the harness prints or stores the figures it returns.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from egosim.pipeline.geometry import intrinsics_from_fov
from egosim.pipeline.media import read_video_file
from egosim.stages.common.frame_plan import plan_resize
from egosim.stages.hands.mediapipe_backend import MediaPipeParams, mediapipe_hands

HOT3D = Path(__file__).resolve().parents[2] / "shared" / "data" / "hot3d_video"
HOT3D_RGB_X = (427, 853)  # the RGB view: middle third of the side-by-side video
NUM_FRAMES, HEIGHT, WIDTH = 61, 480, 832
FPS = 16.0  # the egosim clip preset's rate: the backend's turn test per second (not the timing)


def _clip_frames() -> np.ndarray:
    """``(61, 480, 832, 3)`` uint8: HOT3D's RGB view, or the synthetic world without the data."""
    path = HOT3D / "ego_centric_aria.mp4"
    if path.is_file():
        frames, _ = read_video_file(path)
        view = frames[:NUM_FRAMES, :, HOT3D_RGB_X[0] : HOT3D_RGB_X[1]]  # (61, 610, 426, 3)
        plan = plan_resize(view.shape[2], view.shape[1], WIDTH, HEIGHT)
        return np.stack([plan.apply(f) for f in view])
    from egosim.world.clip import render_clip  # no shared data: the synthetic world
    from egosim.world.config import WorldConfig

    return render_clip(WorldConfig()).frames[:NUM_FRAMES]


def _seconds(frames: np.ndarray, video_mode: bool, repeats: int = 2) -> float:
    """Best wall time of the whole backend (detect, sides, smooth, lift) over ``repeats`` runs."""
    k = intrinsics_from_fov(WIDTH, HEIGHT, 90.0)
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        mediapipe_hands(frames, k, params=MediaPipeParams(video_mode=video_mode), fps=FPS)
        best = min(best, time.perf_counter() - start)
    return best


def bench_hands_mediapipe() -> list[dict]:
    """Seconds per 61-frame 480x832 clip, video mode against per-image mode (the baseline)."""
    frames = _clip_frames()
    video = _seconds(frames, video_mode=True)
    image = _seconds(frames, video_mode=False)
    return [
        {
            "name": "hands_mediapipe_seconds_per_clip",
            "value": round(video, 3),
            "unit": "s per 61-frame 480x832 clip",
            "baseline": "MediaPipe per-image mode (static_image_mode=True)",
            "baseline_value": round(image, 3),
        }
    ]
