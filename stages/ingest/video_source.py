"""Ingest backend for video files, and the resampling of already-decoded clips."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path
from typing import Protocol

import numpy as np

from egosim.pipeline.geometry import intrinsics_from_fov
from egosim.pipeline.media import MediaError, iter_video_file, probe_video_file
from egosim.pipeline.records import Clip
from egosim.pipeline.stage import ClipRejected
from egosim.stages.ingest.standardise import plan_resize, resample_windows

VIDEO_SUFFIXES = frozenset({".mp4", ".mov", ".mkv", ".avi", ".webm", ".m4v"})


class ClipFormat(Protocol):
    """The ingest parameters that shape a clip (an ``IngestConfig`` satisfies it)."""

    fps: float
    num_frames: int
    height: int
    width: int
    stride: int
    max_clips_per_source: int
    horizontal_fov_deg: float
    intrinsics: tuple[float, ...]


def source_intrinsics(cfg: ClipFormat, width: int, height: int) -> np.ndarray:
    """The given source intrinsics, or a centred pinhole from the configured FOV guess."""
    if cfg.intrinsics:
        return np.asarray(cfg.intrinsics, dtype=np.float64)
    return intrinsics_from_fov(width, height, cfg.horizontal_fov_deg)


def read_video_clips(path: Path, cfg: ClipFormat) -> Iterator[Clip]:
    """Cut one video file into standardised clips (streaming: one clip in memory at a time)."""
    try:
        info = probe_video_file(path)
    except MediaError as exc:
        raise ClipRejected(str(exc)) from exc
    plan = plan_resize(info.width, info.height, cfg.width, cfg.height)
    intrinsics = plan.intrinsics(source_intrinsics(cfg, info.width, info.height))
    frames = ((t, plan.apply(f)) for t, f in iter_video_file(path))
    count = 0
    try:
        for window in resample_windows(
            frames, cfg.fps, cfg.num_frames, cfg.stride, cfg.max_clips_per_source
        ):
            count += 1
            yield Clip(
                clip_id=f"{path.stem}-w{window.index:03d}",
                source="video",
                source_uri=str(path),
                fps=cfg.fps,
                timestamps=window.timestamps,
                intrinsics=intrinsics,
                frames=window.frames,
            ).check()
    except MediaError as exc:
        raise ClipRejected(f"{exc} (after {count} complete clip(s))") from exc
    if count == 0:
        needed = (cfg.num_frames - 1) / cfg.fps
        raise ClipRejected(
            f"video file {path} is shorter than one clip: {cfg.num_frames} frames at "
            f"{cfg.fps} fps need {needed:.2f} s"
        )


def standardise_clip(clip: Clip, cfg: ClipFormat) -> Iterator[Clip]:
    """Resample and resize a decoded clip (with its ground truth) into standard clips."""
    plan = plan_resize(clip.width, clip.height, cfg.width, cfg.height)
    pairs = zip(clip.timestamps.tolist(), range(clip.num_frames), strict=True)
    windows = resample_windows(
        ((t, np.array([i])) for t, i in pairs),
        cfg.fps,
        cfg.num_frames,
        cfg.stride,
        cfg.max_clips_per_source,
    )
    count = 0
    for window in windows:
        idx = window.source_indices  # (T,) indices into the source clip

        def pick(a: np.ndarray | None, idx: np.ndarray = idx) -> np.ndarray | None:
            return None if a is None else a[idx]

        def image(a: np.ndarray | None, nearest: bool = False, idx: np.ndarray = idx):
            if a is None:
                return None
            out = [plan.apply(a[i], nearest) for i in idx]
            return np.stack(out)

        count += 1
        yield replace(
            clip,
            clip_id=f"{clip.clip_id}-w{window.index:03d}",
            fps=cfg.fps,
            timestamps=window.timestamps,
            intrinsics=plan.intrinsics(clip.intrinsics),
            frames=image(clip.frames),
            world_from_cam=pick(clip.world_from_cam),
            depth=image(clip.depth, nearest=True),
            static_frames=image(clip.static_frames),
            static_depth=image(clip.static_depth, nearest=True),
            first_frame_clean=None
            if clip.first_frame_clean is None or idx[0] != 0
            else plan.apply(clip.first_frame_clean),
            hand_joints=pick(clip.hand_joints),
            hand_valid=pick(clip.hand_valid),
            hand_confidence=pick(clip.hand_confidence),
            hand_mask=image(clip.hand_mask, nearest=True),
            object_mask=image(clip.object_mask, nearest=True),
            object_poses=pick(clip.object_poses),
        ).check()
    if count == 0:
        raise ClipRejected(
            f"clip {clip.clip_id} ({clip.num_frames} frames over "
            f"{clip.timestamps[-1] - clip.timestamps[0]:.2f} s) is shorter than one "
            f"{cfg.num_frames}-frame clip at {cfg.fps} fps"
        )
