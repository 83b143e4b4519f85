"""Per-clip and overall tables of ``evaluation`` shards (``egosim report``)."""

from __future__ import annotations

import math
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from egosim.pipeline.shards import ShardReader, find_shards
from egosim.schemas.pack import EVALUATION

FIGURES = (
    "psnr",
    "psnr_baseline",
    "psnr_hand",
    "psnr_hand_baseline",
    "ssim",
    "ssim_baseline",
    "lpips",
    "depth_err",
    "cam_err",
)


def read_evaluations(paths: Iterable[str | Path]) -> list[dict[str, Any]]:
    """Every row of the evaluation shards (files, folders of shards, or run folders)."""
    rows: list[dict[str, Any]] = []
    for file in find_shards(paths, "evaluate"):
        with ShardReader(file, EVALUATION) as reader:
            rows += list(reader.iter_rows())
    return rows


def overall(rows: list[dict[str, Any]]) -> dict[str, float | None]:
    """Mean of each figure over the clips that have it (None when no clip has it)."""
    out: dict[str, float | None] = {}
    for name in FIGURES:
        values = [r[name] for r in rows if r.get(name) is not None and not math.isnan(r[name])]
        out[name] = sum(values) / len(values) if values else None
    return out


def format_table(rows: list[dict[str, Any]]) -> str:
    """A plain-text table: one line per clip, then the overall means."""

    def cell(v: Any) -> str:
        return "-" if v is None else f"{v:.4f}" if isinstance(v, float) else str(v)

    header = ["clip_id", *FIGURES]
    lines = [header] + [[r["clip_id"], *(cell(r.get(f)) for f in FIGURES)] for r in rows]
    mean = overall(rows)
    lines.append(["overall", *(cell(mean[f]) for f in FIGURES)])
    widths = [max(len(line[i]) for line in lines) for i in range(len(header))]
    return "\n".join(
        "  ".join(c.ljust(wd) for c, wd in zip(line, widths, strict=True)) for line in lines
    )
