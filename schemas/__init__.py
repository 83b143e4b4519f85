"""Shard schemas: one per shard kind, versioned, with column docs and row validators."""

from __future__ import annotations

from egosim.schemas.base import (
    Column,
    RowValidationError,
    SchemaCompatibilityError,
    SchemaError,
    ShardSchema,
    schema_identity,
)
from egosim.schemas.clips import CLIPS
from egosim.schemas.poses import POSES
from egosim.schemas.rejects import REJECTS

SCHEMAS: dict[str, ShardSchema] = {s.name: s for s in (CLIPS, REJECTS, POSES)}


def get_schema(name: str) -> ShardSchema:
    """Return the declared schema called ``name``; raises KeyError listing the known ones."""
    try:
        return SCHEMAS[name]
    except KeyError:
        raise KeyError(f"unknown schema {name!r}; known: {sorted(SCHEMAS)}") from None


__all__ = [
    "CLIPS",
    "POSES",
    "REJECTS",
    "SCHEMAS",
    "Column",
    "RowValidationError",
    "SchemaCompatibilityError",
    "SchemaError",
    "ShardSchema",
    "get_schema",
    "schema_identity",
]
