"""Stages declare the columns they read per input role; the executor reads only those (issue 12).

Covers: the declaration is checked against the role's schema when a stage is registered; a
stage with a declaration receives only those columns (plus ``clip_id``) and an undeclared read
fails the task; ``clip_from_row`` builds a clip from a row that lacks optional columns; and the
dataset workflow's shards are identical whether stages read their declared columns or every
column (the done-when of issue 12).
"""

from __future__ import annotations

import hashlib
from collections.abc import Mapping
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import pytest

from egosim.pipeline.clip_io import (
    CLIP_REQUIRED_COLUMNS,
    clip_from_row,
    row_from_clip,
    write_clips,
)
from egosim.pipeline.execute import run_shard_task
from egosim.pipeline.records import ClipValueError
from egosim.pipeline.runner import run_workflow
from egosim.pipeline.shards import ShardReader, row_content_hash
from egosim.pipeline.stage import (
    ClipStage,
    DeclaredRow,
    StageError,
    UndeclaredColumnError,
    join_columns,
    register_stage,
    registered_stages,
)
from egosim.pipeline.workflow import load_workflow
from egosim.schemas import CLIPS, ShardSchema
from egosim.schemas.captions import CAPTIONS
from egosim.schemas.poses import POSES
from tests.conftest import make_clip, one_shard_task, translated, write_poses

REPO = Path(__file__).resolve().parents[1]
TINY = ["height=64", "width=112", "num_frames=9", "fps=8"]  # as tests/test_dataset.py


class _SpyStage(ClipStage):
    """Records the keys of the rows it is given; writes a caption row per clip."""

    name = "test_columns_spy"
    description = "records the columns it receives (tests/test_columns.py)"
    inputs: ClassVar[Mapping[str, ShardSchema]] = {"clips": CLIPS}
    optional_inputs: ClassVar[Mapping[str, ShardSchema]] = {"poses": POSES}
    output = CAPTIONS
    columns: ClassVar[Mapping[str, tuple[str, ...]]] = {
        "clips": ("num_frames", "text"),
        "poses": ("world_from_cam",),
    }
    seen: ClassVar[list[dict[str, set[str]]]] = []  # keys of every role's row, per clip
    read: ClassVar[str | None] = None  # a clips column process also reads (None: none)

    def process(self, rows: Mapping[str, Mapping[str, Any]]) -> dict[str, Any]:
        """The clip's text as its caption, after recording what it was given."""
        type(self).seen.append({role: set(row) for role, row in rows.items()})
        clip = rows["clips"]
        if self.read is not None:
            clip[self.read]
        return {"clip_id": clip["clip_id"], "text": f"{clip['num_frames']}", "origin": "spy"}


class _WholeSpyStage(_SpyStage):
    """The same spy with no declaration: it gets every column."""

    name = "test_columns_spy_whole"
    columns: ClassVar[Mapping[str, tuple[str, ...]]] = {}


for _stage in (_SpyStage, _WholeSpyStage):
    if _stage.name not in registered_stages():  # test modules may be imported twice
        register_stage(_stage)


@pytest.fixture
def spy_inputs(tmp_path: Path) -> dict[str, Path]:
    clips = [make_clip("a", num_frames=4), make_clip("b", num_frames=5, seed=1)]
    write_clips(tmp_path / "clips.parquet", clips, stage="test")
    poses = write_poses(
        tmp_path / "poses.parquet", clips[1], translated(clips[1].world_from_cam, np.ones(3))
    )
    return {"clips": tmp_path / "clips.parquet", "poses": poses}


def _bad_stage(columns: Mapping[str, Any]) -> type[ClipStage]:
    return type(
        "BadStage",
        (_SpyStage,),
        {"name": "test_columns_bad", "columns": columns, "__module__": __name__},
    )


def test_a_declared_column_the_schema_lacks_is_refused_naming_stage_role_and_column() -> None:
    with pytest.raises(StageError) as caught:
        register_stage(_bad_stage({"clips": ("video", "vidoe"), "poses": ("world_from_cam",)}))
    message = str(caught.value)
    assert "stage 'test_columns_bad'" in message
    assert "role 'clips' has no column 'vidoe' in schema 'clips'" in message
    assert "'video'" not in message.replace("'vidoe'", "")  # the good name is not blamed
    assert "test_columns_bad" not in registered_stages()  # refused, not registered


def test_an_unknown_role_and_a_bare_string_are_refused_all_at_once() -> None:
    with pytest.raises(StageError) as caught:
        register_stage(_bad_stage({"clip": ("video",), "poses": "world_from_cam"}))
    message = str(caught.value)
    assert "role 'clip' is not an input role (roles: ['clips', 'poses'])" in message
    assert "role 'poses' must list column names, got the string 'world_from_cam'" in message


def test_read_columns_are_the_declared_ones_plus_clip_id_in_schema_order() -> None:
    assert _SpyStage.read_columns("clips") == ["clip_id", "num_frames", "text"]
    assert _SpyStage.read_columns("poses") == ["clip_id", "world_from_cam"]
    assert _WholeSpyStage.read_columns("clips") is None  # undeclared role: read whole
    whole = type(
        "WholeByListing",
        (_SpyStage,),
        {"columns": {"poses": POSES.column_names}, "__module__": __name__},
    )
    assert whole.read_columns("poses") is None  # every column declared: read whole (verified)


def test_join_columns_merges_roles_keeping_order_without_duplicates() -> None:
    merged = join_columns({"clips": ("video", "fps")}, {"clips": ("fps", "depth"), "poses": ()})
    assert merged == {"clips": ("video", "fps", "depth"), "poses": ()}


def test_a_stage_with_a_declaration_receives_only_those_columns(
    spy_inputs: dict[str, Path], tmp_path: Path
) -> None:
    _SpyStage.seen.clear()
    task = one_shard_task("test_columns_spy", tmp_path / "out", spy_inputs)
    result = run_shard_task(task)
    assert (result.rows, result.rejected) == (1, 0)
    # clip "a" has no poses row: the executor reports it unmatched, process never sees it
    assert _SpyStage.seen == [
        {"clips": {"clip_id", "num_frames", "text"}, "poses": {"clip_id", "world_from_cam"}}
    ]
    with ShardReader(tmp_path / "out" / "test_columns_spy.parquet") as reader:
        assert [(r["clip_id"], r["text"]) for r in reader.iter_rows()] == [("b", "5")]


def test_without_a_declaration_every_column_arrives(
    spy_inputs: dict[str, Path], tmp_path: Path
) -> None:
    _SpyStage.seen.clear()
    task = one_shard_task(
        "test_columns_spy_whole", tmp_path / "out", {"clips": spy_inputs["clips"]}
    )
    assert run_shard_task(task).rows == 2
    assert [s["clips"] for s in _SpyStage.seen] == [set(CLIPS.column_names)] * 2


def test_reading_an_undeclared_column_fails_the_task_not_the_clip(
    spy_inputs: dict[str, Path], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(_SpyStage, "read", "video")
    task = one_shard_task("test_columns_spy", tmp_path / "out", {"clips": spy_inputs["clips"]})
    with pytest.raises(UndeclaredColumnError, match="reads column 'video' of input role 'clips'"):
        run_shard_task(task)
    assert not (tmp_path / "out" / "test_columns_spy.parquet").exists()


def test_a_declared_row_refuses_undeclared_schema_columns_only() -> None:
    row = DeclaredRow({"clip_id": "a", "fps": 8.0}, "s", "clips", CLIPS.column_names)
    assert row["fps"] == 8.0 and row.get("fps") == 8.0
    assert "video" not in row and row.get("not_a_column", 3) == 3
    with pytest.raises(UndeclaredColumnError, match="stage 's' reads column 'video'"):
        row.get("video")
    with pytest.raises(UndeclaredColumnError, match="declared: \\['clip_id', 'fps'\\]"):
        row["video"]
    with pytest.raises(KeyError):
        row["not_a_column"]


def test_clip_from_row_treats_absent_optional_columns_as_null() -> None:
    clip = make_clip("c", num_frames=4)
    row = row_from_clip(clip)
    full = clip_from_row(row)
    keep = (*CLIP_REQUIRED_COLUMNS, "world_from_cam", "hand_joints")
    part = clip_from_row({k: row[k] for k in keep})
    np.testing.assert_array_equal(part.frames, full.frames)  # the same decoded video
    np.testing.assert_allclose(part.world_from_cam, clip.world_from_cam, atol=1e-12)
    np.testing.assert_allclose(part.hand_joints, clip.hand_joints, atol=1e-6)
    assert full.depth is not None and full.hand_mask is not None and full.text is not None
    assert part.depth is None and part.hand_mask is None and part.text is None
    assert part.object_poses is None and part.static_frames is None
    # object poses without their count: the count follows from the poses
    posed = clip_from_row({k: row[k] for k in (*keep, "object_poses")})
    np.testing.assert_array_equal(posed.object_poses, full.object_poses)


def test_clip_from_row_names_the_clip_and_the_missing_required_columns() -> None:
    row = row_from_clip(make_clip("c", num_frames=3))
    del row["video"], row["timestamps"]
    with pytest.raises(ClipValueError, match=r"clip 'c'.*\['timestamps', 'video'\]"):
        clip_from_row(row)


def _column_hashes(run: Path) -> dict[tuple[str, str, str], str]:
    """SHA-256 of every column of every row of every shard of a run, by (step, shard, column)."""
    out: dict[tuple[str, str, str], str] = {}
    for shard in sorted(run.glob("*/*.parquet")):
        with ShardReader(shard) as reader:
            names = reader.arrow_schema.names
            rows = list(reader.iter_rows())
        for name in names:
            h = hashlib.sha256()
            for row in rows:
                h.update(row_content_hash(row, [name]).encode())
            out[(shard.parent.name, shard.name, name)] = h.hexdigest()
    return out


def test_dataset_shards_are_identical_with_declared_columns_or_all(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Issue 12's done-when: the dataset workflow writes the same content either way.

    Synthetic human and robot clips (the robot's embodiment_mask reaches hand_mask) through
    every step of workflows/dataset.yaml, once as the stages declare and once with every
    column read; every column of every row of every shard (rejects included) must hash alike.
    About 10 s; dropping ``embodiment_mask`` from hand_mask's declaration makes it fail.
    """
    overrides = [f"ingest.{kv}" for kv in [*TINY, "synthetic_count=2", "synthetic_robot_every=2"]]
    overrides += ["pack.frame_stride=1", "ingest.robot_mask_dilate_px=1"]
    wf = load_workflow(REPO / "workflows" / "dataset.yaml", overrides)
    declared = tmp_path / "declared"
    run_workflow(wf, declared, scheduler="here")
    with monkeypatch.context() as patch:
        patch.setattr(ClipStage, "read_columns", classmethod(lambda cls, role: None))
        everything = tmp_path / "everything"
        run_workflow(wf, everything, scheduler="here")
    a, b = _column_hashes(declared), _column_hashes(everything)
    assert {k[0] for k in a} >= {s.name for s in wf.steps}  # every step wrote shards
    with ShardReader(declared / "pack" / "shard-00000.parquet") as reader:  # both clips packed
        assert reader.read_column("clip_id") == ["synth-robot-00000", "synth-tabletop-00001"]
    assert a.keys() == b.keys()
    assert [k for k in a if a[k] != b[k]] == []
