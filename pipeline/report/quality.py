"""The per-clip quality figures that stages record, as the report plots them.

Each :class:`QualityFigure` names the stage whose rows hold it, the columns it reads and how a
row becomes one number (a column as it is, or the mean of a per-frame column). Figures of a
stage the run does not have, and rows where the column is null, are left out.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from egosim.pipeline.report.run_data import RunData


@dataclass(frozen=True)
class QualityFigure:
    """One per-clip number a stage records."""

    stage: str  # registered stage whose output rows hold it
    name: str  # label in the report
    columns: tuple[str, ...]  # columns it reads
    value: Callable[[Mapping[str, Any]], float | None]  # row -> the figure (None: not recorded)
    doc: str  # one line: what it measures and which way is good


def column(name: str) -> Callable[[Mapping[str, Any]], float | None]:
    """The figure is the row's ``name`` column (None when null or not finite)."""

    def value(row: Mapping[str, Any]) -> float | None:
        v = row.get(name)
        return None if v is None or not math.isfinite(float(v)) else float(v)

    return value


def mean_of(name: str) -> Callable[[Mapping[str, Any]], float | None]:
    """The figure is the mean of the row's list column ``name`` (nested lists flattened)."""

    def value(row: Mapping[str, Any]) -> float | None:
        v = row.get(name)
        if v is None:
            return None
        arr = np.asarray(v, dtype=np.float64).ravel()
        arr = arr[np.isfinite(arr)]
        return float(arr.mean()) if arr.size else None

    return value


def count_of(name: str) -> Callable[[Mapping[str, Any]], float | None]:
    """The figure is the length of the row's list column ``name``."""

    def value(row: Mapping[str, Any]) -> float | None:
        v = row.get(name)
        return None if v is None else float(len(v))

    return value


FIGURES: tuple[QualityFigure, ...] = (
    QualityFigure(
        "depth_camera",
        "registered fraction",
        ("registered",),
        mean_of("registered"),
        "frames whose pose the backend estimated (not interpolated); higher is better",
    ),
    QualityFigure(
        "depth_camera",
        "depth confidence (confident fraction)",
        ("confident_fraction",),
        column("confident_fraction"),
        "first-frame depth pixels whose confidence reaches the threshold; higher is better",
    ),
    QualityFigure(
        "depth_camera",
        "SfM reprojection error (px)",
        ("reprojection_error_px",),
        column("reprojection_error_px"),
        "mean reprojection error of the SfM model; lower is better (sfm backend only)",
    ),
    QualityFigure(
        "pose_clean",
        "camera jitter before cleaning (mm)",
        ("jitter_before_mm",),
        column("jitter_before_mm"),
        "RMS second difference of the input camera centre (thousandths of a unit if not metric)",
    ),
    QualityFigure(
        "pose_clean",
        "camera jitter after cleaning (mm)",
        ("jitter_after_mm",),
        column("jitter_after_mm"),
        "the same on the cleaned trajectory; lower is smoother",
    ),
    QualityFigure(
        "pose_clean",
        "rotation jitter after cleaning (deg)",
        ("jitter_after_deg",),
        column("jitter_after_deg"),
        "RMS second difference of the cleaned rotation; lower is smoother",
    ),
    QualityFigure(
        "pose_clean",
        "outlier frames repaired",
        ("outlier_frames",),
        count_of("outlier_frames"),
        "frames the jump test flagged and repaired",
    ),
    QualityFigure(
        "hands",
        "hand detection rate",
        ("hand_valid",),
        mean_of("hand_valid"),
        "fraction of (frame, hand) slots with a kept hand",
    ),
    QualityFigure(
        "hand_mask",
        "hand mask coverage",
        ("coverage",),
        mean_of("coverage"),
        "mean fraction of each frame's pixels masked as hand or arm",
    ),
    QualityFigure(
        "inpaint",
        "inpainted fraction of frame 0",
        ("masked_fraction",),
        column("masked_fraction"),
        "pixels of frame 0 that had to be filled",
    ),
    QualityFigure(
        "inpaint",
        "filled from other frames",
        ("reprojected_fraction",),
        column("reprojected_fraction"),
        "of the filled pixels: seen in later frames and reprojected (higher is better)",
    ),
    QualityFigure(
        "scene_cloud",
        "scene cloud kept fraction",
        ("kept_fraction",),
        column("kept_fraction"),
        "unprojected pixels kept after flying-pixel filtering",
    ),
    QualityFigure(
        "scene_render",
        "visible fraction",
        ("visible_fraction",),
        mean_of("visible_fraction"),
        "mean fraction of pixels a scene point landed on; higher is better",
    ),
    QualityFigure(
        "keypoint_render",
        "keypoints in view",
        ("keypoint_visible",),
        mean_of("keypoint_visible"),
        "fraction of (frame, joint) slots with a valid joint inside the image",
    ),
)


@dataclass(frozen=True)
class FigureValues:
    """One figure over the clips of one step."""

    figure: QualityFigure  # what was measured
    step: str  # the step whose rows it came from
    values: dict[str, float]  # clip id -> value (clips that record it)

    def stats(self) -> dict[str, float]:
        """count, mean, median, min and max of the values (count 0 and NaN when empty)."""
        arr = np.asarray(list(self.values.values()), dtype=np.float64)
        if not arr.size:
            return {
                "count": 0,
                "mean": math.nan,
                "median": math.nan,
                "min": math.nan,
                "max": math.nan,
            }
        return {
            "count": float(arr.size),
            "mean": float(arr.mean()),
            "median": float(np.median(arr)),
            "min": float(arr.min()),
            "max": float(arr.max()),
        }


def collect(run: RunData, figures: Sequence[QualityFigure] = FIGURES) -> list[FigureValues]:
    """Every figure of every step of ``run`` that runs the figure's stage, in figure order."""
    out = []
    for fig in figures:
        for step in run.steps_of(fig.stage):
            rows = run.rows(step.step, list(fig.columns))
            values = {cid: v for cid, row in rows.items() if (v := fig.value(row)) is not None}
            out.append(FigureValues(fig, step.step, values))
    return out
