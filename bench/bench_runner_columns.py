"""What reading only the declared columns saves the executor (issue 12, ``ClipStage.columns``).

:func:`bench_runner_columns` makes one synthetic clip at the default size (480x832, 61 frames,
through the ``ingest`` stage) and, for ``hand_mask`` and ``inpaint``, measures per clip:

- the bytes the executor reads from Parquet for the stage's input rows (Arrow buffers of the
  columns read) with the stage's declaration, against reading every column;
- the seconds of the stage's whole task on that clip (read, decode, process, write) with the
  declaration, against the same task with every column read (``read_columns`` returning None,
  as for a stage without a declaration), both measured in the same run, best of a few repeats.

Run it alone with ``python -m bench.run --only runner_columns`` (about 90 s on 2 cores).
"""

from __future__ import annotations

import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pyarrow.parquet as pq

from egosim.pipeline.execute import ShardTask, run_shard_task
from egosim.pipeline.shards import ShardWriter
from egosim.pipeline.stage import ClipStage, SourceStage, get_stage
from egosim.schemas import CLIPS
from egosim.schemas.hand_mask import HAND_MASK

HEIGHT, WIDTH, FRAMES = 480, 832, 61  # the default clip format
REPEATS = 2  # task timings: best of this many (shared machines are noisy)


def _make_inputs(folder: Path) -> dict[str, Path]:
    """A one-clip ``clips`` shard from the synthetic world and its ground-truth ``hand_mask``."""
    ingest = get_stage("ingest").from_params(
        {"source": "synthetic", "synthetic_count": 1, "synthetic_articulated_every": 0}
    )
    if not isinstance(ingest, SourceStage):
        raise TypeError("ingest is not a source stage")
    (row,) = [r for unit in ingest.list_units(None) for r in ingest.process_unit(unit)]
    if (row["height"], row["width"], row["num_frames"]) != (HEIGHT, WIDTH, FRAMES):
        raise RuntimeError(f"ingest made a {row['height']}x{row['width']} clip, not the default")
    clips = folder / "clips.parquet"
    with ShardWriter(clips, CLIPS, stage="bench") as writer:
        writer.write_row(row)
    masks = folder / "hand_mask.parquet"
    with ShardWriter(masks, HAND_MASK, stage="bench") as writer:
        writer.write_row(
            {
                "clip_id": row["clip_id"],
                "num_frames": FRAMES,
                "width": WIDTH,
                "height": HEIGHT,
                "hand_mask": row["hand_mask"],  # the world's true masks
                "coverage": [0.0] * FRAMES,
                "backend": "keypoints",
            }
        )
    return {"clips": clips, "hand_mask": masks}


def _bytes_read(stage: type[ClipStage], inputs: dict[str, Path], every: bool) -> int:
    """Arrow bytes of the stage's input rows as the executor reads them (or every column)."""
    total = 0
    for role, path in inputs.items():
        columns = None if every else stage.read_columns(role)
        total += pq.ParquetFile(path).read_row_group(0, columns=columns).nbytes
    return total


@contextmanager
def _every_column() -> Iterator[None]:
    """Make every stage read every column, as without declarations."""
    saved = ClipStage.__dict__["read_columns"]
    ClipStage.read_columns = classmethod(lambda cls, role: None)  # type: ignore[method-assign]
    try:
        yield
    finally:
        ClipStage.read_columns = saved  # type: ignore[method-assign]


def _task_seconds(stage: str, inputs: dict[str, Path], out: Path) -> float:
    """Best wall time of the stage's task on the one-clip shard over ``REPEATS`` runs."""
    best = float("inf")
    for k in range(REPEATS):
        task = ShardTask(
            step=stage,
            stage=stage,
            params={},
            shard_index=0,
            shard_count=1,
            output=out / f"{stage}-{k}.parquet",
            rejects=out / f"{stage}-{k}-rejects.parquet",
            inputs=inputs,
            fingerprint=f"bench-{k}",
        )
        start = time.perf_counter()
        result = run_shard_task(task)
        best = min(best, time.perf_counter() - start)
        if (result.rows, result.rejected) != (1, 0):
            raise RuntimeError(f"{stage}: {result.rows} rows, {result.rejected} rejected")
    return best


def _figures(stage: str, inputs: dict[str, Path], folder: Path) -> list[dict]:
    cls = get_stage(stage)
    if not issubclass(cls, ClipStage):
        raise TypeError(f"{stage} is not a clip stage")
    declared_bytes = _bytes_read(cls, inputs, every=False)
    every_bytes = _bytes_read(cls, inputs, every=True)
    (folder / "declared").mkdir(exist_ok=True)
    (folder / "every").mkdir(exist_ok=True)
    declared_s = _task_seconds(stage, inputs, folder / "declared")
    with _every_column():
        every_s = _task_seconds(stage, inputs, folder / "every")
    size = f"{HEIGHT}x{WIDTH}x{FRAMES}"
    return [
        {
            "name": f"{stage}_input_bytes_per_clip_{size}",
            "value": declared_bytes / 1e6,
            "unit": "MB",
            "baseline": "every column read",
            "baseline_value": every_bytes / 1e6,
        },
        {
            "name": f"{stage}_task_seconds_per_clip_{size}",
            "value": declared_s,
            "unit": "s",
            "baseline": "every column read",
            "baseline_value": every_s,
        },
    ]


def bench_runner_columns() -> list[dict]:
    """Input bytes and task seconds per clip of hand_mask and inpaint, declared vs every column."""
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        inputs = _make_inputs(folder)
        figures: list[dict] = []
        for stage, roles in (("hand_mask", {"clips": inputs["clips"]}), ("inpaint", inputs)):
            (folder / stage).mkdir()
            figures += _figures(stage, roles, folder / stage)
        return figures
