"""The dataset workflow on the synthetic world, and the EgoDex path through ingest."""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from egosim.pipeline import media
from egosim.pipeline.check import check_shard
from egosim.pipeline.cli import EXIT_STEP_REJECTED_ALL, app
from egosim.pipeline.clip_io import clip_from_row, read_clips
from egosim.pipeline.runner import run_workflow
from egosim.pipeline.shards import ShardReader
from egosim.pipeline.workflow import load_workflow
from egosim.stages.ingest.stage import IngestConfig, IngestStage
from egosim.world import WorldConfig, render_clip
from egosim.world.egodex_export import write_egodex

REPO = Path(__file__).resolve().parents[1]
TINY = ["height=64", "width=112", "num_frames=9", "fps=8"]


def test_dataset_workflow_builds_checked_shards_from_the_synthetic_world(tmp_path: Path) -> None:
    overrides = [f"ingest.{kv}" for kv in [*TINY, "synthetic_count=3", "units_per_shard=2"]]
    overrides.append("pack.frame_stride=1")  # 9 source frames make one 9-frame sample
    wf = load_workflow(REPO / "workflows" / "dataset.yaml", overrides)
    out = tmp_path / "data"
    summary = run_workflow(wf, out, n_workers=2, gpu_workers=0)
    shards = sorted((out / "ingest").glob("shard-*.parquet"))
    assert len(shards) == 2 and summary.rejected == 0
    every = sorted(out.glob("*/shard-*.parquet"))
    assert len(every) == 2 * len(wf.steps)  # every step wrote both shards
    assert {p.parent.name for p in every} == {s.name for s in wf.steps}
    assert all(check_shard(s) == [] for s in every)
    for step in wf.steps:  # every clip made it through every step
        with ShardReader(out / step.name / "shard-00001.parquet") as reader:
            assert reader.read_column("clip_id") == ["synth-art-00002"], step.name
    clips = [c for s in shards for c in read_clips(s)]
    assert [c.clip_id for c in clips] == [
        "synth-tabletop-00000",
        "synth-tabletop-00001",
        "synth-art-00002",
    ]
    truth = render_clip(WorldConfig(seed=1, height=64, width=112, num_frames=9, fps=8.0))
    np.testing.assert_array_equal(clips[1].world_from_cam, truth.world_from_cam)
    np.testing.assert_array_equal(clips[1].hand_mask, truth.hand_mask)
    np.testing.assert_allclose(clips[1].hand_joints, truth.hand_joints, atol=1e-6)


@pytest.mark.slow
def test_dataset_workflow_mixes_human_and_robot_clips(tmp_path: Path) -> None:
    """ingest.synthetic_robot_every=2: clips 0 and 2 show the URDF robot arm; every step takes
    both kinds, and the robot clips' hand masks cover their true arm (the embodiment mask)."""
    overrides = [f"ingest.{kv}" for kv in [*TINY, "synthetic_count=3", "synthetic_robot_every=2"]]
    overrides += ["pack.frame_stride=1", "ingest.robot_mask_dilate_px=1"]
    wf = load_workflow(REPO / "workflows" / "dataset.yaml", overrides)
    out = tmp_path / "data"
    summary = run_workflow(wf, out, n_workers=2, gpu_workers=0)
    assert summary.rejected == 0
    every = sorted(out.glob("*/shard-*.parquet"))
    assert all(check_shard(s) == [] for s in every)
    with ShardReader(out / "pack" / "shard-00000.parquet") as reader:
        assert reader.read_column("clip_id") == [
            "synth-robot-00000",
            "synth-tabletop-00001",
            "synth-robot-00002",
        ]
    clips = {c.clip_id: c for c in read_clips(out / "ingest" / "shard-00000.parquet")}
    with ShardReader(out / "hand_mask" / "shard-00000.parquet") as reader:
        for row in reader.iter_rows():
            clip = clips[row["clip_id"]]
            if clip.embodiment_mask is None:
                continue
            masks = media.decode_lossless_video(row["hand_mask"]).astype(bool)
            truth = clip.hand_mask.astype(bool)  # the true arm
            assert (masks & truth).sum() >= 0.99 * truth.sum(), clip.clip_id


def test_egodex_files_ingest_back_to_the_ground_truth(tmp_path: Path) -> None:
    truth = render_clip(WorldConfig(seed=4, height=64, width=112, num_frames=8, fps=8.0))
    write_egodex(truth, tmp_path / "egodex" / "pick", stem="0")
    stage = IngestStage(IngestConfig(height=64, width=112, num_frames=8, fps=8.0))
    (unit,) = stage.list_units(str(tmp_path / "egodex"))
    assert unit.startswith("egodex:")
    (row,) = list(stage.process_unit(unit))
    clip = clip_from_row(row)
    assert clip.source == "egodex"
    np.testing.assert_allclose(clip.world_from_cam, truth.world_from_cam, atol=1e-5)
    valid = truth.hand_valid
    np.testing.assert_allclose(clip.hand_joints[valid], truth.hand_joints[valid], atol=1e-5)
    np.testing.assert_allclose(clip.intrinsics, truth.intrinsics, rtol=1e-6)


def test_egodex_file_with_a_missing_key_is_rejected_by_name(tmp_path: Path) -> None:
    import h5py

    truth = render_clip(WorldConfig(seed=5, height=64, width=112, num_frames=8, fps=8.0))
    hdf5, _ = write_egodex(truth, tmp_path / "pick", stem="0")
    with h5py.File(hdf5, "a") as fh:
        del fh["transforms/camera"]
    result = CliRunner().invoke(
        app,
        [
            "stage",
            "ingest",
            "--input",
            str(tmp_path),
            "--output",
            str(tmp_path / "o.parquet"),
            *[a for kv in TINY for a in ("--param", kv)],
        ],
    )
    assert result.exit_code == EXIT_STEP_REJECTED_ALL, result.output  # nothing came through
    assert "0 rows, 1 rejected" in result.output
    with ShardReader(tmp_path / "o.rejects.parquet") as reader:
        (row,) = list(reader.iter_rows())
    assert "transforms/camera" in row["reason"] and "0.hdf5" in row["reason"]


def test_identical_runs_write_byte_identical_shards(tmp_path: Path) -> None:
    """No wall-clock time or other run-varying value lands in shard content (issue 11)."""
    overrides = [f"ingest.{kv}" for kv in [*TINY, "synthetic_count=1"]]
    overrides.append("pack.frame_stride=1")
    wf = load_workflow(REPO / "workflows" / "dataset.yaml", overrides)
    digests = []
    for name in ("a", "b"):
        out = tmp_path / name
        run_workflow(wf, out, n_workers=2, gpu_workers=0)
        files = sorted(out.glob("*/*.parquet"))
        assert len(files) >= len(wf.steps)
        digests.append(
            {str(p.relative_to(out)): hashlib.sha256(p.read_bytes()).hexdigest() for p in files}
        )
    assert digests[0].keys() == digests[1].keys()
    differ = sorted(k for k in digests[0] if digests[0][k] != digests[1][k])
    assert differ == [], f"shards that differ between identical runs: {differ}"
