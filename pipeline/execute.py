"""Run one stage on one shard: the unit of work the runner schedules (and `egosim stage` runs).

A :class:`ShardTask` is plain data (picklable) so that a Dask worker can run it. The executor
skips a task whose output exists with the same fingerprint, records rejected clips in a
rejects shard next to the output, and writes both atomically (rejects first, output last, so
an existing output always has its rejects).
"""

from __future__ import annotations

import hashlib
import json
import time
import traceback
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from egosim.pipeline.shards import CorruptShardError, ShardReader, ShardWriter, read_shard_meta
from egosim.pipeline.stage import ClipRejected, ClipStage, SourceStage, Stage, get_stage
from egosim.schemas import REJECTS, SchemaCompatibilityError


def fingerprint(payload: Mapping[str, Any]) -> str:
    """A short stable hash of a JSON-able mapping."""
    text = json.dumps(payload, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:20]


def task_fingerprint(
    stage_cls: type[Stage],
    params: Mapping[str, Any],
    inputs: Mapping[str, str],
    index: int,
    count: int,
) -> str:
    """Fingerprint of one output shard: stage, its version, params, input fingerprints, shard."""
    return fingerprint(
        {
            "stage": stage_cls.name,
            "stage_version": stage_cls.version,
            "params": dict(params),
            "inputs": dict(inputs),
            "shard": [index, count],
        }
    )


@dataclass(frozen=True)
class ShardTask:
    """One stage applied to one shard."""

    step: str  # workflow step name
    stage: str  # registered stage name
    params: dict[str, Any]  # stage parameters (validated by the stage's config)
    shard_index: int  # index of this shard
    shard_count: int  # number of shards of the step
    output: Path  # output shard path
    rejects: Path  # rejects shard path
    inputs: dict[str, Path] = field(default_factory=dict)  # role -> input shard (clip stages)
    units: tuple[str, ...] = ()  # units for source stages
    input_fingerprints: dict[str, str] = field(default_factory=dict)  # role/unit -> fingerprint
    fingerprint: str = ""  # fingerprint of the output this task makes


@dataclass(frozen=True)
class ShardResult:
    """What running one task did."""

    step: str  # workflow step name
    shard_index: int  # shard index
    output: str  # output path
    rows: int  # rows written (or present when skipped)
    rejected: int  # clips rejected in this run
    skipped: bool  # True when the output already existed with the same fingerprint
    seconds: float  # wall time


def is_complete(task: ShardTask) -> bool:
    """True when the task's output exists and carries the task's fingerprint."""
    if not task.output.is_file() or not task.rejects.is_file():
        return False
    try:
        return read_shard_meta(task.output).fingerprint == task.fingerprint
    except (CorruptShardError, SchemaCompatibilityError):
        return False


def run_shard_task(task: ShardTask, *_dependencies: Any) -> ShardResult:
    """Run one task (skipping it when complete). Extra arguments only order Dask tasks."""
    start = time.perf_counter()
    if is_complete(task):
        with ShardReader(task.output) as reader:
            rows = reader.num_rows
        return ShardResult(task.step, task.shard_index, str(task.output), rows, 0, True, 0.0)
    stage = get_stage(task.stage).from_params(task.params)
    rejects: list[dict[str, Any]] = []
    common = {
        "stage": stage.name,
        "params": stage.params(),
        "inputs": task.input_fingerprints,
        "fingerprint": task.fingerprint,
    }
    with ShardWriter(task.output, stage.output, **common) as writer:
        if isinstance(stage, SourceStage):
            _run_source(stage, task, writer, rejects)
        elif isinstance(stage, ClipStage):
            _run_clips(stage, task, writer, rejects)
        else:
            raise TypeError(f"stage {stage.name!r} is neither a source nor a clip stage")
        rows = writer.rows_written
        # Rejects are committed before the output is renamed into place (end of this block).
        with ShardWriter(task.rejects, REJECTS, **common) as rejects_writer:
            for row in rejects:
                rejects_writer.write_row(row)
    return ShardResult(
        task.step,
        task.shard_index,
        str(task.output),
        rows,
        len(rejects),
        False,
        time.perf_counter() - start,
    )


def _reject(task: ShardTask, stage: Stage, clip_id: str, exc: BaseException, fp: str) -> dict:
    reason = str(exc) if isinstance(exc, ClipRejected) else f"{type(exc).__name__}: {exc}"
    if not isinstance(exc, ClipRejected | ValueError | OSError):
        reason += " | " + traceback.format_exc(limit=3).strip().splitlines()[-1]
    return {
        "step": task.step,
        "stage": stage.name,
        "shard": task.output.name,
        "clip_id": clip_id,
        "reason": reason,
        "input_fingerprint": fp,
    }


def _run_source(
    stage: SourceStage, task: ShardTask, writer: ShardWriter, rejects: list[dict[str, Any]]
) -> None:
    for unit in task.units:
        try:
            for row in stage.process_unit(unit):
                writer.write_row(row)
        except Exception as exc:  # one bad unit must not stop the shard
            fp = task.input_fingerprints.get(unit, "")
            rejects.append(_reject(task, stage, unit, exc, fp))


def _run_clips(
    stage: ClipStage, task: ShardTask, writer: ShardWriter, rejects: list[dict[str, Any]]
) -> None:
    schemas = stage.input_schemas()
    missing = [r for r in stage.inputs if r not in task.inputs]
    if missing:
        raise ValueError(f"stage {stage.name!r} needs input roles {missing}")
    unknown = [r for r in task.inputs if r not in schemas]
    if unknown:
        raise ValueError(f"stage {stage.name!r} has no input roles {unknown}")
    roles = [r for r in schemas if r in task.inputs]  # required first: the primary is required
    readers = {role: ShardReader(task.inputs[role], schemas[role]) for role in roles}
    primary, others = roles[0], roles[1:]
    indexes = {role: readers[role].row_group_of() for role in others}
    try:
        for row in readers[primary].iter_rows():
            clip_id = row["clip_id"]
            joined: dict[str, Any] = {primary: row}
            absent = [role for role in others if clip_id not in indexes[role]]
            if absent:
                continue  # rejected upstream in another branch: nothing to join with
            for role in others:
                group = readers[role].read_row_group(indexes[role][clip_id])
                joined[role] = next(r for r in group if r["clip_id"] == clip_id)
            try:
                writer.write_row(stage.process(joined))
            except Exception as exc:  # one bad clip must not stop the shard
                fp = task.input_fingerprints.get(primary, "")
                rejects.append(_reject(task, stage, clip_id, exc, fp))
    finally:
        for reader in readers.values():
            reader.__exit__()
