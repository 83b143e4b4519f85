"""Shards and runs on an object store: a local S3 server (moto) started by the tests, no network.

What is checked: URL parsing and joining; a shard round trip through s3fs with its completion
marker; writes killed at each step of a commit (inside the write, after the move before the
marker, a stray temporary key) are never listed, checked or resumed from; ``egosim run --out
s3://...`` with an ``s3://`` input, ``egosim check`` on its shards, and a resume that recomputes
exactly the shard whose commit did not finish.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from collections.abc import Iterator
from pathlib import Path

import fsspec
import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from egosim.pipeline import storage
from egosim.pipeline.check import check_paths
from egosim.pipeline.cli import app
from egosim.pipeline.clip_io import read_clips, write_clips
from egosim.pipeline.media import write_video_file
from egosim.pipeline.runner import run_workflow
from egosim.pipeline.shards import ShardReader, find_shards
from egosim.pipeline.workflow import parse_workflow
from egosim.schemas import CLIPS
from tests.conftest import make_clip, smooth_frames

REPO = Path(__file__).resolve().parents[1]
SMALL = {"height": 48, "width": 80, "num_frames": 8, "fps": 8.0}  # tiny ingest clips
BUCKET = "egosim-test"


@pytest.fixture(scope="module")
def s3_server() -> Iterator[dict[str, str]]:
    """A moto S3 server on a free local port; yields the environment that points at it."""
    from moto.server import ThreadedMotoServer

    server = ThreadedMotoServer(ip_address="127.0.0.1", port=0, verbose=False)
    server.start()
    host, port = server.get_host_and_port()
    env = {
        "AWS_ACCESS_KEY_ID": "testing",
        "AWS_SECRET_ACCESS_KEY": "testing",
        "AWS_DEFAULT_REGION": "us-east-1",
        "FSSPEC_S3_ENDPOINT_URL": f"http://{host}:{port}",
    }
    try:
        yield env
    finally:
        server.stop()


@pytest.fixture
def s3(s3_server: dict[str, str], tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> str:
    """A fresh bucket prefix on the local server, reachable as ``s3://`` through fsspec config."""
    import s3fs

    for key, value in s3_server.items():
        monkeypatch.setenv(key, value)
    # fsspec read its environment at import: give this process the endpoint as well.
    monkeypatch.setitem(
        fsspec.config.conf, "s3", {"endpoint_url": s3_server["FSSPEC_S3_ENDPOINT_URL"]}
    )
    monkeypatch.setenv(storage.CACHE_ENV, str(tmp_path / "cache"))
    s3fs.S3FileSystem.clear_instance_cache()
    fs = fsspec.filesystem("s3")
    if not fs.exists(BUCKET):
        fs.mkdir(BUCKET)
    return f"s3://{BUCKET}/{tmp_path.name}"


def s3_keys(prefix: str) -> list[str]:
    """Every key under an ``s3://`` prefix, relative to it."""
    fs, root = storage.filesystem(prefix)
    return sorted(k[len(root) + 1 :] for k in fs.find(root))


def test_locations_parse_join_and_refuse_escapes(tmp_path: Path) -> None:
    assert storage.location("data/run") == Path("data/run")
    assert storage.location(f"file://{tmp_path}") == tmp_path
    assert storage.location("s3://bucket/run/") == "s3://bucket/run"
    assert storage.join("s3://bucket/run", "ingest", "shard-00000.parquet") == (
        "s3://bucket/run/ingest/shard-00000.parquet"
    )
    loc = "s3://bucket/run/ingest/shard-00000.parquet"
    assert storage.name(loc) == "shard-00000.parquet"
    assert storage.parent(loc) == "s3://bucket/run/ingest"
    assert storage.with_name(loc, "rejects-00000.parquet") == (
        "s3://bucket/run/ingest/rejects-00000.parquet"
    )
    assert storage.marker_of(loc) == loc + ".complete"
    for bad in ("..", "a/b", "", "."):
        with pytest.raises(storage.StorageError, match="path part"):
            storage.join("s3://bucket/run", bad)
    with pytest.raises(storage.StorageError, match="nosuchproto://x"):
        storage.location("nosuchproto://x")


def test_shard_round_trip_on_s3_commits_with_a_marker(s3: str) -> None:
    clips = [make_clip("a", seed=1), make_clip("b", seed=2)]
    loc = storage.join(s3, "clips", "shard-00000.parquet")
    write_clips(loc, clips, stage="test", params={"k": 1})
    assert s3_keys(s3) == ["clips/shard-00000.parquet", "clips/shard-00000.parquet.complete"]
    marker = json.loads(storage.read_text(storage.marker_of(loc)))
    assert marker == {"size": storage.size(loc)}
    assert storage.is_committed(loc)
    back = list(read_clips(loc))
    assert [c.clip_id for c in back] == ["a", "b"]
    for a, b in zip(clips, back, strict=True):
        np.testing.assert_array_equal(a.world_from_cam, b.world_from_cam)
        np.testing.assert_array_equal(a.hand_mask, b.hand_mask)
        assert np.abs(a.frames.astype(int) - b.frames).mean() < 3  # H.264
    with ShardReader(loc, CLIPS) as reader:
        assert reader.meta.params == {"k": 1} and reader.num_rows == 2
    assert find_shards([s3], "clips") == [
        f"s3://{BUCKET}/{Path(s3).name}/clips/shard-00000.parquet"
    ]
    count, problems = check_paths([storage.join(s3, "clips")])
    assert count == 1 and problems == []
    # Overwriting drops the old marker before the move and writes a new one for the new size.
    write_clips(loc, clips[:1], stage="test")
    assert storage.is_committed(loc) and len(list(read_clips(loc))) == 1
    assert json.loads(storage.read_text(storage.marker_of(loc)))["size"] == storage.size(loc)


# A child process that writes one shard to S3 and dies at a chosen point of the commit.
KILLED_WRITER = textwrap.dedent(
    """
    import os, sys
    from egosim.pipeline import storage
    from egosim.pipeline.clip_io import write_clips
    from tests.conftest import make_clip

    loc, when = sys.argv[1], sys.argv[2]

    def die(*args, **kwargs):
        os._exit(137)  # as SIGKILL: no cleanup, no finally blocks

    if when == "before-marker":  # moved into place, killed before the marker is written
        storage.write_marker = die
    clips = [make_clip("a", seed=1), make_clip("b", seed=2)]

    def rows():
        yield clips[0]
        if when == "mid-write":  # killed after a row was written, before anything commits
            die()
        yield clips[1]

    write_clips(loc, rows(), stage="test")
    """
)


def run_killed_writer(loc: str, when: str, env: dict[str, str]) -> None:
    proc = subprocess.run(
        [sys.executable, "-c", KILLED_WRITER, loc, when],
        cwd=REPO,
        env={**os.environ, **env, "PYTHONPATH": str(REPO.parent)},
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 137, proc.stderr


def test_killed_writes_are_never_listed_checked_or_taken_as_done(
    s3: str, s3_server: dict[str, str]
) -> None:
    folder = storage.join(s3, "step")
    good = storage.join(folder, "shard-00000.parquet")
    write_clips(good, [make_clip("g", seed=3)], stage="test")

    mid = storage.join(folder, "shard-00001.parquet")
    run_killed_writer(mid, "mid-write", s3_server)
    assert not storage.exists(mid) and not storage.is_committed(mid)

    late = storage.join(folder, "shard-00002.parquet")
    run_killed_writer(late, "before-marker", s3_server)
    assert storage.exists(late)  # the bytes landed under the final key ...
    assert not storage.is_committed(late)  # ... but the commit did not finish

    # A partial temporary key, as a store that shows unfinished uploads would leave one.
    fs, root = storage.filesystem(folder)
    fs.pipe_file(f"{root}/shard-00003.parquet{storage.TMP_MARKER}deadbeef", b"PAR1\0\0partial")

    listed = [storage.name(p) for p in storage.list_files(folder, "*.parquet")]
    assert listed == ["shard-00000.parquet"]
    assert [storage.name(p) for p in find_shards([folder], "step")] == ["shard-00000.parquet"]
    count, problems = check_paths([folder])
    assert (count, problems) == (1, [])
    result = CliRunner().invoke(app, ["check", folder])
    assert result.exit_code == 0 and "checked 1 shard(s): 0 violation(s)" in result.output
    # Named explicitly, the uncommitted shard is read as it is (its content hashes hold).
    assert [c.clip_id for c in read_clips(late)] == ["a", "b"]

    removed = storage.remove_temporaries(s3)
    assert [storage.name(p) for p in removed] == [
        f"shard-00003.parquet{storage.TMP_MARKER}deadbeef"
    ]
    assert not any(storage.TMP_MARKER in k for k in s3_keys(s3))


def tiny_videos(folder: Path) -> Path:
    folder.mkdir(parents=True)
    for i in range(2):
        write_video_file(folder / f"v{i}.mp4", smooth_frames(24, 60, 90, seed=i), fps=24.0)
    return folder


def two_step_workflow() -> dict:
    return {
        "name": "remote",
        "steps": {
            "ingest": {"stage": "ingest", "params": {**SMALL, "units_per_shard": 1}},
            "caption": {"stage": "caption", "inputs": {"clips": "ingest"}},
        },
    }


def test_run_reads_and_writes_s3_and_check_and_resume_behave(s3: str, tmp_path: Path) -> None:
    videos = tiny_videos(tmp_path / "videos")
    fs, root = storage.filesystem(s3)
    fs.put(str(videos), f"{root}/input", recursive=True)
    wf_file = tmp_path / "wf.yaml"
    wf_file.write_text(yaml.safe_dump(two_step_workflow()))
    out = storage.join(s3, "run")
    cli = CliRunner()
    args = ["run", str(wf_file), "--input", f"{s3}/input", "--out", out, "--scheduler", "here"]
    result = cli.invoke(app, args)
    assert result.exit_code == 0, result.output

    keys = s3_keys(out)
    for record in ("manifest.json", "summary.json", "workflow.resolved.yaml", "rejects.parquet"):
        assert record in keys and f"{record}.complete" in keys
    assert "logs/run.log" in keys
    shards = [k for k in keys if k.endswith(".parquet") and "/" in k]
    assert sorted(shards) == [
        f"{step}/{kind}-0000{i}.parquet"
        for step in ("caption", "ingest")
        for kind in ("rejects", "shard")
        for i in (0, 1)
    ]
    assert all(f"{k}.complete" in keys for k in shards)
    assert not any(storage.TMP_MARKER in k for k in keys)
    summary = json.loads(storage.read_text(storage.join(out, "summary.json")))
    by_step = {s["step"]: s for s in summary["steps"]}
    assert by_step["ingest"]["clips_out"] == 2 and not by_step["ingest"]["final"]
    assert by_step["caption"]["clips_out"] == 2 and by_step["caption"]["final"]
    resolved = yaml.safe_load(storage.read_text(storage.join(out, "workflow.resolved.yaml")))
    assert resolved["input"] == f"{s3}/input"  # the URL the user gave, not the local copy

    result = cli.invoke(app, ["check", out])
    assert result.exit_code == 0, result.output
    assert "checked 9 shard(s): 0 violation(s)" in result.output  # 8 step shards + rejects

    # Killed between the move and the marker: that shard is not done; a resume redoes it only.
    undone = storage.join(out, "caption", "shard-00001.parquet")
    fs.rm_file(storage.filesystem(storage.marker_of(undone))[1])
    workflow = parse_workflow(two_step_workflow())
    again = run_workflow(workflow, out, source=f"{s3}/input", scheduler="here")
    redone = sorted((r.step, r.shard_index) for r in again.results if not r.skipped)
    assert redone == [("caption", 1)]
    assert storage.is_committed(undone)
    assert {s.step: s.clips_out for s in again.report.steps} == {"ingest": 2, "caption": 2}


def test_stage_command_reads_and_writes_urls(s3: str, tmp_path: Path) -> None:
    videos = tiny_videos(tmp_path / "videos")
    fs, root = storage.filesystem(s3)
    fs.put_file(str(videos / "v0.mp4"), f"{root}/in/v0.mp4")
    cli = CliRunner()
    clips = storage.join(s3, "one", "clips.parquet")
    params = [a for k, v in SMALL.items() for a in ("--set", f"{k}={v}")]
    args = ["stage", "ingest", "--input", f"{s3}/in/v0.mp4", "--output", clips, *params]
    result = cli.invoke(app, args)
    assert result.exit_code == 0, result.output
    captions = storage.join(s3, "one", "captions.parquet")
    result = cli.invoke(app, ["stage", "caption", "--input", clips, "--output", captions])
    assert result.exit_code == 0, result.output
    assert s3_keys(storage.join(s3, "one")) == sorted(
        f"{name}{end}"
        for name in ("clips", "clips.rejects", "captions", "captions.rejects")
        for end in (".parquet", ".parquet.complete")
    )
    result = cli.invoke(app, ["inspect", captions])
    assert result.exit_code == 0 and "schema: captions" in result.output, result.output
    assert "clip_id=v0-w000" in result.output
    result = cli.invoke(app, ["check", storage.join(s3, "one")])
    assert result.exit_code == 0 and "checked 4 shard(s): 0 violation(s)" in result.output


def test_run_into_a_missing_bucket_fails_with_the_stores_message(s3: str, tmp_path: Path) -> None:
    wf_file = tmp_path / "wf.yaml"
    wf_file.write_text(yaml.safe_dump(two_step_workflow()))
    out = "s3://no-such-egosim-bucket/run"
    args = ["run", str(wf_file), "--out", out, "--scheduler", "here"]
    with pytest.warns(UserWarning, match="could not copy the run log"):
        result = CliRunner().invoke(app, args)
    assert result.exit_code == 2, result.output
    assert "no-such-egosim-bucket" in result.output and "bucket" in result.output.lower()
    assert not fsspec.filesystem("s3").exists("no-such-egosim-bucket")  # never created


def test_remote_input_is_downloaded_once_into_the_cache(s3: str, tmp_path: Path) -> None:
    videos = tiny_videos(tmp_path / "videos")
    fs, root = storage.filesystem(s3)
    fs.put(str(videos), f"{root}/in", recursive=True)
    local = storage.local_copy(f"{s3}/in")
    assert local.is_relative_to(tmp_path / "cache")
    assert sorted(p.name for p in local.iterdir()) == ["v0.mp4", "v1.mp4"]
    for name in ("v0.mp4", "v1.mp4"):
        assert (local / name).read_bytes() == (videos / name).read_bytes()
    stamp = (local / "v0.mp4").stat().st_mtime_ns
    inode = (local / "v0.mp4").stat().st_ino
    assert storage.local_copy(f"{s3}/in") == local
    assert (local / "v0.mp4").stat().st_ino == inode  # kept, not downloaded again
    assert (local / "v0.mp4").stat().st_mtime_ns == stamp
    with pytest.raises(FileNotFoundError, match="nothing-here"):
        storage.local_copy(f"{s3}/nothing-here")


@pytest.mark.slow
def test_run_on_a_local_dask_cluster_writes_s3_from_the_workers(s3: str, tmp_path: Path) -> None:
    videos = tiny_videos(tmp_path / "videos")
    out = storage.join(s3, "run")
    workflow = parse_workflow(two_step_workflow())
    summary = run_workflow(workflow, out, source=str(videos), n_workers=2, gpu_workers=0)
    assert len(summary.results) == 4 and set(summary.workers.values()) <= {"cpu-0", "cpu-1"}
    count, problems = check_paths([out])
    assert (count, problems) == (9, [])
