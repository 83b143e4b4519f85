"""Where ingest's crop window sits in a source whose aspect differs from the clip's.

Ingest scales every source to cover the clip size and crops the overflow
(:func:`egosim.stages.common.frame_plan.plan_resize`). The window's place is an *anchor*: two
fractions ``(x, y)`` in ``[0, 1]`` of the slack along each axis, ``(0.5, 0.5)`` the centre. An
upright phone video (1080x1920) scaled to cover 832x480 keeps a 480-row band of 1479 rows: the
centre band is the middle 32% of the picture, and egocentric footage holds its hands low.

With ``crop="hands"`` (:func:`choose_anchor`) the band is placed over the hands: MediaPipe's
detector (:func:`egosim.stages.common.hand_landmarks.detect_hand_landmarks`, per-image mode) runs
on :data:`SAMPLE_FRAMES` frames spread evenly over the source at :data:`DETECT_LONG_SIDE` pixels,
and along each cut axis the window takes the place (in steps of 1/16 of the slack) that covers
the most of the hands' boxes (:func:`place_window`). One anchor per source: every clip of a
source (and depth_camera's source track, through the recorded ``source_crop``) uses the same
window. A source whose crop drops less than :data:`MIN_CUT_FRACTION` of a side (16:9 into
832x480 drops 2.5%) keeps the configured anchor without detection, and so does a source where
no hand is found (said in a log line).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Protocol

import cv2
import numpy as np

from egosim.pipeline.media import MediaError, VideoFileInfo, iter_video_file
from egosim.stages.common.frame_plan import Anchor, ResizePlan, plan_resize
from egosim.stages.common.hand_landmarks import (
    HandLandmarkParams,
    MediaPipeUnavailableError,
    detect_hand_landmarks,
)

log = logging.getLogger(__name__)

SAMPLE_FRAMES = 8  # source frames the hands are looked for on, spread evenly over its length
DETECT_LONG_SIDE = 640  # the sampled frames' longer side at detection, pixels
MIN_CUT_FRACTION = 0.1  # below this share of a scaled side cut away, no detection: the anchor
HAND_MARGIN = 0.15  # each side of a hand's landmark box grows by this fraction of its size
ANCHOR_STEPS = 16  # the hands' anchor is a multiple of 1 / ANCHOR_STEPS (see place_window)
SEEK_AFTER_S = 30.0  # longer videos are sampled by seeking (shorter: one decoding pass)
# Per-image detection (a few frames far apart: nothing to track), the full frame plus the
# detector's default lower-frame tiles, no following through misses.
DETECT_PARAMS = HandLandmarkParams(video_mode=False, track_misses=False)


class CropFormat(Protocol):
    """The ingest parameters that place the crop (an ``IngestConfig`` satisfies it)."""

    crop: str
    crop_anchor: tuple[float, ...]
    height: int
    width: int


def configured(cfg: CropFormat) -> Anchor:
    """The configured anchor ``crop_anchor`` as an ``(x, y)`` pair."""
    return float(cfg.crop_anchor[0]), float(cfg.crop_anchor[1])


def choose_anchor(
    cfg: CropFormat,
    src_width: int,
    src_height: int,
    sample: Callable[[int], Sequence[np.ndarray]],
    what: str,
) -> Anchor:
    """The anchor of a ``src_width x src_height`` source: ``crop_anchor``, or with
    ``crop="hands"`` the window over the hands found on ``sample(SAMPLE_FRAMES)`` (evenly spread
    ``(H, W, 3)`` uint8 RGB source frames; called only when the crop cuts enough to matter).
    ``what`` names the source in the log line."""
    anchor = configured(cfg)
    plan = plan_resize(src_width, src_height, cfg.width, cfg.height)
    if cfg.crop != "hands" or cut_fraction(plan) < MIN_CUT_FRACTION:
        return anchor
    frames = [f for f in sample(SAMPLE_FRAMES) if f is not None]
    try:
        boxes = hand_boxes(frames)
    except MediaPipeUnavailableError as exc:
        log.warning("%s: crop at anchor %s, hands not looked for: %s", what, anchor, exc)
        return anchor
    if not boxes:
        log.info(
            "%s: no hand found on %d sampled frames; crop at anchor (%.2f, %.2f)",
            what,
            len(frames),
            *anchor,
        )
        return anchor
    placed = hands_anchor(plan, boxes, anchor)
    crop = plan_resize(src_width, src_height, cfg.width, cfg.height, placed).source_crop
    log.info(
        "%s: %d hands on %d sampled frames; crop anchor (%.3f, %.3f), source pixels %s",
        what,
        len(boxes),
        len(frames),
        *placed,
        tuple(round(v, 1) for v in crop),
    )
    return placed


def cut_fraction(plan: ResizePlan) -> float:
    """The larger share of a scaled side the crop drops (0 when nothing is cut)."""
    return max(1 - plan.width / plan.scaled_width, 1 - plan.height / plan.scaled_height)


def hand_boxes(frames: Sequence[np.ndarray]) -> list[tuple[float, float, float, float]]:
    """``(x0, y0, x1, y1)`` of every hand found on ``frames`` (``(H, W, 3)`` uint8 RGB of one
    size), as fractions of the frame, each side grown by :data:`HAND_MARGIN` of its size.
    Frames are shrunk to :data:`DETECT_LONG_SIDE` first (never enlarged)."""
    if not frames:
        return []
    small = np.stack([shrink(f) for f in frames])  # (K, h, w, 3)
    raw = detect_hand_landmarks(small, DETECT_PARAMS)
    sh, sw = small.shape[1:3]
    boxes: list[tuple[float, float, float, float]] = []
    for i, k in zip(*np.nonzero(raw.present), strict=True):
        uv = raw.uv[i, k]  # (21, 2) pixels of the small frame
        lo, hi = uv.min(axis=0), uv.max(axis=0)  # (2,), (2,)
        pad = HAND_MARGIN * (hi - lo)
        lo, hi = lo - pad, hi + pad
        boxes.append((lo[0] / sw, lo[1] / sh, hi[0] / sw, hi[1] / sh))
    return boxes


def hands_anchor(
    plan: ResizePlan, boxes: Sequence[tuple[float, float, float, float]], fallback: Anchor
) -> Anchor:
    """The anchor whose window covers the most of ``boxes`` (fractions of the source frame)
    along each axis the crop cuts; ``fallback``'s value along an axis it does not cut."""
    arr = np.clip(np.asarray(boxes, dtype=np.float64).reshape(-1, 4), 0.0, 1.0)  # (N, 4)
    out = list(fallback)
    axes = ((0, plan.scaled_width, plan.width), (1, plan.scaled_height, plan.height))
    for axis, scaled, length in axes:
        slack = scaled - length
        if slack <= 0:
            continue
        spans = arr[:, [axis, axis + 2]] * scaled  # (N, 2) scaled pixels
        out[axis] = place_window(spans, length, slack)
    return out[0], out[1]


def place_window(spans: np.ndarray, length: int, slack: int) -> float:
    """The anchor in ``[0, 1]`` along one axis (a multiple of ``1 / ANCHOR_STEPS``) whose
    window of ``length`` pixels, at offset ``floor(anchor * slack)`` as
    :func:`~egosim.stages.common.frame_plan.plan_resize` puts it, covers the most of ``spans
    (N, 2)`` (start, end pixels): the sum over spans of the share of each inside the window.
    Of equal covers, the one whose window centre is nearest the spans' mean centre.

    The anchor moves in steps so that another encode of the same pictures (a few hands found
    differently) keeps the same window: on the bench's portrait variants the unstepped anchor
    was 0.877 (H.264), 0.882 (H.264, display matrix) and 0.848 (HEVC), 29 scaled rows apart.
    """
    steps = np.arange(ANCHOR_STEPS + 1) / ANCHOR_STEPS  # (S,) candidate anchors
    offsets = np.floor(steps * slack)[:, None]  # (S, 1)
    a, b = spans[None, :, 0], spans[None, :, 1]  # (1, N)
    inside = np.clip(np.minimum(b, offsets + length) - np.maximum(a, offsets), 0.0, None)
    cover = (inside / np.maximum(b - a, 1e-9)).sum(axis=1)  # (S,)
    best = np.flatnonzero(cover >= cover.max() - 1e-9)
    centre = float(spans.mean(axis=0).mean())  # mean of the spans' centres
    return float(steps[best[np.argmin(np.abs(offsets[best, 0] + length / 2 - centre))]])


def sample_video(path: Path, info: VideoFileInfo) -> Callable[[int], list[np.ndarray]]:
    """A ``sample(count)`` for :func:`choose_anchor`: ``count`` frames of a video file spread
    evenly over its declared length, shrunk to :data:`DETECT_LONG_SIDE`. Videos longer than
    :data:`SEEK_AFTER_S` seek to each frame; shorter ones (or when seeking fails) are decoded
    in one pass. A decoding error ends the sample with the frames read (ingest itself reports
    the file's errors)."""

    def sample(count: int) -> list[np.ndarray]:
        if info.duration_s > SEEK_AFTER_S:
            try:
                return _seek_frames(path, info, count)
            except MediaError as exc:
                log.info("%s: seeking for crop samples failed (%s); one pass instead", path, exc)
        return _pass_frames(path, info, count)

    return sample


def shrink(frame: np.ndarray) -> np.ndarray:
    """``frame`` with its longer side at most :data:`DETECT_LONG_SIDE` (area average)."""
    h, w = frame.shape[:2]
    s = DETECT_LONG_SIDE / max(h, w)
    if s >= 1.0:
        return frame
    return cv2.resize(frame, (round(w * s), round(h * s)), interpolation=cv2.INTER_AREA)


def _seek_frames(path: Path, info: VideoFileInfo, count: int) -> list[np.ndarray]:
    """The first frame from half a frame before each of ``count`` evenly spread times on
    (seeking: :func:`~egosim.pipeline.media.iter_video_file` with ``start``), the same frames
    as :func:`_pass_frames` picks by index."""
    out = []
    for k in range(count):
        start = info.start_s + (k + 0.5) * info.duration_s / count
        for _, frame in iter_video_file(path, start=start):
            out.append(shrink(frame))
            break
    return out


def _pass_frames(path: Path, info: VideoFileInfo, count: int) -> list[np.ndarray]:
    """``count`` frames at evenly spread indices of the declared frame count (else of the
    duration times the rate; else the first ``count`` frames a second apart), one pass."""
    total = info.num_frames or round(info.duration_s * info.fps)
    if total > 0:
        wanted = sample_indices(total, count)
    else:
        wanted = [round(k * info.fps) for k in range(count)]
    out: list[np.ndarray] = []
    try:
        for index, (_, frame) in enumerate(iter_video_file(path)):
            if index in wanted:
                out.append(shrink(frame))
            if index >= wanted[-1]:
                break
    except MediaError as exc:
        log.info("%s: crop samples stop after %d frames: %s", path, len(out), exc)
    return out


def sample_indices(n: int, count: int) -> list[int]:
    """Up to ``count`` distinct indices spread evenly over ``0..n-1`` (mid-points of ``count``
    equal parts)."""
    return sorted({min(n - 1, int((k + 0.5) * n / count)) for k in range(count)}) if n else []


def sample_frames(n: int, get: Callable[[int], np.ndarray]) -> Callable[[int], list[np.ndarray]]:
    """A ``sample(count)`` over ``n`` frames that ``get(i)`` returns (decoded or read from a
    file), spread evenly, shrunk to :data:`DETECT_LONG_SIDE`."""

    def sample(count: int) -> list[np.ndarray]:
        return [shrink(get(i)) for i in sample_indices(n, count)]

    return sample
