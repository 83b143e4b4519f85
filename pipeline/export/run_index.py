"""Find a run's steps by the schema they wrote and read one clip's row from any of them.

A run folder (``egosim run``) holds one folder per step (``RUN/<step>/shard-NNNNN.parquet``);
step names are the workflow's (``cameras`` runs ``depth_camera``, ``poses`` runs
``pose_clean`` ...), so exporters look steps up by the **schema** their shards declare, not by
name. Steps are taken in the order of ``RUN/workflow.resolved.yaml`` when it exists (so the
first step that wrote a schema wins), else in name order. Every shard is opened through
:class:`~egosim.pipeline.shards.ShardReader` with the declared schema, so a shard of another
schema version is refused (``SchemaCompatibilityError``) and every row read is verified.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from egosim.pipeline.shards import SHARD_GLOB, ShardReader, read_shard_meta
from egosim.schemas import ShardSchema

MAX_RESOLVED_BYTES = 1 << 20  # workflow.resolved.yaml larger than this is refused


class ExportError(ValueError):
    """A run, clip or option an exporter cannot use; the message names it and says why."""


@dataclass
class RunIndex:
    """The steps of one run folder, by schema name, and where each clip's rows are."""

    root: Path  # the run folder
    steps: dict[str, str]  # schema name -> step folder (the first step that wrote it)
    _where: dict[str, dict[str, tuple[Path, int]]] = field(default_factory=dict)  # lazy

    @classmethod
    def open(cls, run: Path) -> RunIndex:
        """Index the run folder ``run``; raises :class:`ExportError` when it holds no steps."""
        root = Path(run)
        if not root.is_dir():
            raise ExportError(f"{root}: not a run folder (expected RUN/<step>/shard-*.parquet)")
        steps: dict[str, str] = {}
        for folder in _step_folders(root):
            shards = sorted(folder.glob(SHARD_GLOB))
            if shards:
                steps.setdefault(read_shard_meta(shards[0]).schema, folder.name)
        if not steps:
            raise ExportError(f"{root}: no step folders with {SHARD_GLOB} files")
        return cls(root, steps)

    def step_of(self, schema: ShardSchema) -> str | None:
        """The step folder that holds ``schema`` shards, or None when the run has none."""
        return self.steps.get(schema.name)

    def _index(self, schema: ShardSchema) -> dict[str, tuple[Path, int]]:
        """``clip_id -> (shard, row group)`` of ``schema``'s step (empty when absent)."""
        if schema.name not in self._where:
            where: dict[str, tuple[Path, int]] = {}
            step = self.step_of(schema)
            if step is not None:
                for shard in sorted((self.root / step).glob(SHARD_GLOB)):
                    with ShardReader(shard, schema) as reader:
                        for cid, group in reader.row_group_of().items():
                            where.setdefault(cid, (shard, group))
            self._where[schema.name] = where
        return self._where[schema.name]

    def clip_ids(self, schema: ShardSchema) -> list[str]:
        """Clip ids in ``schema``'s step, in shard then row order."""
        return list(self._index(schema))

    def row(self, schema: ShardSchema, clip_id: str) -> dict[str, Any] | None:
        """The verified row of ``clip_id`` in ``schema``'s step, or None when it has none."""
        found = self._index(schema).get(clip_id)
        if found is None:
            return None
        shard, group = found
        with ShardReader(shard, schema) as reader:
            rows = [r for r in reader.read_row_group(group) if r["clip_id"] == clip_id]
        return rows[0] if rows else None

    def rows(self, schema: ShardSchema) -> Iterator[dict[str, Any]]:
        """Every row of ``schema``'s step, one at a time (verified), in shard order."""
        step = self.step_of(schema)
        if step is None:
            raise ExportError(
                f"{self.root}: no step wrote {schema.name!r} shards (steps: {self.steps})"
            )
        for shard in sorted((self.root / step).glob(SHARD_GLOB)):
            with ShardReader(shard, schema) as reader:
                yield from reader.iter_rows()


def _step_folders(root: Path) -> list[Path]:
    """Step folders of ``root`` in workflow order (``workflow.resolved.yaml``), else by name."""
    folders = sorted(p for p in root.iterdir() if p.is_dir())
    resolved = root / "workflow.resolved.yaml"
    if not resolved.is_file():
        return folders
    if resolved.stat().st_size > MAX_RESOLVED_BYTES:
        raise ExportError(f"{resolved}: larger than {MAX_RESOLVED_BYTES} bytes")
    try:
        order = list((yaml.safe_load(resolved.read_text()) or {}).get("steps") or {})
    except (yaml.YAMLError, AttributeError) as exc:
        raise ExportError(f"{resolved}: unreadable resolved workflow ({exc})") from exc
    rank = {name: i for i, name in enumerate(order)}
    return sorted(folders, key=lambda p: (rank.get(p.name, len(rank)), p.name))
