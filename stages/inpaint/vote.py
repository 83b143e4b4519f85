"""A per-pixel vote of several fills of the same hole: the colour two of three agree on.

The depth fill (later frames reprojected through an estimated depth and estimated poses) can
be far off where the cameras are (blurred head motion, a plane sweep that matched the moving
hand): on the real DWM clip 00013 it pasted a dark hand-shaped patch and scored 2.9 dB below
OpenCV Telea. No single test on the ring tells that apart from a good fill, but two other fills
that fail in other ways do: the image-aligned fill (homographies, no depth) and Telea itself
(smooth, never far off near the hole's edge). Each hole pixel takes the per-channel **median**
of the fills: where the depth fill agrees with either of the others it stands, where it is off
the colour falls between the other two. No threshold is involved.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from egosim.stages.inpaint.reproject_fill import FillResult, InpaintInputError


def median_vote(fills: Sequence[FillResult]) -> FillResult:
    """Per-channel median, per hole pixel, of ``fills`` (all of the same frame and hole).

    Outside the hole the first fill's pixels are kept. Each hole pixel's ``fill_source`` and
    ``source_frame`` are those of the fill whose colour lies nearest (L1) the median colour (the
    earliest on a tie), so the record still says where the colour mostly came from.
    """
    if not fills:
        raise InpaintInputError("median_vote needs at least one fill")
    first = fills[0]
    for other in fills[1:]:
        if other.image.shape != first.image.shape or not np.array_equal(other.filled, first.filled):
            raise InpaintInputError("fills to vote on must share the frame's size and the hole")
    hole = first.filled  # (H, W) bool
    if len(fills) == 1 or not hole.any():
        return first
    colours = np.stack([f.image[hole] for f in fills]).astype(np.float32)  # (F, M, 3)
    median = np.median(colours, axis=0)  # (M, 3)
    nearest = np.argmin(np.abs(colours - median[None]).sum(axis=2), axis=0)  # (M,)
    image = first.image.copy()
    image[hole] = np.clip(np.round(median), 0, 255).astype(np.uint8)
    sources = np.stack([f.fill_source[hole] for f in fills])  # (F, M)
    frames = np.stack([f.source_frame[hole] for f in fills])  # (F, M)
    fill_source = first.fill_source.copy()
    source_frame = first.source_frame.copy()
    pick = np.arange(hole.sum())  # (M,)
    fill_source[hole] = sources[nearest, pick]
    source_frame[hole] = frames[nearest, pick]
    return FillResult(image, fill_source, source_frame, hole)
