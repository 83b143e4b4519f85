"""What a run folder holds, read once for the report: steps, counts, seconds, rejects, rows.

A run folder is what ``egosim run`` writes (``RUN/<step>/shard-*.parquet``, ``manifest.json``,
``summary.json``, ``rejects.parquet``, ``workflow.resolved.yaml``). Steps are known by the
stage they run (from ``summary.json``, else the resolved workflow), so a report finds the
``scene_render`` step whatever the workflow named it.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from egosim.pipeline.shards import SHARD_GLOB, ShardReader
from egosim.schemas import REJECTS
from egosim.schemas.ids import path_under, validate_id


class RunFolderError(ValueError):
    """A folder is not a readable run folder; the message names the folder and the problem."""


@dataclass(frozen=True)
class StepInfo:
    """One step of the run as the report shows it."""

    step: str  # workflow step name (its folder under the run)
    stage: str  # registered stage name
    source: bool  # True for a source step: clips_in counts input units
    shards: int  # shard tasks of the step
    clips_in: int  # clips (units, for a source step) it was given
    clips_out: int  # rows in its output shards
    rejected: int  # clips it rejected
    unmatched: int  # clips absent from another input
    seconds: float  # wall seconds its tasks took in the last run (summed over shards)
    skipped_shards: int  # shards the last run skipped as already done


@dataclass(frozen=True)
class Reject:
    """One rejected clip (or source unit)."""

    step: str  # step that rejected it
    stage: str  # its stage
    shard: str  # shard file name
    clip_id: str  # the clip id or source unit
    reason: str  # why


@dataclass
class RunData:
    """A run folder's records; shards are read lazily through :meth:`rows`."""

    root: Path  # the run folder
    workflow: str  # workflow name
    source: str | None  # the run's input (None: built-in source, e.g. the synthetic world)
    steps: list[StepInfo]  # in workflow order
    rejects: list[Reject]  # every reject of the run
    outcome: str  # summary.json's verdict ('ok', 'step_rejected_all', ...)
    problem: str  # its sentence ('' when ok)
    _cache: dict[tuple[str, tuple[str, ...] | None], dict[str, dict]] = field(
        default_factory=dict, repr=False
    )

    def steps_of(self, stage: str) -> list[StepInfo]:
        """The steps that run ``stage``, in workflow order."""
        return [s for s in self.steps if s.stage == stage]

    def step_of(self, stage: str) -> StepInfo | None:
        """The first step that runs ``stage`` (None when the workflow has none)."""
        found = self.steps_of(stage)
        return found[0] if found else None

    def shard_files(self, step: str) -> list[Path]:
        """The output shards of ``step``, sorted."""
        folder = path_under(self.root, validate_id(step, "step name"))
        return sorted(folder.glob(SHARD_GLOB))

    def rows(self, step: str, columns: list[str] | None = None) -> dict[str, dict[str, Any]]:
        """Rows of ``step`` by clip id (only ``columns``, plus ``clip_id``; all when None)."""
        cols = None if columns is None else tuple(dict.fromkeys(["clip_id", *columns]))
        key = (step, cols)
        if key not in self._cache:
            out: dict[str, dict[str, Any]] = {}
            for path in self.shard_files(step):
                with ShardReader(path) as reader:
                    for row in reader.iter_rows(None if cols is None else list(cols)):
                        out[row["clip_id"]] = row
            self._cache[key] = out
        return self._cache[key]

    def rejects_by_clip(self) -> dict[str, list[Reject]]:
        """Rejects keyed by clip id (a source unit's id is its unit string)."""
        out: dict[str, list[Reject]] = {}
        for r in self.rejects:
            out.setdefault(r.clip_id, []).append(r)
        return out


def _read_json(path: Path) -> Any:
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise RunFolderError(f"{path}: not valid JSON ({exc})") from exc


def _seconds_from_manifest(manifest: dict) -> dict[str, tuple[float, int]]:
    """Per step: (seconds summed over results, skipped shards) from ``manifest.json``."""
    out: dict[str, tuple[float, int]] = {}
    for r in manifest.get("results", []):
        seconds, skipped = out.get(r["step"], (0.0, 0))
        out[r["step"]] = (seconds + float(r.get("seconds", 0.0)), skipped + bool(r.get("skipped")))
    return out


def load_run(root: Path) -> RunData:
    """Read a run folder's records (raises :class:`RunFolderError` naming what is missing)."""
    root = Path(root)
    if not root.is_dir():
        raise RunFolderError(f"{root}: not a folder (expected a run folder from `egosim run`)")
    summary_path, manifest_path = root / "summary.json", root / "manifest.json"
    if not summary_path.is_file():
        raise RunFolderError(
            f"{root}: no summary.json; is this a run folder written by `egosim run`?"
        )
    summary = _read_json(summary_path)
    manifest = _read_json(manifest_path) if manifest_path.is_file() else {}
    timing = _seconds_from_manifest(manifest)
    steps = []
    for s in summary.get("steps", []):
        seconds, skipped = timing.get(s["step"], (0.0, 0))
        steps.append(
            StepInfo(
                step=s["step"],
                stage=s["stage"],
                source=bool(s["source"]),
                shards=int(s["shards"]),
                clips_in=int(s["clips_in"]),
                clips_out=int(s["clips_out"]),
                rejected=int(s["rejected"]),
                unmatched=int(s.get("unmatched", 0)),
                seconds=float(s.get("seconds", seconds)),
                skipped_shards=int(s.get("skipped_shards", skipped)),
            )
        )
    workflow, source = "", None
    resolved = root / "workflow.resolved.yaml"
    if resolved.is_file():
        data = yaml.safe_load(resolved.read_text()) or {}
        workflow, source = str(data.get("name", "")), data.get("input")
    return RunData(
        root=root,
        workflow=workflow,
        source=source,
        steps=steps,
        rejects=list(_iter_rejects(root / "rejects.parquet")),
        outcome=str(summary.get("outcome", "")),
        problem=str(summary.get("problem", "")),
    )


def _iter_rejects(path: Path) -> Iterator[Reject]:
    if not path.is_file():
        return
    with ShardReader(path, REJECTS) as reader:
        for r in reader.iter_rows(["step", "stage", "shard", "clip_id", "reason"]):
            yield Reject(r["step"], r["stage"], r["shard"], r["clip_id"], r["reason"])
