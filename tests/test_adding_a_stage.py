"""The "Adding a stage" recipe of docs/design.md, followed to the letter by a trivial stage.

A real stage puts the schema in ``schemas/<name>.py`` (plus one line in ``SCHEMAS``), the stage in
``stages/<name>/stage.py`` and its registry line in ``stages/__init__.py``; here all three live in
this file so that the example stays out of the product. It then runs through the runner like any
stage: in a workflow, on a tiny shard, with a parameter set as ``--set`` would, and by
``egosim stage``.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from pathlib import Path
from typing import Any, ClassVar

import pyarrow as pa
import pytest
from typer.testing import CliRunner

from egosim.pipeline import media
from egosim.pipeline.cli import app
from egosim.pipeline.clip_io import write_clips
from egosim.pipeline.runner import IN_PROCESS, run_workflow
from egosim.pipeline.shards import ShardReader
from egosim.pipeline.stage import (
    ClipRejected,
    ClipStage,
    ConfigError,
    StageConfig,
    register_stage,
    registered_stages,
)
from egosim.pipeline.workflow import parse_workflow
from egosim.schemas import CLIPS, ShardSchema
from egosim.schemas.base import Column
from tests.conftest import make_clip

# 1. The schema: a name, a version, one documented column per value, row validators.


def _check_brightness(row: Mapping[str, Any]) -> list[str]:
    value = row["mean_brightness"]
    return [] if 0 <= value <= 255 else [f"mean_brightness must be in [0, 255], got {value}"]


BRIGHTNESS = ShardSchema(
    name="example_brightness",
    version=1,
    doc="Mean brightness of each clip (the example stage of docs/design.md).",
    columns=(
        Column("clip_id", pa.string(), "Clip id (joins with the clips shard)."),
        Column("num_frames", pa.int32(), "Frames T the mean is taken over."),
        Column("mean_brightness", pa.float64(), "Mean RGB value over every frame, 0..255."),
    ),
    validators=(_check_brightness,),
)


# 2. The stage: a frozen config (every field with a default and a comment, checked in
#    __post_init__), declared inputs and output, one process() per clip.


@dataclasses.dataclass(frozen=True)
class BrightnessConfig(StageConfig):
    """Parameters of ``example_brightness``."""

    min_frames: int = 1  # clips with fewer frames are rejected

    def __post_init__(self) -> None:
        if self.min_frames < 1:
            raise ConfigError(f"min_frames must be >= 1, got {self.min_frames}")


class BrightnessStage(ClipStage):
    """Mean brightness per clip."""

    name = "example_brightness"
    description = "mean brightness per clip (docs/design.md example)"
    config_class = BrightnessConfig
    inputs: ClassVar[Mapping[str, ShardSchema]] = {"clips": CLIPS}
    output = BRIGHTNESS
    config: BrightnessConfig

    def process(self, rows: Mapping[str, Mapping[str, Any]]) -> dict[str, Any]:
        """One output row for the clip; a short clip is rejected with the reason."""
        clip = rows["clips"]
        if clip["num_frames"] < self.config.min_frames:
            raise ClipRejected(
                f"clip has {clip['num_frames']} frames, min_frames is {self.config.min_frames}"
            )
        video = media.decode_rgb_video(clip["video"], clip["height"], clip["width"])
        return {
            "clip_id": clip["clip_id"],
            "num_frames": clip["num_frames"],
            "mean_brightness": float(video.mean()),
        }


# 3. The registry line (in stages/__init__.py for a real stage; guarded here because test
#    modules can be imported twice).
if BrightnessStage.name not in registered_stages():
    register_stage(BrightnessStage)


# 4. Its tests: the config refuses bad values, and the stage runs through the runner.


@pytest.fixture
def tiny_shard(tmp_path: Path) -> Path:
    path = tmp_path / "clips.parquet"
    clips = [make_clip("long", num_frames=6), make_clip("short", num_frames=2, seed=1)]
    write_clips(path, clips, stage="test")
    return path


def test_example_stage_config_is_checked() -> None:
    with pytest.raises(ConfigError, match="min_frames must be >= 1, got 0"):
        BrightnessStage.from_params({"min_frames": "0"})
    with pytest.raises(ConfigError, match="expected an integer, got 'many'"):
        BrightnessStage.from_params({"min_frames": "many"})


def test_example_stage_runs_through_the_runner(tiny_shard: Path, tmp_path: Path) -> None:
    workflow = parse_workflow(
        {
            "name": "example",
            "inputs": {"clips": "clips"},
            "steps": {"brightness": {"stage": "example_brightness", "inputs": "clips"}},
        },
        overrides=["brightness.min_frames=3"],
    )
    out = tmp_path / "run"
    summary = run_workflow(workflow, out, scheduler=IN_PROCESS, inputs={"clips": [tiny_shard]})
    (result,) = summary.results
    assert (result.rows, result.rejected) == (1, 1)
    with ShardReader(out / "brightness" / "shard-00000.parquet", BRIGHTNESS) as reader:
        (row,) = list(reader.iter_rows())
        assert reader.meta.params == {"min_frames": 3}
    assert row["clip_id"] == "long" and 0 < row["mean_brightness"] < 255
    (step,) = summary.report.steps
    assert (step.clips_in, step.clips_out, step.rejected) == (2, 1, 1)
    assert step.reasons[0].example_clip_id == "short"
    assert "min_frames is 3" in step.reasons[0].example_reason

    # The same stage by `egosim stage`: one shard, the same fingerprint as the one-step run.
    single = tmp_path / "single.parquet"
    result = CliRunner().invoke(
        app,
        [
            *("stage", "example_brightness", "--input", str(tiny_shard)),
            *("--output", str(single), "--set", "min_frames=3"),
        ],
    )
    assert result.exit_code == 0, result.output
    with (
        ShardReader(single, BRIGHTNESS) as a,
        ShardReader(out / "brightness" / "shard-00000.parquet", BRIGHTNESS) as b,
    ):
        assert a.meta.fingerprint == b.meta.fingerprint
        assert list(a.iter_rows()) == list(b.iter_rows())
