"""Benchmark of ``depth_camera``: seconds per 61-frame 480x832 synthetic clip (SfM + plane
sweep) against the issue's target.

The plane sweep alone, against a numpy + OpenCV reference of the same algorithm, is timed by
:mod:`bench.bench_plane_sweep` (``python -m bench.run --only plane_sweep``), which needs no SfM.

Call :func:`bench_depth_camera`; the harness prints or stores the figures it returns. Rendering
the clip (about a minute on 2 cores) is not timed.
"""

from __future__ import annotations

import time

from egosim.pipeline.clip_io import row_from_clip
from egosim.stages.depth_camera.stage import DepthCameraConfig, DepthCameraStage
from egosim.world import WorldConfig, render_clip


def bench_depth_camera() -> list[dict]:
    """Seconds per clip of the ``sfm`` backend against the issue's 60 s target."""
    clip = render_clip(WorldConfig(seed=0, mode="wild"))
    row = row_from_clip(clip)
    stage = DepthCameraStage(DepthCameraConfig())
    start = time.perf_counter()
    stage.process({"clips": row})
    stage_s = time.perf_counter() - start
    return [
        {
            "name": "depth_camera_sfm_seconds_per_clip_61x480x832",
            "value": stage_s,
            "unit": "s",
            "baseline": "target (issue): 60 s per clip on 2 cores",
            "baseline_value": 60.0,
        },
    ]
