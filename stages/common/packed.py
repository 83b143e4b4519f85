"""Decode ``pack`` rows into the model's :class:`~egosim.model.TrainingSample` (shared reader).

``pack`` writes the rows; ``train`` (through :class:`~.pack_dataset.PackDataset`),
``simulate`` and ``evaluate`` read them with :func:`sample_from_pack_row`, so one function decides
what a packed sample is. The media decoder, :func:`decode_pack_row` (with
:class:`PackRowError`), lives in :mod:`egosim.pipeline.export.pack_rows` so that the exporters
(pipeline, which may not import stages) share it; it is re-exported here.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from egosim.model.conditioning import TrainingSample
from egosim.pipeline.export.pack_rows import CONDITION_COLUMNS, PackRowError, decode_pack_row

__all__ = ["CONDITION_COLUMNS", "PackRowError", "decode_pack_row", "sample_from_pack_row"]


def sample_from_pack_row(row: Mapping[str, Any]) -> TrainingSample:
    """The model's training sample (conditions + target) of one pack row."""
    videos = decode_pack_row(row)
    return TrainingSample(
        target_video=videos["target"],
        scene_video=videos["scene"],
        visibility=videos["visible"],
        skeleton_video=videos["skeleton"],
        first_frame=videos["first_frame"],
        prompt=str(row["prompt"]),
    )
