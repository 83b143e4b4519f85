"""Colour refinement of a keypoint-capsule mask: GrabCut seeded from the skeleton.

The capsule mask is only as good as its average radii and its guessed forearm direction. A
colour model fixes both: Gaussian-mixture colour models of hand and background are learned from
the image itself (OpenCV's GrabCut), seeded with

- certainly hand: the thin skeleton core (pixels under the bones, the palm centre, the start of
  the forearm);
- probably hand: the capsule mask;
- probably background: a band around the capsule mask, ``band`` pixels wide;
- background: everything else in the region of interest.

GrabCut then relabels the two "probably" regions with the learned colour models and a contrast-
sensitive smoothness term. Work happens in the bounding box of the band, downscaled so that its
longer side is at most ``max_side`` pixels (speed), and the result is upscaled back.
"""

from __future__ import annotations

import cv2
import numpy as np


class ColourModelError(ValueError):
    """Inputs to the colour refinement disagree in shape or type."""


def refine_with_colour(
    image: np.ndarray,
    mask: np.ndarray,
    core: np.ndarray,
    band: int,
    iterations: int = 3,
    max_side: int = 256,
    min_kept: float = 0.5,
) -> np.ndarray:
    """Refine ``mask (H, W)`` uint8 with GrabCut on ``image (H, W, 3)`` uint8 RGB.

    ``core (H, W)`` uint8 marks certain hand pixels; ``band`` is the width in pixels of the
    probably-background band around ``mask``. Returns the refined ``(H, W)`` uint8 mask (1 =
    hand). An empty ``mask`` is returned as is; pixels of ``core`` always stay hand.
    """
    if image.ndim != 3 or image.shape[:2] != mask.shape or mask.shape != core.shape:
        raise ColourModelError(
            f"image (H, W, 3), mask and core (H, W) must agree, got {image.shape}, "
            f"{mask.shape}, {core.shape}"
        )
    if not mask.any() or not core.any():
        return mask.copy()
    height, width = mask.shape
    band = max(1, int(band))
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * band + 1, 2 * band + 1))
    near = cv2.dilate(mask, kernel)  # (H, W) capsule mask plus the band
    ys, xs = np.nonzero(near)
    y0, y1 = max(0, ys.min() - band), min(height, ys.max() + band + 1)
    x0, x1 = max(0, xs.min() - band), min(width, xs.max() + band + 1)
    labels = np.full((y1 - y0, x1 - x0), cv2.GC_BGD, np.uint8)  # (h, w) region of interest
    labels[near[y0:y1, x0:x1] > 0] = cv2.GC_PR_BGD
    labels[mask[y0:y1, x0:x1] > 0] = cv2.GC_PR_FGD
    labels[core[y0:y1, x0:x1] > 0] = cv2.GC_FGD
    crop = cv2.cvtColor(np.ascontiguousarray(image[y0:y1, x0:x1]), cv2.COLOR_RGB2BGR)
    factor = min(1.0, max_side / max(crop.shape[:2]))
    if factor < 1.0:
        size = (max(1, round(crop.shape[1] * factor)), max(1, round(crop.shape[0] * factor)))
        crop = cv2.resize(crop, size, interpolation=cv2.INTER_AREA)
        small = cv2.resize(labels, size, interpolation=cv2.INTER_NEAREST)
    else:
        small = labels
    if not np.any(small == cv2.GC_BGD) and not np.any(small == cv2.GC_PR_BGD):
        return mask.copy()  # nothing to learn a background from
    bgd_model = np.zeros((1, 65), np.float64)
    fgd_model = np.zeros((1, 65), np.float64)
    cv2.setRNGSeed(0)
    cv2.grabCut(crop, small, None, bgd_model, fgd_model, iterations, cv2.GC_INIT_WITH_MASK)
    hand = ((small == cv2.GC_FGD) | (small == cv2.GC_PR_FGD)).astype(np.uint8)  # (h', w')
    if factor < 1.0:
        hand = cv2.resize(hand, (x1 - x0, y1 - y0), interpolation=cv2.INTER_LINEAR)
    out = np.zeros_like(mask)
    out[y0:y1, x0:x1] = hand
    out |= core
    if out.sum() < min_kept * mask.sum():
        return mask.copy()
    return out
