"""Ingest's rules from source frames to clip frames, shared by ``ingest`` and ``depth_camera``'s
source track (which re-reads a source and must pick and resize exactly the frames ingest did):
the rate rule (:func:`targets_reached`: each target time ``k / fps`` takes the nearer of two
neighbouring source frames) and the spatial rule (:func:`plan_resize`: scale to cover, centre
crop). Stages import no other stage, so these live here (``egosim.stages.ingest.standardise``
uses them too).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from egosim.pipeline.geometry import crop_intrinsics, scale_intrinsics

RATE_TOLERANCE = 1e-6  # relative: a source within this of the target fps counts as at the target
TIME_TOLERANCE_S = 1e-6  # a target time this much after a frame's timestamp still reaches it
IMAGE_SUFFIXES = frozenset({".jpg", ".jpeg", ".png", ".bmp", ".webp"})  # frame-folder images


def frame_files(folder: Path) -> list[Path]:
    """The images of a frame folder (:data:`IMAGE_SUFFIXES`) in frame order: names sorted with
    their digit runs compared as numbers, so ``ffmpeg``'s ``%d.jpg`` (1, 2, ..., 10) and zero-padded
    names (0001, 0002, ...) both keep time order (a plain sort put 10 before 2)."""
    images = (p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)
    return sorted(images, key=_natural_key)


def _natural_key(path: Path) -> tuple[tuple[int | str, ...], str]:
    """Sort key of a file name: text parts lower-cased, digit runs as numbers, name as tie-break.

    ``re.split`` with one group alternates text and digit runs, text first (maybe empty), so
    every name has text at even and numbers at odd positions: ints only meet ints. The digit
    runs are told by position, not by ``str.isdigit``, which is also true of characters ``int``
    refuses (a superscript ``²`` in a name raised ValueError).
    """
    parts = re.split(r"(\d+)", path.name)
    return tuple(int(t) if i % 2 else t.lower() for i, t in enumerate(parts)), path.name


ClipFrame = tuple[float, int, np.ndarray]  # one clip frame: (time, source frame index, frame)


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


def targets_reached(
    current: ClipFrame, prev: ClipFrame | None, next_target: int, fps: float
) -> list[tuple[int, ClipFrame]]:
    """The clip frames from ``next_target`` on whose times the ``current`` source frame reaches.

    Each takes whichever of ``prev`` and ``current`` is nearer in time (``prev`` on a tie) and
    keeps its target time.
    """
    time = current[0]
    picks: list[tuple[int, ClipFrame]] = []
    while next_target + len(picks) <= time * fps + TIME_TOLERANCE_S * fps:
        target_time = (next_target + len(picks)) / fps
        pick = current
        if prev is not None and abs(prev[0] - target_time) <= abs(time - target_time):
            pick = prev
        picks.append((next_target + len(picks), (target_time, pick[1], pick[2])))
    return picks
