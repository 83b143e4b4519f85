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

The band must also hold scene the cameras step can pose from (ingest v9): where the hands'
band keeps fewer than :data:`STATIC_MIN_MATCHES` SIFT matches between a sampled frame and the
next source frame outside the hands (:func:`static_matches`), the window moves to the band
nearest the hands among those within :data:`SCENE_TOLERANCE` of the most such matches and
keeping at least :data:`HANDS_KEEP_FRACTION` of the best band's hands (:func:`texture_anchor`).
An upright phone video's hands band over a plain table (the EgoDex portrait variant: 15-16
matches there, 40-44 with the table's far edge and the curtain's hem in view, by encode) was
rejected by cameras otherwise.
"""

from __future__ import annotations

import functools
import importlib.metadata
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
# The scene the cameras need (texture_anchor): SIFT with a low contrast threshold (OpenCV's
# default 0.04 finds under a dozen points on the portrait's table, too few to compare bands),
# nearest-neighbour ratio test, then a RANSAC fundamental matrix between a frame and the next.
STATIC_MIN_MATCHES = 30  # fewer verified matches (median over pairs) in the hands' band: move
# it (twice COLMAP's 15 inliers for a verified pair; set on the EgoDex portrait variant, 16)
HANDS_KEEP_FRACTION = 0.5  # a band moved for the scene keeps this share of the best hand cover
SCENE_TOLERANCE = 0.1  # windows within this share of the most static matches count as equal
SIFT_CONTRAST = 0.01  # SIFT contrast threshold of the static-match count
MATCH_RATIO = 0.8  # Lowe's ratio test of the static-match count
MATCH_RANSAC_PX = 1.0  # fundamental-matrix RANSAC threshold, pixels of the sampled frames
# Per-image detection (a few frames far apart: nothing to track), the full frame plus the
# detector's default lower-frame tiles, no following through misses, and no second pass on
# contrast-stretched dim frames (hands16's pass needs the whole clip's detections; the crop reads a
# few frames: unmeasured there, so ingest keeps its detections as they were).
DETECT_PARAMS = HandLandmarkParams(video_mode=False, track_misses=False, stretch_gain=1.0)


@functools.cache  # one lookup of the package's metadata per process, not one per file unit
def crop_detector() -> str:
    """What the hands crop looks for hands with, for run fingerprints: ``mediapipe <version>``,
    or ``none`` when MediaPipe is not installed (every band then stays at the anchor), so that a
    run resumed where the detector differs ingests again rather than keeping other crops."""
    try:
        return f"mediapipe {importlib.metadata.version('mediapipe')}"
    except importlib.metadata.PackageNotFoundError:
        return "none"


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
    sample: FrameSample,
    what: str,
) -> Anchor:
    """The anchor of a ``src_width x src_height`` source: ``crop_anchor``, or with
    ``crop="hands"`` the window over the hands found on ``sample(SAMPLE_FRAMES)`` (evenly spread
    ``(H, W, 3)`` uint8 RGB source frames; read only when the crop cuts enough to matter); a
    hands' band with too little static scene for the cameras moves (:func:`texture_anchor`,
    against the source frame after each sampled one).
    ``what`` names the source in the log line."""
    anchor = configured(cfg)
    plan = plan_resize(src_width, src_height, cfg.width, cfg.height)
    if cfg.crop != "hands" or cut_fraction(plan) < MIN_CUT_FRACTION:
        return anchor
    frames = sample(SAMPLE_FRAMES)
    try:
        per_frame = frame_hand_boxes(frames)
    except MediaPipeUnavailableError as exc:
        log.warning("%s: crop at anchor %s, hands not looked for: %s", what, anchor, exc)
        return anchor
    boxes = [b for found in per_frame for b in found]
    if not boxes:
        log.info(
            "%s: no hand found on %d sampled frames; crop at anchor (%.2f, %.2f)",
            what,
            len(frames),
            *anchor,
        )
        return anchor
    placed = hands_anchor(plan, boxes, anchor)
    following = sample.following(SAMPLE_FRAMES)
    placed, scene = texture_anchor(plan, frames, following, per_frame, placed)
    crop = plan_resize(src_width, src_height, cfg.width, cfg.height, placed).source_crop
    log.info(
        "%s: %d hands on %d sampled frames; crop anchor (%.3f, %.3f), source pixels %s%s",
        what,
        len(boxes),
        len(frames),
        *placed,
        tuple(round(v, 1) for v in crop),
        scene,
    )
    return placed


def cut_fraction(plan: ResizePlan) -> float:
    """The larger share of a scaled side the crop drops (0 when nothing is cut)."""
    return max(1 - plan.width / plan.scaled_width, 1 - plan.height / plan.scaled_height)


Box = tuple[float, float, float, float]  # x0, y0, x1, y1 as fractions of the frame


def frame_hand_boxes(frames: Sequence[np.ndarray]) -> list[list[Box]]:
    """Per frame of ``frames`` (``(H, W, 3)`` uint8 RGB of one size), the ``(x0, y0, x1, y1)``
    of every hand found on it, as fractions of the frame, each side grown by
    :data:`HAND_MARGIN` of its size. Frames are shrunk to :data:`DETECT_LONG_SIDE` first
    (never enlarged)."""
    if not frames:
        return []
    small = np.stack([shrink(f) for f in frames])  # (K, h, w, 3)
    raw = detect_hand_landmarks(small, DETECT_PARAMS)
    sh, sw = small.shape[1:3]
    boxes: list[list[Box]] = [[] for _ in frames]
    for i, k in zip(*np.nonzero(raw.present), strict=True):
        uv = raw.uv[i, k]  # (21, 2) pixels of the small frame
        lo, hi = uv.min(axis=0), uv.max(axis=0)  # (2,), (2,)
        pad = HAND_MARGIN * (hi - lo)
        lo, hi = lo - pad, hi + pad
        boxes[i].append((lo[0] / sw, lo[1] / sh, hi[0] / sw, hi[1] / sh))
    return boxes


def hands_anchor(
    plan: ResizePlan, boxes: Sequence[tuple[float, float, float, float]], fallback: Anchor
) -> Anchor:
    """The anchor whose window covers the most of ``boxes`` (fractions of the source frame)
    along each axis the crop cuts; ``fallback``'s value along an axis it does not cut."""
    out = list(fallback)
    axes = ((0, plan.scaled_width, plan.width), (1, plan.scaled_height, plan.height))
    for axis, scaled, length in axes:
        slack = scaled - length
        if slack <= 0:
            continue
        out[axis] = place_window(box_spans(boxes, axis, scaled), length, slack)
    return out[0], out[1]


def box_spans(boxes: Sequence[Box] | np.ndarray, axis: int, scaled: int) -> np.ndarray:
    """``(N, 2)`` start and end of each box (fractions of the source frame, clipped to it) along
    ``axis`` (0 = x, 1 = y), in pixels of the frame scaled to ``scaled`` along that axis."""
    arr = np.clip(np.asarray(boxes, dtype=np.float64).reshape(-1, 4), 0.0, 1.0)  # (N, 4)
    return arr[:, [axis, axis + 2]] * scaled


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
    steps, offsets, cover = window_cover(spans, length, slack)
    best = np.flatnonzero(cover >= cover.max() - 1e-9)
    centre = float(spans.mean(axis=0).mean())  # mean of the spans' centres
    return float(steps[best[np.argmin(np.abs(offsets[best] + length / 2 - centre))]])


def window_cover(
    spans: np.ndarray, length: int, slack: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The candidate anchors ``(S,)`` (k / ANCHOR_STEPS), their window offsets ``(S,)`` (scaled
    pixels, as plan_resize floors them) and how much of ``spans (N, 2)`` each window of
    ``length`` covers ``(S,)`` (the sum over spans of the share of each inside)."""
    steps = np.arange(ANCHOR_STEPS + 1) / ANCHOR_STEPS  # (S,) candidate anchors
    offsets = np.floor(steps * slack)  # (S,)
    a, b = spans[None, :, 0], spans[None, :, 1]  # (1, N)
    ends = offsets[:, None] + length  # (S, 1)
    inside = np.clip(np.minimum(b, ends) - np.maximum(a, offsets[:, None]), 0.0, None)
    cover = (inside / np.maximum(b - a, 1e-9)).sum(axis=1)  # (S,)
    return steps, offsets, cover


def texture_anchor(
    plan: ResizePlan,
    frames: Sequence[np.ndarray],
    following: Sequence[np.ndarray | None],
    per_frame: Sequence[Sequence[Box]],
    placed: Anchor,
) -> tuple[Anchor, str]:
    """``placed`` (the hands' anchor), or a band with more static scene for the cameras, and
    a note for the log line.

    Along the axis the crop cuts, each candidate window (k / ANCHOR_STEPS) counts
    :func:`static_matches` inside it. If the hands' window has at least
    :data:`STATIC_MIN_MATCHES`, it stays. Otherwise, of the windows covering at least
    :data:`HANDS_KEEP_FRACTION` of the best window's hands (the hand boxes of ``per_frame``),
    those within :data:`SCENE_TOLERANCE` of the most matches count as equal, and the one
    nearest the hands' window is taken (when it has more matches than the hands' window).

    The tolerance is there for the same reason as the steps: the match counts of neighbouring
    windows differ by a few matches from encode to encode. With the plain most-matches window
    the three encodes of the bench's portrait variant got 0.5625, 0.625 and 0.5625; with it,
    0.625 each."""
    axis = 1 if plan.scaled_height - plan.height > plan.scaled_width - plan.width else 0
    scaled, length = (plan.scaled_height, plan.height) if axis else (plan.scaled_width, plan.width)
    slack = scaled - length
    pairs = [
        (f, g, b) for f, g, b in zip(frames, following, per_frame, strict=True) if g is not None
    ]
    if slack <= 0 or not pairs:
        return placed, ""
    spans = box_spans([b for found in per_frame for b in found], axis, scaled)  # (N, 2) pixels
    steps, offsets, cover = window_cover(spans, length, slack)
    counts = []  # per pair: (S,) matches inside each window
    for f, g, found in pairs:
        pos = static_matches(f, g, found)[..., axis] * scaled  # (M, 2) scaled pixels, both frames
        inside = (pos[None] >= offsets[:, None, None]) & (
            pos[None] < offsets[:, None, None] + length
        )
        counts.append(inside.all(axis=2).sum(axis=1))  # (S,)
    matches = np.median(np.stack(counts), axis=0)  # (S,)
    here = int(np.argmin(np.abs(steps - placed[axis])))
    note = f"; {matches[here]:.0f} static matches in the band"
    if matches[here] >= STATIC_MIN_MATCHES:
        return placed, note
    keeps = np.flatnonzero(cover >= HANDS_KEEP_FRACTION * cover.max() - 1e-9)
    near_best = matches[keeps] >= (1 - SCENE_TOLERANCE) * matches[keeps].max() - 1e-9
    best = keeps[near_best]
    pick = int(best[np.argmin(np.abs(best - here))])
    if matches[pick] <= matches[here]:
        return placed, note + f" (under {STATIC_MIN_MATCHES}, no better band keeps the hands)"
    out = list(placed)
    out[axis] = float(steps[pick])
    return (out[0], out[1]), (
        f"{note} (under {STATIC_MIN_MATCHES}): moved from {steps[here]:.3f} to the band with "
        f"{matches[pick]:.0f}, hands cover {cover[pick]:.1f} of {cover.max():.1f}"
    )


def static_matches(frame: np.ndarray, following: np.ndarray, boxes: Sequence[Box]) -> np.ndarray:
    """``(M, 2, 2)``: the SIFT matches between ``frame`` and ``following`` (the next source
    frame, ``(H, W, 3)`` uint8 RGB, the same size) outside the hand ``boxes`` that a RANSAC
    fundamental matrix keeps, as ``(x, y)`` fractions of the frame in each of the two frames
    (``[:, 0]`` in ``frame``, ``[:, 1]`` in ``following``). Empty when too few match."""
    h, w = frame.shape[:2]
    mask = np.full((h, w), 255, np.uint8)
    for x0, y0, x1, y1 in boxes:
        mask[
            max(0, int(y0 * h)) : int(np.ceil(y1 * h)), max(0, int(x0 * w)) : int(np.ceil(x1 * w))
        ] = 0
    sift = cv2.SIFT_create(contrastThreshold=SIFT_CONTRAST)
    kp1, d1 = sift.detectAndCompute(cv2.cvtColor(frame, cv2.COLOR_RGB2GRAY), mask)
    kp2, d2 = sift.detectAndCompute(cv2.cvtColor(following, cv2.COLOR_RGB2GRAY), mask)
    empty = np.zeros((0, 2, 2))
    if d1 is None or d2 is None or len(kp1) < 8 or len(kp2) < 8:
        return empty
    knn = cv2.BFMatcher(cv2.NORM_L2).knnMatch(d1, d2, k=2)
    good = [m[0] for m in knn if len(m) == 2 and m[0].distance < MATCH_RATIO * m[1].distance]
    if len(good) < 8:
        return empty
    a = np.float64([kp1[m.queryIdx].pt for m in good])  # (G, 2) pixels
    b = np.float64([kp2[m.trainIdx].pt for m in good])  # (G, 2)
    _, inliers = cv2.findFundamentalMat(a, b, cv2.FM_RANSAC, MATCH_RANSAC_PX, 0.999)
    if inliers is None:
        return empty
    keep = inliers.ravel() > 0
    return np.stack([a[keep], b[keep]], axis=1) / np.array([w, h])  # (M, 2, 2)


class FrameSample:
    """A ``sample(count)`` for :func:`choose_anchor` that also gives the source frame after
    each sampled one (:meth:`following`), which the static-scene count matches against.
    ``read(count)`` returns ``(frame, next frame or None)`` pairs; it runs once per count."""

    def __init__(self, read: Callable[[int], list[tuple[np.ndarray, np.ndarray | None]]]) -> None:
        self._read = read
        self._pairs: dict[int, list[tuple[np.ndarray, np.ndarray | None]]] = {}

    def pairs(self, count: int) -> list[tuple[np.ndarray, np.ndarray | None]]:
        """The ``(frame, next frame or None)`` pairs of ``count`` spread samples."""
        if count not in self._pairs:
            self._pairs[count] = self._read(count)
        return self._pairs[count]

    def __call__(self, count: int) -> list[np.ndarray]:
        """``count`` frames spread evenly over the source (fewer where it has fewer)."""
        return [f for f, _ in self.pairs(count)]

    def following(self, count: int) -> list[np.ndarray | None]:
        """The source frame after each of :meth:`__call__`'s frames (None after the last)."""
        return [g for _, g in self.pairs(count)]


def sample_video(path: Path, info: VideoFileInfo) -> FrameSample:
    """A :class:`FrameSample` of a video file: ``count`` frames spread evenly over its declared
    length and the frame after each, shrunk to :data:`DETECT_LONG_SIDE`. Videos longer than
    :data:`SEEK_AFTER_S` seek to each frame; shorter ones (or when seeking fails) are decoded
    in one pass. A decoding error ends the sample with the frames read (ingest itself reports
    the file's errors)."""

    def read(count: int) -> list[tuple[np.ndarray, np.ndarray | None]]:
        if info.duration_s > SEEK_AFTER_S:
            try:
                return _seek_frames(path, info, count)
            except MediaError as exc:
                log.info("%s: seeking for crop samples failed (%s); one pass instead", path, exc)
        return _pass_frames(path, info, count)

    return FrameSample(read)


def shrink(frame: np.ndarray) -> np.ndarray:
    """``frame`` with its longer side at most :data:`DETECT_LONG_SIDE` (area average)."""
    h, w = frame.shape[:2]
    s = DETECT_LONG_SIDE / max(h, w)
    if s >= 1.0:
        return frame
    return cv2.resize(frame, (round(w * s), round(h * s)), interpolation=cv2.INTER_AREA)


def _seek_frames(
    path: Path, info: VideoFileInfo, count: int
) -> list[tuple[np.ndarray, np.ndarray | None]]:
    """The first frame from half a frame before each of ``count`` evenly spread times on
    (seeking: :func:`~egosim.pipeline.media.iter_video_file` with ``start``), the same frames
    as :func:`_pass_frames` picks by index, each with the frame after it."""
    out: list[tuple[np.ndarray, np.ndarray | None]] = []
    for k in range(count):
        start = info.start_s + (k + 0.5) * info.duration_s / count
        got: list[np.ndarray] = []
        for _, frame in iter_video_file(path, start=start):
            got.append(shrink(frame))
            if len(got) == 2:
                break
        if got:
            out.append((got[0], got[1] if len(got) > 1 else None))
    return out


def _pass_frames(
    path: Path, info: VideoFileInfo, count: int
) -> list[tuple[np.ndarray, np.ndarray | None]]:
    """``count`` frames at evenly spread indices of the declared frame count (else of the
    duration times the rate; else the first ``count`` frames a second apart), each with the
    frame after it, one pass."""
    total = info.num_frames or round(info.duration_s * info.fps)
    if total > 0:
        wanted = sample_indices(total, count)
    else:
        wanted = [round(k * info.fps) for k in range(count)]
    firsts: dict[int, np.ndarray] = {}
    nexts: dict[int, np.ndarray] = {}
    try:
        for index, (_, frame) in enumerate(iter_video_file(path)):
            if index in wanted:
                firsts[index] = shrink(frame)
            if index - 1 in firsts:
                nexts[index - 1] = shrink(frame)
            if index > wanted[-1]:
                break
    except MediaError as exc:
        log.info("%s: crop samples stop after %d frames: %s", path, len(firsts), exc)
    return [(firsts[i], nexts.get(i)) for i in wanted if i in firsts]


def sample_indices(n: int, count: int) -> list[int]:
    """Up to ``count`` distinct indices spread evenly over ``0..n-1`` (mid-points of ``count``
    equal parts)."""
    return sorted({min(n - 1, int((k + 0.5) * n / count)) for k in range(count)}) if n else []


def sample_frames(n: int, get: Callable[[int], np.ndarray]) -> FrameSample:
    """A :class:`FrameSample` over ``n`` frames that ``get(i)`` returns (decoded or read from a
    file): spread evenly, each with the frame after it, shrunk to :data:`DETECT_LONG_SIDE`."""

    def read(count: int) -> list[tuple[np.ndarray, np.ndarray | None]]:
        return [
            (shrink(get(i)), shrink(get(i + 1)) if i + 1 < n else None)
            for i in sample_indices(n, count)
        ]

    return FrameSample(read)
