"""Observable runs: the run log, the live/plain progress display and the dashboard address."""

from __future__ import annotations

import importlib.util
import io
import re
from collections.abc import Iterator
from pathlib import Path

import pyarrow.parquet as pq
import pytest
import yaml
from typer.testing import CliRunner

from egosim.pipeline.cli import app
from egosim.pipeline.execute import (
    CLIP_DONE,
    CLIP_REJECTED,
    TASK_STARTED,
    ShardResult,
    ShardTask,
)
from egosim.pipeline.media import write_video_file
from egosim.pipeline.observe import ConsoleObserver, RunObserver, log_path
from egosim.pipeline.runner import IN_PROCESS, run_workflow
from egosim.pipeline.workflow import load_workflow
from tests.conftest import smooth_frames

SMALL = {"height": 48, "width": 80, "num_frames": 8, "fps": 8.0}
HAS_BOKEH = importlib.util.find_spec("bokeh") is not None


@pytest.fixture
def videos(tmp_path: Path) -> Path:
    """Two good videos and one that cannot be read."""
    folder = tmp_path / "videos"
    folder.mkdir()
    for i in range(2):
        write_video_file(folder / f"v{i}.mp4", smooth_frames(12, 48, 80, seed=i), fps=8.0)
    (folder / "bad.mp4").write_bytes(b"not a video")
    return folder


@pytest.fixture(scope="module")
def scheduler() -> Iterator[str]:
    """An in-process Dask cluster (threads of this process), shared by the module."""
    import torch
    from distributed import LocalCluster

    threads = torch.get_num_threads()
    with LocalCluster(
        n_workers=1, threads_per_worker=1, processes=False, dashboard_address=":0"
    ) as cluster:
        yield cluster.scheduler_address
    torch.set_num_threads(threads)


def _workflow(tmp_path: Path) -> Path:
    steps = {
        "ingest": {"params": {**SMALL, "units_per_shard": 2}},
        "captions": {"stage": "caption", "inputs": {"clips": "ingest"}},
    }
    path = tmp_path / "wf.yaml"
    path.write_text(yaml.safe_dump({"name": "obs", "steps": steps}))
    return path


def _clip_ids(out: Path, step: str) -> list[str]:
    ids: list[str] = []
    for shard in sorted((out / step).glob("shard-*.parquet")):
        ids += pq.read_table(shard, columns=["clip_id"]).column("clip_id").to_pylist()
    return ids


class Recorder(RunObserver):
    """Keeps every call, to check what the runner tells an observer."""

    def __init__(self) -> None:
        self.calls: list[tuple] = []

    def run_started(self, name, tasks) -> None:
        self.calls.append(("started", name, len(tasks)))

    def dashboard(self, link, reason) -> None:
        self.calls.append(("dashboard", link, reason))

    def clip_settled(self, step, shard_index, clip_id, outcome) -> None:
        self.calls.append(("clip", step, shard_index, clip_id, outcome))

    def task_finished(self, result) -> None:
        self.calls.append(("task", result.step, result.shard_index, result.rows))

    def run_finished(self) -> None:
        self.calls.append(("finished",))


def test_run_log_names_step_stage_shard_and_every_clip(tmp_path: Path, videos: Path) -> None:
    out = tmp_path / "run"
    recorder = Recorder()
    wf = load_workflow(_workflow(tmp_path))
    run_workflow(wf, out, source=str(videos), scheduler=IN_PROCESS, observer=recorder)
    text = log_path(out).read_text()
    lines = text.splitlines()
    made = _clip_ids(out, "ingest")
    assert len(made) == 2 and made == _clip_ids(out, "captions")
    # Every caption clip: one 'done' line naming step, stage, shard and clip.
    for cid in made:
        done = [ln for ln in lines if "stage=caption shard=" in ln and f"clip={cid} done" in ln]
        assert len(done) == 1, (cid, text)
        assert re.search(r"step=captions stage=caption shard=shard-0000[01]\.parquet", done[0])
    # The unreadable unit: a WARNING with its reason, in the shard that had it.
    (bad,) = [ln for ln in lines if "bad.mp4 rejected:" in ln]
    assert " WARNING " in bad and "step=ingest stage=ingest shard=shard-0000" in bad
    assert "cannot read video file" in bad
    assert "step ingest: 3 in, 2 out, 1 rejected" in text
    assert "step captions: 2 in, 2 out, 0 rejected" in text
    # The observer heard each clip once, each task once, and the end.
    clips = [c for c in recorder.calls if c[0] == "clip" and c[4] != TASK_STARTED]
    assert sorted(c[3] for c in clips if c[1] == "captions") == sorted(made)
    started = [c for c in recorder.calls if c[0] == "clip" and c[4] == TASK_STARTED]
    assert sorted((c[1], c[2]) for c in started) == sorted(
        (step, i) for step in ("captions", "ingest") for i in (0, 1)
    )
    assert [c[4] for c in clips if c[1] == "ingest"].count(CLIP_REJECTED) == 1
    assert len([c for c in recorder.calls if c[0] == "task"]) == 4
    assert recorder.calls[0] == ("started", "obs", 4) and recorder.calls[-1] == ("finished",)
    # A second run appends to the same log and says it skipped.
    run_workflow(wf, out, source=str(videos), scheduler=IN_PROCESS)
    again = log_path(out).read_text()
    assert again.startswith(text) and again.count("skipped: done before") == 4


def test_dask_run_prints_the_dashboard_or_why_and_logs_each_line_once(
    tmp_path: Path, videos: Path, scheduler: str
) -> None:
    out = tmp_path / "run"
    args = ["run", str(_workflow(tmp_path)), "--input", str(videos), "--out", str(out)]
    result = CliRunner().invoke(app, [*args, "--scheduler", scheduler])
    assert result.exit_code == 0, result.output
    if HAS_BOKEH:
        assert re.search(r"Dask dashboard: http://\S+:\d+/status", result.output), result.output
    else:
        assert "the Dask dashboard is off: bokeh is not installed" in result.output
    # Not a terminal: plain progress lines with the step's clip count.
    assert re.search(
        r"\[\d/4\] captions\[\d\]: 1 rows, 0 rejected \(.*s\); captions \d/2 clips", result.output
    )
    assert "captions 2/2 clips" in result.output, result.output
    text = log_path(out).read_text()
    for cid in _clip_ids(out, "captions"):  # in-process workers log once, not also forwarded
        assert text.count(f"clip={cid} done") == 1, text
    assert text.count("step=captions stage=caption") == 2 * 2 + 2  # start, end and 2 clips


@pytest.mark.slow
def test_worker_processes_forward_their_log_records(tmp_path: Path, videos: Path) -> None:
    out = tmp_path / "run"
    wf = load_workflow(_workflow(tmp_path))
    recorder = Recorder()
    run_workflow(wf, out, source=str(videos), n_workers=1, gpu_workers=0, observer=recorder)
    text = log_path(out).read_text()
    made = _clip_ids(out, "captions")
    for cid in made:
        (line,) = [
            ln for ln in text.splitlines() if "stage=caption" in ln and f"clip={cid} done" in ln
        ]
        assert " [tcp://" in line  # forwarded from the worker process, tagged with its address
    (dash,) = [c for c in recorder.calls if c[0] == "dashboard"]
    if HAS_BOKEH:
        assert dash[1].startswith("http://") and dash[2] == ""
    else:
        assert dash[1] == "" and "bokeh is not installed" in dash[2]
    # Per-clip progress events came back from the worker process.
    clips = [c for c in recorder.calls if c[0] == "clip" and c[1] == "captions"]
    assert sorted(c[3] for c in clips if c[4] != TASK_STARTED) == sorted(made)


def _tasks(tmp_path: Path) -> list[ShardTask]:
    """Two ingest shards (2 and 1 units) and the two caption shards that read them."""
    tasks = []
    for i, units in enumerate([("u0", "u1"), ("u2",)]):
        out = tmp_path / "ingest" / f"shard-{i:05d}.parquet"
        common = {"params": {}, "shard_index": i, "shard_count": 2}
        tasks.append(ShardTask("ingest", "ingest", output=out, rejects=out, units=units, **common))
    for i in range(2):
        src = tmp_path / "ingest" / f"shard-{i:05d}.parquet"
        out = tmp_path / "captions" / f"shard-{i:05d}.parquet"
        common = {"params": {}, "shard_index": i, "shard_count": 2}
        tasks.append(
            ShardTask(
                "captions", "caption", output=out, rejects=out, inputs={"clips": src}, **common
            )
        )
    return tasks


def test_progress_counts_clips_and_learns_totals_from_upstream(tmp_path: Path) -> None:
    stream = io.StringIO()
    observer = ConsoleObserver(stream=stream, live=False)
    tasks = _tasks(tmp_path)
    observer.run_started("wf", tasks)
    ingest, captions = observer.steps["ingest"], observer.steps["captions"]
    assert (ingest.total, captions.total) == (3, None)  # captions: not known before ingest ran
    observer.dashboard("", "the Dask dashboard is off: bokeh is not installed")
    observer.clip_settled("ingest", 0, "u0", CLIP_DONE)
    observer.clip_settled("ingest", 0, "u1", CLIP_REJECTED)
    assert (ingest.done, ingest.rejected) == (2, 1)
    observer.task_finished(ShardResult("ingest", 0, str(tasks[0].output), 1, 1, False, 0.5))
    assert captions.total is None  # one of the two caption shards knows its input size
    observer.clip_settled("ingest", 1, "u2", CLIP_DONE)
    observer.task_finished(ShardResult("ingest", 1, str(tasks[1].output), 3, 0, False, 0.5))
    assert captions.total == 1 + 3  # rows the ingest shards wrote
    observer.clip_settled("captions", 1, "", TASK_STARTED)  # sets the clock, counts no clip
    assert captions.done == 0 and captions.start is not None
    observer.clip_settled("captions", 1, "c0", CLIP_DONE)
    assert captions.done == 1 and captions.rate(captions.start + 2.0) == pytest.approx(0.5)
    assert captions.eta(captions.start + 2.0) == pytest.approx(6.0)  # 3 left at 0.5 clip/s
    # A skipped shard settles nothing this run: its rows count as done.
    observer.task_finished(ShardResult("captions", 0, str(tasks[2].output), 1, 0, True, 0.0))
    observer.task_finished(ShardResult("captions", 1, str(tasks[3].output), 3, 0, False, 1.0))
    assert captions.done == captions.total == 4
    observer.run_finished()
    lines = stream.getvalue().splitlines()
    assert lines[0] == "wf: 4 shard task(s) in 2 step(s)"
    assert lines[1] == "the Dask dashboard is off: bokeh is not installed"
    assert lines[2].startswith("[1/4] ingest[0]: 1 rows, 1 rejected (0.5 s); ingest 2/3 clips")
    assert lines[4].startswith("[3/4] captions[0]: 1 rows, 0 rejected (skipped); captions 2/4")
    assert lines[5].startswith("[4/4] captions[1]: 3 rows, 0 rejected (1.0 s); captions 4/4")


def test_live_display_draws_a_bar_per_step(tmp_path: Path) -> None:
    stream = io.StringIO()
    observer = ConsoleObserver(stream=stream, live=True)
    tasks = _tasks(tmp_path)
    observer.run_started("wf", tasks)
    observer.dashboard("http://127.0.0.1:8787/status", "")
    for i, unit in enumerate(["u0", "u1"]):
        observer.clip_settled("ingest", 0, unit, CLIP_DONE if i else CLIP_REJECTED)
    observer.task_finished(ShardResult("ingest", 0, str(tasks[0].output), 1, 1, False, 0.5))
    observer.run_finished()
    text = stream.getvalue()
    assert "Dask dashboard: http://127.0.0.1:8787/status" in text
    assert re.search(r"ingest\s.*2/3 clips", text) and "captions" in text, text
    assert ConsoleObserver(stream=io.StringIO()).live is False  # not a terminal: plain lines


def test_progress_knows_the_size_of_an_input_shard_at_a_url() -> None:
    # A workflow input given as an fsspec URL is sized through pipeline.storage, as it is read.
    from egosim.pipeline.clip_io import write_clips
    from tests.conftest import make_clip

    src = "memory://egosim-observe-test/clips/shard-00000.parquet"
    write_clips(src, [make_clip("c0"), make_clip("c1", seed=1)])
    out = Path("unused") / "captions" / "shard-00000.parquet"
    task = ShardTask(
        "captions", "caption", {}, 0, 1, output=out, rejects=out, inputs={"clips": src}
    )
    observer = ConsoleObserver(stream=io.StringIO(), live=False)
    observer.run_started("wf", [task])
    assert observer.steps["captions"].total == 2
