"""Make source frames into clips: resample in time, resize and crop, keep intrinsics consistent.

Time: target frames sit at ``k / fps`` seconds from the source's first frame; each takes the
source frame nearest in time (no source fps is assumed; timestamps decide). Long sources are cut
into windows of ``num_frames`` target frames, a new window every ``stride`` target frames.

Space: the frame is scaled to cover the target size, then centre-cropped; the intrinsics are
scaled and shifted the same way (:func:`egosim.pipeline.geometry.scale_intrinsics`,
:func:`~egosim.pipeline.geometry.crop_intrinsics`).
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from dataclasses import dataclass

import cv2
import numpy as np

from egosim.pipeline.geometry import crop_intrinsics, scale_intrinsics


@dataclass(frozen=True)
class ResizePlan:
    """How one source size maps onto the target size."""

    scale: float  # uniform scale factor applied first
    crop_x: int  # left edge of the crop in the scaled image
    crop_y: int  # top edge of the crop in the scaled image
    src_width: int  # source width
    src_height: int  # source height
    scaled_width: int  # width after scaling
    scaled_height: int  # height after scaling
    width: int  # target width
    height: int  # target height

    def apply(self, frame: np.ndarray, nearest: bool = False) -> np.ndarray:
        """Resize and crop one ``(h, w[, c])`` image to ``(height, width[, c])``.

        ``nearest`` keeps values exact (masks, labels, depth) instead of interpolating.
        """
        size = (self.scaled_width, self.scaled_height)
        interp = cv2.INTER_AREA if self.scale < 1 else cv2.INTER_LINEAR
        if nearest:
            interp = cv2.INTER_NEAREST
        scaled = cv2.resize(frame, size, interpolation=interp)
        return scaled[
            self.crop_y : self.crop_y + self.height, self.crop_x : self.crop_x + self.width
        ]

    def intrinsics(self, source_intrinsics: np.ndarray) -> np.ndarray:
        """Intrinsics of the output given those of the source frame."""
        sx = self.scaled_width / self.src_width
        sy = self.scaled_height / self.src_height
        scaled = scale_intrinsics(source_intrinsics, sx, sy)
        return crop_intrinsics(scaled, self.crop_x, self.crop_y)


def plan_resize(src_width: int, src_height: int, width: int, height: int) -> ResizePlan:
    """Scale to cover ``width x height`` and centre-crop (aspect ratio kept, no padding)."""
    scale = max(width / src_width, height / src_height)
    scaled_w = max(width, round(src_width * scale))
    scaled_h = max(height, round(src_height * scale))
    return ResizePlan(
        scale=scale,
        crop_x=(scaled_w - width) // 2,
        crop_y=(scaled_h - height) // 2,
        src_width=src_width,
        src_height=src_height,
        scaled_width=scaled_w,
        scaled_height=scaled_h,
        width=width,
        height=height,
    )


@dataclass(frozen=True)
class Window:
    """One clip's worth of resampled frames."""

    index: int  # window number within the source
    frames: np.ndarray  # (T, H, W, 3) uint8, already resized
    timestamps: np.ndarray  # (T,) target times in seconds from the source's first frame
    source_indices: np.ndarray  # (T,) index of each chosen source frame


def resample_windows(
    frames: Iterable[tuple[float, np.ndarray]],
    fps: float,
    num_frames: int,
    stride: int,
    max_windows: int = 0,
) -> Iterator[Window]:
    """Stream ``(time, frame)`` pairs into windows of ``num_frames`` frames at ``fps``.

    Memory stays bounded by one window. Frames are used as given (resize them first).
    """
    stride = stride or num_frames
    kept: dict[int, tuple[float, int, np.ndarray]] = {}  # target index -> (time, src idx, frame)
    next_target = 0
    window = 0
    t0: float | None = None
    prev: tuple[float, int, np.ndarray] | None = None
    for src_index, (time, frame) in enumerate(frames):
        if t0 is None:
            t0 = time
        time -= t0
        current = (time, src_index, frame)
        while next_target / fps <= time:
            target_time = next_target / fps
            pick = current
            if prev is not None and abs(prev[0] - target_time) <= abs(time - target_time):
                pick = prev
            start = window * stride
            if next_target >= start:
                kept[next_target] = (target_time, pick[1], pick[2])
            next_target += 1
            if next_target == start + num_frames:
                yield _make_window(window, [kept[i] for i in range(start, start + num_frames)])
                window += 1
                if max_windows and window >= max_windows:
                    return
                new_start = window * stride
                kept = {k: v for k, v in kept.items() if k >= new_start}
        prev = current


def _make_window(index: int, picks: list[tuple[float, int, np.ndarray]]) -> Window:
    return Window(
        index=index,
        frames=np.stack([p[2] for p in picks]),
        timestamps=np.array([p[0] for p in picks], dtype=np.float64),
        source_indices=np.array([p[1] for p in picks], dtype=np.int64),
    )
