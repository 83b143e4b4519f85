"""The caption stage: source text when present, the template otherwise."""

from __future__ import annotations

from pathlib import Path

from egosim.pipeline.clip_io import write_clips
from egosim.pipeline.execute import ShardTask, run_shard_task
from egosim.pipeline.shards import ShardReader
from egosim.schemas.captions import CAPTIONS
from tests.conftest import make_clip


def test_caption_uses_source_text_then_template(tmp_path: Path) -> None:
    with_text = make_clip("a")
    without = make_clip("b")
    without.text = None
    write_clips(tmp_path / "clips.parquet", [with_text, without])
    task = ShardTask(
        step="caption",
        stage="caption",
        params={"prefix": "egocentric:"},
        shard_index=0,
        shard_count=1,
        output=tmp_path / "captions.parquet",
        rejects=tmp_path / "rejects.parquet",
        inputs={"clips": tmp_path / "clips.parquet"},
    )
    result = run_shard_task(task)
    assert result.rows == 2 and result.rejected == 0
    with ShardReader(tmp_path / "captions.parquet", CAPTIONS) as reader:
        rows = list(reader.iter_rows())
    assert rows[0] == {
        "clip_id": "a",
        "text": "egocentric: a hand picks up a box",
        "origin": "source",
    }
    assert rows[1]["origin"] == "template" and rows[1]["text"].startswith("egocentric: A first")
