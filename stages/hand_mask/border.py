"""Pixels of a clip that are not picture: a black border that stays black in every frame.

Real egocentric video often carries one: a letterbox bar (HOT3D's RGB view ends in a band of
black rows), the outside of a fisheye circle in the corners, the black wedges of a rotated crop.
Those pixels are black whatever the scene does, so over a clip their brightest value stays near
zero, while the darkest real surface (a near-black floor) brightens as the head moves or under
compression noise. :func:`not_image` finds them once per clip, and the ``keypoints`` backend
never masks them: they are not picture, so no hand or arm is there (a mask there would only
send the inpainting to paint scene over black).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class BorderParams:
    """What counts as a black border (levels are 8-bit values of the brightest channel)."""

    core_level: float = 2.0  # a border's core: pixels no brighter than this in any frame
    rim_level: float = 10.0  # ... grown over the connected pixels no brighter than this in any
    # frame (the compression ringing and the fisheye circle's soft edge beside the core)
    min_fraction: float = 0.002  # a border holds at least this fraction of the frame's pixels
    # in its core and touches the frame's edge (a small black thing in a still view does not)
    min_frames: int = 5  # fewer frames cannot tell a black border from dark picture: none
    # found (one frame of DWM 00013 darkened x0.5 put 2.9% of the frame, 213 hand px, in it)

    def __post_init__(self) -> None:
        problems = []
        if self.min_frames < 1:
            problems.append(f"min_frames must be >= 1, got {self.min_frames}")
        if not 0.0 <= self.core_level <= self.rim_level <= 64.0:
            problems.append(
                f"need 0 <= core_level <= rim_level <= 64, got {self.core_level}, {self.rim_level}"
            )
        if not 0.0 < self.min_fraction <= 1.0:
            problems.append(f"min_fraction must be in (0, 1], got {self.min_fraction}")
        if problems:
            raise ValueError("; ".join(problems))


def not_image(frames: np.ndarray, params: BorderParams | None = None) -> np.ndarray:
    """``(H, W)`` bool: the clip's black border, pixels that are not picture in any frame.

    ``frames (T, H, W, 3)`` uint8. A pixel's brightness is its brightest channel in its brightest
    frame. The border is each 8-connected region of pixels no brighter than ``rim_level`` that
    touches the frame's edge and holds at least ``min_fraction`` of the frame in pixels no
    brighter than ``core_level``. A clip without one, or of fewer than ``min_frames`` frames,
    gives all False.
    """
    p = params or BorderParams()
    h, w = frames.shape[1:3]
    if len(frames) < p.min_frames:
        return np.zeros((h, w), bool)
    brightest = np.zeros((h, w), np.uint8)
    for frame in frames:  # one frame at a time: a clip's max without a (T, H, W) temporary
        np.maximum(brightest, frame.max(axis=2), out=brightest)
    core = brightest <= p.core_level  # (H, W)
    if core.sum() < p.min_fraction * h * w:
        return np.zeros((h, w), bool)
    dark = (brightest <= p.rim_level).astype(np.uint8)  # (H, W)
    count, comp = cv2.connectedComponents(dark, connectivity=8)
    edge = np.zeros((h, w), bool)
    edge[[0, -1], :] = True
    edge[:, [0, -1]] = True
    at_edge = np.zeros(count, bool)
    at_edge[np.unique(comp[edge & (dark > 0)])] = True
    cores = np.bincount(comp[core], minlength=count)  # (count,) core pixels per region
    keep = at_edge & (cores >= p.min_fraction * h * w)
    keep[0] = False  # label 0: the bright pixels
    return keep[comp]
