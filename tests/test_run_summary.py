"""Runs that say what they produced: the summary table, summary.json and the exit codes."""

from __future__ import annotations

import dataclasses
import json
import re
from collections.abc import Iterator
from pathlib import Path

import pyarrow.parquet as pq
import pytest
import yaml
from typer.testing import CliRunner

from egosim.pipeline.cli import EXIT_FINAL_STEP_EMPTY, EXIT_STEP_REJECTED_ALL, app
from egosim.pipeline.clip_io import write_clips
from egosim.pipeline.media import write_video_file
from egosim.pipeline.shards import ShardWriter
from egosim.pipeline.summary import (
    FinalStepEmptyError,
    Outcome,
    RunReport,
    StepRejectedAllError,
    StepSummary,
    format_report,
    group_reasons,
    summarize_tasks,
)
from egosim.schemas import REJECTS
from egosim.schemas.captions import CAPTIONS
from tests.conftest import make_clip, one_shard_task, smooth_frames

SMALL = {"height": 48, "width": 80, "num_frames": 8, "fps": 8.0}


@pytest.fixture(scope="module")
def scheduler() -> Iterator[str]:
    """An in-process Dask cluster shared by this module's runs (`--scheduler`), so the tests
    pay no worker start-up; the local-cluster path is covered by tests/test_runner.py."""
    import torch
    from distributed import LocalCluster

    threads = torch.get_num_threads()  # the runner's task wrapper sets 1 in its worker
    with LocalCluster(
        n_workers=1, threads_per_worker=1, processes=False, dashboard_address=None
    ) as cluster:
        yield cluster.scheduler_address
    torch.set_num_threads(threads)


def _workflow(tmp_path: Path, with_captions: bool) -> Path:
    steps: dict = {"ingest": {"params": {**SMALL, "units_per_shard": 2}}}
    if with_captions:
        steps["captions"] = {"stage": "caption", "inputs": {"clips": "ingest"}}
    path = tmp_path / "wf.yaml"
    path.write_text(yaml.safe_dump({"name": "t", "steps": steps}))
    return path


def _corrupt(path: Path, text: str = "not a video") -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(text.encode())
    return path


def test_run_where_ingest_rejects_everything_exits_3_and_says_why(
    tmp_path: Path, scheduler: str
) -> None:
    videos = tmp_path / "videos"
    _corrupt(videos / "a.mp4")
    _corrupt(videos / "b.mp4", "truncated too")
    out = tmp_path / "run"
    args = ["run", str(_workflow(tmp_path, False)), "--input", str(videos), "--out", str(out)]
    result = CliRunner().invoke(app, [*args, "--scheduler", scheduler])
    assert result.exit_code == EXIT_STEP_REJECTED_ALL == 3, result.output
    assert "run summary" in result.output and "ALL REJECTED" in result.output
    # Two files with different paths count as one reason, shown once with its count.
    assert "2 x cannot read video file <clip>" in result.output, result.output
    assert "step 'ingest' produced no clip from the 2 input unit(s)" in result.output
    table = result.output.split("run summary", 1)[1].split("error:", 1)[0]
    assert all(len(line) <= 100 for line in table.splitlines()), table
    summary = json.loads((out / "summary.json").read_text())
    assert summary["outcome"] == "step_rejected_all"
    (ingest,) = summary["steps"]
    assert (ingest["clips_in"], ingest["clips_out"], ingest["rejected"]) == (2, 0, 2)
    assert ingest["reasons"][0]["count"] == 2
    assert ingest["reasons"][0]["example_clip_id"].endswith(("a.mp4", "b.mp4"))
    assert not list(out.glob("*.tmp-*"))  # the JSON files were renamed into place


def test_run_with_one_good_and_one_bad_input_exits_0_and_counts_the_reject(
    tmp_path: Path, scheduler: str
) -> None:
    videos = tmp_path / "videos"
    videos.mkdir()
    write_video_file(videos / "good.mp4", smooth_frames(30, 60, 90), fps=30.0)
    _corrupt(videos / "bad.mp4")
    out = tmp_path / "run"
    args = ["run", str(_workflow(tmp_path, True)), "--input", str(videos), "--out", str(out)]
    result = CliRunner().invoke(app, [*args, "--scheduler", scheduler])
    assert result.exit_code == 0, result.output
    assert "1 rejected in all" in result.output and "e.g. video:" in result.output
    summary = json.loads((out / "summary.json").read_text())
    assert summary["outcome"] == "ok" and summary["problem"] == "" and summary["rejected"] == 1
    ingest, captions = summary["steps"]
    made = pq.read_metadata(out / "ingest" / "shard-00000.parquet").num_rows
    assert made >= 1
    assert (ingest["source"], ingest["clips_in"], ingest["clips_out"]) == (True, 2, made)
    assert (ingest["rejected"], ingest["final"]) == (1, False)
    assert ingest["reasons"][0]["example_clip_id"].endswith("bad.mp4")
    assert (captions["clips_in"], captions["clips_out"], captions["rejected"]) == (made, made, 0)
    assert captions["final"] and not captions["source"]


def test_stage_exits_non_zero_when_every_clip_is_rejected(tmp_path: Path) -> None:
    cli = CliRunner()
    bad = _corrupt(tmp_path / "bad.mp4")
    output = tmp_path / "clips_out.parquet"
    result = cli.invoke(app, ["stage", "ingest", "--input", str(bad), "--output", str(output)])
    assert result.exit_code == EXIT_STEP_REJECTED_ALL, result.output
    assert "cannot read video file" in result.output

    # A clip stage: pose_clean needs poses these clips do not have.
    clips = [dataclasses.replace(make_clip(f"c{i}"), world_from_cam=None) for i in range(2)]
    shard = tmp_path / "clips.parquet"
    write_clips(shard, clips, stage="test")
    output = tmp_path / "poses.parquet"
    result = cli.invoke(
        app, ["stage", "pose_clean", "--input", str(shard), "--output", str(output)]
    )
    assert result.exit_code == EXIT_STEP_REJECTED_ALL, result.output
    assert "rejected every one of the 2 clip(s)" in result.output
    assert "2 x clip <clip> has no world_from_cam" in result.output, result.output

    # Nothing rejected, nothing to do: an empty final output is its own code.
    empty = tmp_path / "empty.parquet"
    write_clips(empty, [], stage="test")
    out = tmp_path / "captions.parquet"
    result = cli.invoke(app, ["stage", "caption", "--input", str(empty), "--output", str(out)])
    assert result.exit_code == EXIT_FINAL_STEP_EMPTY == 4, result.output
    assert "final step(s) 'caption' wrote no clip" in result.output


def _captions_output(task, clip_ids: list[str], rejected: dict[str, str]) -> None:
    """Write what a caption task would leave: rows for ``clip_ids`` and the ``rejected`` ones."""
    with ShardWriter(task.output, CAPTIONS, stage="caption") as writer:
        for cid in clip_ids:
            writer.write_row({"clip_id": cid, "text": "t", "origin": "template"})
    with ShardWriter(task.rejects, REJECTS, stage="caption") as writer:
        for cid, reason in rejected.items():
            row = {"step": "caption", "stage": "caption", "shard": task.output.name}
            writer.write_row({**row, "clip_id": cid, "reason": reason, "input_fingerprint": ""})


def test_summary_counts_in_out_rejected_and_unmatched_from_disk(tmp_path: Path) -> None:
    shard = tmp_path / "clips.parquet"
    write_clips(shard, [make_clip(f"c{i}") for i in range(4)], stage="test")
    task = one_shard_task("caption", tmp_path, {"clips": shard})
    # c0 written; c1 and c2 rejected with reasons differing in a number; c3 never given.
    reasons = {"c1": "c1 is 2.5 s long", "c2": "c2 is 1.5 s long"}
    _captions_output(task, ["c0"], reasons)
    report = summarize_tasks([task])
    (step,) = report.steps
    assert (step.clips_in, step.clips_out, step.rejected, step.unmatched) == (4, 1, 2, 1)
    assert step.final and not step.source and not step.rejected_all
    assert report.outcome is Outcome.OK and report.rejected == 2
    report.raise_for_outcome()  # OK: nothing raised
    (group,) = step.reasons
    assert (group.pattern, group.count, group.example_clip_id) == ("<clip> is N s long", 2, "c1")

    _captions_output(task, [], reasons)  # now nothing made it through
    report = summarize_tasks([task])
    assert report.outcome is Outcome.STEP_REJECTED_ALL and report.steps[0].rejected_all
    with pytest.raises(StepRejectedAllError, match="rejected every one of the 4 clip"):
        report.raise_for_outcome()

    _captions_output(task, [], {})  # no rejects, no rows: only "empty" applies
    report = summarize_tasks([task])
    with pytest.raises(FinalStepEmptyError):
        report.raise_for_outcome()


def test_missing_output_is_incomplete_not_a_verdict_on_the_clips(tmp_path: Path) -> None:
    shard = tmp_path / "clips.parquet"
    write_clips(shard, [make_clip("c0")], stage="test")
    task = one_shard_task("caption", tmp_path, {"clips": shard})
    report = summarize_tasks([task])
    assert report.outcome is Outcome.INCOMPLETE and report.steps[0].missing_shards == 1
    report.raise_for_outcome()  # the runner reports failed tasks itself
    _captions_output(task, ["c0"], {})
    assert summarize_tasks([task]).outcome is Outcome.OK
    # An output an earlier run left with other inputs is not this task's output.
    stale = dataclasses.replace(task, fingerprint="other inputs")
    assert summarize_tasks([stale]).steps[0].missing_shards == 1


def test_reasons_group_and_the_table_fits_100_columns() -> None:
    long_id = "video:/data/" + "x" * 150 + ".mp4"
    rejects = [
        ("video:/d/a.mp4", "cannot read video file /d/a.mp4: [Errno -1094995529] bad"),
        ("video:/d/b.mp4", "cannot read video file /d/b.mp4: [Errno -1094995529] bad"),
        (long_id, "video file is shorter than one clip: 61 frames need 3.75 s, " + "y" * 200),
        ("v1-w000", "fingerprint 3fa9c2d81b0e mismatch"),
    ]
    groups = group_reasons(rejects)
    assert [g.count for g in groups] == [2, 1, 1]
    assert groups[0].pattern == "cannot read video file <clip>: [Errno -1094995529] bad"
    assert groups[2].pattern == "fingerprint <hash> mismatch"
    step = StepSummary(
        step="ingest",
        stage="ingest",
        source=True,
        shards=1,
        clips_in=4,
        clips_out=0,
        rejected=4,
        unmatched=0,
        missing_shards=0,
        final=True,
        reasons=groups,
    )
    text = format_report(RunReport((step,), Outcome.STEP_REJECTED_ALL, "x"), top=2)
    assert all(len(line) <= 100 for line in text.splitlines()), text
    assert "4 units" in text and "ALL REJECTED" in text
    assert "1 more reason(s), 1 reject(s)" in text
    assert "e.g. …" + "x" * 20 in text and "x.mp4\n" in text  # long ids keep their end


def test_closing_table_numbers_match_the_runs_outputs_rejects_and_manifest(
    tmp_path: Path, scheduler: str
) -> None:
    videos = tmp_path / "videos"
    videos.mkdir()
    for i in range(3):
        write_video_file(videos / f"v{i}.mp4", smooth_frames(12, 48, 80, seed=i), fps=8.0)
    _corrupt(videos / "zz_bad.mp4")
    out = tmp_path / "run"
    args = ["run", str(_workflow(tmp_path, True)), "--input", str(videos), "--out", str(out)]
    result = CliRunner().invoke(app, [*args, "--scheduler", scheduler])
    assert result.exit_code == 0, result.output
    summary = json.loads((out / "summary.json").read_text())
    manifest = json.loads((out / "manifest.json").read_text())
    rejects = pq.read_table(out / "rejects.parquet").to_pylist()
    table = result.output.split("run summary", 1)[1]
    for step in summary["steps"]:
        name = step["step"]
        rows = sum(pq.read_metadata(p).num_rows for p in (out / name).glob("shard-*.parquet"))
        rejected = [r for r in rejects if r["step"] == name]
        seconds = sum(r["seconds"] for r in manifest["results"] if r["step"] == name)
        assert step["clips_out"] == rows and step["rejected"] == len(rejected)
        assert step["seconds"] == pytest.approx(seconds) and seconds > 0
        assert step["skipped_shards"] == 0
        # The printed row: step, in, out, rejected, unmatched, seconds.
        clips_in = f"{step['clips_in']} units" if step["source"] else str(step["clips_in"])
        row = rf"\n{name}\s+{clips_in}\s+{rows}\s+{len(rejected)}\s+0\s+{seconds:.1f}\s"
        assert re.search(row, table), (row, table)
    ingest, captions = summary["steps"]
    assert (ingest["clips_in"], ingest["clips_out"], ingest["rejected"]) == (4, 3, 1)
    assert captions["clips_in"] == 3 == captions["clips_out"]
    # A second run skips every shard: no seconds, and the table says so.
    result = CliRunner().invoke(app, [*args, "--scheduler", scheduler])
    assert result.exit_code == 0, result.output
    again = json.loads((out / "summary.json").read_text())
    assert [s["seconds"] for s in again["steps"]] == [0.0, 0.0]
    assert [s["skipped_shards"] for s in again["steps"]] == [2, 2]
    assert [s["clips_out"] for s in again["steps"]] == [3, 3]  # from disk, not from this run
    assert re.search(r"\ncaptions\s+3\s+3\s+0\s+0\s+0\.0\s+final, 2 skipped", result.output)
