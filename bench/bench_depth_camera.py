"""Benchmark of ``depth_camera``: seconds per 61-frame 480x832 synthetic clip (SfM + plane
sweep) against the issue's target.

The plane sweep alone, against a numpy + OpenCV reference of the same algorithm, is timed by
:mod:`bench.bench_plane_sweep` (``python -m bench.run --only plane_sweep``), which needs no SfM.

Call :func:`bench_depth_camera`; the harness prints or stores the figures it returns. Rendering
the clip (about a minute on 2 cores) is not timed.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from egosim.pipeline.clip_io import row_from_clip
from egosim.pipeline.geometry import umeyama
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


def ate_after_sim3(estimated: np.ndarray, truth: np.ndarray) -> float:
    """RMS camera-centre error (truth units) after one similarity fit of ``estimated (T, 4, 4)``
    centres onto ``truth (T, 4, 4)`` centres."""
    src, dst = estimated[:, :3, 3], truth[:, :3, 3]
    s, rot, trans = umeyama(src, dst)
    moved = s * src @ rot.T + trans  # (T, 3)
    return float(np.sqrt(np.mean(np.sum((moved - dst) ** 2, axis=1))))


def window_figures(
    windows: list[tuple[np.ndarray, np.ndarray]],
) -> dict[str, float]:
    """ATE of windows ``[(estimated (T, 4, 4), truth (T, 4, 4)), ...]`` of one source: with one
    Sim3 per window (mean of the windows' RMS) and one Sim3 for the whole source (RMS)."""
    per_window = [ate_after_sim3(e, t) for e, t in windows]
    est = np.concatenate([e for e, _ in windows])
    truth = np.concatenate([t for _, t in windows])
    return {
        "ate_per_window": float(np.mean(per_window)),
        "ate_per_source": ate_after_sim3(est, truth),
        # metric scale error of each window's (metric) poses: estimate / truth - 1
        "scale_error": [1.0 / umeyama(e[:, :3, 3], t[:, :3, 3])[0] - 1.0 for e, t in windows],
    }


def bench_source_track_synthetic(
    seed: int = 0,
    mode: str = "wild",
    variant: str = "default",
    num_frames: int = 122,
    size: tuple[int, int] = (240, 416),
    work: Path | None = None,
) -> dict[str, Any]:
    """A synthetic video with true poses cut into windows by ingest (61 frames at 16 fps), its
    cameras estimated per window (``source_track off``) and from one source track (``auto``):
    ATE (metres) after one Sim3 per window and one per source, scales and focals per window."""
    from egosim.pipeline import media
    from egosim.stages.ingest.stage import IngestConfig
    from egosim.stages.ingest.video_source import read_video_clips

    height, width = size
    clip = render_clip(
        WorldConfig(
            seed=seed, mode=mode, variant=variant, num_frames=num_frames, height=height, width=width
        )
    )
    work = work or Path(tempfile.mkdtemp(prefix="egosim_track_"))
    path = work / f"synthetic_{variant}_{mode}_{seed}.mp4"
    media.write_video_file(path, clip.frames, clip.fps)
    cfg = IngestConfig(
        source="video",
        height=height,
        width=width,
        intrinsics=tuple(float(v) for v in clip.intrinsics),
    )
    rows = [row_from_clip(c) for c in read_video_clips(path, cfg)]
    truth = np.asarray(clip.world_from_cam)  # (T, 4, 4)
    out: dict[str, Any] = {"case": f"{variant}/{mode}/{seed}", "windows": len(rows)}
    for mode_name in ("off", "auto"):
        stage = DepthCameraStage(DepthCameraConfig(source_track=mode_name))
        pairs, scales, focals, posed, seconds = [], [], [], [], []
        for row in rows:
            start = time.perf_counter()
            est = stage.estimate(row)
            seconds.append(time.perf_counter() - start)
            idx = np.asarray(row["source_frame_indices"])
            pairs.append((np.asarray(est.world_from_cam), truth[idx]))
            scales.append(est.metric_scale)
            focals.append(float(est.intrinsics[0]))
            posed.append(float(np.mean(est.posed_by_codes() != 3)))
        out[mode_name] = {
            **window_figures(pairs),
            "scales": scales,
            "focals": focals,
            "posed": posed,
            "seconds": seconds,
        }
    return out


def main() -> None:
    """``python -m bench.bench_depth_camera track [SEED MODE VARIANT ...]``: the source-track
    figures on synthetic videos (default: seed 0 wild default, seed 1 wild alt)."""
    import json
    import sys

    args = sys.argv[1:]
    if not args or args[0] != "track":
        print(json.dumps(bench_depth_camera(), indent=1))
        return
    cases = [tuple(a.split(":")) for a in args[1:]] or [
        ("0", "wild", "default"),
        ("1", "wild", "alt"),
    ]
    for seed, mode, variant in cases:
        print(json.dumps(bench_source_track_synthetic(int(seed), mode, variant)), flush=True)


if __name__ == "__main__":
    main()
