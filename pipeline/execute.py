"""Run one stage on one shard: the unit of work the runner schedules (and `egosim stage` runs).

A :class:`ShardTask` is plain data (picklable) so that a Dask worker can run it. The executor
skips a task whose output exists with the same fingerprint, records rejected clips in a
rejects shard next to the output, and writes both atomically (rejects first, output last, so
an existing output always has its rejects). A clip stage's input roles are read with only the
columns it declares (``ClipStage.columns``, plus ``clip_id`` for the join); a stage that reads
an undeclared column fails the task (:class:`UndeclaredColumnError`), it is not a reject. Each
role's row reaches ``process`` as the typed record of its schema
(:mod:`egosim.pipeline.records`), which also answers the plain mapping access.

It logs through ``logging.getLogger(__name__)`` (the run log, ``RUN/logs/run.log``; see
:mod:`egosim.pipeline.observe`): a line per task started and finished and one per clip, each
naming the step, stage, shard and clip. An optional ``on_clip`` callback hears of every clip
(or source unit) as it is settled, for live progress displays.
"""

from __future__ import annotations

import hashlib
import json
import logging
import time
import traceback
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

from egosim.pipeline import storage
from egosim.pipeline.records import Record, record_class
from egosim.pipeline.shards import CorruptShardError, ShardReader, ShardWriter, read_shard_meta
from egosim.pipeline.stage import (
    ClipRejected,
    ClipStage,
    SourceStage,
    Stage,
    UndeclaredColumnError,
    get_stage,
)
from egosim.pipeline.storage import Location
from egosim.schemas import REJECTS, SchemaCompatibilityError

log = logging.getLogger(__name__)

# What happened to one clip (or source unit) of a task, as passed to an ``on_clip`` callback.
CLIP_DONE = "done"  # the stage wrote a row for it (a source unit: it made its clips)
CLIP_REJECTED = "rejected"  # it went to the rejects table
CLIP_UNMATCHED = "unmatched"  # absent from another input (rejected in another branch)
TASK_STARTED = "started"  # not a clip: the task began computing (clip id ''), for clip rates

# on_clip(clip id or source unit, one of the CLIP_* outcomes)
ClipCallback = Callable[[str, str], None]


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
    output: Location  # output shard: a local path or an fsspec URL (pipeline.storage)
    rejects: Location  # rejects shard path
    inputs: dict[str, Location] = field(default_factory=dict)  # role -> input shard (clip stages)
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
    if not storage.is_committed(task.output) or not storage.is_committed(task.rejects):
        return False
    try:
        return read_shard_meta(task.output).fingerprint == task.fingerprint
    except (CorruptShardError, SchemaCompatibilityError):
        return False


def primary_role(task: ShardTask) -> str | None:
    """The input role whose clips a clip task iterates (None for a source task).

    It is the first role the stage declares that the task was given (required roles come
    first, so it is always a required one).
    """
    schemas = get_stage(task.stage).input_schemas()
    return next((role for role in schemas if role in task.inputs), None)


def task_label(task: ShardTask) -> str:
    """``step=… stage=… shard=…``: how log lines name a task."""
    return f"step={task.step} stage={task.stage} shard={storage.name(task.output)}"


def run_shard_task(
    task: ShardTask, *_dependencies: Any, on_clip: ClipCallback | None = None
) -> ShardResult:
    """Run one task (skipping it when complete). Extra arguments only order Dask tasks.

    ``on_clip`` is called once per clip (per unit, for a source stage) with its outcome
    (:data:`CLIP_DONE`, :data:`CLIP_REJECTED` or :data:`CLIP_UNMATCHED`), and once with
    ``("", TASK_STARTED)`` when the task starts computing (not when it is skipped).
    """
    start = time.perf_counter()
    if is_complete(task):
        with ShardReader(task.output) as reader:
            rows = reader.num_rows
        log.info(
            "%s skipped: done before with the same fingerprint (%d rows)", task_label(task), rows
        )
        return ShardResult(task.step, task.shard_index, str(task.output), rows, 0, True, 0.0)
    what = f"{len(task.units)} unit(s)" if task.units else f"inputs {sorted(task.inputs)}"
    log.info("%s started: %s", task_label(task), what)
    if on_clip is not None:
        on_clip("", TASK_STARTED)
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
            _run_source(stage, task, writer, rejects, on_clip)
        elif isinstance(stage, ClipStage):
            _run_clips(stage, task, writer, rejects, on_clip)
        else:
            raise TypeError(f"stage {stage.name!r} is neither a source nor a clip stage")
        rows = writer.rows_written
        # Rejects are committed before the output is renamed into place (end of this block).
        with ShardWriter(task.rejects, REJECTS, **common) as rejects_writer:
            for row in rejects:
                rejects_writer.write_row(row)
    seconds = time.perf_counter() - start
    log.info(
        "%s finished: %d rows, %d rejected, %.2f s", task_label(task), rows, len(rejects), seconds
    )
    return ShardResult(
        task.step, task.shard_index, str(task.output), rows, len(rejects), False, seconds
    )


def _reject(task: ShardTask, stage: Stage, clip_id: str, exc: BaseException, fp: str) -> dict:
    reason = str(exc) if isinstance(exc, ClipRejected) else f"{type(exc).__name__}: {exc}"
    crashed = not isinstance(exc, ClipRejected | ValueError | OSError)
    if crashed:
        reason += " | " + traceback.format_exc(limit=3).strip().splitlines()[-1]
    # An unexpected exception keeps its traceback in the run log.
    log.warning(
        "%s clip=%s rejected: %s",
        task_label(task),
        clip_id,
        reason,
        exc_info=exc if crashed else None,
    )
    return {
        "step": task.step,
        "stage": stage.name,
        "shard": storage.name(task.output),
        "clip_id": clip_id,
        "reason": reason,
        "input_fingerprint": fp,
    }


def _settled(
    task: ShardTask, clip_id: str, outcome: str, start: float, on_clip: ClipCallback | None
) -> None:
    """Log one settled clip (or unit) and tell ``on_clip``."""
    if outcome != CLIP_REJECTED:  # rejects were logged with their reason
        log.info(
            "%s clip=%s %s in %.2f s",
            task_label(task),
            clip_id,
            outcome,
            time.perf_counter() - start,
        )
    if on_clip is not None:
        on_clip(clip_id, outcome)


def _run_source(
    stage: SourceStage,
    task: ShardTask,
    writer: ShardWriter,
    rejects: list[dict[str, Any]],
    on_clip: ClipCallback | None,
) -> None:
    for unit in task.units:
        start = time.perf_counter()
        outcome = CLIP_DONE
        try:
            for row in stage.process_unit(unit):
                writer.write_row(row)
                log.info("%s unit=%s made clip=%s", task_label(task), unit, row["clip_id"])
        except Exception as exc:  # one bad unit must not stop the shard
            fp = task.input_fingerprints.get(unit, "")
            rejects.append(_reject(task, stage, unit, exc, fp))
            outcome = CLIP_REJECTED
        _settled(task, unit, outcome, start, on_clip)


def _run_clips(
    stage: ClipStage,
    task: ShardTask,
    writer: ShardWriter,
    rejects: list[dict[str, Any]],
    on_clip: ClipCallback | None,
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
    # Only the columns the stage declares (ClipStage.columns) are read and decoded.
    columns = {role: stage.read_columns(role) for role in roles}
    try:
        for row in readers[primary].iter_rows(columns[primary]):
            clip_id = row["clip_id"]
            start = time.perf_counter()
            joined: dict[str, Any] = {primary: _record(stage, primary, row)}
            absent = [role for role in others if clip_id not in indexes[role]]
            if absent:  # rejected upstream in another branch: nothing to join with
                log.info("%s clip=%s not in input(s) %s", task_label(task), clip_id, absent)
                _settled(task, clip_id, CLIP_UNMATCHED, start, on_clip)
                continue
            for role in others:
                group = readers[role].read_row_group(indexes[role][clip_id], columns[role])
                found = next(r for r in group if r["clip_id"] == clip_id)
                joined[role] = _record(stage, role, found)
            outcome = CLIP_DONE
            try:
                writer.write_row(stage.process(joined))
            except UndeclaredColumnError:  # a bug in the stage's declaration, not in the clip
                raise
            except Exception as exc:  # one bad clip must not stop the shard
                fp = task.input_fingerprints.get(primary, "")
                rejects.append(_reject(task, stage, clip_id, exc, fp))
                outcome = CLIP_REJECTED
            _settled(task, clip_id, outcome, start, on_clip)
    finally:
        for reader in readers.values():
            reader.__exit__()


def _record(stage: ClipStage, role: str, row: dict[str, Any]) -> Record:
    """``row`` as ``process`` gets it: the typed record of the role's schema
    (:func:`egosim.pipeline.records.record_class`), refusing the columns that were not read."""
    schema = stage.input_schemas()[role]
    return record_class(schema)(row, stage.name, role, schema.column_names)
