"""The runner and the CLI end to end on small videos: resume, rejects, GPU placement."""

from __future__ import annotations

from pathlib import Path

import pyarrow.parquet as pq
import pytest
import yaml
from typer.testing import CliRunner

from egosim.pipeline.check import check_shard
from egosim.pipeline.cli import app
from egosim.pipeline.clip_io import read_clips, write_clips
from egosim.pipeline.media import write_video_file
from egosim.pipeline.runner import run_workflow
from egosim.pipeline.shards import ShardReader, read_shard_meta
from egosim.pipeline.workflow import load_workflow, parse_workflow
from tests.conftest import make_clip, smooth_frames

SMALL = {"height": 48, "width": 80, "num_frames": 8, "fps": 8.0}
SMALL_SET = [f"ingest.{k}={v}" for k, v in SMALL.items()]


@pytest.fixture
def videos(tmp_path: Path) -> Path:
    folder = tmp_path / "videos"
    folder.mkdir()
    for i in range(3):
        write_video_file(folder / f"v{i}.mp4", smooth_frames(30, 60, 90, seed=i), fps=30.0)
    return folder


def workflow_file(tmp_path: Path, resources: dict | None = None) -> Path:
    step = {"stage": "ingest", "params": {**SMALL, "units_per_shard": 1}}
    if resources:
        step["resources"] = resources
    path = tmp_path / "wf.yaml"
    path.write_text(yaml.safe_dump({"name": "t", "steps": {"ingest": step}}))
    return path


def test_stage_command_and_one_step_run_make_the_same_shard(tmp_path: Path, videos: Path) -> None:
    cli = CliRunner()
    video = videos / "v0.mp4"
    single = tmp_path / "single.parquet"
    params = [a for k, v in SMALL.items() for a in ("--set", f"{k}={v}")]
    result = cli.invoke(
        app, ["stage", "ingest", "--input", str(video), "--output", str(single), *params]
    )
    assert result.exit_code == 0, result.output
    result = cli.invoke(app, ["check", str(single)])
    assert result.exit_code == 0 and "0 violation(s)" in result.output, result.output

    wf = tmp_path / "one.yaml"
    wf.write_text(yaml.safe_dump({"steps": {"ingest": {"params": SMALL}}}))
    out = tmp_path / "run"
    result = cli.invoke(
        app, ["run", str(wf), "--input", str(video), "--out", str(out), "--workers", "1"]
    )
    assert result.exit_code == 0, result.output
    shard = out / "ingest" / "shard-00000.parquet"
    assert read_shard_meta(shard).fingerprint == read_shard_meta(single).fingerprint
    assert pq.read_table(shard).drop(["video"]).equals(pq.read_table(single).drop(["video"]))
    a, b = list(read_clips(shard)), list(read_clips(single))
    assert [c.clip_id for c in a] == [c.clip_id for c in b] == ["v0-w000"]
    assert (a[0].frames == b[0].frames).all()
    assert (out / "workflow.resolved.yaml").is_file() and (out / "manifest.json").is_file()


def test_rerun_skips_finished_shards_and_recomputes_what_is_missing(
    tmp_path: Path, videos: Path
) -> None:
    out = tmp_path / "run"
    wf = load_workflow(workflow_file(tmp_path))
    first = run_workflow(wf, out, source=str(videos), n_workers=2, gpu_workers=0)
    assert len(first.results) == 3 and not any(r.skipped for r in first.results)
    (out / "ingest" / "shard-00001.parquet").unlink()  # as if killed before this shard landed
    second = run_workflow(wf, out, source=str(videos), n_workers=2, gpu_workers=0)
    assert sorted(r.shard_index for r in second.results if not r.skipped) == [1]
    changed = load_workflow(workflow_file(tmp_path), ["ingest.crf=30"])
    third = run_workflow(changed, out, source=str(videos), n_workers=2, gpu_workers=0)
    assert not any(r.skipped for r in third.results)  # a changed parameter recomputes
    assert all(check_shard(p) == [] for p in (out / "ingest").glob("shard-*.parquet"))


def test_bad_clip_goes_to_rejects_and_the_shard_goes_on(tmp_path: Path, videos: Path) -> None:
    (videos / "v1.mp4").write_bytes(b"truncated")
    write_video_file(videos / "v3.mp4", smooth_frames(3, 60, 90), fps=30.0)  # too short
    out = tmp_path / "run"
    wf = parse_workflow({"steps": {"ingest": {"params": {**SMALL, "units_per_shard": 4}}}})
    summary = run_workflow(wf, out, source=str(videos), n_workers=1, gpu_workers=0)
    assert summary.rejected == 2
    rejects = pq.read_table(out / "rejects.parquet").to_pylist()
    reasons = {Path(r["clip_id"].split(":", 1)[1]).name: r["reason"] for r in rejects}
    assert "cannot read video file" in reasons["v1.mp4"]
    assert "shorter than one clip" in reasons["v3.mp4"]
    assert all(r["stage"] == "ingest" and r["input_fingerprint"] for r in rejects)
    ids = [c.clip_id for c in read_clips(out / "ingest" / "shard-00000.parquet")]
    assert ids == ["v0-w000", "v2-w000"]


def test_gpu_steps_run_only_on_workers_that_declare_a_gpu(tmp_path: Path, videos: Path) -> None:
    wf = load_workflow(workflow_file(tmp_path, resources={"GPU": 1}))
    summary = run_workflow(wf, tmp_path / "run", source=str(videos), n_workers=2, gpu_workers=1)
    assert len(summary.workers) == 3
    assert set(summary.workers.values()) == {"gpu-0"}
    cpu_wf = load_workflow(workflow_file(tmp_path))
    cpu = run_workflow(cpu_wf, tmp_path / "run2", source=str(videos), n_workers=2, gpu_workers=1)
    assert len(cpu.workers) == 3  # untagged steps may run anywhere


def test_cli_reports_errors_without_tracebacks(tmp_path: Path) -> None:
    cli = CliRunner()
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump({"steps": {"x": {"stage": "nope"}}}))
    result = cli.invoke(app, ["run", str(bad), "--out", str(tmp_path / "o")])
    assert result.exit_code == 2 and "unknown stage 'nope'" in result.output
    junk = tmp_path / "junk.parquet"
    junk.write_bytes(b"PAR1 nonsense")
    result = cli.invoke(app, ["check", str(junk)])
    assert result.exit_code == 1 and "junk.parquet" in result.output
    result = cli.invoke(app, ["stages"])
    assert result.exit_code == 0 and "ingest" in result.output


def test_synth_writes_shards_of_per_shard_clips(tmp_path: Path) -> None:
    out = tmp_path / "synth"
    args = ["synth", "--out", str(out), "--n", "3", "--per-shard", "2"]
    args += ["--height", "24", "--width", "32", "--frames", "5", "--fps", "8"]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    shards = sorted(out.glob("shard-*.parquet"))
    assert [s.name for s in shards] == ["shard-00000.parquet", "shard-00001.parquet"]
    assert [pq.read_metadata(s).num_rows for s in shards] == [2, 1]
    assert "(2 clips)" in result.output and "(1 clips)" in result.output


def test_stage_takes_set_and_the_deprecated_param_alias(tmp_path: Path) -> None:
    shard = tmp_path / "clips.parquet"
    write_clips(shard, [make_clip("c0")], stage="test")
    cli = CliRunner()
    for flag in ("--set", "--param"):
        out = tmp_path / f"captions{flag}.parquet"
        args = ["stage", "caption", "--input", str(shard), "--output", str(out)]
        result = cli.invoke(app, [*args, flag, "prefix=Hi", flag, "prefer_source=no"])
        assert result.exit_code == 0, result.output
        assert ("deprecated" in result.output) == (flag == "--param")
        with ShardReader(out) as reader:
            (row,) = list(reader.iter_rows())
            assert reader.meta.params["prefer_source"] is False
        assert row["text"].startswith("Hi ") and row["origin"] == "template"
    result = cli.invoke(app, [*args, "--set", "prefer_source=maybe"])
    assert result.exit_code == 2 and "expected a boolean, got 'maybe'" in result.output
