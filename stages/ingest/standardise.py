"""Make source frames into clips: the clip policy in time, then resize and crop in space.

Time (the clip policy, :class:`WindowPolicy`):

- **Rate.** Target frames sit at ``k / fps`` seconds from the source's first frame; each takes
  the source frame nearest in time (timestamps decide, no source fps is assumed). A source
  slower than ``fps`` is never upsampled: it keeps its own rate, every source frame is one clip
  frame, the clip's fps is the source's and its timestamps are the source frames' own times.
- **Full windows.** Long sources are cut into windows of ``num_frames`` frames, a new window
  every ``stride`` frames (of the clip's rate).
- **Short sources.** A source that gives fewer than ``num_frames`` frames gives one clip of the
  longest ``1 + 4k`` frames it holds (the Wan VAE's latent layout: the first frame alone, then
  groups of :data:`VAE_TEMPORAL_FACTOR`), when that is at least ``min_frames``; below that it is
  rejected with a reason naming the source, its duration and the minimum.
- **Tail.** With ``tail="keep"``, after the last full window the window that would have come
  next (starting ``stride`` after the last one) gives one more clip of the longest ``1 + 4k``
  frames that remain, when at least ``min_frames``; ``tail="drop"`` never makes one.

Every window records the index of each of its frames in the source and what the policy did
(``full``, ``short`` or ``tail``).

Space: the frame is scaled to cover the target size, then cropped to a window placed by the
config's crop anchor (the centre, or over the hands: :mod:`egosim.stages.ingest.crop_anchor`);
the intrinsics are scaled and shifted the same way
(:func:`egosim.pipeline.geometry.scale_intrinsics`,
:func:`~egosim.pipeline.geometry.crop_intrinsics`) and each clip records the window in source
pixels (``source_crop``).
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from typing import Literal

import numpy as np

from egosim.pipeline.stage import ClipRejected
from egosim.stages.common.frame_plan import (  # shared with depth_camera's source track
    RATE_TOLERANCE,
    ClipFrame,
    targets_reached,
)

VAE_TEMPORAL_FACTOR = 4  # Wan VAE: latent frame 0 is pixel frame 0, then one per 4 frames
ClipKind = Literal["full", "short", "tail"]
TailPolicy = Literal["keep", "drop"]


def longest_model_clip(available: int) -> int:
    """The most ``1 + 4k`` frames within ``available`` frames (0 when none)."""
    if available < 1:
        return 0
    return 1 + VAE_TEMPORAL_FACTOR * ((available - 1) // VAE_TEMPORAL_FACTOR)


@dataclass(frozen=True)
class WindowPolicy:
    """How a source's frames become clips in time (see the module docstring for the rules)."""

    fps: float  # target frames per second; a slower source keeps its own rate
    num_frames: int  # frames of a full window
    min_frames: int = 1  # fewest frames of a short or tail clip (which are 1 + 4k long)
    stride: int = 0  # frames between window starts, at the clip's rate; 0 = num_frames
    tail: TailPolicy = "keep"  # keep: the remainder after the last full window may give a clip
    max_windows: int = 0  # clips kept per source; 0 = all
    preset: str = ""  # name of the ingest preset, recorded in each clip's policy

    def __post_init__(self) -> None:
        problems = []
        if not self.fps > 0:
            problems.append(f"fps must be > 0, got {self.fps}")
        if self.num_frames < 1:
            problems.append(f"num_frames must be >= 1, got {self.num_frames}")
        if self.min_frames < 1:
            problems.append(f"min_frames must be >= 1, got {self.min_frames}")
        if self.stride < 0 or self.max_windows < 0:
            problems.append(
                f"stride and max_windows must be >= 0, got {self.stride}, {self.max_windows}"
            )
        if self.tail not in ("keep", "drop"):
            problems.append(f"tail must be 'keep' or 'drop', got {self.tail!r}")
        if problems:
            raise ValueError("; ".join(problems))

    @property
    def minimum(self) -> int:
        """Fewest frames of any clip: ``min_frames``, or ``num_frames`` when that is smaller."""
        return min(self.min_frames, self.num_frames)

    def clip_fps(self, source_fps: float | None) -> float:
        """The clip's rate: the target, or the source's own when the source is slower."""
        if (
            source_fps is not None
            and source_fps > 0
            and source_fps < self.fps * (1 - RATE_TOLERANCE)
        ):
            return float(source_fps)
        return float(self.fps)

    def short_length(self, available: int) -> int:
        """Frames of a short or tail clip from ``available`` frames; 0 when below the minimum."""
        n = longest_model_clip(min(available, self.num_frames - 1))
        return n if n >= self.min_frames else 0

    def label(self, kind: ClipKind) -> str:
        """The ``clip_policy`` value of a clip: ``kind`` and the preset, e.g. ``short:egosim``."""
        return f"{kind}:{self.preset}" if self.preset else kind


@dataclass(frozen=True)
class Window:
    """One clip's worth of frames, chosen by the clip policy."""

    index: int  # window number within the source
    frames: np.ndarray  # (T, H, W, 3) uint8, already resized
    timestamps: np.ndarray  # (T,) seconds from the source's first frame
    source_indices: np.ndarray  # (T,) index of each chosen source frame
    fps: float  # the clip's frame rate (the target, or the slower source's own)
    kind: ClipKind  # full: num_frames window; short: whole short source; tail: the remainder


def _window(
    kept: dict[int, ClipFrame], index: int, start: int, n: int, fps: float, kind: ClipKind
) -> Window:
    """Window ``index``: the ``n`` kept clip frames from clip frame ``start``."""
    picks = [kept[i] for i in range(start, start + n)]
    return Window(
        index=index,
        frames=np.stack([p[2] for p in picks]),
        timestamps=np.array([p[0] for p in picks], dtype=np.float64),
        source_indices=np.array([p[1] for p in picks], dtype=np.int64),
        fps=fps,
        kind=kind,
    )


def _too_short(
    what: str, count: int, duration: float, made: int, fps: float, policy: WindowPolicy
) -> ClipRejected:
    """The rejection of a source of ``count`` frames over ``duration`` s that gave ``made``."""
    minimum = policy.minimum
    return ClipRejected(
        f"{what} is shorter than one clip: {count} source frame(s) over {duration:.2f} s "
        f"give {made} frame(s) at {fps:g} fps; the minimum is {minimum} frames "
        f"({(minimum - 1) / fps:.2f} s at {fps:g} fps), a full clip {policy.num_frames}"
    )


def resample_windows(
    frames: Iterable[tuple[float, np.ndarray]],
    policy: WindowPolicy,
    source_fps: float | None = None,
    what: str = "source",
) -> Iterator[Window]:
    """Stream ``(time, frame)`` pairs into the windows that ``policy`` makes of them.

    ``source_fps`` is the source's nominal rate (None: treat it as at least the target). Memory
    stays bounded by one window. Frames are used as given (resize them first). Raises
    :class:`~egosim.pipeline.stage.ClipRejected` naming ``what``, its duration and the minimum
    when the source gives no clip at all.
    """
    fps = policy.clip_fps(source_fps)
    keep_rate = fps != policy.fps
    num, stride = policy.num_frames, policy.stride or policy.num_frames
    kept: dict[int, ClipFrame] = {}  # clip index -> (time, src idx, frame)
    next_target = 0  # the next clip-rate frame index to fill
    window = 0  # windows made so far
    count = 0  # source frames seen
    t0: float | None = None
    last_time = 0.0
    prev: ClipFrame | None = None

    for src_index, (time, frame) in enumerate(frames):
        count += 1
        if t0 is None:
            t0 = time
        time -= t0
        last_time = time
        current = (time, src_index, frame)
        start = window * stride
        if keep_rate:  # every source frame is a clip frame, at its own time
            picks = [(next_target, current)]
        else:
            picks = targets_reached(current, prev, next_target, fps)
        for target, (t, idx, img) in picks:
            if target >= start:
                kept[target] = (t, idx, img)
            next_target = target + 1
            if next_target == start + num:
                yield _window(kept, window, start, num, fps, "full")
                window += 1
                if policy.max_windows and window >= policy.max_windows:
                    return
                start = window * stride
                kept = {k: v for k, v in kept.items() if k >= start}
        prev = current

    # The stream ended: a short source's one clip, or the tail after the last full window.
    start = window * stride
    n = policy.short_length(next_target - start)
    if window == 0 and n:
        yield _window(kept, 0, 0, n, fps, "short")
    elif window and n and policy.tail == "keep":
        yield _window(kept, window, start, n, fps, "tail")
    elif window == 0:
        raise _too_short(what, count, last_time, next_target, fps, policy)
