"""The Dask runner: a workflow times its shards becomes a graph of :class:`ShardTask`.

- One task per (step, shard); shard ``i`` of a step depends on shard ``i`` of its inputs.
- Default: a local ``dask.distributed`` cluster of process workers sized to the machine.
  ``scheduler="tcp://HOST:PORT"`` runs the same graph on an existing cluster (its workers need
  egosim installed and the output folder on a shared filesystem).
- Steps with ``resources: {GPU: 1}`` only run on workers that declare a ``GPU`` resource. A local
  cluster gives one worker per visible CUDA device that resource; with none, GPU steps run on
  the CPU workers (with a warning) instead of waiting forever.
- ``OUT`` (and ``--input``) may be an fsspec URL (``s3://bucket/run``): shards and records are
  written through :mod:`egosim.pipeline.storage` (temporary key, move, completion marker); the
  run's lock and log live in a local scratch folder (:func:`~egosim.pipeline.storage.scratch_dir`;
  the log is copied to ``OUT/logs/run.log`` at the end), and a remote input is first copied to
  the local cache (:func:`~egosim.pipeline.storage.local_copy`) for readers that need files.
  The local cluster comes from :mod:`egosim.pipeline.cluster` (dask-cuda GPU workers when
  installed).
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
- The runner is the one planner: :func:`plan_tasks` builds every :class:`ShardTask` and its
  fingerprint. ``egosim stage`` plans a one-step workflow (:func:`plan_stage`) and runs it here
  (:func:`run_tasks_here`); ``simulate`` and ``evaluate`` run their workflow files with the given
  shards as the workflow's ``inputs``, in this process (``scheduler=IN_PROCESS``) or on Dask.
- Observable: a run appends its log to ``OUT/logs/run.log`` (Dask workers forward their
  records), starts the local cluster's dashboard (when bokeh is importable) and tells a
  :class:`~egosim.pipeline.observe.RunObserver` the dashboard's address (or why it is off),
  every clip settled and every task finished (see :mod:`egosim.pipeline.observe`).
"""

from __future__ import annotations

import contextlib
import dataclasses
import fcntl
import json
import logging
import math
import os
import socket
import warnings
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path, PurePosixPath
from typing import Any

import yaml

from egosim.pipeline import cluster as clusters
from egosim.pipeline import storage
from egosim.pipeline.execute import (
    ClipCallback,
    ShardResult,
    ShardTask,
    run_shard_task,
    task_fingerprint,
)
from egosim.pipeline.observe import (
    LOG_TOPIC,
    PROGRESS_TOPIC,
    RunObserver,
    dashboard_unavailable,
    forward_logs,
    handle_forwarded,
    log_path,
    run_log,
)
from egosim.pipeline.shards import (
    CorruptShardError,
    ShardReader,
    ShardWriter,
    read_shard_meta,
    rejects_file_name,
    shard_file_name,
    verify_shard,
)
from egosim.pipeline.stage import SourceStage, StageError, config_to_data, get_stage
from egosim.pipeline.storage import Location
from egosim.pipeline.summary import RunReport, summarize_tasks
from egosim.pipeline.workflow import Step, Workflow
from egosim.schemas import REJECTS, SchemaError
from egosim.schemas.ids import path_under, validate_id

log = logging.getLogger(__name__)

DASHBOARD_ADDRESS = ":8787"  # the local cluster's dashboard (Dask's usual port; another if taken)


class RunError(StageError):
    """Some tasks of a run failed as a whole (not a per-clip reject); lists each of them."""

    def __init__(self, message: str, report: RunReport | None = None) -> None:
        super().__init__(message)
        self.report = report  # what the tasks that finished produced (None before any ran)


class RunLockedError(RunError):
    """Another run holds the output folder's lock; the message names the folder and its pid."""


LOCK_NAME = ".lock"  # lock file of a run folder


@contextlib.contextmanager
def run_lock(out: Location) -> Iterator[Path]:
    """Hold an exclusive lock on ``out/.lock`` for the ``with`` block, or raise at once.

    ``fcntl.flock`` is released by the kernel when the process dies, so a killed run never
    leaves a stale lock. (On network filesystems without flock support, two runs from different
    machines are not kept apart.) A remote ``out`` is locked in its local scratch folder: two
    runs on this machine are kept apart, runs from two machines are not.
    """
    scratch = storage.scratch_dir(out)
    scratch.mkdir(parents=True, exist_ok=True)
    path = scratch / LOCK_NAME
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


def remove_stale_temporaries(out: Location) -> list[Location]:
    """Delete the ``*.tmp-*`` files or keys under ``out`` (only while holding :func:`run_lock`)."""
    return storage.remove_temporaries(out)


def discard_if_damaged(task: ShardTask) -> bool:
    """Remove ``task.output`` if it claims to be done (same fingerprint) but fails verification.

    Returns True when it was removed (the task then recomputes it). Outputs with another
    fingerprint are recomputed anyway and are not read here.
    """
    if not storage.exists(task.output):
        return False
    try:
        if read_shard_meta(task.output).fingerprint != task.fingerprint:
            return False
    except (CorruptShardError, SchemaError):
        return False  # unreadable provenance: the executor recomputes it anyway
    try:
        verify_shard(task.output)
    except CorruptShardError as exc:
        warnings.warn(f"recomputing {task.output}: {exc}", stacklevel=2)
        storage.remove(task.output)
        return True
    return False


@dataclass(frozen=True)
class RunSummary:
    """What a run did, per shard task."""

    out: Location  # output folder (a local path or an fsspec URL)
    results: list[ShardResult]  # one per task, in completion order
    report: RunReport  # per step: clips in, out, rejected, reasons (also OUT/summary.json)
    workers: dict[str, str] = field(default_factory=dict)  # task key -> worker that ran it

    @property
    def rejected(self) -> int:
        """Clips rejected by tasks that ran in this run."""
        return sum(r.rejected for r in self.results)


def shard_path(out: Location, step: str, index: int) -> Location:
    """Where shard ``index`` of ``step`` lives under the run folder.

    ``step`` must be a valid identifier and the path must stay under ``out``
    (:class:`~egosim.schemas.ids.InvalidIdError`, :class:`~egosim.schemas.ids.PathEscapeError`;
    a URL ``out`` is joined by :func:`egosim.pipeline.storage.join`, which refuses separators).
    """
    return _under(out, validate_id(step, "step name"), shard_file_name(index))


def rejects_path(out: Location, step: str, index: int) -> Location:
    """Where the rejects of shard ``index`` of ``step`` live (checked like :func:`shard_path`)."""
    return _under(out, validate_id(step, "step name"), rejects_file_name(index))


def _under(out: Location, *parts: str) -> Location:
    """``out / parts``, checked to stay under ``out`` (links resolved for local paths)."""
    return path_under(out, *parts) if storage.is_local(out) else storage.join(out, *parts)


# A step's shards as its readers see them: (path, fingerprint) per shard index.
_Shards = list[tuple[Path, str]]


def plan_tasks(
    workflow: Workflow,
    source: str | Sequence[str] | None,
    out: Path,
    inputs: Mapping[str, Sequence[Path]] | None = None,
    one_shard: bool = False,
) -> list[ShardTask]:
    """Turn a workflow into tasks, in dependency order, with their fingerprints.

    This is the one place where shard tasks and their fingerprints are built (``egosim run``,
    ``egosim stage``, ``simulate`` and ``evaluate`` all plan here). ``source`` is the input of
    source steps (several for ``egosim stage ingest``); ``inputs`` gives the shards of each
    workflow input (``Workflow.inputs``), fingerprinted by their provenance. ``one_shard`` puts
    every unit of a source step in one shard (``egosim stage``).
    """
    by_step = _given_inputs(workflow, inputs or {})
    tasks: list[ShardTask] = []
    for step in workflow.steps:
        stage_cls = get_stage(step.stage)
        stage = stage_cls.from_params(step.params)
        params = stage.params()
        # Per shard: (units, input paths by role, input fingerprints by role or unit).
        shards: list[tuple[tuple[str, ...], dict[str, Path], dict[str, str]]] = []
        if isinstance(stage, SourceStage):
            shards = _source_shards(step.name, stage, source, one_shard)
        else:
            counts = {role: len(by_step[up]) for role, up in step.inputs.items()}
            if len(set(counts.values())) != 1:
                raise RunError(f"step {step.name!r}: inputs have different shard counts {counts}")
            for i in range(next(iter(counts.values()))):
                ups = {role: by_step[up][i] for role, up in step.inputs.items()}
                paths = {role: path for role, (path, _) in ups.items()}
                shards.append(((), paths, {role: fp for role, (_, fp) in ups.items()}))
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
        by_step[step.name] = [(t.output, t.fingerprint) for t in step_tasks]
        tasks += step_tasks
    return tasks


def _given_inputs(workflow: Workflow, inputs: Mapping[str, Sequence[Path]]) -> dict[str, _Shards]:
    """The shards of each workflow input, with the fingerprints their provenance records."""
    missing = sorted(set(workflow.inputs) - set(inputs))
    unknown = sorted(set(inputs) - set(workflow.inputs))
    if missing or unknown:
        raise RunError(
            f"workflow {workflow.name!r} takes inputs {sorted(workflow.inputs)}; "
            f"missing {missing}, unknown {unknown}"
        )
    given: dict[str, _Shards] = {}
    for name, paths in inputs.items():
        if not paths:
            raise RunError(f"workflow input {name!r}: no shards given")
        located = [storage.location(p) for p in paths]
        given[name] = [(p, read_shard_meta(p).fingerprint) for p in located]
    return given


def _source_shards(
    step: str, stage: SourceStage, source: str | Sequence[str] | None, one_shard: bool
) -> list[tuple[tuple[str, ...], dict[str, Path], dict[str, str]]]:
    """Deal a source step's units out to shards (``units_per_shard`` each, or all in one)."""
    sources = [source] if source is None or isinstance(source, str) else list(source)
    units = [u for src in sources for u in stage.list_units(src)]
    if not units:
        raise RunError(f"step {step!r}: no inputs found under {source!r}")
    per = len(units) if one_shard else max(1, stage.units_per_shard())
    chunks = [tuple(units[i * per : (i + 1) * per]) for i in range(math.ceil(len(units) / per))]
    return [(chunk, {}, {u: stage.unit_fingerprint(u) for u in chunk}) for chunk in chunks]


def plan_stage(
    stage: str,
    params: Mapping[str, Any],
    output: Location,
    inputs: Mapping[str, Location] | None = None,
    source: Sequence[str] | None = None,
) -> ShardTask:
    """The task of ``egosim stage``: a one-step workflow, planned by :func:`plan_tasks`.

    A clip stage reads ``inputs`` (role -> shard) as workflow inputs; a source stage lists the
    units of every path in ``source`` into one shard. The task writes ``output`` and its rejects
    beside it (``NAME.rejects.parquet``); its fingerprint is that of a one-shard ``egosim run``.
    """
    stage_cls = get_stage(stage)
    schemas = stage_cls.input_schemas()
    given = dict(inputs or {})
    unknown = sorted(set(given) - set(schemas))
    if unknown:
        raise StageError(f"stage {stage!r} has no input roles {unknown} (takes {list(schemas)})")
    step = Step(
        name=validate_id(stage, "step name"),
        stage=stage,
        params=config_to_data(stage_cls.from_params(params).config),
        inputs={role: role for role in given},
    )
    workflow = Workflow(
        name=stage, steps=(step,), inputs={role: schemas[role].name for role in given}
    )
    (task,) = plan_tasks(
        workflow,
        source[0] if source and len(source) == 1 else source,
        storage.parent(output),
        inputs={role: [path] for role, path in given.items()},
        one_shard=True,
    )
    stem = PurePosixPath(storage.name(output)).stem
    rejects = storage.with_name(output, stem + ".rejects.parquet")
    return dataclasses.replace(task, output=output, rejects=rejects)


def run_tasks_here(
    tasks: Sequence[ShardTask],
    progress: Callable[[ShardResult, int, int], None] | None = None,
    observer: RunObserver | None = None,
) -> list[ShardResult]:
    """Run ``tasks`` one after another in this process (dependency order), no Dask.

    Like a worker, a finished output is verified before it is skipped. ``observer`` hears of
    every clip and task.
    """
    results = []
    for task in tasks:
        discard_if_damaged(task)
        on_clip = None
        if observer is not None:
            on_clip = _clip_reporter(observer.clip_settled, task)
        results.append(run_shard_task(task, on_clip=on_clip))
        if observer is not None:
            observer.task_finished(results[-1])
        if progress is not None:
            progress(results[-1], len(results), len(tasks))
    return results


def _clip_reporter(report: Callable[[str, int, str, str], None], task: ShardTask) -> ClipCallback:
    """An ``on_clip`` callback of ``task`` that calls ``report(step, shard, clip, outcome)``."""

    def on_clip(clip_id: str, outcome: str) -> None:
        report(task.step, task.shard_index, clip_id, outcome)

    return on_clip


def _post_progress(step: str, shard_index: int, clip_id: str, outcome: str) -> None:
    """Worker side: send one settled clip to the client as a Dask event."""
    from distributed import get_worker

    message = {"step": step, "shard_index": shard_index, "clip_id": clip_id, "outcome": outcome}
    get_worker().log_event(PROGRESS_TOPIC, message)


def _run_and_name_worker(
    task: ShardTask, client_process: tuple[str, int], *deps: Any
) -> tuple[ShardResult, str]:
    """Worker-side wrapper: run the task and say which worker ran it.

    A worker in another process than the client's (``client_process`` = host, pid) forwards
    the task's log records to the client as Dask events; one in the client's process logs
    straight to the run log.
    """
    from distributed import get_worker

    try:
        import torch

        torch.set_num_threads(1)
    except ImportError:  # pragma: no cover - torch is a hard dependency
        pass
    worker = get_worker()
    here = (socket.gethostname(), os.getpid()) == tuple(client_process)
    forwarding = contextlib.nullcontext() if here else forward_logs(_post_log)
    with forwarding:
        discard_if_damaged(task)
        result = run_shard_task(task, on_clip=_clip_reporter(_post_progress, task))
    return result, worker.name


def _post_log(attrs: dict[str, Any]) -> None:
    """Worker side: send one log record's attributes to the client as a Dask event."""
    from distributed import get_worker

    get_worker().log_event(LOG_TOPIC, attrs)


def local_cluster(
    n_workers: int | None = None,
    gpu_workers: int | None = None,
    dashboard_address: str | None = DASHBOARD_ADDRESS,
) -> Any:
    """A local cluster of process workers; ``gpu_workers`` of them declare ``GPU: 1``.

    ``gpu_workers`` defaults to the number of visible CUDA devices; with dask-cuda installed
    they come from ``LocalCUDACluster`` (:func:`egosim.pipeline.cluster.local_cluster`). The
    scheduler's HTTP server (the dashboard, when bokeh is importable) listens on
    ``dashboard_address``.
    """
    return clusters.local_cluster(n_workers, gpu_workers, dashboard_address)


IN_PROCESS = "here"  # scheduler value of run_workflow: run every task in this process, no Dask


def run_workflow(
    workflow: Workflow,
    out: Path,
    source: str | None = None,
    scheduler: str | None = None,
    n_workers: int | None = None,
    gpu_workers: int | None = None,
    progress: Callable[[ShardResult, int, int], None] | None = None,
    inputs: Mapping[str, Sequence[Path]] | None = None,
    observer: RunObserver | None = None,
) -> RunSummary:
    """Run every (step, shard) task of ``workflow``; see the module doc.

    ``scheduler``: None for a local Dask cluster, ``tcp://HOST:PORT`` for an existing one, or
    :data:`IN_PROCESS` to run the tasks one after another in this process. ``inputs`` gives the
    shards of the workflow's declared inputs. ``observer`` hears of the run as it goes
    (progress displays); the run's log goes to ``out/logs/run.log``. Raises
    :class:`RunLockedError` at once when another run holds ``out``.
    """
    out = storage.location(out)
    storage.makedirs(out)
    observer = observer or RunObserver()
    scratch = storage.scratch_dir(out)
    with run_lock(out), run_log(scratch), _log_copied(scratch, out):
        try:
            return _run_locked(
                workflow,
                out,
                source,
                scheduler,
                n_workers,
                gpu_workers,
                progress,
                inputs,
                observer,
            )
        except Exception:
            log.exception("run of workflow %r in %s failed", workflow.name, out)
            raise
        finally:
            observer.run_finished()


def _run_locked(
    workflow: Workflow,
    out: Path,
    source: str | None,
    scheduler: str | None,
    n_workers: int | None,
    gpu_workers: int | None,
    progress: Callable[[ShardResult, int, int], None] | None,
    inputs: Mapping[str, Sequence[Path]] | None,
    observer: RunObserver,
) -> RunSummary:
    """:func:`run_workflow` once the run holds its folder's lock and its log is open."""
    log.info("run of workflow %r into %s, input %r", workflow.name, out, source)
    remove_stale_temporaries(out)
    write_text_atomic(
        storage.join(out, "workflow.resolved.yaml"),
        yaml.safe_dump(
            {
                **workflow.to_dict(),
                "input": source,
                **({"given": _given_record(inputs)} if inputs else {}),
            },
            sort_keys=False,
        ),
    )
    tasks = plan_tasks(workflow, local_source(source), out, inputs)
    log.info("planned %d shard task(s) in %d step(s)", len(tasks), len(workflow.steps))
    observer.run_started(workflow.name, tasks)
    if scheduler == IN_PROCESS:
        results = run_tasks_here(tasks, progress, observer)
        report = _write_run_records(out, tasks, results)
        return RunSummary(out=out, results=results, report=report)
    return _run_on_dask(workflow, out, tasks, scheduler, n_workers, gpu_workers, progress, observer)


def _given_record(inputs: Mapping[str, Sequence[Path]]) -> dict[str, list[str]]:
    return {name: [str(p) for p in paths] for name, paths in inputs.items()}


def _run_on_dask(
    workflow: Workflow,
    out: Path,
    tasks: list[ShardTask],
    scheduler: str | None,
    n_workers: int | None,
    gpu_workers: int | None,
    progress: Callable[[ShardResult, int, int], None] | None,
    observer: RunObserver,
) -> RunSummary:
    """Run planned ``tasks`` on a Dask cluster once the run holds its folder's lock."""
    from distributed import Client

    cluster = None
    if scheduler is None:
        cluster = local_cluster(n_workers, gpu_workers)
        client = Client(cluster)
    else:
        client = Client(scheduler)
    try:
        _follow_cluster(client, observer)
        keys = _submit_tasks(client, workflow, tasks)
        results, workers, failures = _collect_results(keys, len(tasks), progress, observer)
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
    report = _write_run_records(out, tasks, results)
    if failures:
        message = f"{len(failures)} task(s) failed:\n  - " + "\n  - ".join(failures)
        raise RunError(message, report)
    return RunSummary(out=out, results=results, report=report, workers=workers)


def _follow_cluster(client: Any, observer: RunObserver) -> None:
    """Tell ``observer`` the dashboard and every settled clip; show the workers' log records."""
    link, reason = _dashboard(client)
    log.info("Dask dashboard: %s", link or reason)
    observer.dashboard(link, reason)

    def on_progress(event: tuple[float, dict[str, Any]]) -> None:
        msg = event[1]  # Dask adds the sending worker's address to it
        observer.clip_settled(msg["step"], msg["shard_index"], msg["clip_id"], msg["outcome"])

    client.subscribe_topic(PROGRESS_TOPIC, on_progress)
    client.subscribe_topic(LOG_TOPIC, lambda event: handle_forwarded(event[1]))


def _submit_tasks(client: Any, workflow: Workflow, tasks: list[ShardTask]) -> dict[Any, str]:
    """Submit every task, after the tasks of the same shard it reads; returns future -> key.

    A step that asks for a GPU runs on CPU workers (with a warning) when no worker declares one.
    """
    client_process = (socket.gethostname(), os.getpid())
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
                stacklevel=3,  # points at run_workflow, as it did before this was split out
            )
            resources.pop("GPU")
        deps = [
            futures[(up, task.shard_index)]
            for up in step.inputs.values()
            if up not in workflow.inputs  # given shards: nothing to wait for
        ]
        key = f"{task.step}-{task.shard_index:05d}-{task.fingerprint}"
        future = client.submit(
            _run_and_name_worker,
            task,
            client_process,
            *deps,
            key=key,
            resources=resources or None,
            pure=False,
        )
        futures[(task.step, task.shard_index)] = future
        keys[future] = key
    return keys


def _collect_results(
    keys: dict[Any, str],
    n_tasks: int,
    progress: Callable[[ShardResult, int, int], None] | None,
    observer: RunObserver,
) -> tuple[list[ShardResult], dict[str, str], list[str]]:
    """Wait for the futures as they finish: the results, each task key's worker, the failures."""
    from distributed import as_completed

    results: list[ShardResult] = []
    workers: dict[str, str] = {}
    failures: list[str] = []
    for future in as_completed(list(keys)):
        key = keys[future]
        try:
            result, worker = future.result()
        except Exception as exc:  # report every failed task, not just the first
            failures.append(f"{key.rsplit('-', 1)[0]}: {type(exc).__name__}: {exc}")
            log.error("task %s failed: %s: %s", key, type(exc).__name__, exc)
            continue
        results.append(result)
        workers[key] = worker
        observer.task_finished(result)
        if progress is not None:
            progress(result, len(results) + len(failures), n_tasks)
    return results, workers, failures


def _dashboard(client: Any) -> tuple[str, str]:
    """The scheduler's dashboard address, or '' and the reason there is none.

    The scheduler always serves HTTP, but the dashboard pages need bokeh where it runs.
    """
    if "dashboard" not in client.scheduler_info(n_workers=0).get("services", {}):
        return "", "the Dask dashboard is off: the scheduler serves no HTTP"
    try:
        reason = client.run_on_scheduler(lambda: dashboard_unavailable())
    except Exception as exc:  # e.g. egosim not importable where the scheduler runs
        log.warning("could not ask the scheduler whether bokeh is installed: %s", exc)
        reason = ""
    if reason:
        return "", f"{reason} on the scheduler"
    return client.dashboard_link, ""


def _workers_with_gpu(client: Any) -> bool:
    info = client.scheduler_info(n_workers=-1)["workers"]
    return any(w.get("resources", {}).get("GPU", 0) > 0 for w in info.values())


def write_text_atomic(path: Location, text: str) -> None:
    """Write ``text`` to a temporary file next to ``path`` and rename it into place.

    A reader sees the old file or the new one, never a half-written one (on an object store:
    a temporary key, moved, then its completion marker; see :mod:`egosim.pipeline.storage`).
    """
    storage.write_text_atomic(storage.location(path), text)


def local_source(source: str | Sequence[str] | None) -> str | Sequence[str] | None:
    """``source`` with every fsspec URL replaced by its local copy (downloaded once).

    Source readers (PyAV, OpenCV, h5py, pycolmap) need local files: a remote ``--input`` is
    copied to the local cache by :func:`egosim.pipeline.storage.local_copy`.
    """
    if source is None:
        return None
    if isinstance(source, str):
        return _local_source(source)
    return [_local_source(s) for s in source]


def _local_source(source: str) -> str:
    """One source: a URL's local copy, a ``file://`` URL's path, anything else as it is."""
    if storage.is_url(source):
        return str(storage.local_copy(source))
    return source.removeprefix("file://")


@contextlib.contextmanager
def _log_copied(scratch: Path, out: Location) -> Iterator[None]:
    """On leaving, copy a remote run's local log to ``OUT/logs/run.log`` (local runs: no-op)."""
    try:
        yield
    finally:
        local_log = log_path(scratch)
        if not storage.is_local(out) and local_log.is_file():
            try:
                storage.upload(local_log, storage.join(out, *local_log.relative_to(scratch).parts))
            except OSError as exc:  # the run's outcome matters more than its log copy
                warnings.warn(f"could not copy the run log to {out}: {exc}", stacklevel=2)


def _write_run_records(
    out: Path, tasks: Sequence[ShardTask], results: list[ShardResult]
) -> RunReport:
    """Write ``manifest.json``, the merged ``rejects.parquet`` and ``summary.json`` of the run."""
    manifest = {
        "tasks": [json.loads(json.dumps(asdict(t), default=str)) for t in tasks],
        "results": [asdict(r) for r in results],
    }
    write_text_atomic(
        storage.join(out, "manifest.json"), json.dumps(manifest, indent=1, default=str)
    )
    with ShardWriter(storage.join(out, "rejects.parquet"), REJECTS, stage="runner") as writer:
        for task in tasks:
            if storage.is_committed(task.rejects):
                with ShardReader(task.rejects, REJECTS) as reader:
                    for row in reader.iter_rows():
                        writer.write_row(row)
    report = summarize_tasks(tasks, results)
    write_text_atomic(storage.join(out, "summary.json"), report.to_json())
    for s in report.steps:
        log.info(
            "step %s: %d in, %d out, %d rejected, %d unmatched, %.2f s",
            s.step,
            s.clips_in,
            s.clips_out,
            s.rejected,
            s.unmatched,
            s.seconds,
        )
    return report
