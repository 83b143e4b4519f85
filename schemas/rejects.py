"""The ``rejects`` schema: clips a stage could not process, with the reason."""

from __future__ import annotations

import pyarrow as pa

from egosim.schemas.base import Column, ShardSchema

REJECTS = ShardSchema(
    name="rejects",
    version=1,
    doc="One row per clip (or input file) that a stage rejected; the rest of its shard went on.",
    columns=(
        Column("step", pa.string(), "Workflow step name (the stage name for one-off runs)."),
        Column("stage", pa.string(), "Stage that rejected the clip."),
        Column("shard", pa.string(), "Output shard the clip would have gone to."),
        Column("clip_id", pa.string(), "Clip id, or the input file for ingest failures."),
        Column("reason", pa.string(), "Why the clip was rejected, readable."),
        Column("input_fingerprint", pa.string(), "Fingerprint of the input the stage was given."),
    ),
)
