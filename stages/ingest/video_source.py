"""Ingest backend for video files, and the standardising of already-decoded clips.

Both apply the clip policy of :mod:`egosim.stages.ingest.standardise` (rate, full windows, short
sources, tail) and record what it did on every clip: ``source_fps``, ``source_num_frames``,
``source_frame_indices`` and ``clip_policy``.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path
from typing import Protocol

import numpy as np

from egosim.pipeline.geometry import intrinsics_from_fov
from egosim.pipeline.media import MediaError, VideoFileInfo, iter_video_file, probe_video_file
from egosim.pipeline.records import Clip
from egosim.pipeline.stage import ClipRejected
from egosim.stages.common.frame_plan import ResizePlan, plan_resize
from egosim.stages.ingest.crop_anchor import (
    choose_anchor,
    configured,
    sample_frames,
    sample_video,
)
from egosim.stages.ingest.standardise import WindowPolicy, resample_windows

# Video files ingest lists (any case): phones (.mp4 .mov .3gp), cameras and camcorders (.mts
# .m2ts .ts .avi), the web (.webm .mkv .flv .ogv), older tools (.mpg .mpeg .wmv .m4v).
VIDEO_SUFFIXES = frozenset(
    {".mp4", ".mov", ".mkv", ".avi", ".webm", ".m4v", ".3gp", ".ts", ".mts", ".m2ts"}
    | {".mpg", ".mpeg", ".wmv", ".flv", ".ogv"}
)
MIN_SOURCE_SIDE = 32  # smallest source width or height accepted, pixels (smaller: rejected)
# A video decoding to fewer frames than its container declares, by more than this fraction
# (and more than 2 frames), whose frames also end short of its declared duration, is
# truncated: its unit gets a reject naming the counts.
TRUNCATION_TOLERANCE = 0.02


class ClipFormat(Protocol):
    """The ingest parameters that shape a clip (an ``IngestConfig`` satisfies it)."""

    preset: str
    fps: float
    num_frames: int
    min_frames: int
    height: int
    width: int
    stride: int
    tail: str
    max_clips_per_source: int
    horizontal_fov_deg: float
    intrinsics: tuple[float, ...]
    crop: str
    crop_anchor: tuple[float, ...]


def window_policy(cfg: ClipFormat) -> WindowPolicy:
    """The clip policy in time that an ingest config asks for."""
    return WindowPolicy(
        fps=cfg.fps,
        num_frames=cfg.num_frames,
        min_frames=cfg.min_frames,
        stride=cfg.stride,
        tail=cfg.tail,  # type: ignore[arg-type]  (checked by the config)
        max_windows=cfg.max_clips_per_source,
        preset=cfg.preset,
    )


def source_intrinsics(cfg: ClipFormat, width: int, height: int) -> np.ndarray:
    """The given source intrinsics, or a centred pinhole from the configured FOV guess."""
    if cfg.intrinsics:
        return np.asarray(cfg.intrinsics, dtype=np.float64)
    return intrinsics_from_fov(width, height, cfg.horizontal_fov_deg)


def read_video_clips(path: Path, cfg: ClipFormat) -> Iterator[Clip]:
    """Cut one video file into standardised clips (streaming: one clip in memory at a time).

    ``source_num_frames`` is the container's declared frame count (None when it declares none).
    Frames are turned upright by the file's display rotation. A source smaller than
    :data:`MIN_SOURCE_SIDE` is rejected; a file read to its end that decodes to fewer frames
    than it declares (by more than :data:`TRUNCATION_TOLERANCE`) and whose decoded frames also
    stop short of its declared duration (truncated, :func:`_reaches_declared_end`) is rejected
    after the clips its decoded part gave, naming both counts, so the loss shows in the rejects
    table.
    """
    try:
        info = probe_video_file(path)
    except MediaError as exc:
        raise ClipRejected(str(exc)) from exc
    if min(info.width, info.height) < MIN_SOURCE_SIDE:
        raise ClipRejected(
            f"video file {path} is {info.width}x{info.height}, smaller than the minimum "
            f"{MIN_SOURCE_SIDE} pixels a side"
        )
    sample = sample_video(path, info)
    anchor = choose_anchor(cfg, info.width, info.height, sample, f"video file {path}")
    plan = plan_resize(info.width, info.height, cfg.width, cfg.height, anchor)
    intrinsics = plan.intrinsics(source_intrinsics(cfg, info.width, info.height))
    decoded, exhausted = 0, False  # frames decoded; True once the decoder reached the end
    span = [np.inf, -np.inf]  # first and last decoded frame times, seconds

    def counted() -> Iterator[tuple[float, np.ndarray]]:
        nonlocal decoded, exhausted
        for t, f in iter_video_file(path):
            decoded += 1
            span[0], span[1] = min(span[0], t), max(span[1], t)
            yield t, plan.apply(f)
        exhausted = True

    frames = counted()
    policy = window_policy(cfg)
    count = 0
    try:
        for window in resample_windows(frames, policy, info.fps, f"video file {path}"):
            count += 1
            yield Clip(
                clip_id=f"{path.stem}-w{window.index:03d}",
                source="video",
                source_uri=str(path),
                fps=window.fps,
                timestamps=window.timestamps,
                intrinsics=intrinsics,
                frames=window.frames,
                source_fps=float(info.fps),
                source_num_frames=info.num_frames or None,
                source_frame_indices=window.source_indices,
                clip_policy=policy.label(window.kind),
                source_crop=np.array(plan.source_crop),
            ).check()
    except MediaError as exc:
        raise ClipRejected(f"{exc} (after {count} complete clip(s))") from exc
    missing = info.num_frames - decoded
    # Only a file read to its end can show truncation (max_clips_per_source stops early).
    if (
        exhausted
        and info.num_frames
        and missing > max(2, TRUNCATION_TOLERANCE * info.num_frames)
        and not _reaches_declared_end(info, decoded, span[0], span[1])
    ):
        raise ClipRejected(
            f"video file {path} is truncated: decoded {decoded} of the {info.num_frames} frames "
            f"its container declares (kept the {count} clip(s) of the decoded part)"
        )


def _reaches_declared_end(info: VideoFileInfo, decoded: int, first: float, last: float) -> bool:
    """Whether frames decoded from ``first`` to ``last`` seconds cover the stream's declared
    duration, up to two frame intervals (or the truncation tolerance of it).

    A container may count frames that decode to nothing (AVI's empty "drop" chunks where a
    variable-rate source was muxed on a fine time grid: 40 frames declared as 1200 at 600 fps):
    then fewer frames decode than it declares though none is lost. A truncated file stops
    early in time. Unknown duration: False (the frame count decides).
    """
    if not info.duration_s or decoded < 2 or not last > first:
        return False
    interval = (last - first) / (decoded - 1)  # seconds per decoded frame
    end = info.start_s + info.duration_s  # where the stream says it ends
    slack = max(2 * interval, TRUNCATION_TOLERANCE * info.duration_s)
    return last + interval >= end - slack


def standardise_clip(clip: Clip, cfg: ClipFormat) -> Iterator[Clip]:
    """Resample and resize a decoded clip (with its ground truth) into standard clips.

    Every per-frame array (frames, poses, depth, hands, masks, object poses) is picked with the
    same source indices, so ground truth stays aligned with the frames. A clip that already
    records its source (``source_frame_indices``, ``source_crop``) keeps indices and a crop
    into that original source. The crop's anchor is chosen on the clip's frames
    (:func:`~egosim.stages.ingest.crop_anchor.choose_anchor`), except for robot clips (a gripper
    or an embodiment mask): the human-hand search would take a gripper or a bystander's hand for
    the action, so they keep the configured ``crop_anchor``.
    """
    frames = clip.frames
    if clip.gripper_opening is not None or clip.embodiment_mask is not None:
        anchor = configured(cfg)
    else:
        sample = sample_frames(clip.num_frames, lambda i: frames[i])
        anchor = choose_anchor(cfg, clip.width, clip.height, sample, f"clip {clip.clip_id}")
    plan = plan_resize(clip.width, clip.height, cfg.width, cfg.height, anchor)
    policy = window_policy(cfg)
    pairs = zip(clip.timestamps.tolist(), range(clip.num_frames), strict=True)
    windows = resample_windows(
        ((t, np.array([i])) for t, i in pairs), policy, clip.fps, f"clip {clip.clip_id}"
    )
    for window in windows:
        idx = window.source_indices  # (T,) indices into the decoded clip

        def pick(a: np.ndarray | None, idx: np.ndarray = idx) -> np.ndarray | None:
            return None if a is None else a[idx]

        def image(
            a: np.ndarray | None, nearest: bool = False, idx: np.ndarray = idx
        ) -> np.ndarray | None:
            if a is None:
                return None
            return np.stack([plan.apply(a[i], nearest) for i in idx])

        origin = clip.source_frame_indices
        yield replace(
            clip,
            clip_id=f"{clip.clip_id}-w{window.index:03d}",
            fps=window.fps,
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
            gripper_opening=pick(clip.gripper_opening),
            hand_mask=image(clip.hand_mask, nearest=True),
            embodiment_mask=image(clip.embodiment_mask, nearest=True),
            object_mask=image(clip.object_mask, nearest=True),
            object_poses=pick(clip.object_poses),
            source_fps=clip.source_fps if clip.source_fps is not None else float(clip.fps),
            source_num_frames=clip.source_num_frames or clip.num_frames,
            source_frame_indices=idx if origin is None else np.asarray(origin)[idx],
            clip_policy=policy.label(window.kind),
            source_crop=crop_in_source(plan, clip.source_crop),
        ).check()


def crop_in_source(plan: ResizePlan, outer: np.ndarray | None) -> np.ndarray:
    """``(4,)`` the crop of ``plan`` in the pixels of the original source: ``plan``'s own when
    its input is the source (``outer`` None), else mapped through ``outer``, the input's crop
    of the source (``x0, y0, x1, y1``)."""
    x0, y0, x1, y1 = plan.source_crop  # pixels of plan's input frame
    if outer is None:
        return np.array([x0, y0, x1, y1])
    ox0, oy0, ox1, oy1 = (float(v) for v in outer)
    sx, sy = (ox1 - ox0) / plan.src_width, (oy1 - oy0) / plan.src_height
    return np.array([ox0 + x0 * sx, oy0 + y0 * sy, ox0 + x1 * sx, oy0 + y1 * sy])
