"""The Dask runner: a workflow times its shards becomes a graph of :class:`ShardTask`.

- One task per (step, shard); shard ``i`` of a step depends on shard ``i`` of its inputs.
- Default: a local ``dask.distributed`` cluster of process workers sized to the machine.
  ``scheduler="tcp://HOST:PORT"`` runs the same graph on an existing cluster (its workers need
  egosim installed and the output folder on a shared filesystem).
- Steps with ``resources: {GPU: 1}`` only run on workers that declare a ``GPU`` resource. A local
  cluster gives one worker per visible CUDA device that resource; with none, GPU steps run on
  the CPU workers (with a warning) instead of waiting forever.
- Output layout: ``OUT/<step>/shard-00000.parquet`` and ``rejects-00000.parquet``,
  ``OUT/rejects.parquet`` (all rejects), ``OUT/manifest.json`` (per-shard results),
  ``OUT/summary.json`` (per step: clips in, out, rejected, top reasons; see
  :mod:`egosim.pipeline.summary`) and ``OUT/workflow.resolved.yaml``. The JSON and YAML files
  are written to a temporary file and renamed into place, like shards.
- One run at a time per output folder: a run holds an exclusive ``flock`` on ``OUT/.lock``
  (which names its pid) and a second run on the same folder fails at once with
  :class:`RunLockedError`. Holding the lock, a run removes the temporary files (``*.tmp-*``)
  that killed or failed runs left behind.
- Before a task is skipped as done, its output is read and verified (page checksums, content
  hashes); a damaged output is removed and recomputed.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import logging
import math
import os
import uuid
import warnings
from collections.abc import Callable, Iterator, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import yaml

from egosim.pipeline.execute import ShardResult, ShardTask, run_shard_task, task_fingerprint
from egosim.pipeline.shards import (
    TMP_MARKER,
    CorruptShardError,
    ShardReader,
    ShardWriter,
    read_shard_meta,
    verify_shard,
)
from egosim.pipeline.stage import SourceStage, StageError, get_stage
from egosim.pipeline.summary import RunReport, summarize_tasks
from egosim.pipeline.workflow import Workflow
from egosim.schemas import REJECTS, SchemaError
from egosim.schemas.ids import path_under, validate_id

log = logging.getLogger(__name__)


class RunError(StageError):
    """Some tasks of a run failed as a whole (not a per-clip reject); lists each of them."""

    def __init__(self, message: str, report: RunReport | None = None) -> None:
        super().__init__(message)
        self.report = report  # what the tasks that finished produced (None before any ran)


class RunLockedError(RunError):
    """Another run holds the output folder's lock; the message names the folder and its pid."""


LOCK_NAME = ".lock"  # lock file of a run folder


@contextlib.contextmanager
def run_lock(out: Path) -> Iterator[Path]:
    """Hold an exclusive lock on ``out/.lock`` for the ``with`` block, or raise at once.

    ``fcntl.flock`` is released by the kernel when the process dies, so a killed run never
    leaves a stale lock. (On network filesystems without flock support, two runs from different
    machines are not kept apart.)
    """
    path = Path(out) / LOCK_NAME
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 64, 0).decode(errors="replace").strip() or "unknown"
            raise RunLockedError(
                f"another egosim run is writing {out} (pid {holder}, lock {path}); wait for it "
                "to finish or use another --out"
            ) from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        yield path
    finally:
        os.close(fd)  # releases the lock


def remove_stale_temporaries(out: Path) -> list[Path]:
    """Delete the ``*.tmp-*`` files under ``out`` (call only while holding :func:`run_lock`)."""
    removed = []
    for path in sorted(Path(out).rglob(f"*{TMP_MARKER}*")):
        if path.is_file() and not path.is_symlink():
            path.unlink(missing_ok=True)
            removed.append(path)
    if removed:
        log.info("removed %d stale temporary file(s) under %s", len(removed), out)
    return removed


def discard_if_damaged(task: ShardTask) -> bool:
    """Remove ``task.output`` if it claims to be done (same fingerprint) but fails verification.

    Returns True when it was removed (the task then recomputes it). Outputs with another
    fingerprint are recomputed anyway and are not read here.
    """
    if not task.output.is_file():
        return False
    try:
        if read_shard_meta(task.output).fingerprint != task.fingerprint:
            return False
    except (CorruptShardError, SchemaError):
        return False  # unreadable provenance: the executor recomputes it anyway
    try:
        verify_shard(task.output)
    except CorruptShardError as exc:
        log.warning("recomputing %s: %s", task.output, exc)
        task.output.unlink(missing_ok=True)
        return True
    return False


@dataclass(frozen=True)
class RunSummary:
    """What a run did, per shard task."""

    out: Path  # output folder
    results: list[ShardResult]  # one per task, in completion order
    report: RunReport  # per step: clips in, out, rejected, reasons (also OUT/summary.json)
    workers: dict[str, str] = field(default_factory=dict)  # task key -> worker that ran it

    @property
    def rejected(self) -> int:
        """Clips rejected by tasks that ran in this run."""
        return sum(r.rejected for r in self.results)


def shard_path(out: Path, step: str, index: int) -> Path:
    """Where shard ``index`` of ``step`` lives under the run folder.

    ``step`` must be a valid identifier and the path must stay under ``out``
    (:class:`~egosim.schemas.ids.InvalidIdError`, :class:`~egosim.schemas.ids.PathEscapeError`).
    """
    return path_under(out, validate_id(step, "step name"), f"shard-{index:05d}.parquet")


def rejects_path(out: Path, step: str, index: int) -> Path:
    """Where the rejects of shard ``index`` of ``step`` live (checked like :func:`shard_path`)."""
    return path_under(out, validate_id(step, "step name"), f"rejects-{index:05d}.parquet")


def plan_tasks(workflow: Workflow, source: str | None, out: Path) -> list[ShardTask]:
    """Turn a workflow into tasks, in dependency order, with their fingerprints."""
    tasks: list[ShardTask] = []
    by_step: dict[str, list[ShardTask]] = {}
    for step in workflow.steps:
        stage_cls = get_stage(step.stage)
        stage = stage_cls.from_params(step.params)
        params = stage.params()
        # Per shard: (units, input paths by role, input fingerprints by role or unit).
        shards: list[tuple[tuple[str, ...], dict[str, Path], dict[str, str]]] = []
        if isinstance(stage, SourceStage):
            units = stage.list_units(source)
            if not units:
                raise RunError(f"step {step.name!r}: no inputs found under {source!r}")
            per = max(1, stage.units_per_shard())
            for i in range(math.ceil(len(units) / per)):
                chunk = tuple(units[i * per : (i + 1) * per])
                shards.append((chunk, {}, {u: stage.unit_fingerprint(u) for u in chunk}))
        else:
            counts = {role: len(by_step[up]) for role, up in step.inputs.items()}
            if len(set(counts.values())) != 1:
                raise RunError(f"step {step.name!r}: inputs have different shard counts {counts}")
            for i in range(next(iter(counts.values()))):
                ups = {role: by_step[up][i] for role, up in step.inputs.items()}
                paths = {role: t.output for role, t in ups.items()}
                shards.append(((), paths, {role: t.fingerprint for role, t in ups.items()}))
        count = len(shards)
        step_tasks = [
            ShardTask(
                step=step.name,
                stage=step.stage,
                params=params,
                shard_index=i,
                shard_count=count,
                output=shard_path(out, step.name, i),
                rejects=rejects_path(out, step.name, i),
                inputs=paths,
                units=units,
                input_fingerprints=in_fps,
                fingerprint=task_fingerprint(stage_cls, params, in_fps, i, count),
            )
            for i, (units, paths, in_fps) in enumerate(shards)
        ]
        by_step[step.name] = step_tasks
        tasks += step_tasks
    return tasks


def _run_and_name_worker(task: ShardTask, *deps: Any) -> tuple[ShardResult, str]:
    """Worker-side wrapper: run the task and say which worker ran it."""
    from distributed import get_worker

    try:
        import torch

        torch.set_num_threads(1)
    except ImportError:  # pragma: no cover - torch is a hard dependency
        pass
    discard_if_damaged(task)
    return run_shard_task(task), get_worker().name


def local_cluster(n_workers: int | None = None, gpu_workers: int | None = None) -> Any:
    """A local cluster of process workers; ``gpu_workers`` of them declare ``GPU: 1``.

    ``gpu_workers`` defaults to the number of visible CUDA devices.
    """
    from distributed import Nanny, Scheduler, SpecCluster

    if gpu_workers is None:
        import torch

        gpu_workers = torch.cuda.device_count()
    if n_workers is None:
        n_workers = max(1, min(os.cpu_count() or 1, 8))
    workers: dict[str, dict[str, Any]] = {}
    for i in range(n_workers):
        options: dict[str, Any] = {"nthreads": 1, "silence_logs": logging.WARNING}
        if i < gpu_workers:
            options["resources"] = {"GPU": 1}
            options["env"] = {"CUDA_VISIBLE_DEVICES": str(i)}
        workers[f"{'gpu' if i < gpu_workers else 'cpu'}-{i}"] = {"cls": Nanny, "options": options}
    scheduler = {"cls": Scheduler, "options": {"dashboard_address": None}}
    return SpecCluster(
        workers=workers, scheduler=scheduler, silence_logs=logging.WARNING, asynchronous=False
    )


def run_workflow(
    workflow: Workflow,
    out: Path,
    source: str | None = None,
    scheduler: str | None = None,
    n_workers: int | None = None,
    gpu_workers: int | None = None,
    progress: Callable[[ShardResult, int, int], None] | None = None,
) -> RunSummary:
    """Run every (step, shard) task of ``workflow`` on a Dask cluster; see the module doc.

    Raises :class:`RunLockedError` at once when another run holds ``out``.
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    with run_lock(out):
        remove_stale_temporaries(out)
        return _run_locked(workflow, out, source, scheduler, n_workers, gpu_workers, progress)


def _run_locked(
    workflow: Workflow,
    out: Path,
    source: str | None,
    scheduler: str | None,
    n_workers: int | None,
    gpu_workers: int | None,
    progress: Callable[[ShardResult, int, int], None] | None,
) -> RunSummary:
    """:func:`run_workflow` once the run holds its folder's lock."""
    from distributed import Client, as_completed

    write_text_atomic(
        out / "workflow.resolved.yaml",
        yaml.safe_dump({**workflow.to_dict(), "input": source}, sort_keys=False),
    )
    tasks = plan_tasks(workflow, source, out)
    cluster = None
    if scheduler is None:
        cluster = local_cluster(n_workers, gpu_workers)
        client = Client(cluster)
    else:
        client = Client(scheduler)
    try:
        gpu_capable = _workers_with_gpu(client)
        futures: dict[tuple[str, int], Any] = {}
        keys: dict[Any, str] = {}
        for task in tasks:
            step = workflow.step(task.step)
            resources = dict(step.resources)
            if resources.get("GPU") and not gpu_capable:
                warnings.warn(
                    f"step {task.step!r} asks for a GPU but no worker declares one: "
                    "running it on CPU workers",
                    stacklevel=2,
                )
                resources.pop("GPU")
            deps = [futures[(up, task.shard_index)] for up in step.inputs.values()]
            key = f"{task.step}-{task.shard_index:05d}-{task.fingerprint}"
            future = client.submit(
                _run_and_name_worker, task, *deps, key=key, resources=resources or None, pure=False
            )
            futures[(task.step, task.shard_index)] = future
            keys[future] = key
        results: list[ShardResult] = []
        workers: dict[str, str] = {}
        failures: list[str] = []
        for future in as_completed(list(futures.values())):
            key = keys[future]
            try:
                result, worker = future.result()
            except Exception as exc:  # report every failed task, not just the first
                failures.append(f"{key.rsplit('-', 1)[0]}: {type(exc).__name__}: {exc}")
                continue
            results.append(result)
            workers[key] = worker
            if progress is not None:
                progress(result, len(results) + len(failures), len(tasks))
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
    report = _write_run_records(out, tasks, results)
    if failures:
        message = f"{len(failures)} task(s) failed:\n  - " + "\n  - ".join(failures)
        raise RunError(message, report)
    return RunSummary(out=out, results=results, report=report, workers=workers)


def _workers_with_gpu(client: Any) -> bool:
    info = client.scheduler_info(n_workers=-1)["workers"]
    return any(w.get("resources", {}).get("GPU", 0) > 0 for w in info.values())


def write_text_atomic(path: Path, text: str) -> None:
    """Write ``text`` to a temporary file next to ``path`` and rename it into place.

    A reader sees the old file or the new one, never a half-written one.
    """
    path = Path(path)
    # Same naming as shard writes (and mode from the umask, unlike mkstemp's 0600).
    tmp = path.with_name(f"{path.name}{TMP_MARKER}{uuid.uuid4().hex[:8]}")
    try:
        tmp.write_text(text)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def _write_run_records(
    out: Path, tasks: Sequence[ShardTask], results: list[ShardResult]
) -> RunReport:
    """Write ``manifest.json``, the merged ``rejects.parquet`` and ``summary.json`` of the run."""
    manifest = {
        "tasks": [json.loads(json.dumps(asdict(t), default=str)) for t in tasks],
        "results": [asdict(r) for r in results],
    }
    write_text_atomic(out / "manifest.json", json.dumps(manifest, indent=1, default=str))
    with ShardWriter(out / "rejects.parquet", REJECTS, stage="runner") as writer:
        for task in tasks:
            if task.rejects.is_file():
                with ShardReader(task.rejects, REJECTS) as reader:
                    for row in reader.iter_rows():
                        writer.write_row(row)
    report = summarize_tasks(tasks)
    write_text_atomic(out / "summary.json", report.to_json())
    return report
