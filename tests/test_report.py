"""The HTML dataset report: numbers against the run, sheets and videos, and a headless browser."""

from __future__ import annotations

import asyncio
import io
import json
import re
import shutil
import subprocess
import tempfile
import time
import urllib.request
from pathlib import Path

import av
import cv2
import numpy as np
import pyarrow.parquet as pq
import pytest
from typer.testing import CliRunner

from egosim.pipeline.cli import app
from egosim.pipeline.media import decode_rgb_video
from egosim.pipeline.report import SECTIONS, ReportConfig, write_report
from egosim.pipeline.report.quality import FIGURES, column, mean_of
from egosim.pipeline.report.sheets import ClipViews, clip_sheet, side_by_side, side_by_side_mp4
from egosim.pipeline.runner import IN_PROCESS, run_workflow
from egosim.pipeline.shards import ShardWriter
from egosim.pipeline.workflow import load_workflow
from egosim.schemas import REJECTS
from egosim.schemas.pack import EVALUATION

REPO = Path(__file__).resolve().parents[1]
CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
# A tiny dataset build: two synthetic clips of 5 frames at 64x96, one per shard.
TINY = [
    "ingest.synthetic_count=2",
    "ingest.units_per_shard=1",
    "ingest.height=64",
    "ingest.width=96",
    "ingest.num_frames=5",
    "ingest.min_frames=5",
    "ingest.fps=8",
    "pack.height=32",
    "pack.width=56",
    "pack.num_frames=5",
    "pack.frame_stride=1",
]
H, W, T = 64, 96, 5


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The dataset workflow run on two tiny synthetic clips, in this process (about 10 s)."""
    out = tmp_path_factory.mktemp("report") / "run"
    workflow = load_workflow(REPO / "workflows" / "dataset.yaml", TINY)
    summary = run_workflow(workflow, out, scheduler=IN_PROCESS)
    assert summary.report.outcome == "ok", summary.report.problem
    return out


@pytest.fixture(scope="module")
def report_dir(run_dir: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """``egosim report RUN --out DIR`` of that run."""
    out = tmp_path_factory.mktemp("report") / "html"
    result = CliRunner().invoke(app, ["report", str(run_dir), "--out", str(out)])
    assert result.exit_code == 0, result.output
    assert f"report written: {out / 'index.html'}" in result.output
    return out


def _rows(run: Path, step: str, columns: list[str]) -> dict[str, dict]:
    rows = {}
    for shard in sorted((run / step).glob("shard-*.parquet")):
        for row in pq.read_table(shard, columns=["clip_id", *columns]).to_pylist():
            rows[row["clip_id"]] = row
    return rows


def test_report_numbers_are_the_runs(run_dir: Path, report_dir: Path) -> None:
    page = (report_dir / "index.html").read_text()
    summary = json.loads((run_dir / "summary.json").read_text())
    for step in summary["steps"]:  # one table row per step with its counts and seconds
        clips_in = f"{step['clips_in']} units" if step["source"] else str(step["clips_in"])
        cells = [step["shards"], clips_in, step["clips_out"], step["rejected"], step["unmatched"]]
        row = f"<td class=l>{step['step']}</td><td class=l>{step['stage']}</td>" + "".join(
            f"<td>{c}</td>" for c in [*cells, f"{step['seconds']:.1f}"]
        )
        assert row in page, row
    # The visible-fraction statistics: recomputed here from the scene_render shards.
    visible = _rows(run_dir, "scene_render", ["visible_fraction"])
    means = [float(np.mean(r["visible_fraction"])) for r in visible.values()]
    stats = re.search(
        r"<td class=l>visible fraction</td><td class=l>scene_render</td>"
        r"<td>(\d+)</td><td>([^<]+)</td><td>[^<]+</td><td>([^<]+)</td><td>([^<]+)</td>",
        page,
    )
    assert stats, "no visible-fraction statistics row"
    assert int(stats.group(1)) == len(means) == 2
    assert float(stats.group(2)) == pytest.approx(np.mean(means), rel=1e-3)
    assert float(stats.group(3)) == pytest.approx(min(means), rel=1e-3)
    assert float(stats.group(4)) == pytest.approx(max(means), rel=1e-3)
    # Every figure has a histogram but the SfM error, which the given-poses backend leaves null.
    assert page.count('class="plotly-graph-div"') == 2 + len(FIGURES) - 1
    assert "Recorded by no clip: SfM reprojection error (px) (cameras)." in page
    assert (report_dir / "plotly.min.js").stat().st_size > 1_000_000  # offline: beside the page


def test_report_clip_sheet_and_video_per_clip(run_dir: Path, report_dir: Path) -> None:
    clips = _rows(run_dir, "ingest", ["video"])
    assert len(clips) == 2
    for cid, row in clips.items():
        sheet = cv2.imread(str(report_dir / "clips" / f"{cid}.jpg"))
        assert sheet.shape == ((1 + 3) * H, 5 * W, 3)  # frame 0 row + times 0, 2, 4
        real = decode_rgb_video(row["video"], H, W)
        top_left = cv2.cvtColor(sheet[20:H, :W], cv2.COLOR_BGR2RGB).astype(float)  # below label
        assert np.abs(top_left - real[0, 20:H]).mean() < 6  # JPEG loss only
        data = (report_dir / "clips" / f"{cid}.mp4").read_bytes()
        with av.open(io.BytesIO(data)) as container:
            stream = container.streams.video[0]
            assert stream.codec_context.name == "h264"
            assert stream.codec_context.pix_fmt == "yuv420p"  # what browsers play
            frames = [f.to_ndarray(format="rgb24") for f in container.decode(stream)]
        assert len(frames) == T and frames[0].shape == (H, 4 * W, 3)
        assert np.abs(frames[0][:, :W].astype(float) - real[0]).mean() < 8


def _add_rejects(run: Path, rejects: list[tuple[str, str, str]]) -> None:
    """Append (step, clip id, reason) rejects to ``run/rejects.parquet``."""
    rows = pq.read_table(run / "rejects.parquet").to_pylist()
    stages = {
        s["step"]: s["stage"] for s in json.loads((run / "summary.json").read_text())["steps"]
    }
    with ShardWriter(run / "rejects.parquet", REJECTS, stage="runner") as writer:
        for row in rows:
            writer.write_row(row)
        for step, cid, reason in rejects:
            writer.write_row(
                {
                    "step": step,
                    "stage": stages[step],
                    "shard": "shard-00000.parquet",
                    "clip_id": cid,
                    "reason": reason,
                    "input_fingerprint": "",
                }
            )


def test_rejects_are_grouped_by_reason_with_every_clip_id(run_dir: Path, tmp_path: Path) -> None:
    run = tmp_path / "run"
    shutil.copytree(run_dir, run)
    drawn = sorted(_rows(run_dir, "ingest", []))[0]  # a clip the pack gate turned away
    _add_rejects(
        run,
        [
            ("pack", drawn, "hand valid fraction 0.05 below 0.1"),
            ("pack", "clip-a", "clip-a: visible fraction 0.12 below 0.2"),
            ("pack", "clip-b", "clip-b: visible fraction 0.08 below 0.2"),
            ("pack", "clip-c", "clip-c has no hand in view"),
            ("ingest", "video:/data/x<y>.mp4", "cannot read video file /data/x<y>.mp4"),
        ],
    )
    page = write_report(run, tmp_path / "html").read_text()
    rejects = page.split('<section id="rejects">', 1)[1].split("</section>", 1)[0]
    assert "<h3>pack (pack): 4 rejected</h3>" in rejects
    assert "<td>2</td><td class=l>&lt;clip&gt;: visible fraction N below 0.2</td>" in rejects
    assert "clip-a<br>clip-b</td>" in rejects and "<td>1</td>" in rejects
    assert "<td class=l>&lt;clip&gt; has no hand in view</td>" in rejects
    assert "video:/data/x&lt;y&gt;.mp4" in rejects and "x<y>" not in page  # escaped
    clips = page.split('<section id="clips">', 1)[1].split("</section>", 1)[0]
    card = clips.split(f'<div class=clip id="clip-{drawn}">', 1)[1].split("</div>", 1)[0]
    assert f'<img src="clips/{drawn}.jpg"' in card  # still drawn, and says who rejected it
    assert "rejected by step &#x27;pack&#x27; (pack): hand valid fraction 0.05 below 0.1" in card
    assert "rejected by step &#x27;ingest&#x27; (ingest): cannot read video file" in clips


def test_report_of_a_remote_run_reads_its_local_copy(
    run_dir: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import fsspec

    monkeypatch.setenv("EGOSIM_CACHE", str(tmp_path / "cache"))
    memory = fsspec.filesystem("memory")
    memory.put(str(run_dir), "/report-test-run", recursive=True)
    try:
        out = tmp_path / "html"
        args = ["report", "memory://report-test-run", "--out", str(out)]
        result = CliRunner().invoke(app, args)
        assert result.exit_code == 0, result.output
        page = (out / "index.html").read_text()
        ids = sorted(_rows(run_dir, "ingest", []))
        assert all(f'<div class=clip id="clip-{cid}">' in page for cid in ids)
        assert all((out / "clips" / f"{cid}.mp4").is_file() for cid in ids)
    finally:
        memory.rm("/report-test-run", recursive=True)


def _evaluation_row(cid: str, psnr: float) -> dict:
    return {
        "clip_id": cid,
        "num_frames": T,
        "psnr": psnr,
        "psnr_hand": None,
        "ssim": 0.5,
        "psnr_baseline": 20.0,
        "psnr_hand_baseline": None,
        "ssim_baseline": 0.4,
        "lpips": None,
        "depth_err": None,
        "cam_err": None,
        "camera_backend": "none",
        "hand_fraction": 0.1,
        "note": "",
    }


def test_report_prints_evaluation_tables_and_puts_a_runs_in_its_page(
    run_dir: Path, tmp_path: Path
) -> None:
    run = tmp_path / "run"
    shutil.copytree(run_dir, run)
    (run / "evaluate").mkdir()
    with ShardWriter(run / "evaluate" / "shard-00000.parquet", EVALUATION, stage="evaluate") as w:
        w.write_row(_evaluation_row("clip-e0", 30.0))
        w.write_row(_evaluation_row("clip-e1", 34.0))
    summary = json.loads((run / "summary.json").read_text())
    step = {**summary["steps"][-1], "step": "evaluate", "stage": "evaluate", "final": True}
    summary["steps"].append(step)
    (run / "summary.json").write_text(json.dumps(summary))
    cli = CliRunner()
    printed = cli.invoke(app, ["report", str(run / "evaluate")])  # no --out: the table
    assert printed.exit_code == 0, printed.output
    assert re.search(r"clip-e1\s+34\.0000", printed.output)
    assert re.search(r"overall\s+32\.0000", printed.output)  # mean PSNR
    out = tmp_path / "html"
    result = cli.invoke(app, ["report", str(run), "--out", str(out), "--max-clips", "0"])
    assert result.exit_code == 0, result.output
    page = (out / "index.html").read_text()
    section = page.split('<section id="evaluation">', 1)[1].split("</section>", 1)[0]
    assert re.search(r"overall\s+32\.0000", section) and "clip-e0" in section


def test_evaluation_table_gets_its_section(run_dir: Path, tmp_path: Path) -> None:
    table = "clip_id  psnr\nc0       31.2000\noverall  31.2000"
    page = write_report(run_dir, tmp_path / "html", ReportConfig(max_clips=0), table).read_text()
    assert f'<section id="evaluation"><h2>Evaluation</h2><pre>{table}</pre>' in page
    assert "not drawn: the report draws the first 0 clips" in page
    assert not list((tmp_path / "html" / "clips").iterdir())


def test_report_of_a_folder_that_is_not_a_run_says_so(tmp_path: Path) -> None:
    (tmp_path / "empty").mkdir()
    result = CliRunner().invoke(app, ["report", str(tmp_path / "empty"), "--out", str(tmp_path)])
    assert result.exit_code == 2
    assert "no summary.json" in result.output and str(tmp_path / "empty") in result.output
    with pytest.raises(ValueError, match="max_clips must be >= 0, got -1"):
        ReportConfig(max_clips=-1)


def _views(t: int = 3, h: int = 40, w: int = 48) -> ClipViews:
    """Flat-coloured views, each picture its own colour, so a sheet's cells can be told apart."""

    def video(rgb: tuple[int, int, int]) -> np.ndarray:
        return np.broadcast_to(np.array(rgb, np.uint8), (t, h, w, 3)).copy()

    real = video((200, 200, 200))
    real[:, :, : w // 2] = (40, 80, 120)
    mask = np.zeros((t, h, w), bool)
    mask[:, h // 2 :, w // 2 :] = True  # bottom-right quarter is hand
    return ClipViews(
        clip_id="c0",
        fps=8.0,
        real=real,
        scene=video((10, 200, 30)),
        visible=~mask,
        skeleton=video((250, 0, 250)),
        hand_mask=mask,
        inpainted=video((90, 60, 30))[0],
    )


def test_sheet_layout_against_hand_built_views() -> None:
    views = _views()
    sheet = clip_sheet(views)  # (4 * 40, 5 * 48, 3): frame-0 row, then times 0, 1, 2
    h, w = 40, 48
    assert sheet.shape == (4 * h, 5 * w, 3)

    def cell(row: int, col: int) -> np.ndarray:  # bottom-right pixel, away from the label
        return sheet[row * h + h - 2, col * w + w - 2]

    assert tuple(cell(0, 1)) == (90, 60, 30)  # inpainted frame 0
    assert tuple(cell(0, 2)) == (0, 0, 0)  # blank
    for row in (1, 2, 3):
        assert tuple(cell(row, 0)) == (200, 200, 200)  # real
        assert tuple(cell(row, 1)) == (10, 200, 30)  # scene render
        assert tuple(cell(row, 2)) == (0, 0, 0)  # visible: the hand quarter is not
        assert tuple(sheet[row * h + 2 + 20, 2 * w + 2]) == (255, 255, 255)  # visible elsewhere
        assert tuple(cell(row, 3)) == (250, 0, 250)  # skeleton
        assert tuple(cell(row, 4)) == (227, 100, 100)  # 0.5 * 200 + (127, 0, 0): hand tint
    with pytest.raises(ValueError, match="clip c0: sheet times \\[3\\] outside its 3 frames"):
        clip_sheet(views, times=[0, 3])


def test_side_by_side_video_round_trips() -> None:
    views = _views(t=6)
    frames = side_by_side(views)
    assert frames.shape == (6, 40, 4 * 48, 3)
    assert (frames[:, :, 48:96] == (10, 200, 30)).all()  # scene render second
    decoded = decode_rgb_video(side_by_side_mp4(views))
    assert decoded.shape == frames.shape
    assert np.abs(decoded.astype(float) - frames).mean() < 3  # CRF 23 on flat colours
    wide = side_by_side(views, max_width=101)  # scaled down, sizes kept even
    assert wide.shape[2] % 2 == 0 and wide.shape[1] % 2 == 0 and wide.shape[2] <= 101


def test_quality_values_skip_nulls_and_nans() -> None:
    assert mean_of("v")({"v": [[1.0, float("nan")], [3.0, 2.0]]}) == pytest.approx(2.0)
    assert mean_of("v")({"v": None}) is None and mean_of("v")({"v": [float("nan")]}) is None
    assert mean_of("r")({"r": [True, False, True, True]}) == pytest.approx(0.75)
    assert column("x")({"x": None}) is None and column("x")({"x": float("inf")}) is None
    assert column("x")({"x": 0.25}) == 0.25


# -- headless Chromium through the DevTools protocol ------------------------------------------

PROBE = """JSON.stringify({
  sections: [...document.querySelectorAll('section')].map(s => [s.id, s.offsetHeight]),
  plots: document.querySelectorAll('.js-plotly-plot').length,
  svgs: document.querySelectorAll('.js-plotly-plot .main-svg').length,
  images: [...document.images].map(i => [i.getAttribute('src'), i.complete, i.naturalWidth]),
  videos: [...document.querySelectorAll('video')].map(
    v => [v.getAttribute('src'), v.readyState, v.videoWidth, v.error && v.error.code]),
})"""
COMPLAINTS = ("Runtime.consoleAPICalled", "Runtime.exceptionThrown", "Log.entryAdded")


def open_in_chromium(url: str, timeout: float = 60.0) -> tuple[dict, list[dict]]:
    """Load ``url`` in headless Chromium; returns the page probe and every console complaint.

    Talks the DevTools protocol over a websocket (tornado's client, installed with Dask):
    console messages, uncaught exceptions and log entries (failed loads) are collected from
    the start; the probe runs once the page has loaded and its videos have their metadata.
    """
    from tornado.websocket import websocket_connect

    async def run() -> tuple[dict, list[dict]]:
        profile = tempfile.mkdtemp(prefix="egosim-chromium-")
        args = [CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--mute-audio"]
        args += ["--remote-debugging-port=0", f"--user-data-dir={profile}", "about:blank"]
        proc = subprocess.Popen(args, stderr=subprocess.PIPE, text=True)
        try:
            port, start = None, time.monotonic()
            while port is None and time.monotonic() - start < timeout:
                line = proc.stderr.readline()
                if not line and proc.poll() is not None:
                    raise RuntimeError(f"chromium exited with {proc.returncode}")
                found = re.search(r"DevTools listening on ws://[^:]+:(\d+)/", line)
                port = int(found.group(1)) if found else None
            assert port is not None, "chromium did not open its DevTools port"
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list") as answer:
                pages = [t for t in json.loads(answer.read()) if t["type"] == "page"]
            ws = await websocket_connect(pages[0]["webSocketDebuggerUrl"])
            events: list[dict] = []
            counter = iter(range(1, 1 << 30))

            async def call(method: str, **params: object) -> dict:
                ident = next(counter)
                await ws.write_message(
                    json.dumps({"id": ident, "method": method, "params": params})
                )
                while True:
                    message = json.loads(await asyncio.wait_for(ws.read_message(), timeout))
                    if message.get("id") == ident:
                        return message
                    events.append(message)

            for method in ("Runtime.enable", "Log.enable", "Page.enable"):
                await call(method)
            await call("Page.navigate", url=url)
            while not any(e.get("method") == "Page.loadEventFired" for e in events):
                events.append(json.loads(await asyncio.wait_for(ws.read_message(), timeout)))
            deadline = time.monotonic() + timeout
            while True:
                answer = await call("Runtime.evaluate", expression=PROBE, returnByValue=True)
                state = json.loads(answer["result"]["result"]["value"])
                ready = all(v[1] >= 1 or v[3] for v in state["videos"])
                if ready or time.monotonic() > deadline:
                    break
                await asyncio.sleep(0.2)
            ws.close()
            return state, [e for e in events if e.get("method") in COMPLAINTS]
        finally:
            proc.terminate()
            proc.wait(timeout=30)
            shutil.rmtree(profile, ignore_errors=True)

    return asyncio.run(run())


needs_chromium = pytest.mark.skipif(
    CHROMIUM is None, reason="chromium is not installed (apt-get install chromium; `make setup`)"
)


@needs_chromium
def test_report_loads_in_headless_chromium_without_errors(report_dir: Path) -> None:
    state, complaints = open_in_chromium((report_dir / "index.html").as_uri())
    assert complaints == [], complaints
    shown = dict(state["sections"])
    assert list(shown) == [s for s in SECTIONS if s != "evaluation"]  # no evaluation here
    assert all(height > 0 for height in shown.values()), shown
    assert state["plots"] == 2 + len(FIGURES) - 1 and state["svgs"] >= state["plots"]  # drawn
    assert len(state["images"]) == 2 and all(ok and w > 0 for _, ok, w in state["images"])
    # Both videos decode in the browser (H.264, yuv420p): metadata with the frame width.
    assert [(v[1] >= 1, v[2], v[3]) for v in state["videos"]] == [(True, 4 * W, None)] * 2


@needs_chromium
def test_the_browser_check_sees_console_errors(tmp_path: Path) -> None:
    page = tmp_path / "bad.html"
    page.write_text("<html><body><script>console.error('boom'); missing();</script></body></html>")
    _, complaints = open_in_chromium(page.as_uri())
    methods = sorted(e["method"] for e in complaints)
    assert methods == ["Runtime.consoleAPICalled", "Runtime.exceptionThrown"], complaints
