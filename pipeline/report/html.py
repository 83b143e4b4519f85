"""Write the static HTML report of a run folder (``egosim report RUN --out DIR``).

The report is one ``index.html`` a browser opens from disk (no server), ``plotly.min.js``
beside it (written once, so the page works offline) and ``clips/<clip id>.jpg`` and ``.mp4``
(a contact sheet and a side-by-side video per clip). Its sections, each an element with a
fixed id that tests look for (:data:`SECTIONS`):

- ``run``: workflow, input and the run's verdict;
- ``steps``: per step clips in / out, rejected, unmatched and seconds, as a table and a chart;
- ``rejects``: per step, rejects grouped by reason (clip ids, paths and numbers taken out, as
  in the run summary), with every clip id of each group;
- ``clips``: per clip its sheet and video, or why it has none (the step that rejected it);
- ``quality``: a histogram per quality figure the stages record (:mod:`.quality`), with
  count, mean, median, min and max;
- ``evaluation``: the evaluation table, when the caller gives one.

Every text that comes from data is HTML-escaped; every file name built from a clip id is
checked to stay under the output folder.
"""

from __future__ import annotations

import html
import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from egosim.pipeline.media import MediaError
from egosim.pipeline.report import sheets
from egosim.pipeline.report.quality import FIGURES, FigureValues, QualityFigure, collect
from egosim.pipeline.report.run_data import RunData, load_run
from egosim.pipeline.summary import group_reasons, reason_key
from egosim.schemas.ids import id_problems, path_under

log = logging.getLogger(__name__)

INDEX = "index.html"  # the page
PLOTLY_JS = "plotly.min.js"  # plotly.js, written beside the page once
CLIPS_DIR = "clips"  # sheets and videos, one of each per clip
SECTIONS = ("run", "steps", "rejects", "clips", "quality", "evaluation")  # section ids, in order
DEFAULT_MAX_CLIPS = 24  # clips that get a sheet and a video (the rest are listed)


@dataclass(frozen=True)
class ReportConfig:
    """What the report shows."""

    max_clips: int = DEFAULT_MAX_CLIPS  # clips with a sheet and a video (in clip id order)
    sheet_times: tuple[int, ...] | None = None  # frames a sheet shows (None: first, mid, last)
    sheet_width: int = 1600  # pixels: sheets wider than this are scaled down
    video_width: int = 1280  # pixels: side-by-side videos wider than this are scaled down
    figures: tuple[QualityFigure, ...] = FIGURES  # the quality figures to plot

    def __post_init__(self) -> None:
        problems = []
        if self.max_clips < 0:
            problems.append(f"max_clips must be >= 0, got {self.max_clips}")
        if self.sheet_width < 64 or self.video_width < 64:
            problems.append(
                f"sheet_width and video_width must be >= 64, got {self.sheet_width}, "
                f"{self.video_width}"
            )
        if self.sheet_times is not None and any(t < 0 for t in self.sheet_times):
            problems.append(f"sheet_times must be >= 0, got {self.sheet_times}")
        if problems:
            raise ValueError("; ".join(problems))


@dataclass(frozen=True)
class ClipEntry:
    """One clip of the clips section."""

    clip_id: str  # the clip (or a rejected source unit)
    sheet: str  # file of its sheet relative to the page ('' when none)
    video: str  # file of its side-by-side video ('' when none)
    note: str  # why there is no sheet, or which step rejected a drawn clip ('' for neither)


def write_report(
    run_dir: Path,
    out_dir: Path,
    config: ReportConfig | None = None,
    evaluation_table: str | None = None,
) -> Path:
    """Write the report of the run folder ``run_dir`` into ``out_dir``; returns the page's path.

    ``evaluation_table`` (plain text, e.g. ``egosim report``'s evaluation table) is shown in
    its own section when given.
    """
    config = config or ReportConfig()
    run = load_run(run_dir)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    _write_plotly_js(out_dir / PLOTLY_JS)
    clips = _write_clips(run, out_dir, config)
    figures = collect(run, config.figures)
    page = _page(run, figures, clips, evaluation_table)
    index = out_dir / INDEX
    tmp = index.with_name(index.name + ".tmp")
    tmp.write_text(page, encoding="utf-8")
    tmp.replace(index)
    log.info("report of %s written to %s (%d clips)", run.root, index, len(clips))
    return index


def _write_plotly_js(path: Path) -> None:
    """plotly.js of the installed plotly, written once (kept when it is already there)."""
    from plotly.offline import get_plotlyjs

    text = get_plotlyjs()
    if path.is_file() and path.stat().st_size == len(text.encode()):
        return
    path.write_text(text, encoding="utf-8")


# -- clips ---------------------------------------------------------------------------------

# Columns each role's row needs for a sheet.
_SHEET_COLUMNS = {
    "clips": ["height", "width", "fps", "video"],
    "hand_mask": ["hand_mask"],
    "keypoints": ["skeleton_video"],
    "inpaint": ["first_frame"],
    "scene_render": ["scene_video", "visible"],
}


def _clip_ids(run: RunData) -> list[str]:
    """Clips the run made (rows of its source steps), then rejected source units."""
    ids: list[str] = []
    for step in run.steps:
        if step.source:
            ids += sorted(run.rows(step.step, []))
    sources = {s.step for s in run.steps if s.source}
    units = sorted({r.clip_id for r in run.rejects if r.step in sources})
    return ids + [u for u in units if u not in ids]


def _write_clips(run: RunData, out_dir: Path, config: ReportConfig) -> list[ClipEntry]:
    steps = {role: run.step_of(stage) for role, stage in sheets.ROLES.items()}
    absent = sorted(sheets.ROLES[r] for r, s in steps.items() if s is None)
    rejects = run.rejects_by_clip()
    folder = out_dir / CLIPS_DIR
    folder.mkdir(exist_ok=True)
    entries = []
    for cid in _clip_ids(run):
        note = ""
        if absent:
            note = f"the workflow has no {', '.join(absent)} step"
        elif id_problems(cid, "clip id"):
            note = _rejected_note(rejects.get(cid, [])) or "not a clip id"
        elif sum(bool(e.sheet) for e in entries) >= config.max_clips:
            note = f"not drawn: the report draws the first {config.max_clips} clips (--max-clips)"
        if note:
            entries.append(ClipEntry(cid, "", "", note))
            continue
        rows = {
            role: run.rows(step.step, _SHEET_COLUMNS[role]).get(cid)  # type: ignore[union-attr]
            for role, step in steps.items()
        }
        missing = [steps[r].step for r, row in rows.items() if row is None]  # type: ignore[union-attr]
        if missing:
            why = _rejected_note(rejects.get(cid, []))
            entries.append(ClipEntry(cid, "", "", why or f"no row in step(s) {missing}"))
            continue
        try:
            views = sheets.decode_views(cid, rows)  # type: ignore[arg-type]
            times = _times(config.sheet_times, len(views.real))
            sheet = sheets.clip_sheet(views, times, config.sheet_width)
            sheet_path = path_under(folder, f"{cid}.jpg")
            video_path = path_under(folder, f"{cid}.mp4")
            sheet_path.write_bytes(sheets.encode_jpeg(sheet))
            video_path.write_bytes(sheets.side_by_side_mp4(views, config.video_width))
        except MediaError as exc:
            log.warning("report: clip=%s has no sheet: %s", cid, exc)
            entries.append(ClipEntry(cid, "", "", f"could not decode: {exc}"))
            continue
        # A clip a later step rejected (e.g. the pack quality gate) keeps its sheet and says so.
        note = _rejected_note(rejects.get(cid, []))
        entries.append(ClipEntry(cid, f"{CLIPS_DIR}/{cid}.jpg", f"{CLIPS_DIR}/{cid}.mp4", note))
    return entries


def _times(asked: Sequence[int] | None, num_frames: int) -> list[int]:
    if asked is None:
        return sheets.sheet_times(num_frames)
    return sorted({min(t, num_frames - 1) for t in asked})


def _rejected_note(rejects: Sequence) -> str:
    if not rejects:
        return ""
    first = rejects[0]
    return f"rejected by step {first.step!r} ({first.stage}): {first.reason}"


# -- page ----------------------------------------------------------------------------------

_CSS = """
body{font-family:system-ui,sans-serif;margin:24px;color:#222;max-width:1500px}
h1{font-size:24px}
h2{font-size:19px;border-bottom:1px solid #ccc;padding-bottom:4px;margin-top:32px}
table{border-collapse:collapse;font-size:13px;margin:8px 0}
th,td{border:1px solid #ddd;padding:3px 8px;text-align:right;vertical-align:top}
th{background:#f3f3f3} td.l,th.l{text-align:left}
.ok{color:#176b2c;font-weight:bold} .bad{color:#a40000;font-weight:bold}
.grid{display:grid;grid-template-columns:repeat(auto-fill,minmax(440px,1fr));gap:12px}
.card{border:1px solid #ddd;padding:6px} .card h3{font-size:14px;margin:2px 0}
.doc{font-size:12px;color:#555} .ids{font-family:monospace;font-size:12px;word-break:break-all}
.clips{display:grid;grid-template-columns:repeat(auto-fill,minmax(640px,1fr));gap:14px}
.clip{border:1px solid #ddd;padding:6px}
.clip h3{font-size:14px;margin:2px 0 6px} .clip img{max-width:100%;display:block}
.clip video{max-width:100%;display:block;margin-top:6px}
pre{background:#f7f7f7;padding:8px;overflow-x:auto;font-size:12px}
"""


def _e(value: object) -> str:
    return html.escape(str(value), quote=True)


def _num(value: float) -> str:
    if isinstance(value, float) and math.isnan(value):
        return "-"
    return f"{value:.4g}" if isinstance(value, float) else str(value)


def _plot(figure: object, div_id: str) -> str:
    """A plotly figure as a div (plotly.js is loaded once by the page)."""
    return figure.to_html(  # type: ignore[attr-defined]
        full_html=False,
        include_plotlyjs=False,
        div_id=div_id,
        config={"displaylogo": False, "displayModeBar": False},
    )


def _run_section(run: RunData) -> str:
    verdict = run.outcome or "unknown"
    cls = "ok" if verdict == "ok" else "bad"
    rows = [
        ("run folder", run.root),
        ("workflow", run.workflow or "-"),
        ("input", run.source if run.source is not None else "built-in source"),
        ("clips made", sum(s.clips_out for s in run.steps if s.source)),
        ("rejects", len(run.rejects)),
    ]
    body = "".join(f"<tr><th class=l>{_e(k)}</th><td class=l>{_e(v)}</td></tr>" for k, v in rows)
    problem = f" — {_e(run.problem)}" if run.problem else ""
    return (
        f'<section id="run"><h2>Run</h2><p>Outcome: <span class={cls}>{_e(verdict)}</span>'
        f"{problem}</p><table>{body}</table></section>"
    )


def _steps_section(run: RunData) -> str:
    import plotly.graph_objects as go

    head = "".join(
        f"<th{' class=l' if i < 2 else ''}>{h}</th>"
        for i, h in enumerate(
            ("step", "stage", "shards", "in", "out", "rejected", "unmatched", "seconds", "skipped")
        )
    )
    body = ""
    for s in run.steps:
        clips_in = f"{s.clips_in} units" if s.source else str(s.clips_in)
        cells = (s.shards, clips_in, s.clips_out, s.rejected, s.unmatched, f"{s.seconds:.1f}")
        body += (
            f"<tr><td class=l>{_e(s.step)}</td><td class=l>{_e(s.stage)}</td>"
            + "".join(f"<td>{_e(c)}</td>" for c in cells)
            + f"<td>{s.skipped_shards}</td></tr>"
        )
    names = [s.step for s in run.steps]
    counts = go.Figure(
        [
            go.Bar(name="in", x=names, y=[s.clips_in for s in run.steps]),
            go.Bar(name="out", x=names, y=[s.clips_out for s in run.steps]),
            go.Bar(name="rejected", x=names, y=[s.rejected for s in run.steps]),
        ]
    )
    counts.update_layout(
        barmode="group", title="clips per step", height=340, margin={"t": 40, "b": 40}
    )
    seconds = go.Figure([go.Bar(x=names, y=[s.seconds for s in run.steps])])
    seconds.update_layout(
        title="seconds per step (last run, summed over shards)",
        height=340,
        margin={"t": 40, "b": 40},
    )
    return (
        '<section id="steps"><h2>Steps</h2>'
        f"<table><tr>{head}</tr>{body}</table>"
        f'<div class="grid"><div class=card>{_plot(counts, "plot-steps-clips")}</div>'
        f"<div class=card>{_plot(seconds, 'plot-steps-seconds')}</div></div></section>"
    )


def _rejects_section(run: RunData) -> str:
    parts = ['<section id="rejects"><h2>Rejects</h2>']
    if not run.rejects:
        parts.append("<p>No clip was rejected.</p>")
    for step in run.steps:
        mine = [r for r in run.rejects if r.step == step.step]
        if not mine:
            continue
        groups = group_reasons([(r.clip_id, r.reason) for r in mine])
        members: dict[str, list[str]] = {}
        for r in mine:
            members.setdefault(reason_key(r.reason, r.clip_id)[0], []).append(r.clip_id)
        parts.append(f"<h3>{_e(step.step)} ({_e(step.stage)}): {len(mine)} rejected</h3>")
        parts.append("<table><tr><th>count</th><th class=l>reason</th><th class=l>clips</th></tr>")
        for g in groups:
            ids = members.get(reason_key(g.example_reason, g.example_clip_id)[0], [])
            parts.append(
                f"<tr><td>{g.count}</td><td class=l>{_e(g.pattern)}</td>"
                f"<td class='l ids'>{'<br>'.join(_e(i) for i in sorted(ids))}</td></tr>"
            )
        parts.append("</table>")
    parts.append("</section>")
    return "".join(parts)


def _quality_section(figures: Sequence[FigureValues]) -> str:
    import plotly.graph_objects as go

    parts = ['<section id="quality"><h2>Quality figures</h2>']
    shown = [f for f in figures if f.values]
    if not shown:
        parts.append("<p>No step of this run records a quality figure.</p>")
    stats_rows = ""
    cards = ""
    for i, fv in enumerate(shown):
        st = fv.stats()
        title = f"{fv.figure.name} — {fv.step}"
        fig = go.Figure([go.Histogram(x=list(fv.values.values()), nbinsx=20)])
        fig.update_layout(
            title=title, height=300, margin={"t": 40, "b": 40}, xaxis_title=fv.figure.name
        )
        fig.update_yaxes(title="clips")
        cards += (
            f"<div class=card>{_plot(fig, f'plot-quality-{i}')}"
            f"<div class=doc>{_e(fv.figure.doc)}</div></div>"
        )
        stats_rows += (
            f"<tr><td class=l>{_e(fv.figure.name)}</td><td class=l>{_e(fv.step)}</td>"
            + "".join(f"<td>{_num(st[k])}</td>" for k in ("count", "mean", "median", "min", "max"))
            + "</tr>"
        )
    if shown:
        head = "".join(f"<th>{h}</th>" for h in ("count", "mean", "median", "min", "max"))
        parts.append(
            f"<table><tr><th class=l>figure</th><th class=l>step</th>{head}</tr>{stats_rows}"
            f"</table><div class=grid>{cards}</div>"
        )
    empty = [f"{f.figure.name} ({f.step})" for f in figures if not f.values]
    if empty:
        parts.append(f"<p class=doc>Recorded by no clip: {_e(', '.join(empty))}.</p>")
    parts.append("</section>")
    return "".join(parts)


def _evaluation_section(table: str | None) -> str:
    if table is None:
        return ""
    return f'<section id="evaluation"><h2>Evaluation</h2><pre>{_e(table)}</pre></section>'


def _clips_section(clips: Sequence[ClipEntry]) -> str:
    parts = [f'<section id="clips"><h2>Clips ({len(clips)})</h2>']
    parts.append(
        "<p class=doc>Sheet: frame 0 | inpainted frame 0, then at a few times real | scene "
        "render | visible | skeleton | hand mask. Video: real | scene render | skeleton | hand "
        "mask.</p><div class=clips>"
    )
    for c in clips:
        parts.append(f'<div class=clip id="clip-{_e(c.clip_id)}"><h3>{_e(c.clip_id)}</h3>')
        if c.sheet:
            parts.append(f'<img src="{_e(c.sheet)}" alt="contact sheet of {_e(c.clip_id)}">')
            parts.append(
                f'<video src="{_e(c.video)}" controls loop muted playsinline preload="metadata">'
                "</video>"
            )
        if c.note:
            parts.append(f"<p class=doc>{_e(c.note)}</p>")
        parts.append("</div>")
    parts.append("</div></section>")
    return "".join(parts)


def _page(
    run: RunData,
    figures: Sequence[FigureValues],
    clips: Sequence[ClipEntry],
    evaluation_table: str | None,
) -> str:
    title = f"egosim report — {run.workflow or run.root.name}"
    return (
        "<!DOCTYPE html><html lang=en><head><meta charset=utf-8>"
        f"<title>{_e(title)}</title><style>{_CSS}</style>"
        f'<script src="{PLOTLY_JS}"></script></head><body>'
        f"<h1>{_e(title)}</h1>"
        + _run_section(run)
        + _steps_section(run)
        + _rejects_section(run)
        + _clips_section(clips)
        + _quality_section(figures)
        + _evaluation_section(evaluation_table)
        + "</body></html>\n"
    )
