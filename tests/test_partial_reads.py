"""Reads of a few columns are verified by per-column content hashes (content format 2, issue 12).

A shard whose bytes in one column were changed with intact Parquet pages (page checksums
recomputed, the stored hashes kept) is refused when only that column is read, by the reader
and by the executor; the other columns still read. Format-1 shards (row hashes only) stay
readable and `egosim check` still verifies them whole.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any, ClassVar

import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from egosim.pipeline.check import check_shard
from egosim.pipeline.clip_io import write_clips
from egosim.pipeline.execute import run_shard_task
from egosim.pipeline.shards import (
    CONTENT_FORMAT,
    CONTENT_KEY,
    ContentMismatchError,
    ShardReader,
    row_content_hash,
)
from egosim.pipeline.stage import ClipStage, register_stage, registered_stages
from egosim.schemas import CLIPS, ShardSchema
from egosim.schemas.captions import CAPTIONS
from tests.conftest import make_clip, one_shard_task


class _VideoLengthStage(ClipStage):
    """Declares only the clip's video; writes its byte length as the caption."""

    name = "test_partial_reads_video"
    description = "reads only video (tests/test_partial_reads.py)"
    inputs: ClassVar[Mapping[str, ShardSchema]] = {"clips": CLIPS}
    output = CAPTIONS
    columns: ClassVar[Mapping[str, tuple[str, ...]]] = {"clips": ("video",)}

    def process(self, rows: Mapping[str, Mapping[str, Any]]) -> dict[str, Any]:
        """The video's size in bytes as text."""
        clip = rows["clips"]
        return {"clip_id": clip["clip_id"], "text": str(len(clip["video"])), "origin": "x"}


if _VideoLengthStage.name not in registered_stages():  # test modules may be imported twice
    register_stage(_VideoLengthStage)


def _shard(path: Path) -> Path:
    write_clips(path, [make_clip("a", num_frames=3), make_clip("b", num_frames=3, seed=1)], "t")
    return path


def _rewrite(path: Path, column: str, row: int, content: bytes | None = None) -> None:
    """Flip one byte of ``column`` in ``row``, rewriting pages (checksums intact) and keeping
    the stored content hashes (or storing ``content`` instead)."""
    footer = pq.ParquetFile(path).metadata.metadata
    table = pq.read_table(path)
    values = table.column(column).to_pylist()
    data = bytearray(values[row])
    data[len(data) // 2] ^= 0x01
    values[row] = bytes(data)
    index = table.schema.get_field_index(column)
    table = table.set_column(index, table.schema.field(index), pa.array(values, pa.binary()))
    meta = {**table.schema.metadata, CONTENT_KEY: content or footer[CONTENT_KEY]}
    pq.write_table(
        table.replace_schema_metadata(meta), path, row_group_size=1, write_page_checksum=True
    )


def test_a_flipped_byte_in_a_declared_column_is_refused_when_only_it_is_read(
    tmp_path: Path,
) -> None:
    path = _shard(tmp_path / "clips.parquet")
    _rewrite(path, "video", 1)
    with ShardReader(path, CLIPS) as reader:
        assert reader.content_format == CONTENT_FORMAT == 2 and reader.columns_hashed
        assert [r["clip_id"] for r in reader.iter_rows(["clip_id", "fps"])] == ["a", "b"]
        rows = reader.iter_rows(["clip_id", "video"])
        assert next(rows)["clip_id"] == "a"  # row 0 is intact
        with pytest.raises(ContentMismatchError, match=r"row 1 \(clip 'b'\).*\['video'\]"):
            next(rows)
        with pytest.raises(ContentMismatchError, match=r"\['video'\]"):
            reader.read_row_group(1, ["clip_id", "video"])
        with pytest.raises(ContentMismatchError, match=r"row 1"):
            list(reader.iter_rows())  # the whole row too


def test_the_executor_refuses_a_damaged_declared_column(tmp_path: Path) -> None:
    clips = _shard(tmp_path / "clips.parquet")
    task = one_shard_task("test_partial_reads_video", tmp_path / "ok", {"clips": clips})
    assert run_shard_task(task).rows == 2
    _rewrite(clips, "video", 0)
    task = one_shard_task("test_partial_reads_video", tmp_path / "bad", {"clips": clips})
    with pytest.raises(ContentMismatchError, match=r"clip 'a'.*\['video'\]"):
        run_shard_task(task)
    assert not (tmp_path / "bad" / "test_partial_reads_video.parquet").exists()


def test_a_damaged_column_hash_in_the_footer_is_caught_by_a_whole_read(tmp_path: Path) -> None:
    path = _shard(tmp_path / "clips.parquet")
    content = json.loads(pq.ParquetFile(path).metadata.metadata[CONTENT_KEY])
    content["columns"][0][CLIPS.column_names.index("text")] = "0" * 64
    table = pq.read_table(path)
    meta = {**table.schema.metadata, CONTENT_KEY: json.dumps(content).encode()}
    pq.write_table(
        table.replace_schema_metadata(meta), path, row_group_size=1, write_page_checksum=True
    )
    problems = check_shard(path)
    assert len(problems) == 1 and "row 0 (clip 'a')" in problems[0] and "['text']" in problems[0]


def test_format_1_shards_stay_readable_and_checked_whole(tmp_path: Path) -> None:
    path = _shard(tmp_path / "clips.parquet")
    content = json.loads(pq.ParquetFile(path).metadata.metadata[CONTENT_KEY])
    with ShardReader(path) as reader:  # format 1: a row hash over every column, no columns
        names = reader.arrow_schema.names
        rows = list(reader.iter_rows())
    old = {
        "format": 1,
        "algorithm": "sha256",
        "meta_sha256": content["meta_sha256"],
        "rows": [row_content_hash(r, names) for r in rows],
    }
    table = pq.read_table(path)
    meta = {**table.schema.metadata, CONTENT_KEY: json.dumps(old).encode()}
    pq.write_table(
        table.replace_schema_metadata(meta), path, row_group_size=1, write_page_checksum=True
    )
    with ShardReader(path, CLIPS) as reader:
        assert reader.content_format == 1 and reader.hashed and not reader.columns_hashed
        assert [r["fps"] for r in reader.iter_rows()] == [r["fps"] for r in rows]
    assert check_shard(path) == []
    _rewrite(path, "video", 1, json.dumps(old).encode())
    with ShardReader(path, CLIPS) as reader:  # format 1: a partial read has only page checksums
        assert len(list(reader.iter_rows(["clip_id", "video"]))) == 2
    problems = check_shard(path)  # ... and check, reading whole rows, finds the change
    assert len(problems) == 1 and "row 1 (clip 'b')" in problems[0] and "row hash" in problems[0]
