"""What a run produced: per step, clips in, out, rejected, seconds, and the top reject reasons.

:func:`summarize_tasks` reads the shards and rejects files that a set of :class:`ShardTask`
left on disk (so a resumed run reports the shards it skipped too) and returns a
:class:`RunReport`; the :class:`ShardResult` of the run's tasks add each step's seconds (wall
time of its tasks, summed) and skipped shards. :func:`format_report` is the closing table.
The report names what went wrong when a run produced nothing; its
:meth:`RunReport.raise_for_outcome` raises a typed :class:`EmptyRunError` for the CLI to turn
into an exit code:

- :class:`StepRejectedAllError`: a step rejected every clip it was given, or a source step
  produced no clip from its input units;
- :class:`FinalStepEmptyError`: a final step (one that no other step reads) wrote no clip.

Reject reasons are grouped once clip ids, paths and numbers are taken out, so "video a.mp4 is
2.1 s" and "video b.mp4 is 2.4 s" count as one reason.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import re
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from enum import StrEnum

from egosim.pipeline import storage
from egosim.pipeline.execute import ShardResult, ShardTask, is_complete
from egosim.pipeline.shards import ShardReader
from egosim.pipeline.stage import SourceStage, get_stage
from egosim.schemas import REJECTS

log = logging.getLogger(__name__)

SUMMARY_VERSION = 2  # version of the summary.json layout (2: per-step seconds, skipped_shards)

# Absolute or relative file paths in a reason ("/data/a.mp4", "./x/y", "~/v.mp4").
_PATH = re.compile(r"(?<![\w/])(?:~|\.{1,2})?/[^\s:,;'\"()\[\]]+")
# Long hexadecimal runs with letters and digits (fingerprints, hashes), not plain numbers.
_HEX = re.compile(r"\b(?=[0-9a-f]*\d)(?=[0-9a-f]*[a-f])[0-9a-f]{8,}\b")
# Numbers, signed, with decimals or exponents.
_NUMBER = re.compile(r"(?<![\w.])-?\d+(?:\.\d+)?(?:[eE][-+]?\d+)?")
_SLOT = "\x00"  # where a number stood in a grouping key


class EmptyRunError(Exception):
    """A run (or one stage) finished but did not produce what it should; carries the report."""

    def __init__(self, message: str, report: RunReport) -> None:
        super().__init__(message)
        self.report = report  # the summary that shows what happened


class StepRejectedAllError(EmptyRunError):
    """A step rejected every clip it was given, or a source step produced no clip."""


class FinalStepEmptyError(EmptyRunError):
    """A final step (read by no other step) wrote no clip."""


class Outcome(StrEnum):
    """The verdict of a run on what it produced."""

    OK = "ok"  # every final step has clips
    STEP_REJECTED_ALL = "step_rejected_all"  # some step rejected every clip it was given
    FINAL_STEP_EMPTY = "final_step_empty"  # a final step is empty (nothing rejected it all)
    INCOMPLETE = "incomplete"  # some task left no output (it failed as a whole)


@dataclass(frozen=True)
class ReasonGroup:
    """Rejects whose reasons differ only in clip ids, paths and numbers."""

    pattern: str  # the reason, with <clip>, <path>, and N for numbers that vary in the group
    count: int  # rejects in this group
    example_clip_id: str  # one clip (or input unit, for source steps) rejected for it
    example_reason: str  # that clip's full reason


@dataclass(frozen=True)
class StepSummary:
    """What one workflow step did, over all its shards."""

    step: str  # workflow step name
    stage: str  # registered stage name
    source: bool  # True for a source step: ``clips_in`` counts input units, not clips
    shards: int  # shard tasks of the step
    clips_in: int  # clips of the step's primary input (input units for a source step)
    clips_out: int  # rows in the step's output shards
    rejected: int  # clips (units, for a source step) the stage rejected
    unmatched: int  # primary-input clips absent from another input (rejected in another branch)
    missing_shards: int  # shard tasks without their output (the task failed)
    final: bool  # True when no other step reads this step's output
    reasons: tuple[ReasonGroup, ...]  # every reject reason group, most frequent first
    seconds: float = 0.0  # wall seconds this run's tasks of the step took (summed over shards)
    skipped_shards: int = 0  # shard tasks this run skipped as already done (0 seconds each)

    @property
    def rejected_all(self) -> bool:
        """True when the step was given work and every bit of it was rejected or produced nothing.

        A clip step that was given clips (not counting unmatched ones) rejected all of them; a
        source step turned its units into no clip at all.
        """
        if self.missing_shards:
            return False
        if self.source:
            return self.clips_in > 0 and self.clips_out == 0
        return self.rejected > 0 and self.clips_out == 0


@dataclass(frozen=True)
class RunReport:
    """The summary of a run (or of one ``egosim stage``): one :class:`StepSummary` per step."""

    steps: tuple[StepSummary, ...]  # in workflow (dependency) order
    outcome: Outcome  # the verdict; see :class:`Outcome`
    problem: str  # one sentence saying what went wrong ("" when the outcome is OK)

    @property
    def rejected(self) -> int:
        """Rejects over all steps."""
        return sum(s.rejected for s in self.steps)

    def to_dict(self) -> dict:
        """JSON-ready data, as written to ``summary.json``."""
        data = asdict(self)
        data["outcome"] = self.outcome.value
        return {"version": SUMMARY_VERSION, **data, "rejected": self.rejected}

    def to_json(self) -> str:
        """The report as indented JSON text."""
        return json.dumps(self.to_dict(), indent=1) + "\n"

    def raise_for_outcome(self) -> None:
        """Raise the :class:`EmptyRunError` matching the outcome; return when the run is OK.

        An ``INCOMPLETE`` outcome raises nothing here: failed tasks are reported by the runner.
        """
        if self.outcome is Outcome.STEP_REJECTED_ALL:
            raise StepRejectedAllError(self.problem, self)
        if self.outcome is Outcome.FINAL_STEP_EMPTY:
            raise FinalStepEmptyError(self.problem, self)


def summarize_tasks(tasks: Sequence[ShardTask], results: Sequence[ShardResult] = ()) -> RunReport:
    """Summarise what ``tasks`` left on disk, per step, in the order steps first appear.

    A step is final when no other task reads its output shards. An output that does not exist
    with the task's fingerprint (the task failed) counts as a missing shard; its step's figures
    cover the shards that exist. ``results`` (what this run's tasks returned) give each step's
    seconds and skipped shards; without them both are 0.
    """
    by_step: dict[str, list[ShardTask]] = {}
    for task in tasks:
        by_step.setdefault(task.step, []).append(task)
    timing: dict[str, list[ShardResult]] = {}
    for result in results:
        timing.setdefault(result.step, []).append(result)
    read = {str(p) for t in tasks for p in t.inputs.values()}  # paths or URLs
    steps = tuple(
        dataclasses.replace(
            _summarize_step(step_tasks, final=not any(str(t.output) in read for t in step_tasks)),
            seconds=sum(r.seconds for r in timing.get(step, [])),
            skipped_shards=sum(r.skipped for r in timing.get(step, [])),
        )
        for step, step_tasks in by_step.items()
    )
    outcome, problem = _verdict(steps)
    return RunReport(steps=steps, outcome=outcome, problem=problem)


def _summarize_step(tasks: list[ShardTask], final: bool) -> StepSummary:
    first = tasks[0]
    stage_cls = get_stage(first.stage)
    source = issubclass(stage_cls, SourceStage)
    roles = list(stage_cls.input_schemas())
    clips_in = clips_out = unmatched = missing = 0
    rejects: list[tuple[str, str]] = []  # (clip_id, reason)
    for task in tasks:
        if not is_complete(task):  # absent, or left by an earlier run with other inputs
            log.warning(
                "step=%s stage=%s shard=%s has no output with this run's fingerprint",
                task.step,
                task.stage,
                storage.name(task.output),
            )
            missing += 1
            continue
        with ShardReader(task.output) as reader:
            out = reader.num_rows
        step_rejects: list[tuple[str, str]] = []
        if storage.is_committed(task.rejects):
            with ShardReader(task.rejects, REJECTS) as reader:
                step_rejects = [
                    (r["clip_id"], r["reason"]) for r in reader.iter_rows(["clip_id", "reason"])
                ]
        if source:
            given = len(task.units)
        else:
            # The executor iterates the first declared role that the task was given.
            primary = next(r for r in roles if r in task.inputs)
            with ShardReader(task.inputs[primary]) as reader:
                given = reader.num_rows
            unmatched += max(0, given - out - len(step_rejects))
        clips_in += given
        clips_out += out
        rejects += step_rejects
    return StepSummary(
        step=first.step,
        stage=first.stage,
        source=source,
        shards=len(tasks),
        clips_in=clips_in,
        clips_out=clips_out,
        rejected=len(rejects),
        unmatched=unmatched,
        missing_shards=missing,
        final=final,
        reasons=group_reasons(rejects),
    )


def _verdict(steps: Sequence[StepSummary]) -> tuple[Outcome, str]:
    incomplete = [s for s in steps if s.missing_shards]
    if incomplete:
        named = ", ".join(f"{s.step!r} ({s.missing_shards} of {s.shards})" for s in incomplete)
        return Outcome.INCOMPLETE, f"shards missing in step(s) {named}"
    for s in steps:  # the first step that rejected everything is the cause of what follows
        if s.rejected_all:
            what = "input unit(s)" if s.source else "clip(s)"
            verb = "produced no clip from" if s.source else "rejected every one of"
            top = f"; top reason: {_fit(' '.join(s.reasons[0].pattern.split()), 160)}"
            top = top if s.reasons else ""
            return Outcome.STEP_REJECTED_ALL, (
                f"step {s.step!r} {verb} the {s.clips_in} {what} it was given{top}"
            )
    empty = [s.step for s in steps if s.final and s.clips_out == 0]
    if empty:
        return (
            Outcome.FINAL_STEP_EMPTY,
            f"final step(s) {', '.join(map(repr, empty))} wrote no clip",
        )
    return Outcome.OK, ""


def reason_key(reason: str, clip_id: str = "") -> tuple[str, tuple[str, ...]]:
    """Split a reason into a grouping key and the numbers taken out of it.

    The clip id (and, for an input unit such as ``video:/a/b.mp4``, its path) becomes
    ``<clip>``, other paths ``<path>``, long hex runs ``<hash>``; each number leaves a slot in
    the key and is returned in order.
    """
    text = reason
    ids = [clip_id, clip_id.split(":", 1)[1] if ":" in clip_id else ""]
    for cid in sorted(filter(None, ids), key=len, reverse=True):
        text = text.replace(cid, "<clip>")
    text = _PATH.sub("<path>", text)
    text = _HEX.sub("<hash>", text)
    numbers = tuple(_NUMBER.findall(text))
    return _NUMBER.sub(_SLOT, text), numbers


def group_reasons(rejects: Sequence[tuple[str, str]]) -> tuple[ReasonGroup, ...]:
    """Group ``(clip_id, reason)`` pairs by :func:`reason_key`, most frequent first.

    In a group's pattern a number that is the same in every member stays; one that varies is
    shown as ``N``.
    """
    groups: dict[str, list[tuple[str, str, tuple[str, ...]]]] = {}
    for clip_id, reason in rejects:
        key, numbers = reason_key(reason, clip_id)
        groups.setdefault(key, []).append((clip_id, reason, numbers))
    out = []
    for key, members in groups.items():
        slots = zip(*(m[2] for m in members), strict=True)
        shown = [vals[0] if len(set(vals)) == 1 else "N" for vals in slots]
        parts = key.split(_SLOT)
        pattern = parts[0] + "".join(n + p for n, p in zip(shown, parts[1:], strict=True))
        clip_id, reason, _ = members[0]
        out.append(ReasonGroup(pattern, len(members), clip_id, reason))
    return tuple(sorted(out, key=lambda g: -g.count))


def _fit(text: str, width: int, keep_end: bool = False) -> str:
    """``text`` cut to ``width`` characters with an ellipsis (at the start when ``keep_end``)."""
    if len(text) <= width:
        return text
    return "…" + text[-(width - 1) :] if keep_end else text[: width - 1] + "…"


def format_report(report: RunReport, top: int = 3, width: int = 100) -> str:
    """The report as a plain-text table of at most ``width`` columns, with ``top`` reasons a step.

    Source steps count input units in (``N units``) and clips out; ``seconds`` is the wall time
    this run's tasks of the step took, summed over shards (skipped shards add none).
    """
    name_w = max([4, *(len(s.step) for s in report.steps)])
    name_w = min(name_w, 24)
    head = (
        f"{'step':<{name_w}}  {'in':>12}  {'out':>8}  {'rejected':>8}  {'unmatched':>9}  "
        f"{'seconds':>8}  note"
    )
    lines = ["run summary", head, "-" * min(width, len(head) + 20)]
    for s in report.steps:
        clips_in = f"{s.clips_in} units" if s.source else str(s.clips_in)
        notes = []
        if s.final:
            notes.append("final")
        if s.missing_shards:
            notes.append(f"{s.missing_shards} shard(s) missing")
        if s.skipped_shards:
            notes.append(f"{s.skipped_shards} skipped")
        if s.rejected_all:
            notes.append("ALL REJECTED")
        elif s.final and s.clips_out == 0 and not s.missing_shards:
            notes.append("EMPTY")
        row = (
            f"{_fit(s.step, name_w):<{name_w}}  {clips_in:>12}  {s.clips_out:>8}  "
            f"{s.rejected:>8}  {s.unmatched:>9}  {s.seconds:>8.1f}  {', '.join(notes)}"
        )
        lines.append(_fit(row, width).rstrip())
    with_reasons = [s for s in report.steps if s.reasons]
    if with_reasons:
        lines.append("")
        lines.append(f"top reject reasons ({report.rejected} rejected in all):")
    for s in with_reasons:
        lines.append(f"  {s.step}:")
        for group in s.reasons[:top]:
            pattern = " ".join(group.pattern.split())  # a reason may hold newlines
            lines.append(_fit(f"    {group.count:>4} x {pattern}", width))
            example = _fit(group.example_clip_id, width - 17, keep_end=True)
            lines.append(f"           e.g. {example}")
        if len(s.reasons) > top:
            rest = sum(g.count for g in s.reasons[top:])
            lines.append(f"           … {len(s.reasons) - top} more reason(s), {rest} reject(s)")
    return "\n".join(lines)
