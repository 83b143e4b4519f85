"""Parquet shard IO: declared schemas, atomic writes, provenance metadata, streaming reads.

Layout of one shard file (see docs/design.md):

- written with ``schema.arrow`` only, never an inferred schema;
- one row group per row, so readers stream one clip at a time (memory bounded by one clip);
- the file's schema metadata holds the schema name and version plus ``egosim.shard``: a JSON
  object with the producing stage, its parameters, the fingerprints of its inputs, the output
  fingerprint and the package version;
- written to a temporary file in the same folder and renamed into place on success, so a killed
  write never leaves a partial shard under the final name; on an object store (an fsspec URL
  such as ``s3://``) to a temporary key, moved into place, then given a completion marker
  (:mod:`egosim.pipeline.storage`), and listings ignore a shard without its marker;
- integrity (docs/design.md, "Integrity"): Parquet page checksums (CRC32) are written and
  verified on every read; the file footer's ``egosim.content`` key holds a SHA-256 per column of
  each row (content format 2; encoded media included; :func:`row_content_hash`), a per-row hash
  of those (:func:`row_hash_from_columns`) and the hash of the provenance JSON. A reader
  verifies each row it reads, in full or only the columns it read, and raises
  :class:`CorruptShardError` on a mismatch. Format-1 shards (row hashes only) are still read:
  their whole rows are verified, their partial reads rely on the page checksums.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from types import TracebackType
from typing import Any

import pyarrow as pa
import pyarrow.parquet as pq

from egosim.pipeline import storage
from egosim.pipeline.storage import TMP_MARKER, Location
from egosim.schemas import SchemaCompatibilityError, ShardSchema, schema_identity
from egosim.schemas.base import check_compatible

SHARD_META_KEY = b"egosim.shard"
CONTENT_KEY = b"egosim.content"  # footer key: per-row content hashes (see module doc)
CONTENT_FORMAT = 2  # layout of the CONTENT_KEY JSON (1: row hashes only; 2: per column too)
__all__ = ["TMP_MARKER"]  # re-exported: the temporary-file infix lives in storage


class ShardError(Exception):
    """Base class of shard IO problems."""


class CorruptShardError(ShardError):
    """A shard file is missing, truncated or not Parquet; the message names the file."""


class ContentMismatchError(CorruptShardError):
    """A shard's decoded content differs from the content hashes stored when it was written."""


def row_content_hash(row: Mapping[str, Any], names: Sequence[str]) -> str:
    """SHA-256 (hex) of a row's values for columns ``names``, in that order.

    Canonical form per column: its name, then either its bytes (binary columns: encoded media)
    or its compact JSON (numbers, strings, lists; floats exactly, by ``repr``), each
    length-prefixed. Rows are hashed as Arrow returns them (``to_pylist``), so the writer and the
    reader see the same values.
    """
    h = hashlib.sha256()
    for name in names:
        value = row.get(name)
        h.update(name.encode() + b"\0")
        if isinstance(value, bytes | bytearray | memoryview):
            data, tag = bytes(value), b"b"
        else:
            data = json.dumps(value, separators=(",", ":"), sort_keys=True, default=str).encode()
            tag = b"j"
        h.update(tag + len(data).to_bytes(8, "little") + data)
    return h.hexdigest()


def column_hashes(row: Mapping[str, Any], names: Sequence[str]) -> list[str]:
    """SHA-256 (hex) of each column of a row: ``row_content_hash(row, [name])`` per name."""
    return [row_content_hash(row, [name]) for name in names]


def row_hash_from_columns(hashes: Sequence[str]) -> str:
    """A format-2 row hash: SHA-256 (hex) of the row's column hashes (as bytes, in file order).

    A full read recomputes each column hash once and checks both the column hashes and this
    root, so the footer's column hashes are themselves verified whenever a row is read whole.
    """
    return hashlib.sha256(b"".join(bytes.fromhex(h) for h in hashes)).hexdigest()


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
        path: Location,
        schema: ShardSchema,
        stage: str,
        params: Mapping[str, Any] | None = None,
        inputs: Mapping[str, str] | None = None,
        fingerprint: str = "",
    ) -> None:
        self.path = storage.location(path)
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
        self._sink: contextlib.AbstractContextManager[Any] | None = None  # storage.atomic_write
        self._arrow = schema.arrow.with_metadata(
            {
                **(schema.arrow.metadata or {}),
                SHARD_META_KEY: json.dumps(asdict(self.meta), sort_keys=True, default=str),
            }
        )
        self._writer: pq.ParquetWriter | None = None
        self._hashes: list[list[str]] = []  # per-column content hashes of each row, in order

    def __enter__(self) -> ShardWriter:
        self._sink = storage.atomic_write(self.path)
        sink = self._sink.__enter__()
        try:
            self._writer = pq.ParquetWriter(
                sink, self._arrow, compression="zstd", write_page_checksum=True
            )
        except BaseException as exc:
            self._sink.__exit__(type(exc), exc, exc.__traceback__)
            raise
        return self

    def write_row(self, row: Mapping[str, Any]) -> None:
        """Validate one row and append it as its own row group."""
        if self._writer is None:
            raise ShardError("ShardWriter.write_row called outside its with-block")
        where = f"{storage.name(self.path)} row {row.get('clip_id', '?')}"
        self.schema.validate_row(row, where=where)
        table = pa.Table.from_pylist([dict(row)], schema=self._arrow)
        self._hashes.append(column_hashes(table.to_pylist()[0], self._arrow.names))
        self._writer.write_table(table)
        self.rows_written += 1

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        assert self._writer is not None and self._sink is not None  # set in __enter__
        if exc_type is None:
            content = {
                "format": CONTENT_FORMAT,
                "algorithm": "sha256",
                "meta_sha256": hashlib.sha256(self._arrow.metadata[SHARD_META_KEY]).hexdigest(),
                "rows": [row_hash_from_columns(h) for h in self._hashes],
                "columns": self._hashes,
            }
            self._writer.add_key_value_metadata({CONTENT_KEY: json.dumps(content)})
        try:
            self._writer.close()
        except BaseException as close_exc:
            if exc_type is None:  # the write failed now: nothing may be committed
                self._sink.__exit__(type(close_exc), close_exc, close_exc.__traceback__)
                raise
        # Commits (rename, or move + marker) on success; deletes the temporary on an error.
        self._sink.__exit__(exc_type, exc, tb)


class ShardReader:
    """Read a shard written by :class:`ShardWriter`, checking its schema name and version.

    Page checksums are verified on every read. With ``verify`` (the default) every row read is
    hashed and compared with the hashes stored at write time (:class:`ContentMismatchError` on a
    difference): a whole row against its row hash, a row of a few columns against those
    columns' hashes (content format 2; a format-1 shard has only row hashes, so its partial
    reads rely on page checksums). Shards written before content hashes existed have none to
    compare (``hashed`` is False) and are read as they are.
    """

    def __init__(
        self, path: Location, schema: ShardSchema | None = None, verify: bool = True
    ) -> None:
        self.path = storage.location(path)
        if not storage.exists(self.path):
            raise CorruptShardError(f"{self.path}: shard file does not exist")
        self._handle = storage.open_read(self.path)
        try:
            self._open(schema, verify)
        except BaseException:
            self._handle.close()
            raise

    def _open(self, schema: ShardSchema | None, verify: bool) -> None:
        """Read and check the footer, schema and provenance (``__init__`` closes on error)."""
        try:
            self._file = pq.ParquetFile(self._handle, page_checksum_verification=True)
            arrow = self._file.schema_arrow
            footer = self._file.metadata.metadata or {}
        except Exception as exc:  # pyarrow raises many types for a damaged footer
            raise CorruptShardError(f"{self.path}: not a readable Parquet shard ({exc})") from exc
        try:
            identity = schema_identity(arrow)
        except (ValueError, UnicodeDecodeError) as exc:
            raise CorruptShardError(f"{self.path}: unreadable schema metadata ({exc})") from exc
        if schema is not None:
            check_compatible(arrow, schema, str(self.path))
        raw = (arrow.metadata or {}).get(SHARD_META_KEY)
        if raw is None:
            name, ver = identity
            raise SchemaCompatibilityError(
                f"{self.path}: not an egosim shard (no {SHARD_META_KEY.decode()} metadata; "
                f"schema {name!r} version {ver})"
            )
        try:
            self.meta = ShardMeta(**json.loads(raw))
        except (ValueError, TypeError) as exc:  # JSON, UTF-8 or field errors
            raise CorruptShardError(f"{self.path}: unreadable provenance metadata ({exc})") from exc
        self.schema = schema
        self.verify = verify  # verify each fully read row against its stored hash
        self.row_hashes: list[str] | None = None  # stored hash of each row (None: unhashed)
        self.column_hashes: list[list[str]] | None = None  # per row, per column (format 2)
        self.content_format: int | None = None  # CONTENT_KEY layout (None: unhashed)
        self._read_content(footer.get(CONTENT_KEY), raw)
        # First row index of each row group (rows are hashed in file order).
        self._starts = [0]
        for i in range(self._file.num_row_groups):
            self._starts.append(self._starts[-1] + self._file.metadata.row_group(i).num_rows)

    def _read_content(self, content: bytes | None, raw_meta: bytes) -> None:
        """Read and check the stored hashes (none for a shard written without them).

        Format 1 holds a hash per row; format 2 (:data:`CONTENT_FORMAT`) adds one per column of
        each row, and its row hash is :func:`row_hash_from_columns` of them.
        """
        if content is None:
            return
        try:
            data = json.loads(content)
            fmt = int(data["format"])
            rows = [str(h) for h in data["rows"]]
            meta_hash = data["meta_sha256"]
            columns = None
            if fmt >= 2:
                columns = [[str(h) for h in row] for row in data["columns"]]
        except (ValueError, TypeError, KeyError) as exc:
            raise CorruptShardError(f"{self.path}: unreadable content hashes ({exc})") from exc
        if fmt not in (1, CONTENT_FORMAT):
            raise CorruptShardError(
                f"{self.path}: content hash format {fmt} is not one this egosim reads "
                f"(1 or {CONTENT_FORMAT})"
            )
        if hashlib.sha256(raw_meta).hexdigest() != meta_hash:
            raise ContentMismatchError(f"{self.path}: provenance metadata differs from its hash")
        num_rows, width = self._file.metadata.num_rows, len(self._file.schema_arrow.names)
        if len(rows) != num_rows or (columns is not None and len(columns) != num_rows):
            raise ContentMismatchError(
                f"{self.path}: {len(rows)} content hashes for {num_rows} rows"
            )
        if columns is not None and any(len(c) != width for c in columns):
            raise ContentMismatchError(
                f"{self.path}: column hashes do not list one hash per column ({width})"
            )
        self.content_format, self.row_hashes, self.column_hashes = fmt, rows, columns

    @property
    def hashed(self) -> bool:
        """True when the shard stores content hashes (every shard written by this egosim)."""
        return self.row_hashes is not None

    @property
    def columns_hashed(self) -> bool:
        """True when a read of a few columns is verified too (content format 2)."""
        return self.column_hashes is not None

    def _checked(
        self, rows: list[dict[str, Any]], group: int, columns: list[str] | None = None
    ) -> list[dict[str, Any]]:
        """``rows`` of row group ``group``, verified against their stored hashes.

        A whole row (``columns`` None) is checked against its row hash (format 2: each column
        hash and their root); a row of a few ``columns`` against those columns' hashes, when the
        shard has them (format 1 shards: page checksums only).
        """
        if not self.verify or self.row_hashes is None:
            return rows
        names = self._file.schema_arrow.names
        for k, row in enumerate(rows):
            index = self._starts[group] + k
            bad = self._row_mismatch(row, index, names, columns)
            if bad:
                raise ContentMismatchError(
                    f"{self.path}: row {index} (clip {row.get('clip_id')!r}) differs from "
                    f"the content hash stored when it was written ({bad})"
                )
        return rows

    def _row_mismatch(
        self, row: Mapping[str, Any], index: int, names: list[str], columns: list[str] | None
    ) -> str:
        """What of row ``index`` differs from its stored hashes ('' when nothing does)."""
        assert self.row_hashes is not None  # checked by the caller
        stored = None if self.column_hashes is None else self.column_hashes[index]
        if stored is None:  # format 1: only whole rows can be checked
            if columns is None and row_content_hash(row, names) != self.row_hashes[index]:
                return "row hash"
            return ""
        wanted = names if columns is None else columns
        position = {name: i for i, name in enumerate(names)}
        found = column_hashes(row, wanted)
        differ = [n for n, h in zip(wanted, found, strict=True) if h != stored[position[n]]]
        if differ:
            return f"columns {differ}"
        if columns is None and row_hash_from_columns(found) != self.row_hashes[index]:
            return "row hash"
        return ""

    @property
    def arrow_schema(self) -> pa.Schema:
        """The Arrow schema stored in the file (with its metadata)."""
        return self._file.schema_arrow

    @property
    def num_row_groups(self) -> int:
        """Number of row groups (one per row for shards written by :class:`ShardWriter`)."""
        return int(self._file.num_row_groups)

    @property
    def num_rows(self) -> int:
        """Number of rows in the shard."""
        return int(self._file.metadata.num_rows)

    def iter_rows(self, columns: list[str] | None = None) -> Iterator[dict[str, Any]]:
        """Yield rows as dicts, one row group at a time."""
        for i in range(self._file.num_row_groups):
            yield from self._checked(self._read_group(i, columns), i, columns)

    def _read_group(self, i: int, columns: list[str] | None = None) -> list[dict[str, Any]]:
        """Rows of row group ``i`` (page checksums verified), or :class:`CorruptShardError`."""
        try:
            return self._file.read_row_group(i, columns=columns).to_pylist()
        except Exception as exc:  # damaged pages raise OSError, ArrowInvalid, and others
            raise CorruptShardError(f"{self.path}: row group {i} unreadable ({exc})") from exc

    def read_column(self, name: str) -> list[Any]:
        """Read one whole column (use for small columns such as ``clip_id``)."""
        try:
            return self._file.read(columns=[name]).column(name).to_pylist()
        except Exception as exc:
            raise CorruptShardError(f"{self.path}: column {name!r} unreadable ({exc})") from exc

    def row_group_of(self) -> dict[str, int]:
        """Map ``clip_id`` to its row group, for joins by clip id without loading the shard."""
        index: dict[str, int] = {}
        for i in range(self._file.num_row_groups):
            for row in self._read_group(i, ["clip_id"]):
                index[row["clip_id"]] = i
        return index

    def read_row_group(self, i: int, columns: list[str] | None = None) -> list[dict[str, Any]]:
        """Read the rows of row group ``i``, verified against their content hashes (a few
        ``columns``: those columns' hashes, on a format-2 shard; see :meth:`_checked`)."""
        return self._checked(self._read_group(i, columns), i, columns)

    def __enter__(self) -> ShardReader:
        return self

    def __exit__(self, *exc: object) -> None:
        self._file.close()
        self._handle.close()


def open_shard(path: Location, schema: ShardSchema | None = None) -> ShardReader:
    """Open a shard for reading; checks ``schema`` name and version when given."""
    return ShardReader(path, schema)


def verify_shard(path: Location) -> None:
    """Read every row of a shard and verify it; raises :class:`CorruptShardError` on damage.

    A shard without content hashes (written before they existed) raises too: its content
    cannot be verified.
    """
    with ShardReader(path) as reader:
        if not reader.hashed:
            raise ContentMismatchError(f"{path}: shard has no content hashes (re-run to add them)")
        for _ in reader.iter_rows():
            pass


def read_shard_meta(path: Location) -> ShardMeta:
    """Read only a shard's provenance metadata (raises :class:`CorruptShardError`)."""
    with open_shard(path) as reader:
        return reader.meta


SHARD_GLOB = "shard-*.parquet"  # the output shards of a step folder


def shard_file_name(index: int) -> str:
    """File name of output shard ``index`` of a step (``shard-00000.parquet``)."""
    return f"shard-{index:05d}.parquet"


def rejects_file_name(index: int) -> str:
    """File name of the rejects of shard ``index`` of a step (``rejects-00000.parquet``)."""
    return f"rejects-{index:05d}.parquet"


STAGE_REJECTS_SUFFIX = ".rejects.parquet"  # the rejects `egosim stage` writes beside its output


def find_shards(paths: Iterable[str | Path], step: str) -> list[Location]:
    """Shard files under ``paths``: files, folders of shards, or run folders with a ``step/``.

    Each path is a local path or an fsspec URL (:func:`egosim.pipeline.storage.location`). A
    file named directly is taken as it is; in folders only committed shards are listed (never a
    temporary file, an ``egosim stage`` rejects file or, remote, a shard without its completion
    marker). Raises
    :class:`FileNotFoundError` naming the paths when nothing is found.
    """
    found: list[Location] = []
    for raw in paths:
        path = storage.location(raw)
        if storage.exists(path):
            found.append(path)
            continue
        if not storage.is_dir(path):
            raise FileNotFoundError(f"no {step} shard or folder at {path}")
        sub = storage.join(path, step)
        folder = sub if storage.is_dir(sub) else path
        # `egosim stage --output shard-00000.parquet` writes shard-00000.rejects.parquet beside it
        found += [
            f
            for f in storage.list_files(folder, SHARD_GLOB)
            if not storage.name(f).endswith(STAGE_REJECTS_SUFFIX)
        ]
    if not found:
        raise FileNotFoundError(
            f"no {step} shards under {[str(p) for p in paths]} (expected {SHARD_GLOB} files, "
            f"or a run folder with a {step}/ step)"
        )
    return found
