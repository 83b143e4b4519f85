"""One camera track per source video: cameras estimated over the whole source, then sampled per
window (depth_camera v9; ``docs/design.md``, "Cameras per source video").

Ingest cuts a long source into windows; estimating each window on its own gave every window its
own world frame, focal and metric scale. Here the source is read again (video file or frame
folder named by the clip's ``source_uri``), every frame resized to the clip's size by ingest's
rule (the crop the clip recorded, ``source_crop``), and the frames ingest's rate rule picks
become the *track frames*: every window frame is one of them. SfM runs on every
``keyframe_stride``-th track frame and KLT + PnP poses the rest (:func:`estimate_track`): one
model, one focal, one world frame per source. The metric scale is pooled over segments of the track
(:func:`pooled_scale`), so every window of a source gets the same one.

Frames are held only while the track is built; a :class:`SourceTrack` keeps poses, the model
points each track frame sees and the segments' depth maps.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from egosim.pipeline.geometry import invert_se3
from egosim.pipeline.media import MediaError, iter_video_file
from egosim.schemas.depth_camera import POSED_BY_INTERPOLATION
from egosim.stages.common.frame_plan import (
    RATE_TOLERANCE,
    CropError,
    ResizePlan,
    frame_files,
    plan_from_crop,
    targets_reached,
)
from egosim.stages.depth_camera.sfm import (
    SfmError,
    SfmOptions,
    SfmResult,
    fill_unregistered,
    keyframe_indices,
    run_sfm,
    spread_to_frames,
)
from egosim.stages.depth_camera.tracking import NOT_POSED, TrackingParams, register_from_sfm


class SourceTrackError(RuntimeError):
    """The source could not be tracked (unreadable, SfM failed, too long); the message says why."""


def _source_frames(kind: str, uri: str, source_fps: float | None) -> Iterator[tuple[float, Any]]:
    """``(time, frame or loader)`` of every source frame, streamed."""
    path = Path(uri)
    if kind == "video" and path.is_file():
        yield from iter_video_file(path)
    elif kind == "frames" and path.is_dir() and source_fps:
        for i, file in enumerate(frame_files(path)):
            yield i / float(source_fps), file
    else:
        raise SourceTrackError(f"source {kind!r} at {uri!r} is not a readable video or folder")


def _rgb(frame: Any) -> np.ndarray:
    if isinstance(frame, np.ndarray):
        return frame
    image = cv2.imread(str(frame), cv2.IMREAD_COLOR)
    if image is None:
        raise SourceTrackError(f"cannot read image {frame}")
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)


def read_track_frames(
    kind: str,
    uri: str,
    fps: float,
    source_fps: float | None,
    size: tuple[int, int],
    first: int,
    count: int,
    source_crop: tuple[float, ...] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """``(picks (N,), frames (M, H, W, 3))``: the source's track frames up to the chunk's end
    and the pixels of those at track positions ``first .. first + count - 1`` (the chunk),
    resized to ``size = (H, W)`` and cropped to ``source_crop`` (the clip's recorded crop,
    ``x0, y0, x1, y1`` source pixels; None: the centre crop, as rows without one were cut).
    The source is decoded only up to the chunk's last frame.

    ``kind`` is the clip's ``source`` (``video`` or ``frames``), ``uri`` its ``source_uri``.
    Streams the source through ingest's rate rule (``frame_plan.targets_reached``), holding
    one chunk.
    Raises :class:`SourceTrackError` for another kind, an unreadable source, or a recorded crop
    that does not fit the source's size (the file was replaced).
    """
    height, width = size
    times: list[float] = []
    kept: list[np.ndarray] = []
    plan: ResizePlan | None = None
    prev: tuple[float, int, Any] | None = None
    picks: list[int] = []
    keep_rate = source_fps is not None and 0 < source_fps < fps * (1 - RATE_TOLERANCE)

    def take(index: int, frame: Any) -> None:
        nonlocal plan
        k = len(picks)
        picks.append(index)
        if first <= k < first + count:
            rgb = _rgb(frame)
            if plan is None:
                try:
                    plan = plan_from_crop(rgb.shape[1], rgb.shape[0], width, height, source_crop)
                except CropError as exc:
                    raise SourceTrackError(f"source {uri!r}: {exc}") from exc
            kept.append(plan.apply(rgb))

    try:
        for index, (time, frame) in enumerate(_source_frames(kind, uri, source_fps)):
            times.append(time)
            t = time - times[0]
            if keep_rate:
                take(index, frame)
            else:
                current = (t, index, frame)
                for _, (_, i, img) in targets_reached(current, prev, len(picks), fps):
                    take(i, img)
                prev = current
            if len(picks) >= first + count:
                break  # the chunk is complete: the rest of the source is not decoded
    except (MediaError, OSError) as exc:
        raise SourceTrackError(f"cannot read source {uri!r}: {exc}") from exc
    if not kept:
        raise SourceTrackError(f"source {uri!r} has no track frames at {first}..{first + count}")
    return np.asarray(picks, dtype=np.int64), np.stack(kept)


THUMBNAIL_SIZE = (64, 36)  # (W, H) of the grey thumbnails a track keeps of its frames


def thumbnail(frame: np.ndarray) -> np.ndarray:
    """``(36, 64)`` float32 grey thumbnail of an ``(H, W, 3)`` uint8 RGB frame (area average)."""
    grey = cv2.cvtColor(np.ascontiguousarray(frame), cv2.COLOR_RGB2GRAY)
    return cv2.resize(grey, THUMBNAIL_SIZE, interpolation=cv2.INTER_AREA).astype(np.float32)


@dataclass(frozen=True)
class SourceTrack:
    """Cameras of one chunk of a source's track frames, in one SfM frame and scale (unscaled)."""

    picks: np.ndarray  # (N,) source frame index of the source's track frames to the chunk's end
    first: int  # track position of the chunk's first frame
    intrinsics: np.ndarray  # (4,) fx, fy, cx, cy of the clip-size frames
    cam_from_world: np.ndarray  # (M, 4, 4) of the chunk's frames; unposed ones interpolated
    posed_by: np.ndarray  # (M,) int8 schema codes (mapper, PnP, or interpolated)
    frame_points: dict[int, np.ndarray]  # chunk frame -> (P, 3) model points seen there
    reprojection_error_px: float  # the SfM model's mean reprojection error
    num_points3d: int  # points in the model
    mapper: str  # which mapper built the model
    metric_scale: float | None = None  # metres per unit of the pooled scale; None = unknown
    scale_source: str = "none"  # hand_size, hand_size_wide or none
    scale_spread: float | None = None  # relative spread of the pooled estimate
    scale_reason: str = ""  # why there is no scale (when metric_scale is None)
    depths: dict[int, tuple[np.ndarray, np.ndarray, tuple[int, ...]]] = dataclasses.field(
        default_factory=dict
    )  # chunk frame of a segment start -> (depth (H, W), confidence (H, W), chunk sources)
    thumbnails: np.ndarray | None = None  # (M, 36, 64) float32 grey of the chunk's frames

    def frame_difference(self, position: int, frame: np.ndarray) -> float:
        """Mean absolute grey difference (0-255) between chunk frame ``position`` as the track
        read it and ``frame`` ``(H, W, 3)`` uint8 (the window's own); 0 without thumbnails."""
        if self.thumbnails is None:
            return 0.0
        return float(np.abs(thumbnail(frame) - self.thumbnails[position]).mean())

    def positions(self, source_indices: np.ndarray, first_target: int) -> np.ndarray | None:
        """``(T,)`` chunk frames of a window's ``source_indices``, or None when they are not
        consecutive track frames inside the chunk. ``first_target`` is the window's first track
        position as its timestamps give it (tried first; else the first match is searched)."""
        idx = np.asarray(source_indices, dtype=np.int64)
        t = len(idx)
        starts = [first_target, *np.flatnonzero(self.picks == idx[0]).tolist()]
        for k0 in starts:
            if (
                k0 >= 0
                and k0 + t <= len(self.picks)
                and np.array_equal(self.picks[k0 : k0 + t], idx)
            ):
                pos = np.arange(k0, k0 + t) - self.first
                if pos[0] >= 0 and pos[-1] < len(self.cam_from_world):
                    return pos
                return None
        return None


def estimate_track(
    frames: np.ndarray,
    prior_focal: float,
    options: SfmOptions,
    keyframe_stride: int,
    tracking: TrackingParams,
    worker_command: list[str] | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict[int, np.ndarray], SfmResult]:
    """SfM on keyframes of ``frames (N, H, W, 3)`` then PnP tracking of the rest.

    Returns ``(intrinsics (4,), cam_from_world (N, 4, 4), posed_by (N,), frame_points, sfm)``;
    frames nothing posed are interpolated and coded :data:`POSED_BY_INTERPOLATION`. Raises
    :class:`SourceTrackError` when SfM finds no model.
    """
    n = len(frames)
    key = keyframe_indices(n, keyframe_stride)  # (K,)
    try:
        sfm = run_sfm(frames[key], None, dataclasses.replace(options, prior_focal=prior_focal))
    except SfmError as exc:
        raise SourceTrackError(f"SfM on the source's {len(key)} keyframes: {exc}") from exc
    sfm = spread_to_frames(sfm, key, n)
    tracked = register_from_sfm(frames, None, sfm, tracking)
    posed_by = tracked.posed_by.copy()
    posed = posed_by != NOT_POSED
    if not posed.any():
        raise SourceTrackError("SfM on the source posed no frame")
    cam_from_world = fill_unregistered(tracked.cam_from_world, posed)  # (N, 4, 4)
    posed_by[~posed] = POSED_BY_INTERPOLATION
    return sfm.intrinsics, cam_from_world, posed_by, tracked.frame_points, sfm


def world_from_cam(track: SourceTrack, positions: np.ndarray) -> np.ndarray:
    """``(T, 4, 4)`` world-from-camera of the track frames at ``positions``."""
    return invert_se3(track.cam_from_world[positions])
