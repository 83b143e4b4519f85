"""The ``captions`` schema: one text prompt per clip (what ``caption`` writes)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import pyarrow as pa

from egosim.schemas.base import Column, ShardSchema


def _check_text(row: Mapping[str, Any]) -> list[str]:
    return [] if row["text"].strip() else ["text is empty"]


CAPTIONS = ShardSchema(
    name="captions",
    version=1,
    doc="A text prompt per clip for the model's text conditioning.",
    columns=(
        Column("clip_id", pa.string(), "Clip id (joins with the clips shard)."),
        Column("text", pa.string(), "The prompt, one or two sentences."),
        Column("origin", pa.string(), "Where the text came from: 'source' or 'template'."),
    ),
    validators=(_check_text,),
)
