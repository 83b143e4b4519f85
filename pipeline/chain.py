"""Chained runs: one workflow run per shard of an input, each fed the previous run's output.

The runner joins rows on ``clip_id`` within one shard index, so one run cannot give segment k's
output state to segment k+1 (issue 13's continuous simulation). :func:`run_chain` runs the
workflow once per shard of the ``over`` input (a link), in order, into ``OUT/link-KK``:

- link 1 takes every workflow input as given;
- link k+1 takes shard k+1 of ``over``, the other inputs as given, and, for the ``feed`` input,
  the rows link k's ``feed_step`` wrote, each re-keyed (``clip_id``) to the row of link k+1's
  ``over`` shard at the same position (a state row is keyed by the clip that starts from it:
  ``egosim.schemas.state.state_for_clip``), written to ``OUT/link-KK/given/<feed>.parquet``.

A link whose ``feed_step`` wrote no row (its clips were rejected) stops the chain with a
:class:`ChainError` naming the link and the step's reject reasons, never with the previous
state passed on unchanged. Each link is an ordinary run, so a re-run skips finished shards.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from pathlib import Path

from egosim.pipeline import storage
from egosim.pipeline.observe import RunObserver
from egosim.pipeline.runner import RunError, RunSummary, run_workflow
from egosim.pipeline.shards import ShardReader, ShardWriter, find_shards
from egosim.pipeline.workflow import Workflow
from egosim.schemas import get_schema


class ChainError(RunError):
    """A chain cannot be set up, or a link left nothing to feed the next; says which."""


def link_dir(out: Path, index: int) -> Path:
    """Run folder of link ``index`` (1-based) under ``out``."""
    return Path(out) / f"link-{index:02d}"


def _rows(paths: Sequence[Path]) -> list[dict]:
    rows: list[dict] = []
    for path in paths:
        with ShardReader(path) as reader:
            rows += list(reader.iter_rows())
    return rows


def check_chain(
    workflow: Workflow, inputs: Mapping[str, Sequence[Path]], over: str, feed: str, step: str
) -> None:
    """Raise :class:`ChainError` listing every problem of a chain's set-up at once."""
    problems = []
    for name, what in ((over, "--chain"), (feed, "--feed")):
        if name not in workflow.inputs:
            problems.append(
                f"{what} {name!r} is not an input of workflow {workflow.name!r} "
                f"(inputs: {sorted(workflow.inputs)})"
            )
    if over == feed:
        problems.append(f"the chained input and the fed input are both {over!r}")
    names = [s.name for s in workflow.steps]
    if step not in names:
        problems.append(f"--feed step {step!r} is not a step of {workflow.name!r} ({names})")
    elif feed in workflow.inputs:
        made = get_stage_output(workflow, step)
        if made != workflow.inputs[feed]:
            problems.append(
                f"step {step!r} writes {made!r} shards, input {feed!r} takes "
                f"{workflow.inputs[feed]!r}"
            )
    if over in workflow.inputs and not inputs.get(over):
        problems.append(f"no shards given for the chained input {over!r}")
    if problems:
        raise ChainError("cannot chain: " + "; ".join(problems))


def get_stage_output(workflow: Workflow, step: str) -> str:
    """The schema name a workflow step writes."""
    from egosim.pipeline.stage import get_stage

    (found,) = [s for s in workflow.steps if s.name == step]
    return get_stage(found.stage).output.name


def run_chain(
    workflow: Workflow,
    out: Path,
    inputs: Mapping[str, Sequence[Path]],
    over: str,
    feed: str,
    feed_step: str,
    scheduler: str | None = None,
    n_workers: int | None = None,
    observer: Callable[[], RunObserver] | None = None,
) -> list[RunSummary]:
    """Run ``workflow`` once per shard of input ``over`` (see the module docstring); returns
    each link's :class:`RunSummary` in order. ``observer`` makes each link's observer (a
    progress display counts one run's tasks)."""
    check_chain(workflow, inputs, over, feed, feed_step)
    out = Path(out)
    schema = get_schema(workflow.inputs[feed])
    links = [Path(p) for p in inputs[over]]
    summaries: list[RunSummary] = []
    given = {name: list(paths) for name, paths in inputs.items()}
    for k, shard in enumerate(links, 1):
        run_out = link_dir(out, k)
        given[over] = [shard]
        if k > 1:
            keys = [row["clip_id"] for row in _rows([shard])]
            prev = link_dir(out, k - 1)
            fed = _rows(find_shards([prev / feed_step], feed_step))
            if not fed:
                report = summaries[-1].report
                reasons = [f"{s.step}: {g.example_reason}" for s in report.steps for g in s.reasons]
                raise ChainError(
                    f"link {k - 1} ({prev}): step {feed_step!r} wrote no row to feed link {k}; "
                    + ("; ".join(reasons) or report.problem or "no reject recorded")
                )
            if len(fed) != len(keys):
                raise ChainError(
                    f"link {k}: {len(fed)} {feed_step!r} rows from link {k - 1} for "
                    f"{len(keys)} {over!r} rows: re-keying pairs them by position"
                )
            path = run_out / "given" / f"{feed}.parquet"
            storage.makedirs(path.parent)
            with ShardWriter(path, schema, stage=f"chain:{feed_step}") as writer:
                for row, key in zip(fed, keys, strict=True):
                    writer.write_row({**row, "clip_id": key})
            given[feed] = [path]
        summaries.append(
            run_workflow(
                workflow,
                run_out,
                scheduler=scheduler,
                n_workers=n_workers,
                inputs=given,
                observer=observer() if observer is not None else None,
            )
        )
    return summaries
