"""Watching a run: the run log file, the live progress display and the Dask dashboard.

- :func:`run_log` sends every ``egosim.*`` logger (each module logs through
  ``logging.getLogger(__name__)``) to ``RUN/logs/run.log`` for the length of a run, one line per
  record with the time, level, module and, for records that Dask workers forwarded, the
  worker's address. A worker in another process sends the records of the task it runs as Dask
  events (:func:`forward_logs`, :func:`handle_forwarded`); a worker in the client's own process
  logs straight to the file.
- A :class:`RunObserver` hears what a run does (tasks planned, the dashboard's address, each
  clip settled, each task finished). :class:`ConsoleObserver` draws one live progress bar per
  step (clips done / total, clips per second, ETA) with rich when its stream is a terminal, and
  writes plain lines otherwise (logs, CI).
- :func:`dashboard_unavailable` says why Dask's dashboard cannot start (bokeh missing).

Nothing here prints to stdout: the live display and plain lines go to the observer's stream
(stderr by default), so stdout keeps only the command's result (the summary table).
"""

from __future__ import annotations

import contextlib
import importlib.util
import logging
import sys
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any, TextIO

from egosim.pipeline import storage
from egosim.pipeline.execute import (
    CLIP_DONE,
    CLIP_REJECTED,
    TASK_STARTED,
    ShardResult,
    ShardTask,
    primary_role,
)
from egosim.pipeline.storage import Location

log = logging.getLogger(__name__)

LOGGER = "egosim"  # the package logger every module's logger is a child of
LOG_DIR = "logs"  # folder of a run's log files, under the run folder
LOG_FILE = "run.log"  # the run log, RUN/logs/run.log (appended to by every run of the folder)
LOG_FORMAT = "%(asctime)s %(levelname)-7s %(name)s%(worker_tag)s: %(message)s"
PROGRESS_TOPIC = "egosim-progress"  # Dask event topic of per-clip progress from workers
LOG_TOPIC = "egosim-log"  # Dask event topic of log records forwarded from workers
DASHBOARD_PACKAGE = "bokeh"  # Dask's dashboard needs it importable on the scheduler


def log_path(out: Path) -> Path:
    """Where the run log of run folder ``out`` lives."""
    return Path(out) / LOG_DIR / LOG_FILE


class _WorkerTag(logging.Filter):
    """Give every record a ``worker_tag`` (`` [worker]`` for forwarded records, else '')."""

    def filter(self, record: logging.LogRecord) -> bool:
        worker = getattr(record, "worker", None)
        record.worker_tag = f" [{worker}]" if worker else ""
        return True


class _ForwardHandler(logging.Handler):
    """Sends the records of one thread (the task's) through ``send`` as plain data."""

    def __init__(self, send: Callable[[dict[str, Any]], None]) -> None:
        super().__init__(logging.INFO)
        self.send = send  # posts one record's attributes (a Dask event, which adds `worker`)
        self.thread = threading.get_ident()  # only this thread's records are the task's

    def emit(self, record: logging.LogRecord) -> None:
        if record.thread != self.thread:
            return
        try:
            attrs = dict(record.__dict__)
            attrs["msg"] = record.getMessage()  # args may not survive the trip
            attrs["args"] = None
            if record.exc_info and not record.exc_text:
                attrs["exc_text"] = logging.Formatter().formatException(record.exc_info)
            attrs["exc_info"] = None
            attrs.pop("message", None)
            self.send(attrs)
        except Exception:  # a log line must never break the task
            self.handleError(record)


@contextlib.contextmanager
def forward_logs(send: Callable[[dict[str, Any]], None]) -> Iterator[None]:
    """Forward the ``egosim`` records this thread emits in the block through ``send``.

    Used on a Dask worker around one task; the client passes what arrives to
    :func:`handle_forwarded`. Lowers the ``egosim`` logger to INFO when it is above.
    """
    logger = logging.getLogger(LOGGER)
    if logger.getEffectiveLevel() > logging.INFO:
        logger.setLevel(logging.INFO)
    handler = _ForwardHandler(send)
    logger.addHandler(handler)
    try:
        yield
    finally:
        logger.removeHandler(handler)


def handle_forwarded(attrs: dict[str, Any]) -> None:
    """Log a record that :func:`forward_logs` sent, through the logger it was made by."""
    record = logging.makeLogRecord(attrs)
    if record.name == LOGGER or record.name.startswith(LOGGER + "."):
        logging.getLogger(record.name).handle(record)


@contextlib.contextmanager
def run_log(out: Path, level: int = logging.INFO) -> Iterator[logging.FileHandler]:
    """Append the ``egosim`` loggers' records to ``RUN/logs/run.log`` for the ``with`` block.

    Lowers the ``egosim`` logger's level to ``level`` for the block (restored after).
    """
    path = log_path(out)
    path.parent.mkdir(parents=True, exist_ok=True)
    handler = logging.FileHandler(path, encoding="utf-8")
    handler.setFormatter(logging.Formatter(LOG_FORMAT))
    handler.addFilter(_WorkerTag())
    logger = logging.getLogger(LOGGER)
    old_level = logger.level
    logger.addHandler(handler)
    if logger.getEffectiveLevel() > level:
        logger.setLevel(level)
    try:
        yield handler
    finally:
        logger.removeHandler(handler)
        logger.setLevel(old_level)
        handler.close()


def dashboard_unavailable() -> str:
    """Why Dask's dashboard cannot start here ('' when it can)."""
    if importlib.util.find_spec(DASHBOARD_PACKAGE) is None:
        return (
            f"the Dask dashboard is off: {DASHBOARD_PACKAGE} is not installed "
            f"(pip install '{DASHBOARD_PACKAGE}>=3.1' to turn it on)"
        )
    return ""


class RunObserver:
    """What a run tells the outside world while it goes; every method does nothing here.

    The runner calls :meth:`run_started` once, :meth:`dashboard` once it knows the cluster,
    :meth:`clip_settled` per clip (from any thread), :meth:`task_finished` per task and
    :meth:`run_finished` at the end.
    """

    def run_started(self, name: str, tasks: Sequence[ShardTask]) -> None:
        """The run planned ``tasks`` (dependency order) for workflow ``name``."""

    def dashboard(self, link: str, reason: str) -> None:
        """The dashboard's address (``link``), or ``reason`` why there is none."""

    def clip_settled(self, step: str, shard_index: int, clip_id: str, outcome: str) -> None:
        """One clip (a unit, for a source step) of a task was written, rejected or unmatched."""

    def task_finished(self, result: ShardResult) -> None:
        """One task finished (or was skipped as done)."""

    def run_finished(self) -> None:
        """The run ended (successfully or not); the display can stop."""


class StepProgress:
    """Clips done / total of one step, fed by settled clips and finished tasks.

    A step's total is known once every one of its shards knows how many clips it is given: a
    source shard its units, a clip shard the rows of its primary input shard (known when the
    upstream task finishes). Until then :attr:`total` is None.
    """

    def __init__(self, step: str, tasks: Sequence[ShardTask]) -> None:
        self.step = step  # workflow step name
        self.given: dict[int, int | None] = {}  # shard index -> clips it is given (None: unknown)
        self.settled: dict[int, int] = {}  # shard index -> clips settled so far
        self.rejected = 0  # clips rejected so far
        self.start: float | None = None  # when the step's first task started computing
        for task in tasks:
            self.given[task.shard_index] = len(task.units) if primary_role(task) is None else None
            self.settled[task.shard_index] = 0

    @property
    def total(self) -> int | None:
        """Clips the step is given over all shards, None while some shard's count is unknown."""
        counts = list(self.given.values())
        return None if any(c is None for c in counts) else sum(counts)  # type: ignore[arg-type]

    @property
    def done(self) -> int:
        """Clips settled (written, rejected or unmatched)."""
        return sum(self.settled.values())

    def rate(self, now: float) -> float | None:
        """Clips per second since the step's first task started (None before a clip settled)."""
        if self.start is None or now <= self.start or self.done < 1:
            return None
        return self.done / (now - self.start)

    def eta(self, now: float) -> float | None:
        """Seconds left at the current rate (None when the total or the rate is unknown)."""
        rate, total = self.rate(now), self.total
        if rate is None or total is None or rate <= 0:
            return None
        return max(0.0, (total - self.done) / rate)


def _num_rows(loc: Location) -> int | None:
    """Rows of the shard at ``loc`` (a path or an fsspec URL) from its footer, None when it
    cannot be read."""
    import pyarrow.parquet as pq

    try:
        with storage.open_read(loc) as f:
            return int(pq.ParquetFile(f).metadata.num_rows)
    except (OSError, ValueError):
        return None


class ConsoleObserver(RunObserver):
    """Live progress per step on a terminal (rich), plain lines on anything else.

    ``stream`` defaults to stderr; ``live`` forces the rich display on or off (default: on
    when the stream is a terminal).
    """

    def __init__(self, stream: TextIO | None = None, live: bool | None = None) -> None:
        self.stream = stream if stream is not None else sys.stderr  # where lines go
        self.live = self.stream.isatty() if live is None else live  # rich display or lines
        self.steps: dict[str, StepProgress] = {}  # step name -> its progress
        self.readers: dict[str, list[tuple[str, int]]] = {}  # output path -> (step, shard)
        self.tasks_total = 0  # tasks planned
        self.tasks_done = 0  # tasks finished
        self._lock = threading.Lock()  # clip events arrive on Dask's client thread
        self._progress = None  # rich Progress while live
        self._bars: dict[str, int] = {}  # step -> rich task id

    def run_started(self, name: str, tasks: Sequence[ShardTask]) -> None:
        """Set up one progress line per step."""
        by_step: dict[str, list[ShardTask]] = {}
        made = {str(t.output) for t in tasks}
        given: list[tuple[str, int, Location]] = []  # (step, shard, input) a workflow input
        for task in tasks:
            by_step.setdefault(task.step, []).append(task)
            role = primary_role(task)
            if role is not None:
                path = str(task.inputs[role])
                self.readers.setdefault(path, []).append((task.step, task.shard_index))
                if path not in made:
                    given.append((task.step, task.shard_index, task.inputs[role]))
        self.steps = {step: StepProgress(step, ts) for step, ts in by_step.items()}
        for step, shard, loc in given:  # shards given to the run: their sizes are known now
            self.steps[step].given[shard] = _num_rows(loc)
        self.tasks_total = len(tasks)
        if self.live:
            self._start_live(name)
        else:
            self._line(f"{name}: {len(tasks)} shard task(s) in {len(by_step)} step(s)")

    def dashboard(self, link: str, reason: str) -> None:
        """Say where the dashboard is, or why it is off."""
        self._line(f"Dask dashboard: {link}" if link else reason)

    def clip_settled(self, step: str, shard_index: int, clip_id: str, outcome: str) -> None:
        """Count one clip of ``step`` (or note that one of its tasks started)."""
        with self._lock:
            progress = self.steps.get(step)
            if progress is None:
                return
            if progress.start is None:
                progress.start = time.monotonic()
            if outcome == TASK_STARTED:
                return
            progress.settled[shard_index] = progress.settled.get(shard_index, 0) + 1
            progress.rejected += outcome == CLIP_REJECTED
            self._refresh(step)

    def task_finished(self, result: ShardResult) -> None:
        """Close the shard's count and give downstream shards their totals."""
        with self._lock:
            self.tasks_done += 1
            progress = self.steps.get(result.step)
            if progress is not None:
                given = progress.given.get(result.shard_index)
                if result.skipped or given is None:
                    # A skipped shard settles nothing this run: count what it holds as done.
                    progress.given[result.shard_index] = max(
                        progress.settled[result.shard_index], result.rows + result.rejected
                    )
                progress.settled[result.shard_index] = progress.given[result.shard_index] or 0
                if progress.start is None:
                    progress.start = time.monotonic()
            for step, shard in self.readers.get(result.output, []):
                self.steps[step].given[shard] = result.rows
                self._refresh(step)
            self._refresh(result.step)
            if not self.live:
                self._plain_task_line(result)

    def run_finished(self) -> None:
        """Stop the live display."""
        if self._progress is not None:
            self._progress.stop()
            self._progress = None

    # -- drawing -------------------------------------------------------------------------

    def _line(self, text: str) -> None:
        if self._progress is not None:
            self._progress.console.print(text, markup=False, highlight=False)
        else:
            self.stream.write(text + "\n")
            self.stream.flush()

    def _start_live(self, name: str) -> None:
        from rich.console import Console
        from rich.progress import (
            BarColumn,
            MofNCompleteColumn,
            Progress,
            TextColumn,
            TimeElapsedColumn,
            TimeRemainingColumn,
        )

        self._progress = Progress(
            TextColumn("{task.description:<14}"),
            BarColumn(),
            MofNCompleteColumn(),
            TextColumn("clips"),
            TextColumn("{task.fields[rate]}"),
            TextColumn("ETA"),
            TimeRemainingColumn(),
            TimeElapsedColumn(),
            console=Console(file=self.stream),
            redirect_stdout=False,
            redirect_stderr=False,
        )
        self._progress.start()
        self._progress.console.print(f"{name}: {self.tasks_total} shard task(s)", markup=False)
        for step, progress in self.steps.items():
            self._bars[step] = self._progress.add_task(
                step, total=progress.total, rate="", start=True
            )

    def _refresh(self, step: str) -> None:
        if self._progress is None or step not in self._bars:
            return
        progress = self.steps[step]
        rate = progress.rate(time.monotonic())
        self._progress.update(
            self._bars[step],
            completed=progress.done,
            total=progress.total,
            rate=f"{rate:.2f}/s" if rate is not None else "",
        )

    def _plain_task_line(self, result: ShardResult) -> None:
        progress = self.steps.get(result.step)
        state = "skipped" if result.skipped else f"{result.seconds:.1f} s"
        text = (
            f"[{self.tasks_done}/{self.tasks_total}] {result.step}[{result.shard_index}]: "
            f"{result.rows} rows, {result.rejected} rejected ({state})"
        )
        if progress is not None:
            now = time.monotonic()
            total = progress.total
            rate, eta = progress.rate(now), progress.eta(now)
            text += f"; {result.step} {progress.done}/{total if total is not None else '?'} clips"
            if rate is not None:
                text += f", {rate:.2f} clips/s"
            if eta is not None:
                text += f", ETA {eta:.0f} s"
        self._line(text)


__all__ = [
    "CLIP_DONE",
    "ConsoleObserver",
    "RunObserver",
    "StepProgress",
    "dashboard_unavailable",
    "forward_logs",
    "handle_forwarded",
    "log_path",
    "run_log",
]
