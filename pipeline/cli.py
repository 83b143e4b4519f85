"""The ``egosim`` command line: thin commands that build configs and call library code.

Library code raises typed errors; only this module turns them into a message and an exit code.

Exit codes (documented in README.md, "The CLI"):

- 0: success; for ``run`` and ``stage``, every final step has clips (some may be rejected);
- 1: ``egosim check`` found violations (or an unexpected crash, with a traceback);
- 2: a bad command line, workflow, parameter, input or shard, or a task that failed as a whole;
- 3: ``run``/``stage``: a step rejected every clip it was given (a source step made no clip);
- 4: ``run``/``stage``: a final step wrote no clip although no step rejected everything.
"""

from __future__ import annotations

import dataclasses
import json
import sys
from pathlib import Path
from typing import Annotated

import typer

from egosim.pipeline import storage
from egosim.pipeline.check import check_paths
from egosim.pipeline.media import MediaError
from egosim.pipeline.records import ClipValueError
from egosim.pipeline.runner import (
    IN_PROCESS,
    RunError,
    local_source,
    plan_stage,
    run_tasks_here,
    run_workflow,
)
from egosim.pipeline.shards import ShardError, ShardReader, find_shards
from egosim.pipeline.stage import SourceStage, StageError, get_stage, registered_stages
from egosim.pipeline.summary import (
    FinalStepEmptyError,
    RunReport,
    StepRejectedAllError,
    format_report,
    summarize_tasks,
)
from egosim.pipeline.workflow import load_workflow
from egosim.schemas import SchemaError

app = typer.Typer(
    help="egosim: egocentric hand-object videos to world-simulator training data.",
    no_args_is_help=True,
    add_completion=False,
)

USER_ERRORS = (StageError, ShardError, SchemaError, MediaError, ClipValueError, OSError)

EXIT_USER_ERROR = 2  # bad workflow, parameter, input or shard; a task failed as a whole
EXIT_STEP_REJECTED_ALL = 3  # a step rejected every clip it was given (a source made none)
EXIT_FINAL_STEP_EMPTY = 4  # a final step wrote no clip


def _fail(exc: BaseException) -> typer.Exit:
    typer.secho(f"error: {exc}", fg=typer.colors.RED, err=True)
    return typer.Exit(code=EXIT_USER_ERROR)


def _finish_with_report(report: RunReport) -> None:
    """Print ``report`` and exit with code 3 or 4 when the run (or stage) produced nothing."""
    typer.echo(format_report(report))
    try:
        report.raise_for_outcome()
    except StepRejectedAllError as exc:
        typer.secho(f"error: {exc}", fg=typer.colors.RED, err=True)
        raise typer.Exit(code=EXIT_STEP_REJECTED_ALL) from exc
    except FinalStepEmptyError as exc:
        typer.secho(f"error: {exc}", fg=typer.colors.RED, err=True)
        raise typer.Exit(code=EXIT_FINAL_STEP_EMPTY) from exc


def _params(items: list[str], flag: str) -> dict[str, str]:
    out = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep:
            raise StageError(f"{flag} {item!r} is not key=value")
        out[key] = value
    return out


# `--param k=v` was the flag of `stage`, `simulate` and `evaluate` before `--set` (every
# command's flag now); it is kept as a hidden alias and warns.
PARAM_ALIAS = typer.Option("--param", hidden=True, help="Deprecated: use --set.")

# Where `simulate` and `evaluate` run their workflow's tasks (default: this process).
SCHEDULER_OPTION = typer.Option(
    "--scheduler",
    help="'here' (this process, no Dask), 'local' (a local Dask cluster) or tcp://HOST:PORT.",
)

# The repository's workflow files (`egosim simulate` and `evaluate` run theirs).
WORKFLOWS_DIR = Path(__file__).resolve().parents[1] / "workflows"


def _settings(set_: list[str] | None, param: list[str] | None) -> dict[str, str]:
    """``--set k=v`` values, with the deprecated ``--param k=v`` ones before them."""
    if param:
        typer.secho("warning: --param is deprecated; use --set", fg=typer.colors.YELLOW, err=True)
    return {**_params(param or [], "--param"), **_params(set_ or [], "--set")}


def _scheduler(name: str) -> str | None:
    """The runner's scheduler for a ``--scheduler`` value ('local' = a local Dask cluster)."""
    return None if name == "local" else name


@app.command()
def run(
    workflow: Annotated[Path, typer.Argument(help="Workflow YAML file.")],
    out: Annotated[
        str,
        typer.Option(
            "--out", help="Run folder for every step's shards: a path or URL (s3://bucket/run)."
        ),
    ],
    input: Annotated[
        str | None,
        typer.Option("--input", help="Input path or URL for source steps (ingest)."),
    ] = None,
    scheduler: Annotated[
        str | None,
        typer.Option(
            "--scheduler", help="Existing Dask scheduler tcp://HOST:PORT, or 'here' (no Dask)."
        ),
    ] = None,
    workers: Annotated[
        int | None, typer.Option("--workers", help="Local cluster size (default: cores).")
    ] = None,
    set_: Annotated[
        list[str] | None, typer.Option("--set", help="Override a parameter: step.param=value.")
    ] = None,
    input_shard: Annotated[
        list[str] | None,
        typer.Option(
            "--input-shard",
            help="A workflow input's shards: NAME=PATH (a shard, a folder, a run's step); "
            "repeat for several.",
        ),
    ] = None,
    chain: Annotated[
        str | None,
        typer.Option("--chain", help="Run once per shard of this input, in order (needs --feed)."),
    ] = None,
    feed: Annotated[
        str | None,
        typer.Option(
            "--feed", help="--chain: INPUT=STEP: each run's STEP output is the next's INPUT."
        ),
    ] = None,
) -> None:
    """Run a workflow on a Dask cluster (local by default); skips finished shards.

    Ends with a summary per step (clips in, out, rejected, top reject reasons),
    also written to OUT/summary.json.

    --input-shard NAME=PATH gives the shards of the workflow's declared inputs. With
    --chain NAME --feed INPUT=STEP the workflow runs once per shard of input NAME, in order,
    into OUT/link-KK; each link's INPUT is the previous link's STEP output keyed by its own
    clips (the closed loop: --chain segment --feed state=fuse). The exit code is the last
    link's.

    Exit codes:
    0  every final step has clips (some clips may have been rejected)
    2  bad workflow, parameter or input; or a task failed as a whole
    3  a step rejected every clip it was given (or the source made no clip)
    4  a final step wrote no clip
    """
    from egosim.pipeline.observe import ConsoleObserver, log_path

    try:
        run_out = storage.location(out)
        wf = load_workflow(workflow, set_ or [])
        given = _input_shards(input_shard or [], wf.inputs)
        if (chain is None) != (feed is None):
            raise StageError("--chain and --feed go together")
        if chain is not None and feed is not None:
            summary = _run_chained(wf, run_out, given, chain, feed, scheduler, workers)
        else:
            # Live progress per step on a terminal (stderr), plain lines otherwise.
            summary = run_workflow(
                wf,
                run_out,
                source=input,
                scheduler=scheduler,
                n_workers=workers,
                observer=ConsoleObserver(),
                inputs=given or None,
            )
    except USER_ERRORS as exc:
        if isinstance(exc, RunError) and exc.report is not None:
            typer.echo(format_report(exc.report))
        raise _fail(exc) from exc
    skipped = sum(r.skipped for r in summary.results)
    typer.echo(
        f"done: {len(summary.results)} shard tasks ({skipped} skipped), "
        f"{summary.rejected} clips rejected in this run; outputs in {out}, log in "
        f"{log_path(storage.scratch_dir(run_out))}"
    )
    _finish_with_report(summary.report)


def _input_shards(items: list[str], declared: dict[str, str]) -> dict[str, list]:
    """``--input-shard NAME=PATH`` values: each input's shard files, in the order given
    (folders expand to their shards, sorted); every bad item is listed at once."""
    from egosim.pipeline.shards import find_shards

    given: dict[str, list] = {}
    problems = []
    for item in items:
        name, sep, path = item.partition("=")
        if not sep or not name or not path:
            problems.append(f"--input-shard takes NAME=PATH, got {item!r}")
            continue
        if name not in declared:
            problems.append(f"--input-shard {name!r}: the workflow's inputs are {sorted(declared)}")
            continue
        try:
            given.setdefault(name, []).extend(find_shards([path], name))
        except FileNotFoundError as exc:
            problems.append(f"--input-shard {item!r}: {exc}")
    if problems:
        raise StageError("; ".join(problems))
    return given


def _run_chained(wf, out, given: dict, chain: str, feed: str, scheduler, workers):
    """``run --chain NAME --feed INPUT=STEP``: one run per shard of NAME
    (:func:`egosim.pipeline.chain.run_chain`); returns the last link's summary."""
    from egosim.pipeline.chain import run_chain
    from egosim.pipeline.observe import ConsoleObserver

    name, sep, step = feed.partition("=")
    if not sep or not name or not step:
        raise StageError(f"--feed takes INPUT=STEP, got {feed!r}")
    summaries = run_chain(wf, out, given, chain, name, step, scheduler, workers, ConsoleObserver)
    for k, summ in enumerate(summaries, 1):
        skipped = sum(r.skipped for r in summ.results)
        typer.echo(
            f"link {k}: {summ.out}: {len(summ.results)} shard tasks ({skipped} skipped), "
            f"{summ.rejected} clips rejected"
        )
    return summaries[-1]


@app.command()
def stage(
    name: Annotated[str, typer.Argument(help="Stage name (see `egosim stages`).")],
    output: Annotated[str, typer.Option("--output", help="Output shard path or URL.")],
    input: Annotated[
        list[str] | None,
        typer.Option("--input", help="Input shard, role=path for several roles, or ingest path."),
    ] = None,
    set_: Annotated[
        list[str] | None,
        typer.Option("--set", help="Stage parameter key=value (nested: a.b=value)."),
    ] = None,
    param: Annotated[list[str] | None, PARAM_ALIAS] = None,
) -> None:
    """Run one stage on one shard, in this process, without a cluster.

    The task is planned by the runner as a one-step workflow (same fingerprint as a one-shard
    `egosim run`). Ends with the same summary and exit codes as `egosim run`:
    3 when the stage rejected every clip (or ingest made no clip),
    4 when it wrote no clip and rejected none (an empty input).
    """
    try:
        stage_cls = get_stage(name)
        params = _settings(set_, param)
        output_at = storage.location(output)
        if issubclass(stage_cls, SourceStage):
            source = local_source(input) if input else None
            task = plan_stage(name, params, output_at, source=source)
        else:
            roles = list(stage_cls.inputs)
            given = dict(i.split("=", 1) if "=" in i else (roles[0], i) for i in input or [])
            inputs = {role: storage.location(p) for role, p in given.items()}
            task = plan_stage(name, params, output_at, inputs=inputs)
        (result,) = run_tasks_here([task])
        report = summarize_tasks([task], [result])
    except USER_ERRORS as exc:
        raise _fail(exc) from exc
    typer.echo(f"{output}: {result.rows} rows, {result.rejected} rejected (see {task.rejects})")
    _finish_with_report(report)


@app.command()
def check(
    paths: Annotated[
        list[str], typer.Argument(help="Shard files or folders of shards (paths or URLs).")
    ],
    allow_empty: Annotated[bool, typer.Option(help="Accept shards with no rows.")] = False,
) -> None:
    """Validate shards; lists every violation and exits non-zero if there is any.

    Checks page checksums and each row's content hash, the schema and its invariants, decoded
    content, and that clip ids are unique across the shards of each folder (a step of a run).
    """
    count, problems = check_paths(paths, allow_empty=allow_empty)
    if not count:
        raise _fail(FileNotFoundError(f"no shards found under {[str(p) for p in paths]}"))
    for problem in problems:
        typer.echo(problem)
    typer.echo(f"checked {count} shard(s): {len(problems)} violation(s)")
    if problems:
        raise typer.Exit(code=1)


@app.command()
def inspect(path: Annotated[str, typer.Argument(help="A shard file (path or URL).")]) -> None:
    """Print a readable summary of one shard: schema, provenance and its rows."""
    try:
        with ShardReader(path) as reader:
            meta = reader.meta
            typer.echo(f"{path}")
            typer.echo(f"  schema: {meta.schema} v{meta.schema_version}, {reader.num_rows} rows")
            typer.echo(f"  stage: {meta.stage}  egosim {meta.package_version}")
            typer.echo(f"  fingerprint: {meta.fingerprint}")
            typer.echo(f"  params: {json.dumps(meta.params, sort_keys=True)}")
            for row in reader.iter_rows():
                typer.echo("  - " + _row_summary(row))
    except USER_ERRORS as exc:
        raise _fail(exc) from exc


def _row_summary(row: dict) -> str:
    parts = []
    for key, value in row.items():
        if value is None:
            continue
        if isinstance(value, bytes):
            parts.append(f"{key}=<{len(value) / 1024:.0f} KiB>")
        elif isinstance(value, list):
            parts.append(f"{key}=[{len(value)}]")
        else:
            parts.append(f"{key}={value}")
    return " ".join(parts)


@app.command()
def stages() -> None:
    """List every stage with its backends, input and output schemas and parameters."""
    for name, cls in sorted(registered_stages().items()):
        ins = ", ".join(f"{r}:{s.name}v{s.version}" for r, s in cls.inputs.items()) or "-"
        ins += "".join(f", [{r}:{s.name}v{s.version}]" for r, s in cls.optional_inputs.items())
        backends = ", ".join(cls.backends) or "-"
        typer.echo(f"{name}: {cls.description}")
        typer.echo(f"  inputs: {ins}  output: {cls.output.name}v{cls.output.version}")
        typer.echo(f"  backends: {backends}  gpu: {cls.gpu}")
        params = ", ".join(f.name for f in dataclasses.fields(cls.config_class))
        typer.echo(f"  params: {params}")


@app.command()
def synth(
    out: Annotated[Path, typer.Option("--out", help="Output folder.")],
    n: Annotated[int, typer.Option("--n", help="Number of clips.")] = 4,
    mode: Annotated[str, typer.Option("--mode", help="tabletop or wild.")] = "tabletop",
    fmt: Annotated[str, typer.Option("--format", help="shards or egodex.")] = "shards",
    seed: Annotated[int, typer.Option("--seed", help="First seed.")] = 0,
    height: Annotated[int, typer.Option(help="Frame height.")] = 480,
    width: Annotated[int, typer.Option(help="Frame width.")] = 832,
    frames: Annotated[int, typer.Option(help="Frames per clip.")] = 61,
    fps: Annotated[float, typer.Option(help="Frames per second.")] = 16.0,
    per_shard: Annotated[int, typer.Option(help="Clips per shard (shards format).")] = 4,
) -> None:
    """Render clips from the synthetic world as clips shards or EgoDex HDF5+MP4 files."""
    from egosim.pipeline.clip_io import write_clip_shards
    from egosim.world import WorldConfig, render_clip
    from egosim.world.egodex_export import write_egodex

    try:
        if fmt not in ("shards", "egodex"):
            raise StageError(f"--format must be shards or egodex, got {fmt!r}")
        if n < 1 or per_shard < 1:
            raise StageError(f"--n and --per-shard must be >= 1, got {n} and {per_shard}")
        configs = [
            WorldConfig(
                seed=seed + i, mode=mode, height=height, width=width, num_frames=frames, fps=fps
            )
            for i in range(n)
        ]
        if fmt == "egodex":
            for i, cfg in enumerate(configs):
                hdf5, _ = write_egodex(render_clip(cfg), out / f"synthetic_{mode}", stem=str(i))
                typer.echo(f"wrote {hdf5}")
            return
        clips = (render_clip(c) for c in configs)
        params = {"mode": mode, "seed": seed}
        for path, count in write_clip_shards(out, clips, per_shard, "synth", params):
            typer.echo(f"wrote {path} ({count} clips)")
    except (*USER_ERRORS, ValueError) as exc:
        raise _fail(exc) from exc


def _model_errors() -> tuple[type[BaseException], ...]:
    from egosim.model.errors import ModelError

    return (*USER_ERRORS, ModelError, ValueError)


@app.command()
def train(
    data: Annotated[
        list[str],
        typer.Option("--data", help="Pack shards, folders of them, or a run folder (or URLs)."),
    ],
    out: Annotated[Path, typer.Option("--out", help="Run directory (resumed when it exists).")],
    preset: Annotated[str, typer.Option("--preset", help="Model preset (tiny, wan2.1-...).")] = (
        "tiny"
    ),
    steps: Annotated[int | None, typer.Option("--steps", help="Optimizer steps in total.")] = None,
    set_: Annotated[
        list[str] | None,
        typer.Option("--set", help="TrainConfig field key=value (e.g. optim.lr=3e-4)."),
    ] = None,
    fresh: Annotated[bool, typer.Option("--fresh", help="Ignore existing checkpoints.")] = False,
    sample_steps: Annotated[
        int, typer.Option("--sample-steps", help="Euler steps of RUN/sample.mp4 (0: none).")
    ] = 20,
    scheduler: Annotated[
        str | None,
        typer.Option("--scheduler", help="Dask scheduler tcp://HOST:PORT: run on a GPU worker."),
    ] = None,
) -> None:
    """Train the simulator on pack or latents shards: config, metrics, checkpoints, previews.

    Many processes: ``torchrun --nproc_per_node N -m egosim.pipeline.cli train ...`` (FSDP2;
    --set batch_size is per rank). Settings are TrainConfig fields, nested ones dotted:
    --set optim.lr=1e-5 --set lora.rank=64; an unknown key or a bad value is refused.
    """
    from egosim.model.train import TrainConfig
    from egosim.pipeline.stage import build_config
    from egosim.stages.train.run import TrainJob, run_training, submit_training

    try:
        params: dict[str, object] = {"preset": preset, **_params(set_ or [], "--set")}
        if steps is not None:
            params["steps"] = steps
        config = build_config(TrainConfig, params, where="train")
        job = TrainJob(tuple(str(p) for p in data), str(out), config, not fresh, sample_steps)
        summary = submit_training(job, scheduler) if scheduler else run_training(job)
    except _model_errors() as exc:
        raise _fail(exc) from exc
    if summary.get("rank", 0) != 0:
        return  # torchrun: rank 0 reports
    curve = ", ".join(
        f"{c['from_step']}-{c['to_step']}: {c['loss']:.4f}" for c in summary["loss_curve"]
    )
    typer.echo(
        f"trained {summary['preset']} to step {summary['step']} on {summary['clips']} clips "
        f"({summary.get('world_size', 1)} process(es)) in {summary['seconds']:.0f}s; loss "
        f"{curve}; run in {out}"
    )


def _bundled_workflow(workflow: Path | None, file_name: str) -> Path:
    """``workflow``, or the repository's ``workflows/FILE_NAME`` when none is given."""
    path = workflow if workflow is not None else WORKFLOWS_DIR / file_name
    if not path.is_file():
        raise FileNotFoundError(f"no workflow file at {path} (give one with --workflow)")
    return path


@app.command()
def simulate(
    out: Annotated[Path, typer.Option("--out", help="Run folder for simulation shards, videos.")],
    data: Annotated[
        list[str] | None,
        typer.Option("--data", help="Pack shards, folders of them, or a run folder (or URLs)."),
    ] = None,
    checkpoint: Annotated[
        str,
        typer.Option(
            "--checkpoint", help="Run directory or .safetensors checkpoint ('' = untrained)."
        ),
    ] = "",
    set_: Annotated[
        list[str] | None,
        typer.Option("--set", help="simulate parameter key=value (e.g. steps=50)."),
    ] = None,
    param: Annotated[list[str] | None, PARAM_ALIAS] = None,
    workflow: Annotated[
        Path | None, typer.Option("--workflow", help="Workflow file (default simulate.yaml).")
    ] = None,
    scheduler: Annotated[str, SCHEDULER_OPTION] = IN_PROCESS,
    continuous: Annotated[
        int,
        typer.Option(
            "--continuous",
            help="Closed loop over N action segments (--state, --segments); 0 = off.",
        ),
    ] = 0,
    state: Annotated[
        Path | None,
        typer.Option("--state", help="--continuous: initial state or scene_cloud shard."),
    ] = None,
    segments: Annotated[
        list[Path] | None,
        typer.Option("--segments", help="--continuous: clips shards of the segments, in order."),
    ] = None,
    generator: Annotated[
        str,
        typer.Option(
            "--generator",
            help="--continuous: clip generator (oracle, oracle_video, model).",
        ),
    ] = "oracle",
) -> None:
    """Generate every packed clip: runs workflows/simulate.yaml, then writes the videos.

    Writes OUT/simulate/shard-*.parquet (with the run's manifest, rejects and summary) and
    OUT/videos/<clip_id>.mp4; a re-run skips the shards that are done. With --continuous N:
    the closed loop (render the state along segment k, generate clip k, fuse it, go on) from
    --state over the N --segments, writing every state, render and clip under OUT and
    OUT/closed_loop.mp4 (``--set`` sets its config: e.g. fusion.voxel_size_m=0.01).
    """
    from egosim.stages.common.pack_dataset import find_pack_shards
    from egosim.stages.simulate.videos import write_videos

    if continuous:
        ignored = {
            "--data": bool(data),
            "--checkpoint": bool(checkpoint),
            "--workflow": workflow is not None,
            "--scheduler": scheduler != IN_PROCESS,
        }
        if any(ignored.values()):
            unused = [flag for flag, given in ignored.items() if given]
            raise _fail(StageError(f"--continuous runs in this process and takes no {unused}"))
        _simulate_continuous(out, continuous, state, segments, generator, _settings(set_, param))
        return
    try:
        if not data:
            raise StageError("--data is required (pack shards), unless --continuous N is given")
        if checkpoint:
            from egosim.model.checkpoint import refuse_pickle
            from egosim.model.inference import resolve_checkpoint

            # Refuse a pickle before any task runs (inside a task it would reject every clip).
            refuse_pickle(resolve_checkpoint(checkpoint))
        settings = {"checkpoint": checkpoint, **_settings(set_, param)}
        wf = load_workflow(
            _bundled_workflow(workflow, "simulate.yaml"),
            [f"simulate.{k}={v}" for k, v in settings.items()],
        )
        summary = run_workflow(
            wf, out, scheduler=_scheduler(scheduler), inputs={"pack": find_pack_shards(data)}
        )
        for result in sorted(summary.results, key=lambda r: r.shard_index):
            typer.echo(f"{result.output}: {result.rows} clips, {result.rejected} rejected")
        shards = [Path(r.output) for r in sorted(summary.results, key=lambda r: r.shard_index)]
        videos = write_videos(shards, out / "videos")
    except _model_errors() as exc:
        raise _fail(exc) from exc
    typer.echo(f"wrote {len(videos)} video(s) under {out / 'videos'}")


def _simulate_continuous(
    out: Path,
    count: int,
    state: Path | None,
    segments: list[Path] | None,
    generator: str,
    settings: dict[str, str],
) -> None:
    """``simulate --continuous N``: build the closed loop's config and run it."""
    from egosim.pipeline.stage import build_config
    from egosim.stages.state_fusion.closed_loop import ClosedLoopConfig, run_closed_loop

    try:
        if state is None:
            raise StageError("--continuous needs --state (an initial state or scene_cloud shard)")
        params = {**settings, "num_segments": count, "generator": generator}
        config = build_config(ClosedLoopConfig, params, where="simulate --continuous")
        result = run_closed_loop(
            state, find_shards(segments or [], "clips") if segments else [], out, config
        )
    except _model_errors() as exc:
        raise _fail(exc) from exc
    for k, path in enumerate(result.states, 1):
        typer.echo(f"segment {k}: {result.clips[k - 1]} -> {path}")
    typer.echo(f"wrote {result.video}")


@app.command()
def evaluate(
    data: Annotated[
        list[str],
        typer.Option("--data", help="Pack shards, folders of them, or a run folder (or URLs)."),
    ],
    simulation: Annotated[
        str,
        typer.Option("--simulation", help="Run folder written by `egosim simulate` (or URL)."),
    ],
    out: Annotated[Path, typer.Option("--out", help="Run folder for evaluation shards.")],
    set_: Annotated[
        list[str] | None,
        typer.Option("--set", help="evaluate parameter key=value (e.g. camera_backend=sfm)."),
    ] = None,
    param: Annotated[list[str] | None, PARAM_ALIAS] = None,
    workflow: Annotated[
        Path | None, typer.Option("--workflow", help="Workflow file (default eval.yaml).")
    ] = None,
    scheduler: Annotated[str, SCHEDULER_OPTION] = IN_PROCESS,
) -> None:
    """Evaluate generated clips against their pack samples: runs workflows/eval.yaml.

    Shard i of --data is paired with shard i of --simulation; prints per-clip and overall tables.
    """
    from egosim.stages.common.pack_dataset import find_pack_shards
    from egosim.stages.evaluate.report import format_table, read_evaluations

    try:
        wf = load_workflow(
            _bundled_workflow(workflow, "eval.yaml"),
            [f"evaluate.{k}={v}" for k, v in _settings(set_, param).items()],
        )
        inputs = {
            "pack": find_pack_shards(data),
            "simulation": find_shards([simulation], "simulate"),
        }
        summary = run_workflow(wf, out, scheduler=_scheduler(scheduler), inputs=inputs)
        shards = [Path(r.output) for r in sorted(summary.results, key=lambda r: r.shard_index)]
        typer.echo(format_table(read_evaluations(shards)))
    except _model_errors() as exc:
        raise _fail(exc) from exc


@app.command()
def report(
    paths: Annotated[
        list[str],
        typer.Argument(help="A run folder or URL (with --out), or evaluation shards/folders."),
    ],
    out: Annotated[
        Path | None,
        typer.Option(
            "--out", help="Write the HTML report of the run folder PATH into this folder."
        ),
    ] = None,
    max_clips: Annotated[
        int, typer.Option("--max-clips", help="Clips that get a contact sheet and a video.")
    ] = 24,
) -> None:
    """Print the evaluation table of evaluation shards, or (--out) write a run's HTML report.

    `egosim report RUN --out DIR` writes DIR/index.html (open it in a browser; no server;
    RUN may be a URL, downloaded to the local cache first):
    per-step counts and seconds, rejects grouped by reason, quality histograms, a contact
    sheet and side-by-side video per clip, and the evaluation table when the run has one.
    """
    from egosim.stages.evaluate.report import format_table, read_evaluations

    try:
        if out is None:
            typer.echo(format_table(read_evaluations(paths)))
            return
        from egosim.pipeline.report import ReportConfig, load_run, write_report

        if len(paths) != 1:
            raise StageError(f"--out takes one run folder, got {len(paths)}: {paths}")
        # A remote run (s3://, gs://) is read from its local copy in the cache.
        where = storage.location(paths[0])
        run_dir = where if isinstance(where, Path) else storage.local_copy(where)
        evaluations = [run_dir / s.step for s in load_run(run_dir).steps_of("evaluate")]
        table = format_table(read_evaluations(evaluations)) if evaluations else None
        index = write_report(run_dir, out, ReportConfig(max_clips=max_clips), table)
        typer.echo(f"report written: {index} (open it in a browser)")
    except (*USER_ERRORS, ValueError) as exc:
        raise _fail(exc) from exc


cluster_app = typer.Typer(
    help="Start Dask clusters for `egosim run --scheduler` (SLURM via dask-jobqueue).",
    no_args_is_help=True,
)
app.add_typer(cluster_app, name="cluster")


@cluster_app.command("slurm")
def cluster_slurm(
    cores: Annotated[int, typer.Option("--cores", help="CPU cores per job.")] = 4,
    memory: Annotated[str, typer.Option("--memory", help="Memory per job (16GB, 64GiB).")] = (
        "16GB"
    ),
    gpus: Annotated[
        int, typer.Option("--gpus", help="GPUs per job: 0 or 1 (the worker declares GPU=1).")
    ] = 0,
    walltime: Annotated[
        str, typer.Option("--walltime", help="Job time limit HH:MM:SS or D-HH:MM:SS.")
    ] = "04:00:00",
    jobs: Annotated[int, typer.Option("--jobs", help="Worker jobs to submit.")] = 1,
    partition: Annotated[str, typer.Option("--partition", help="SLURM partition.")] = "",
    account: Annotated[str, typer.Option("--account", help="SLURM account.")] = "",
    prologue: Annotated[
        list[str] | None,
        typer.Option("--prologue", help="Shell line run before the worker (repeatable)."),
    ] = None,
    job_extra: Annotated[
        list[str] | None,
        typer.Option("--job-extra", help="Extra #SBATCH directive, e.g. --constraint=a100."),
    ] = None,
    python: Annotated[
        str, typer.Option("--python", help="Python on the nodes (default: this one).")
    ] = "",
    local_directory: Annotated[
        str, typer.Option("--local-directory", help="Worker scratch folder on the node.")
    ] = "",
    log_directory: Annotated[
        str, typer.Option("--log-directory", help="Folder of the jobs' output files.")
    ] = "",
    print_job_script: Annotated[
        bool,
        typer.Option("--print-job-script", help="Print one job's sbatch script; submit nothing."),
    ] = False,
) -> None:
    """Start a SLURM-backed Dask cluster (dask-jobqueue) and keep it up until Ctrl-C.

    Prints the scheduler address to pass to `egosim run --scheduler`; each job runs one Dask
    worker, and with --gpus 1 it books one GPU and declares the GPU=1 resource that GPU steps
    need. With --print-job-script it prints the sbatch script of one job and exits.
    """
    from egosim.pipeline.cluster import ClusterError, SlurmConfig, slurm_cluster, slurm_job_script

    try:
        config = SlurmConfig(
            cores=cores,
            memory=memory,
            gpus=gpus,
            walltime=walltime,
            jobs=jobs,
            partition=partition,
            account=account,
            prologue=tuple(prologue or ()),
            job_extra=tuple(job_extra or ()),
            python=python,
            local_directory=local_directory,
            log_directory=log_directory,
        )
        if print_job_script:
            typer.echo(slurm_job_script(config))
            return
        cluster = slurm_cluster(config)
    except (ClusterError, OSError, ValueError) as exc:
        raise _fail(exc) from exc
    try:
        cluster.scale(jobs=config.jobs)
        typer.echo(f"scheduler: {cluster.scheduler_address}")
        typer.echo(f"dashboard: {cluster.dashboard_link}")
        typer.echo(
            f"submitted {config.jobs} job(s); run: egosim run WORKFLOW --out OUT "
            f"--scheduler {cluster.scheduler_address}   (Ctrl-C stops the cluster)"
        )
        import time

        while True:
            time.sleep(3600)
    except KeyboardInterrupt:
        typer.echo("stopping the cluster and its jobs")
    finally:
        cluster.close()


# --- egosim view and egosim export (issue 16): Foxglove MCAPs and other tools' layouts ------

export_app = typer.Typer(
    help="Export a run for another tool: videox-fun, egosim-csv, dwm (packed samples), lerobot.",
    no_args_is_help=True,
)
app.add_typer(export_app, name="export")


def _export_errors() -> tuple[type[BaseException], ...]:
    from egosim.pipeline.export.foxglove import FoxgloveExportError
    from egosim.pipeline.export.run_index import ExportError

    return (*USER_ERRORS, ExportError, FoxgloveExportError)


@app.command()
def view(
    run: Annotated[Path, typer.Argument(help="Run folder (egosim run --out).")],
    out: Annotated[
        Path, typer.Option("--out", help="FILE.mcap for one clip, else a folder of CLIP.mcap.")
    ],
    clip: Annotated[
        list[str] | None, typer.Option("--clip", help="Clip id to export (repeat; default all).")
    ] = None,
    set_: Annotated[
        list[str] | None,
        typer.Option("--set", help="image_format=png, jpeg_quality=N, max_cloud_points=N."),
    ] = None,
) -> None:
    """Write one Foxglove MCAP per clip: every step's output aligned in time and space.

    Real, scene, visibility, skeleton and hand-mask videos, the inpainted first frame,
    calibration, raw/cleaned/source camera transforms, scene and state clouds and the 3D hand
    skeleton (topics: egosim.pipeline.export.view). Open the file in Foxglove.
    """
    from egosim.pipeline.export.view import ViewConfig, write_run_view
    from egosim.pipeline.stage import build_config

    try:
        config = build_config(ViewConfig, _params(set_ or [], "--set"), where="view")
        paths = write_run_view(run, out, clip or (), config)
    except _export_errors() as exc:
        raise _fail(exc) from exc
    for path in paths:
        typer.echo(f"wrote {path}")


def _run_export(kind: str, run: Path, out: Path, set_: list[str] | None) -> None:
    """Build the exporter's config from ``--set`` and export; exit 3 when no clip was written."""
    from egosim.pipeline.export import dwm, egosim_csv, videox_fun
    from egosim.pipeline.stage import build_config

    exporters = {
        "videox-fun": (videox_fun.VideoXFunConfig, videox_fun.export_videox_fun),
        "egosim-csv": (egosim_csv.EgoSimCsvConfig, egosim_csv.export_egosim_csv),
        "dwm": (dwm.DwmConfig, dwm.export_dwm),
    }
    config_class, export = exporters[kind]
    try:
        config = build_config(config_class, _params(set_ or [], "--set"), where=kind)
        result = export(run, out, config)
    except _export_errors() as exc:
        raise _fail(exc) from exc
    _finish_export(
        run,
        result.skipped,
        len(result.written),
        f"{kind}: {len(result.written)} clip(s) in {out} (index {result.index}), "
        f"{len(result.skipped)} skipped",
    )


def _finish_export(run: Path, skipped: dict[str, str], written: int, summary: str) -> None:
    """Print what an export skipped and its summary; exit 3 when it wrote no clip."""
    for cid, why in skipped.items():
        typer.secho(f"skipped {cid}: {why}", fg=typer.colors.YELLOW, err=True)
    typer.echo(summary)
    if not written:
        typer.secho(f"error: no clip of {run} was exported", fg=typer.colors.RED, err=True)
        raise typer.Exit(code=EXIT_STEP_REJECTED_ALL)


RUN_ARGUMENT = typer.Argument(help="Run folder, folder of pack shards, or one pack shard.")
EXPORT_OUT = typer.Option("--out", help="Output folder.")


@export_app.command("videox-fun")
def export_videox_fun(
    run: Annotated[Path, RUN_ARGUMENT],
    out: Annotated[Path, EXPORT_OUT],
    set_: Annotated[
        list[str] | None, typer.Option("--set", help="crf=N, absolute_paths=true, overwrite=true.")
    ] = None,
) -> None:
    """VideoX-Fun: metadata.json + videos/, control/, masks/, skeletons/, first_frames/."""
    _run_export("videox-fun", run, out, set_)


@export_app.command("egosim-csv")
def export_egosim_csv(
    run: Annotated[Path, RUN_ARGUMENT],
    out: Annotated[Path, EXPORT_OUT],
    set_: Annotated[list[str] | None, typer.Option("--set", help="crf=N, overwrite=true.")] = None,
) -> None:
    """The EgoSim release: metadata.csv + one folder per clip (video, ego prior, mask, ...)."""
    _run_export("egosim-csv", run, out, set_)


@export_app.command("dwm")
def export_dwm(
    run: Annotated[Path, RUN_ARGUMENT],
    out: Annotated[Path, EXPORT_OUT],
    set_: Annotated[
        list[str] | None,
        typer.Option(
            "--set", help="fps, num_frames, height, width, resize=pad|crop, short=pad|reject."
        ),
    ] = None,
) -> None:
    """DWM: GROUP/videos, videos_static, videos_hands, prompts + dataset_files/GROUP.txt."""
    _run_export("dwm", run, out, set_)


@export_app.command("lerobot")
def export_lerobot(
    run: Annotated[Path, typer.Argument(help="Run folder (egosim run --out).")],
    out: Annotated[Path, EXPORT_OUT],
    robot_type: Annotated[
        str, typer.Option("--robot-type", help="meta/info.json robot_type.")
    ] = "egosim",
) -> None:
    """LeRobot v3.0: one episode per clip, the conditions as extra video keys, camera poses,
    intrinsics and hand joints per frame (robotics users load it with their own tools)."""
    from egosim.stages.ingest.lerobot_export import export_lerobot as write_lerobot

    try:
        report = write_lerobot(run, out, robot_type)
    except (*USER_ERRORS, FileExistsError) as exc:
        raise _fail(exc) from exc
    _finish_export(
        run,
        report.skipped,
        report.episodes,
        f"lerobot: {report.episodes} episode(s), {report.frames} frames, video keys "
        f"{', '.join(report.video_keys)} in {out}; {len(report.skipped)} skipped",
    )


# --- egosim weights and egosim presets (issue 14): published weights, export, memory plan -----

weights_app = typer.Typer(
    help="Inspect a transformer weights folder, or export a trained run's transformer.",
    no_args_is_help=True,
)
app.add_typer(weights_app, name="weights")


@weights_app.command("check")
def weights_check(
    folder: Annotated[Path, typer.Argument(help="Weights folder (diffusers or Wan/VideoX-Fun).")],
    preset: Annotated[
        list[str] | None, typer.Option("--preset", help="Check only these presets (repeat).")
    ] = None,
) -> None:
    """Report what a weights folder holds and which preset it fits, reading headers only.

    Exit 0 when it fits a preset, 2 when it fits none or cannot be read.
    """
    from egosim.model.weights import check_weights_folder

    try:
        report = check_weights_folder(folder, preset or None)
    except _model_errors() as exc:
        raise _fail(exc) from exc
    typer.echo(report.format())
    if not report.fits:
        names = ", ".join(report.problems)
        raise _fail(ValueError(f"{report.weights.folder} fits no preset ({names})"))


@weights_app.command("export")
def weights_export(
    run: Annotated[Path, typer.Argument(help="Run directory (latest checkpoint) or checkpoint.")],
    out: Annotated[Path, typer.Option("--out", help="New folder for the diffusers transformer.")],
    ema: Annotated[bool, typer.Option("--ema/--no-ema", help="Use the EMA weights if any.")] = True,
    dtype: Annotated[
        str, typer.Option("--dtype", help="Stored dtype: keep, bf16, fp16 or fp32.")
    ] = "keep",
) -> None:
    """Write a trained run's transformer as a diffusers folder (LoRA merged).

    ``WanTransformer3DModel.from_pretrained(OUT)`` loads it.
    """
    import torch

    from egosim.model.weights import export_transformer

    dtypes = {"keep": None, "bf16": torch.bfloat16, "fp16": torch.float16, "fp32": torch.float32}
    try:
        if dtype not in dtypes:
            raise ValueError(f"--dtype must be one of {sorted(dtypes)}, got {dtype!r}")
        written = export_transformer(run, out, use_ema=ema, dtype=dtypes[dtype])
    except _model_errors() as exc:
        raise _fail(exc) from exc
    typer.echo(f"wrote {written} (WanTransformer3DModel.from_pretrained loads it)")


@app.command()
def presets(
    memory: Annotated[
        bool, typer.Option("--memory", help="Also print the per-GPU memory plan (Wan presets).")
    ] = False,
    gpus: Annotated[int, typer.Option("--gpus", help="GPUs FSDP2 shards over (--memory).")] = 8,
    markdown: Annotated[
        bool, typer.Option("--markdown", help="Memory plan as the Markdown table of the docs.")
    ] = False,
) -> None:
    """List the model presets: parameters, latent size at the default clip, weights layout."""
    from egosim.model.memory_plan import (
        GIB,
        default_plans,
        format_table,
        latent_shape,
        parameter_count,
        sequence_length,
    )
    from egosim.model.presets import EGOSIM_IN_CHANNELS, PRESETS
    from egosim.model.weights import expected_layout

    try:
        for name, p in PRESETS.items():
            count = parameter_count(p.transformer, EGOSIM_IN_CHANNELS).total
            latent = "x".join(map(str, latent_shape(p, p.num_frames, p.height, p.width)))
            tokens = sequence_length(p, p.num_frames, p.height, p.width)
            typer.echo(
                f"{name} params {count:,} (in 52); clip {p.num_frames}x{p.height}x{p.width} -> "
                f"latent {latent} (CxTxHxW), {tokens:,} tokens; weights: {expected_layout(p)}"
            )
        if memory:
            plans = default_plans(gpus)
            if markdown:
                typer.echo(format_table(plans))
                return
            typer.echo(f"\nper-GPU memory (GiB), full fine-tuning, AdamW, FSDP2 over {gpus} GPUs:")
            for plan in plans:
                typer.echo(
                    f"  {plan.preset} batch {plan.setup.batch_per_gpu}: "
                    f"{plan.total / GIB:.1f} (model states {plan.model_states / GIB:.1f}, "
                    f"activations {plan.activations / GIB:.1f})"
                )
    except _model_errors() as exc:
        raise _fail(exc) from exc


# --- egosim hands (issue 10): licensed MANO and HaMeR files to safetensors, never unpickled ------

hands_app = typer.Typer(
    help="Convert MANO and HaMeR files for the hands stage's regressor backend.",
    no_args_is_help=True,
)
app.add_typer(hands_app, name="hands")


@hands_app.command("convert-mano")
def hands_convert_mano(
    pkl: Annotated[Path, typer.Argument(help="The licensed MANO_RIGHT.pkl.")],
    out: Annotated[Path, typer.Option("--out", help="Weights folder to write mano.safetensors.")],
) -> None:
    """Write OUT/mano.safetensors from MANO's .pkl, read as data (it is never unpickled)."""
    from egosim.stages.hands.convert_mano import convert_mano_pickle

    try:
        written = convert_mano_pickle(pkl, out)
    except USER_ERRORS as exc:
        raise _fail(exc) from exc
    typer.echo(f"wrote {written}")


@hands_app.command("convert-hamer")
def hands_convert_hamer(
    checkpoint: Annotated[Path, typer.Argument(help="HaMeR checkpoint (hamer.ckpt).")],
    out: Annotated[Path, typer.Option("--out", help="Weights folder to write.")],
    num_heads: Annotated[int, typer.Option(help="ViT attention heads (ViT-H: 16).")] = 16,
    decoder_heads: Annotated[int, typer.Option(help="MANO head decoder heads.")] = 8,
) -> None:
    """Write OUT/config.json and OUT/model.safetensors from a HaMeR checkpoint, read as data."""
    from egosim.stages.hands.convert_checkpoint import HamerLayout, convert_hamer_checkpoint

    layout = HamerLayout(num_heads=num_heads, decoder_heads=decoder_heads)
    try:
        dropped = convert_hamer_checkpoint(checkpoint, out, layout)
    except USER_ERRORS as exc:
        raise _fail(exc) from exc
    typer.echo(f"wrote {out} (dropped {', '.join(dropped) or 'nothing'}); add mano.safetensors")


def main() -> None:  # pragma: no cover - console entry point
    """Console entry point."""
    app()


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
