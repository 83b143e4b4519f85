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
- The runner is the one planner: :func:`plan_tasks` builds every :class:`ShardTask` and its
  fingerprint. ``egosim stage`` plans a one-step workflow (:func:`plan_stage`) and runs it here
  (:func:`run_tasks_here`); ``simulate`` and ``evaluate`` run their workflow files with the given
  shards as the workflow's ``inputs``, in this process (``scheduler=IN_PROCESS``) or on Dask.
"""

from __future__ import annotations

import contextlib
import dataclasses
import fcntl
import json
import logging
import math
import os
import uuid
import warnings
from collections.abc import Callable, Iterator, Mapping, Sequence
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
    rejects_file_name,
    shard_file_name,
    verify_shard,
)
from egosim.pipeline.stage import SourceStage, StageError, config_to_data, get_stage
from egosim.pipeline.summary import RunReport, summarize_tasks
from egosim.pipeline.workflow import Step, Workflow
from egosim.schemas import REJECTS, SchemaError
from egosim.schemas.ids import path_under, validate_id


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
        warnings.warn(f"recomputing {task.output}: {exc}", stacklevel=2)
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
    return path_under(out, validate_id(step, "step name"), shard_file_name(index))


def rejects_path(out: Path, step: str, index: int) -> Path:
    """Where the rejects of shard ``index`` of ``step`` live (checked like :func:`shard_path`)."""
    return path_under(out, validate_id(step, "step name"), rejects_file_name(index))


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
        given[name] = [(Path(p), read_shard_meta(Path(p)).fingerprint) for p in paths]
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
    output: Path,
    inputs: Mapping[str, Path] | None = None,
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
        output.parent,
        inputs={role: [path] for role, path in given.items()},
        one_shard=True,
    )
    rejects = output.with_name(output.stem + ".rejects.parquet")
    return dataclasses.replace(task, output=output, rejects=rejects)


def run_tasks_here(
    tasks: Sequence[ShardTask],
    progress: Callable[[ShardResult, int, int], None] | None = None,
) -> list[ShardResult]:
    """Run ``tasks`` one after another in this process (dependency order), no Dask.

    Like a worker, a finished output is verified before it is skipped.
    """
    results = []
    for task in tasks:
        discard_if_damaged(task)
        results.append(run_shard_task(task))
        if progress is not None:
            progress(results[-1], len(results), len(tasks))
    return results


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
) -> RunSummary:
    """Run every (step, shard) task of ``workflow``; see the module doc.

    ``scheduler``: None for a local Dask cluster, ``tcp://HOST:PORT`` for an existing one, or
    :data:`IN_PROCESS` to run the tasks one after another in this process. ``inputs`` gives the
    shards of the workflow's declared inputs. Raises :class:`RunLockedError` at once when
    another run holds ``out``.
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    with run_lock(out):
        remove_stale_temporaries(out)
        write_text_atomic(
            out / "workflow.resolved.yaml",
            yaml.safe_dump(
                {
                    **workflow.to_dict(),
                    "input": source,
                    **({"given": _given_record(inputs)} if inputs else {}),
                },
                sort_keys=False,
            ),
        )
        tasks = plan_tasks(workflow, source, out, inputs)
        if scheduler == IN_PROCESS:
            results = run_tasks_here(tasks, progress)
            report = _write_run_records(out, tasks, results)
            return RunSummary(out=out, results=results, report=report)
        return _run_on_dask(workflow, out, tasks, scheduler, n_workers, gpu_workers, progress)


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
) -> RunSummary:
    """Run planned ``tasks`` on a Dask cluster once the run holds its folder's lock."""
    from distributed import Client, as_completed

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
            deps = [
                futures[(up, task.shard_index)]
                for up in step.inputs.values()
                if up not in workflow.inputs  # given shards: nothing to wait for
            ]
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
