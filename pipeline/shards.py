"""Parquet shard IO: declared schemas, atomic writes, provenance metadata, streaming reads.

Layout of one shard file (see docs/design.md):

- written with ``schema.arrow`` only, never an inferred schema;
- one row group per row, so readers stream one clip at a time (memory bounded by one clip);
- the file's schema metadata holds the schema name and version plus ``egosim.shard``: a JSON
  object with the producing stage, its parameters, the fingerprints of its inputs, the output
  fingerprint and the package version;
- written to a temporary file in the same folder and renamed into place on success, so a killed
  write never leaves a partial shard under the final name.
"""

from __future__ import annotations

import json
import os
import uuid
from collections.abc import Iterator, Mapping
from dataclasses import asdict, dataclass, field
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from types import TracebackType
from typing import Any

import pyarrow as pa
import pyarrow.parquet as pq

from egosim.schemas import SchemaCompatibilityError, ShardSchema, schema_identity
from egosim.schemas.base import check_compatible

SHARD_META_KEY = b"egosim.shard"
TMP_MARKER = ".tmp-"


class ShardError(Exception):
    """Base class of shard IO problems."""


class CorruptShardError(ShardError):
    """A shard file is missing, truncated or not Parquet; the message names the file."""


def package_version() -> str:
    """The installed egosim version (``0+unknown`` when run from an uninstalled tree)."""
    try:
        return version("egosim")
    except PackageNotFoundError:
        return "0+unknown"


@dataclass(frozen=True)
class ShardMeta:
    """Provenance stored in every shard."""

    schema: str  # schema name
    schema_version: int  # schema version
    stage: str  # stage that wrote the shard ("api" for the Python API)
    params: dict[str, Any] = field(default_factory=dict)  # resolved stage parameters
    inputs: dict[str, str] = field(default_factory=dict)  # input role -> input fingerprint
    fingerprint: str = ""  # fingerprint of this output (stage, params, inputs, shard index)
    package_version: str = field(default_factory=package_version)  # egosim version that wrote it


class ShardWriter:
    """Write rows of one schema to a shard atomically; use as a context manager.

    Each row is validated against the schema's row validators before it is written. On an
    exception inside the ``with`` block the temporary file is removed and nothing appears.
    """

    def __init__(
        self,
        path: Path,
        schema: ShardSchema,
        stage: str,
        params: Mapping[str, Any] | None = None,
        inputs: Mapping[str, str] | None = None,
        fingerprint: str = "",
    ) -> None:
        self.path = Path(path)
        self.schema = schema
        self.meta = ShardMeta(
            schema=schema.name,
            schema_version=schema.version,
            stage=stage,
            params=dict(params or {}),
            inputs=dict(inputs or {}),
            fingerprint=fingerprint,
        )
        self.rows_written = 0
        self._tmp = self.path.with_name(f"{self.path.name}{TMP_MARKER}{uuid.uuid4().hex[:8]}")
        self._arrow = schema.arrow.with_metadata(
            {
                **(schema.arrow.metadata or {}),
                SHARD_META_KEY: json.dumps(asdict(self.meta), sort_keys=True, default=str),
            }
        )
        self._writer: pq.ParquetWriter | None = None

    def __enter__(self) -> ShardWriter:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._writer = pq.ParquetWriter(self._tmp, self._arrow, compression="zstd")
        return self

    def write_row(self, row: Mapping[str, Any]) -> None:
        """Validate one row and append it as its own row group."""
        if self._writer is None:
            raise ShardError("ShardWriter.write_row called outside its with-block")
        self.schema.validate_row(row, where=f"{self.path.name} row {row.get('clip_id', '?')}")
        table = pa.Table.from_pylist([dict(row)], schema=self._arrow)
        self._writer.write_table(table)
        self.rows_written += 1

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        assert self._writer is not None  # set in __enter__
        self._writer.close()
        if exc_type is None:
            os.replace(self._tmp, self.path)
        else:
            self._tmp.unlink(missing_ok=True)


class ShardReader:
    """Read a shard written by :class:`ShardWriter`, checking its schema name and version."""

    def __init__(self, path: Path, schema: ShardSchema | None = None) -> None:
        self.path = Path(path)
        if not self.path.is_file():
            raise CorruptShardError(f"{self.path}: shard file does not exist")
        try:
            self._file = pq.ParquetFile(self.path)
        except (pa.ArrowInvalid, OSError) as exc:
            raise CorruptShardError(f"{self.path}: not a readable Parquet shard ({exc})") from exc
        arrow = self._file.schema_arrow
        if schema is not None:
            check_compatible(arrow, schema, str(self.path))
        raw = (arrow.metadata or {}).get(SHARD_META_KEY)
        if raw is None:
            name, ver = schema_identity(arrow)
            raise SchemaCompatibilityError(
                f"{self.path}: not an egosim shard (no {SHARD_META_KEY.decode()} metadata; "
                f"schema {name!r} version {ver})"
            )
        self.meta = ShardMeta(**json.loads(raw))
        self.schema = schema

    @property
    def arrow_schema(self) -> pa.Schema:
        """The Arrow schema stored in the file (with its metadata)."""
        return self._file.schema_arrow

    @property
    def num_rows(self) -> int:
        """Number of rows in the shard."""
        return int(self._file.metadata.num_rows)

    def iter_rows(self, columns: list[str] | None = None) -> Iterator[dict[str, Any]]:
        """Yield rows as dicts, one row group at a time."""
        for i in range(self._file.num_row_groups):
            try:
                table = self._file.read_row_group(i, columns=columns)
            except (pa.ArrowInvalid, OSError) as exc:
                raise CorruptShardError(f"{self.path}: row group {i} unreadable ({exc})") from exc
            yield from table.to_pylist()

    def read_column(self, name: str) -> list[Any]:
        """Read one whole column (use for small columns such as ``clip_id``)."""
        return self._file.read(columns=[name]).column(name).to_pylist()

    def row_group_of(self) -> dict[str, int]:
        """Map ``clip_id`` to its row group, for joins by clip id without loading the shard."""
        index: dict[str, int] = {}
        for i in range(self._file.num_row_groups):
            for cid in self._file.read_row_group(i, columns=["clip_id"]).column(0).to_pylist():
                index[cid] = i
        return index

    def read_row_group(self, i: int) -> list[dict[str, Any]]:
        """Read the rows of row group ``i``."""
        return self._file.read_row_group(i).to_pylist()

    def __enter__(self) -> ShardReader:
        return self

    def __exit__(self, *exc: object) -> None:
        self._file.close()


def open_shard(path: Path, schema: ShardSchema | None = None) -> ShardReader:
    """Open a shard for reading; checks ``schema`` name and version when given."""
    return ShardReader(path, schema)


def read_shard_meta(path: Path) -> ShardMeta:
    """Read only a shard's provenance metadata (raises :class:`CorruptShardError`)."""
    with open_shard(path) as reader:
        return reader.meta


def is_temporary(path: Path) -> bool:
    """True for the temporary files of unfinished writes."""
    return TMP_MARKER in Path(path).name
