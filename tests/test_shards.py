"""Shard IO: declared schemas, provenance, atomic writes, streaming, typed errors."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from egosim.pipeline.check import check_shard
from egosim.pipeline.clip_io import read_clips, row_from_clip, write_clips
from egosim.pipeline.records import Clip
from egosim.pipeline.shards import CorruptShardError, ShardWriter, open_shard
from egosim.schemas import CLIPS, REJECTS, RowValidationError, SchemaCompatibilityError
from tests.conftest import make_clip


def assert_clips_close(a: Clip, b: Clip) -> None:
    assert a.clip_id == b.clip_id and a.text == b.text
    np.testing.assert_array_equal(a.timestamps, b.timestamps)
    np.testing.assert_array_equal(a.intrinsics, b.intrinsics)
    np.testing.assert_array_equal(a.world_from_cam, b.world_from_cam)
    np.testing.assert_array_equal(a.hand_joints, b.hand_joints)
    np.testing.assert_array_equal(a.hand_mask, b.hand_mask)
    np.testing.assert_array_equal(a.object_mask, b.object_mask)
    np.testing.assert_array_equal(a.object_poses, b.object_poses)
    np.testing.assert_array_equal(a.first_frame_clean, b.first_frame_clean)
    assert np.abs(a.depth - b.depth).max() <= 1e-4  # quantised to 0.1 mm
    assert np.abs(a.frames.astype(int) - b.frames).mean() < 3  # H.264


def test_clips_round_trip_and_provenance(tmp_path: Path) -> None:
    clips = [make_clip("a", seed=1), make_clip("b", seed=2)]
    path = tmp_path / "s.parquet"
    write_clips(path, clips, stage="test", params={"k": 1})
    with open_shard(path, CLIPS) as reader:
        assert reader.num_rows == 2
        assert reader.meta.stage == "test" and reader.meta.params == {"k": 1}
        assert reader.meta.schema == "clips" and reader.meta.schema_version == CLIPS.version
        assert reader.arrow_schema.field("fps").metadata[b"doc"]  # column docs stored
    back = list(read_clips(path))
    for a, b in zip(clips, back, strict=True):
        assert_clips_close(a, b)
    assert pq.ParquetFile(path).num_row_groups == 2  # one row group per clip: streaming
    assert check_shard(path) == []


def test_wrong_schema_name_or_version_raises_typed_error(tmp_path: Path) -> None:
    path = tmp_path / "rejects.parquet"
    with ShardWriter(path, REJECTS, stage="t"):
        pass
    with pytest.raises(SchemaCompatibilityError, match="'rejects' version 1, expected 'clips'"):
        list(read_clips(path))
    old = CLIPS.arrow.with_metadata(
        {b"egosim.schema.name": b"clips", b"egosim.schema.version": b"0"}
    )
    pq.write_table(pa.Table.from_pylist([], schema=old), tmp_path / "old.parquet")
    with pytest.raises(SchemaCompatibilityError, match="version 0"):
        open_shard(tmp_path / "old.parquet", CLIPS)


def test_truncated_or_missing_shard_raises_corrupt_error(tmp_path: Path) -> None:
    path = tmp_path / "s.parquet"
    write_clips(path, [make_clip()])
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(CorruptShardError, match=r"s\.parquet"):
        open_shard(path, CLIPS)
    assert "not a readable Parquet shard" in check_shard(path)[0]
    with pytest.raises(CorruptShardError, match="does not exist"):
        open_shard(tmp_path / "missing.parquet")


def test_row_validation_lists_every_problem(tmp_path: Path) -> None:
    row = row_from_clip(make_clip())
    row["fps"] = -1.0
    row["timestamps"] = row["timestamps"][:-1]
    row["intrinsics"] = [10.0, 10.0, 500.0, 5.0]
    writer = ShardWriter(tmp_path / "bad.parquet", CLIPS, stage="t")
    with pytest.raises(RowValidationError) as err, writer:
        writer.write_row(row)
    message = str(err.value)
    assert "fps must be positive" in message
    assert "timestamps has 5 entries" in message
    assert "principal point" in message
    assert not (tmp_path / "bad.parquet").exists()  # failed write leaves nothing
    assert not list(tmp_path.iterdir())


def test_nan_poses_are_rejected_by_the_schema() -> None:
    row = row_from_clip(make_clip())
    row["world_from_cam"][2][3] = float("nan")
    assert any("NaN" in p for p in CLIPS.row_problems(row))


def test_killed_writer_leaves_no_visible_shard(tmp_path: Path) -> None:
    out = tmp_path / "killed.parquet"
    script = textwrap.dedent(
        f"""
        import time
        from egosim.pipeline.clip_io import row_from_clip
        from egosim.pipeline.shards import ShardWriter
        from egosim.schemas import CLIPS
        from tests.conftest import make_clip
        row = row_from_clip(make_clip())
        with ShardWriter({str(out)!r}, CLIPS, stage="t") as w:
            for i in range(1000):
                w.write_row({{**row, "clip_id": f"c{{i}}"}})
                print("row", flush=True)
                time.sleep(0.05)
        """
    )
    repo = Path(__file__).resolve().parents[1]
    proc = subprocess.Popen(
        [sys.executable, "-c", script], cwd=repo, stdout=subprocess.PIPE, text=True
    )
    assert proc.stdout is not None
    for _ in range(3):
        proc.stdout.readline()
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    time.sleep(0.1)
    assert not out.exists()
    assert check_shard(out)[0].endswith("shard file does not exist")


def test_find_shards_leaves_out_the_rejects_egosim_stage_writes(tmp_path: Path) -> None:
    """``egosim stage --output d/shard-00000.parquet`` writes d/shard-00000.rejects.parquet, which
    matches the shard glob: a folder listing skips it, a file named directly is taken."""
    from egosim.pipeline.shards import find_shards

    out = tmp_path / "clips"
    write_clips(out / "shard-00000.parquet", [make_clip("a")], stage="ingest")
    with ShardWriter(out / "shard-00000.rejects.parquet", REJECTS, stage="ingest"):
        pass
    assert find_shards([out], "ingest") == [out / "shard-00000.parquet"]
    assert find_shards([out / "shard-00000.rejects.parquet"], "ingest") == [
        out / "shard-00000.rejects.parquet"
    ]
