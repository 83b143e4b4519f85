"""Shard schemas as code: Arrow types, a docstring per column, a version, row validators.

A :class:`ShardSchema` is the single source of truth for one kind of shard. Writers always pass
``schema.arrow`` (never an inferred schema); readers compare the file's schema name and version
with the declared one and raise :class:`SchemaCompatibilityError` on a mismatch.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import pyarrow as pa

SCHEMA_NAME_KEY = b"egosim.schema.name"
SCHEMA_VERSION_KEY = b"egosim.schema.version"
COLUMN_DOC_KEY = b"doc"

RowValidator = Callable[[Mapping[str, Any]], list[str]]


class SchemaError(Exception):
    """Base class of schema problems."""


class SchemaCompatibilityError(SchemaError):
    """A shard was written with another schema name or version than the reader expects."""


class RowValidationError(SchemaError):
    """One row breaks its schema's invariants; the message lists every problem."""


@dataclass(frozen=True)
class Column:
    """One column: its name, Arrow type, whether it may be null and what it holds."""

    name: str  # column name in the Parquet file
    type: pa.DataType  # Arrow type, fixed at declaration
    doc: str  # what the column holds, with units and shape
    nullable: bool = False  # True for optional ground truth and optional outputs


@dataclass(frozen=True)
class ShardSchema:
    """A named, versioned shard schema with row validators."""

    name: str  # schema name stored in every file's metadata
    version: int  # bumped whenever a column changes meaning, type or name
    doc: str  # one paragraph on what a shard of this kind holds
    columns: tuple[Column, ...]  # ordered columns
    validators: tuple[RowValidator, ...] = field(default=())  # invariant checks on one row
    # Columns whose values are identifiers that may become paths (checked by schemas.ids);
    # None: ``clip_id`` when the schema has it, except in the rejects table, whose clip_id may
    # name an input file.
    id_columns: tuple[str, ...] | None = None

    @property
    def arrow(self) -> pa.Schema:
        """The Arrow schema with name and version in its metadata and docs on each field."""
        fields = [
            pa.field(c.name, c.type, nullable=c.nullable, metadata={COLUMN_DOC_KEY: c.doc})
            for c in self.columns
        ]
        metadata = {SCHEMA_NAME_KEY: self.name.encode(), SCHEMA_VERSION_KEY: str(self.version)}
        return pa.schema(fields, metadata=metadata)

    @property
    def identifier_columns(self) -> tuple[str, ...]:
        """The columns validated as identifiers (see ``id_columns``)."""
        if self.id_columns is not None:
            return self.id_columns
        if self.name == "rejects" or "clip_id" not in self.column_names:
            return ()
        return ("clip_id",)

    @property
    def column_names(self) -> tuple[str, ...]:
        """Column names in declaration order."""
        return tuple(c.name for c in self.columns)

    def row_problems(self, row: Mapping[str, Any]) -> list[str]:
        """Every problem of one row (missing columns, nulls where not allowed, invariants)."""
        problems: list[str] = []
        for column in self.columns:
            if column.name not in row:
                problems.append(f"missing column {column.name!r}")
            elif row[column.name] is None and not column.nullable:
                problems.append(f"column {column.name!r} is null but required")
        from egosim.schemas.ids import id_problems  # ids imports this module

        for name in self.identifier_columns:  # reported even when other columns are bad
            if row.get(name) is not None:
                problems.extend(id_problems(row[name], name.replace("_", " ")))
        if problems:
            return problems
        for validator in self.validators:
            problems.extend(validator(row))
        return problems

    def validate_row(self, row: Mapping[str, Any], where: str = "") -> None:
        """Raise :class:`RowValidationError` listing every problem of ``row``."""
        problems = self.row_problems(row)
        if problems:
            prefix = f"{where}: " if where else ""
            raise RowValidationError(prefix + "; ".join(problems))


def schema_identity(arrow_schema: pa.Schema) -> tuple[str | None, int | None]:
    """Read ``(name, version)`` from an Arrow schema's metadata; ``None`` where absent."""
    meta = arrow_schema.metadata or {}
    name = meta.get(SCHEMA_NAME_KEY)
    version = meta.get(SCHEMA_VERSION_KEY)
    return (
        name.decode() if name is not None else None,
        int(version) if version is not None else None,
    )


def check_compatible(found: pa.Schema, expected: ShardSchema, where: str) -> None:
    """Raise :class:`SchemaCompatibilityError` unless ``found`` is ``expected`` by name+version."""
    name, version = schema_identity(found)
    if name != expected.name or version != expected.version:
        raise SchemaCompatibilityError(
            f"{where}: shard schema is {name!r} version {version}, "
            f"expected {expected.name!r} version {expected.version}"
        )
    missing = [c for c in expected.column_names if c not in found.names]
    if missing:
        raise SchemaCompatibilityError(f"{where}: shard lacks columns {missing}")
