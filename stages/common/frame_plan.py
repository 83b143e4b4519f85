"""Ingest's rules from source frames to clip frames, shared by ``ingest`` and ``depth_camera``'s
source track (which re-reads a source and must pick and resize exactly the frames ingest did):
the rate rule (:func:`targets_reached`: each target time ``k / fps`` takes the nearer of two
neighbouring source frames) and the spatial rule (:func:`plan_resize`: scale to cover, then crop
a window placed by an anchor, the centre by default). The crop a clip was cut with is recorded
in source pixels (:attr:`ResizePlan.source_crop`, the clips column ``source_crop``) and
:func:`plan_from_crop` rebuilds the same plan from it. Stages import no other stage, so these
live here (``egosim.stages.ingest.standardise`` uses them too).
"""

from __future__ import annotations

import math
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
Anchor = tuple[float, float]  # where the crop window sits in the scaled frame: x, y in [0, 1]
CENTRE: Anchor = (0.5, 0.5)  # the centre crop
CROP_TOLERANCE_PX = 0.01  # a recorded crop may be off a whole scaled pixel by this (float round)


class CropError(ValueError):
    """A recorded crop does not fit the source and clip sizes it is applied to."""


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

    @property
    def source_crop(self) -> tuple[float, float, float, float]:
        """``(x0, y0, x1, y1)``: the region of the source frame the output shows, in source
        pixels (edges, so the whole frame of a ``W x H`` source is ``(0, 0, W, H)``)."""
        sx = self.src_width / self.scaled_width
        sy = self.src_height / self.scaled_height
        return (
            self.crop_x * sx,
            self.crop_y * sy,
            (self.crop_x + self.width) * sx,
            (self.crop_y + self.height) * sy,
        )

    @property
    def cuts(self) -> bool:
        """Whether the crop drops any scaled pixels (else the anchor changes nothing)."""
        return self.scaled_width > self.width or self.scaled_height > self.height

    def intrinsics(self, source_intrinsics: np.ndarray) -> np.ndarray:
        """Intrinsics of the output given those of the source frame."""
        sx = self.scaled_width / self.src_width
        sy = self.scaled_height / self.src_height
        scaled = scale_intrinsics(source_intrinsics, sx, sy)
        return crop_intrinsics(scaled, self.crop_x, self.crop_y)


def plan_resize(
    src_width: int, src_height: int, width: int, height: int, anchor: Anchor = CENTRE
) -> ResizePlan:
    """Scale to cover ``width x height`` and crop (aspect ratio kept, no padding).

    ``anchor`` places the crop window in the scaled frame: ``(0, 0)`` its top-left corner,
    ``(1, 1)`` its bottom-right, ``(0.5, 0.5)`` the centre (``(scaled - size) // 2``). Raises
    :class:`CropError` for an anchor outside ``[0, 1]``.
    """
    ax, ay = float(anchor[0]), float(anchor[1])
    if not (0.0 <= ax <= 1.0 and 0.0 <= ay <= 1.0):
        raise CropError(f"crop anchor must be two fractions in [0, 1], got {tuple(anchor)}")
    scale = max(width / src_width, height / src_height)
    scaled_w = max(width, round(src_width * scale))
    scaled_h = max(height, round(src_height * scale))
    return ResizePlan(
        scale=scale,
        crop_x=math.floor(ax * (scaled_w - width)),  # 0.5: (scaled_w - width) // 2 exactly
        crop_y=math.floor(ay * (scaled_h - height)),
        src_width=src_width,
        src_height=src_height,
        scaled_width=scaled_w,
        scaled_height=scaled_h,
        width=width,
        height=height,
    )


def plan_from_crop(
    src_width: int,
    src_height: int,
    width: int,
    height: int,
    source_crop: tuple[float, ...] | np.ndarray | None,
) -> ResizePlan:
    """The plan that cut ``source_crop`` (a clip's recorded ``(x0, y0, x1, y1)``, source pixels)
    from a ``src_width x src_height`` source into ``width x height`` frames; the centre crop for
    None (rows written before the crop was recorded). Raises :class:`CropError` when the crop
    is not one this scale makes of this source (another size, or a window off the scaled grid).
    """
    plan = plan_resize(src_width, src_height, width, height)
    if source_crop is None:
        return plan
    x0, y0, x1, y1 = (float(v) for v in source_crop)
    fx = plan.scaled_width / src_width  # scaled pixels per source pixel
    fy = plan.scaled_height / src_height
    crop_x, crop_y = round(x0 * fx), round(y0 * fy)
    slack_x, slack_y = plan.scaled_width - width, plan.scaled_height - height
    if not (
        0 <= crop_x <= slack_x
        and 0 <= crop_y <= slack_y
        and abs(x0 * fx - crop_x) <= CROP_TOLERANCE_PX
        and abs(y0 * fy - crop_y) <= CROP_TOLERANCE_PX
        and abs(x1 * fx - (crop_x + width)) <= CROP_TOLERANCE_PX
        and abs(y1 * fy - (crop_y + height)) <= CROP_TOLERANCE_PX
    ):
        raise CropError(
            f"recorded crop {tuple(source_crop)} is not a {width}x{height} window of the "
            f"{plan.scaled_width}x{plan.scaled_height} scaled {src_width}x{src_height} source"
        )
    return ResizePlan(
        scale=plan.scale,
        crop_x=crop_x,
        crop_y=crop_y,
        src_width=src_width,
        src_height=src_height,
        scaled_width=plan.scaled_width,
        scaled_height=plan.scaled_height,
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
