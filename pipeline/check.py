"""Validate shards: integrity, schema, version, row invariants, decoded content, unique ids.

:func:`check_shard` never raises, whatever the file holds: it returns every violation it finds,
each naming the file (and the clip where there is one), so ``egosim check`` can list them all
and exit non-zero. A damaged row group is reported and the check goes on with the next one.
:func:`check_paths` checks many files and, across the shards of one folder (one step of a run),
that no clip id appears twice.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from egosim.pipeline import storage
from egosim.pipeline.clip_io import clip_from_row
from egosim.pipeline.shards import CorruptShardError, ShardReader
from egosim.pipeline.storage import Location
from egosim.schemas import SCHEMAS, SchemaError, schema_identity


def _clip_content_problems(row: Mapping[str, Any]) -> list[str]:
    """Decode a clips row and check what only the decoded arrays show."""
    try:
        clip = clip_from_row(row)
    except Exception as exc:  # any decoder failure on damaged bytes is a violation
        return [f"cannot decode: {type(exc).__name__}: {exc}"]
    problems = []
    t = row["num_frames"]
    for name in ("frames", "depth", "static_frames", "static_depth", "hand_mask", "object_mask"):
        value = getattr(clip, name)
        if value is not None and len(value) != t:
            problems.append(f"{name} decodes to {len(value)} frames, num_frames is {t}")
    if clip.hand_mask is not None and not np.isin(clip.hand_mask, (0, 1)).all():
        problems.append("hand_mask has values outside {0, 1}")
    for name in ("depth", "static_depth"):
        value = getattr(clip, name)
        if value is not None and (not np.all(np.isfinite(value)) or value.min() < 0):
            problems.append(f"{name} has negative or non-finite values")
    return problems


CONTENT_CHECKS: dict[str, Callable[[Mapping[str, Any]], list[str]]] = {
    "clips": _clip_content_problems,
}


@dataclass
class ShardReport:
    """What checking one shard found."""

    path: Location  # the shard file (a local path or an fsspec URL)
    problems: list[str] = field(default_factory=list)  # every violation, readable
    schema: str | None = None  # schema name, when the file could be opened
    clip_ids: list[str] = field(default_factory=list)  # clip ids of the rows that could be read


def check_shard(path: Location, allow_empty: bool = False) -> list[str]:
    """Every violation in one shard file, as ``"<file> [clip <id>]: <problem>"`` strings."""
    return inspect_shard(path, allow_empty).problems


def inspect_shard(path: Location, allow_empty: bool = False) -> ShardReport:
    """Check one shard; never raises (an unexpected error is reported as a violation)."""
    report = ShardReport(path)
    try:
        _inspect(report, allow_empty)
    except Exception as exc:  # the promise: no traceback, whatever the input
        report.problems.append(f"{path}: cannot be checked ({type(exc).__name__}: {exc})")
    return report


def _inspect(report: ShardReport, allow_empty: bool) -> None:
    path, problems = report.path, report.problems
    try:
        reader = ShardReader(path, verify=True)
    except (CorruptShardError, SchemaError) as exc:
        problems.append(str(exc))
        return
    with reader:
        name, version = schema_identity(reader.arrow_schema)
        schema = SCHEMAS.get(name or "")
        if schema is None:
            problems.append(f"{path}: unknown schema {name!r}")
            return
        if version != schema.version:
            problems.append(
                f"{path}: schema {name!r} version {version}, this egosim reads version "
                f"{schema.version}"
            )
            return
        report.schema = schema.name
        missing = [c for c in schema.column_names if c not in reader.arrow_schema.names]
        if missing:
            problems.append(f"{path}: shard lacks columns {missing}")
            return
        if not reader.hashed:
            problems.append(f"{path}: no content hashes (written before they existed; re-run)")
        if reader.num_rows == 0 and not allow_empty and schema.name != "rejects":
            problems.append(f"{path}: shard holds no rows")
        seen: set[str] = set()
        content = CONTENT_CHECKS.get(schema.name)
        for group in range(reader.num_row_groups):
            try:
                rows = reader.read_row_group(group)
            except CorruptShardError as exc:
                problems.append(str(exc))
                continue
            for row in rows:
                where = f"{path} clip {row.get('clip_id')!r}"
                if "clip_id" in row and schema.name != "rejects":
                    if row["clip_id"] in seen:
                        problems.append(f"{where}: duplicate clip id")
                    seen.add(row["clip_id"])
                    report.clip_ids.append(row["clip_id"])
                row_problems = schema.row_problems(row)
                if not row_problems and content is not None:
                    row_problems = content(row)
                problems += [f"{where}: {p}" for p in row_problems]


def check_paths(paths: list[Location], allow_empty: bool = False) -> tuple[int, list[str]]:
    """Check every shard under ``paths``: ``(shards checked, every violation)``. Never raises.

    Besides each file's own problems: a clip id in two shards of the same folder and schema
    (two shards of one step of a run) is a violation, since joins by clip id would keep one.
    """
    try:
        shards = find_shards(paths)
    except OSError as exc:
        return 0, [f"cannot list shards under {[str(p) for p in paths]}: {exc}"]
    problems: list[str] = []
    owners: dict[tuple[Location, str], dict[str, Location]] = defaultdict(dict)
    for shard in shards:
        report = inspect_shard(shard, allow_empty)
        problems += report.problems
        if report.schema is None or report.schema == "rejects":
            continue
        seen = owners[(storage.parent(shard), report.schema)]
        for clip_id in dict.fromkeys(report.clip_ids):
            if clip_id in seen:
                problems.append(
                    f"{shard} clip {clip_id!r}: clip id also in {storage.name(seen[clip_id])} "
                    "(clip ids must be unique across the shards of a step)"
                )
            else:
                seen[clip_id] = shard
    return len(shards), problems


def find_shards(paths: list[Location]) -> list[Location]:
    """Expand folders into the ``.parquet`` files under them (sorted); files stay as given.

    Paths may be fsspec URLs. Folders list committed shards only: a temporary file or key
    left by a killed write, or a remote shard without its completion marker, is not checked
    (it is not part of the run; the next run removes or rewrites it).
    """
    found: list[Location] = []
    for raw in paths:
        path = storage.location(raw)
        if storage.is_dir(path):
            found += storage.list_files(path, "*.parquet", recursive=True)
        else:
            found.append(path)
    return found
