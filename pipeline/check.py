"""Validate shards: schema, version, row invariants, and decoded-content invariants.

:func:`check_shard` never raises for a bad shard: it returns every violation it finds, each
naming the file and the clip, so ``egosim check`` can list them all and exit non-zero.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from egosim.pipeline.clip_io import clip_from_row
from egosim.pipeline.media import MediaError
from egosim.pipeline.records import ClipValueError
from egosim.pipeline.shards import CorruptShardError, ShardReader
from egosim.schemas import SCHEMAS, SchemaCompatibilityError, schema_identity


def _clip_content_problems(row: Mapping[str, Any]) -> list[str]:
    """Decode a clips row and check what only the decoded arrays show."""
    try:
        clip = clip_from_row(row)
    except (MediaError, ClipValueError, ValueError) as exc:
        return [str(exc)]
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


def check_shard(path: Path, allow_empty: bool = False) -> list[str]:
    """Every violation in one shard file, as ``"<file> [clip <id>]: <problem>"`` strings."""
    path = Path(path)
    try:
        reader = ShardReader(path)
    except (CorruptShardError, SchemaCompatibilityError) as exc:
        return [str(exc)]
    with reader:
        name, version = schema_identity(reader.arrow_schema)
        schema = SCHEMAS.get(name or "")
        if schema is None:
            return [f"{path}: unknown schema {name!r}"]
        if version != schema.version:
            return [
                f"{path}: schema {name!r} version {version}, this egosim reads version "
                f"{schema.version}"
            ]
        problems: list[str] = []
        if reader.num_rows == 0 and not allow_empty and schema.name != "rejects":
            problems.append(f"{path}: shard holds no rows")
        seen: set[str] = set()
        content = CONTENT_CHECKS.get(schema.name)
        try:
            for row in reader.iter_rows():
                where = f"{path} clip {row.get('clip_id')!r}"
                if "clip_id" in row and schema.name != "rejects":
                    if row["clip_id"] in seen:
                        problems.append(f"{where}: duplicate clip id")
                    seen.add(row["clip_id"])
                row_problems = schema.row_problems(row)
                if not row_problems and content is not None:
                    row_problems = content(row)
                problems += [f"{where}: {p}" for p in row_problems]
        except CorruptShardError as exc:
            problems.append(str(exc))
    return problems


def find_shards(paths: list[Path]) -> list[Path]:
    """Expand folders into the ``.parquet`` files under them (sorted); files stay as given."""
    found: list[Path] = []
    for path in paths:
        if Path(path).is_dir():
            found += sorted(p for p in Path(path).rglob("*.parquet") if ".tmp-" not in p.name)
        else:
            found.append(Path(path))
    return found
