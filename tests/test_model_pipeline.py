"""pack -> train -> simulate -> evaluate on a tiny synthetic clip through the real stage chain."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from egosim.model.errors import CheckpointMismatchError
from egosim.model.inference import load_trained
from egosim.model.metrics import psnr
from egosim.model.train import OptimConfig, TrainConfig
from egosim.pipeline import media
from egosim.pipeline.cli import app
from egosim.pipeline.clip_io import write_clips
from egosim.pipeline.execute import ShardTask, run_shard_task
from egosim.pipeline.shards import ShardReader, ShardWriter
from egosim.pipeline.stage import ClipRejected, ConfigError, get_stage
from egosim.schemas.pack import EVALUATION, PACK, SIMULATION
from egosim.schemas.scene import SCENE_RENDER
from egosim.stages.common.pack_dataset import PackDataset
from egosim.stages.common.packed import PackRowError, sample_from_pack_row
from egosim.stages.evaluate.report import format_table, overall
from egosim.stages.pack.stage import PackStage
from egosim.stages.train.run import TrainJob, run_training
from egosim.world import WorldConfig, render_clip

H, W, T = 64, 112, 9  # clip size
PH, PW = 32, 56  # packed (training) size
PACK_ROLES = {
    "clips": "clips",
    "scene_render": "scene_render",
    "keypoints": "keypoints",
    "captions": "captions",
    "inpaint": "inpaint",
    "cameras": "cameras",
    "hand_mask": "hand_mask",
}


def _task(tmp: Path, step: str, stage: str, inputs: dict[str, Path], params=None) -> ShardTask:
    return ShardTask(
        step=step,
        stage=stage,
        params=params or {},
        shard_index=0,
        shard_count=1,
        output=tmp / f"{step}.parquet",
        rejects=tmp / f"{step}.rejects.parquet",
        inputs=inputs,
    )


@pytest.fixture(scope="module")
def chain(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """Upstream shards of one synthetic clip (given backends) and its pack shard at 32x56."""
    tmp = tmp_path_factory.mktemp("chain")
    clip = render_clip(WorldConfig(seed=0, height=H, width=W, num_frames=T))
    out = {"clips": tmp / "clips.parquet", "dir": tmp}
    write_clips(out["clips"], [clip])
    steps = (
        ("cameras", "depth_camera", {"clips": "clips"}, {"backend": "given"}),
        ("hands", "hands", {"clips": "clips"}, {"backend": "given"}),
        ("keypoints", "keypoint_render", {"clips": "clips", "hands": "hands"}, None),
        ("hand_mask", "hand_mask", {"clips": "clips", "hands": "hands"}, None),
        ("inpaint", "inpaint", {"clips": "clips", "hand_mask": "hand_mask"}, None),
        ("scene_cloud", "scene_cloud", {"clips": "clips", "inpaint": "inpaint"}, None),
        ("scene_render", "scene_render", {"clips": "clips", "scene_cloud": "scene_cloud"}, None),
        ("captions", "caption", {"clips": "clips"}, None),
        ("pack", "pack", PACK_ROLES, {"height": PH, "width": PW}),
    )
    for step, stage, roles, params in steps:
        inputs = {role: out[src] for role, src in roles.items()}
        result = run_shard_task(_task(tmp, step, stage, inputs, params))
        assert result.rows == 1, f"{step} made no row"
        out[step] = tmp / f"{step}.parquet"
    return out


def _rows(chain: dict[str, Path]) -> dict[str, dict]:
    rows = {}
    for role, step in PACK_ROLES.items():
        with ShardReader(chain[step]) as reader:
            rows[role] = next(reader.iter_rows())
    return rows


def _pack_row(chain: dict[str, Path]) -> dict:
    with ShardReader(chain["pack"], PACK) as reader:
        return next(reader.iter_rows())


def test_pack_row_holds_every_condition_at_the_training_size(chain) -> None:
    row = _pack_row(chain)
    PACK.validate_row(row)
    assert (row["num_frames"], row["height"], row["width"]) == (T, PH, PW)
    assert row["first_frame_source"] == "inpaint" and row["prompt"]
    assert row["frame_indices"] == list(range(T))
    assert row["registered_fraction"] == 1.0 and row["hand_valid_fraction"] > 0.5
    assert row["hand_mask"] is not None and row["depth0"] is not None
    with ShardReader(chain["clips"]) as reader:
        clip = next(reader.iter_rows())
    # Intrinsics scale with the resize (pixel-corner convention: c' = c * s).
    np.testing.assert_allclose(row["intrinsics"], np.asarray(clip["intrinsics"]) * 0.5)
    ds = PackDataset(chain["pack"])
    sample = ds[0]
    assert len(ds) == 1 and ds.clip_ids == [row["clip_id"]]
    assert sample.target_video.shape == (T, PH, PW, 3)
    assert 0.5 < float(np.mean(sample.visibility)) <= 1.0
    frames = media.decode_rgb_video(clip["video"], H, W)
    small = frames.reshape(T, PH, 2, PW, 2, 3).mean(axis=(2, 4))
    assert psnr(sample.target_video, small) > 30


def test_quality_gate_rejects_with_every_reason(chain) -> None:
    rows = _rows(chain)
    rows["keypoints"] = {**rows["keypoints"], "keypoint_visible": [[False] * 42] * T}
    rows["scene_render"] = {**rows["scene_render"], "visible_fraction": [0.5] * T}
    stage = PackStage.from_params({"min_visible_fraction": 0.9})
    with pytest.raises(ClipRejected, match="quality gate") as err:
        stage.process(rows)
    assert "visible_fraction" in str(err.value) and "hand_valid_fraction 0.000" in str(err.value)
    # Through the executor: the reason lands in the rejects shard (a render that saw half).
    d = chain["dir"]
    inputs = {role: chain[step] for role, step in PACK_ROLES.items()}
    inputs["scene_render"] = d / "scene_render_half.parquet"
    with ShardWriter(inputs["scene_render"], SCENE_RENDER, stage="test") as writer:
        writer.write_row(rows["scene_render"])
    task = _task(d, "pack_gated", "pack", inputs, {"min_visible_fraction": 0.9})
    assert run_shard_task(task).rejected == 1
    with ShardReader(task.rejects) as reader:
        assert "quality gate" in next(reader.iter_rows())["reason"]


def test_mismatched_inputs_name_what_differs(chain) -> None:
    rows = _rows(chain)
    bad = {**rows, "scene_render": {**rows["scene_render"], "num_frames": 5}}
    bad["keypoints"] = {**rows["keypoints"], "width": 100}
    with pytest.raises(ClipRejected, match="inputs disagree") as err:
        PackStage().process(bad)
    assert "scene_render num_frames is 5, clips has 9" in str(err.value)
    assert "keypoints width is 100, clips has 112" in str(err.value)
    with pytest.raises(ConfigError, match="1 \\+ 4k"):
        PackStage.from_params({"num_frames": 6})


def test_bad_pack_rows_are_named() -> None:
    row = {"clip_id": "x", "num_frames": 9, "height": 32, "width": 56, "prompt": "p"}
    row |= dict.fromkeys(("target_video", "visible", "skeleton_video", "first_frame"), b"")
    with pytest.raises(PackRowError, match="missing conditions \\['scene_video'\\]"):
        sample_from_pack_row({**row, "scene_video": None})


def test_pack_row_with_wrong_size_is_named(chain) -> None:
    row = {**_pack_row(chain), "num_frames": 13}
    with pytest.raises(
        PackRowError, match=r"target is \(9, 32, 56, 3\), expected \(13, 32, 56, 3\)"
    ):
        sample_from_pack_row(row)


@pytest.fixture(scope="module")
def run_dir(chain) -> Path:
    """A 4-step tiny training run on the packed clip."""
    out = chain["dir"] / "run"
    config = TrainConfig(
        steps=4, preview_steps=2, checkpoint_every=2, optim=OptimConfig(warmup_steps=1)
    )
    summary = run_training(TrainJob((str(chain["pack"]),), str(out), config, sample_steps=2))
    assert summary["step"] == 4 and summary["resumed_from"] == 0
    return out


def test_train_writes_run_and_resumes(chain, run_dir: Path, tmp_path: Path) -> None:
    for name in ("config.json", "metrics.jsonl", "data.json", "sample.mp4", "summary.json"):
        assert (run_dir / name).is_file(), name
    assert list((run_dir / "checkpoints").glob("step_*/state.json"))
    assert list((run_dir / "previews").glob("*.png"))
    assert (
        json.loads((run_dir / "data.json").read_text())["clip_ids"]
        == PackDataset(chain["pack"]).clip_ids
    )
    # The CLI resumes the same run directory to 6 steps.
    result = CliRunner().invoke(
        app,
        [
            *("train", "--data", str(chain["pack"]), "--out", str(run_dir), "--steps", "6"),
            *("--set", "preview_steps=0", "--set", "optim.warmup_steps=1"),
            *("--set", "checkpoint_every=2"),
            *("--sample-steps", "0"),
        ],
    )
    assert result.exit_code == 0, result.output
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["resumed_from"] == 4 and summary["step"] == 6
    # A bad --set is a clear error naming the field.
    result = CliRunner().invoke(
        app, ["train", "--data", str(chain["pack"]), "--out", str(tmp_path), "--set", "optim.lr=-1"]
    )
    assert result.exit_code == 2 and "lr must be > 0" in result.output


def test_checkpoint_from_another_preset_is_refused(run_dir: Path) -> None:
    with pytest.raises(
        CheckpointMismatchError, match=r"preset 'tiny'; asked for 'wan2\.1-fun-1\.3b-inp'"
    ):
        load_trained(run_dir, preset="wan2.1-fun-1.3b-inp")


def test_simulate_and_evaluate_run_their_workflows(chain, run_dir: Path, tmp_path: Path) -> None:
    out = tmp_path / "sim"
    args = [
        *("simulate", "--data", str(chain["pack"]), "--checkpoint", str(run_dir)),
        *("--out", str(out), "--set", "steps=2"),
    ]
    # Whichever test ran last trained the module's run (4 steps, or 6 after the CLI resume).
    trained_to = json.loads((run_dir / "summary.json").read_text())["step"]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    shard = out / "simulate" / "shard-00000.parquet"  # the runner's layout: OUT/<step>/
    assert f"{shard}: 1 clips, 0 rejected" in result.output
    with ShardReader(shard, SIMULATION) as reader:
        row = next(reader.iter_rows())
    SIMULATION.validate_row(row)
    assert row["checkpoint_step"] == trained_to and row["sampling_steps"] == 2
    assert (row["num_frames"], row["height"], row["width"]) == (T, PH, PW)
    video, _ = media.read_video_file(out / "videos" / f"{row['clip_id']}.mp4")
    assert video.shape == (T, PH, PW, 3)
    # the file is the shard's MP4 itself, not a second encode
    assert (out / "videos" / f"{row['clip_id']}.mp4").read_bytes() == row["video"]
    resolved = yaml.safe_load((out / "workflow.resolved.yaml").read_text())
    assert resolved["steps"]["simulate"]["params"]["steps"] == 2
    assert resolved["given"] == {"pack": [str(chain["pack"])]}
    # The runner owns the run: a second run skips the finished shard.
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    manifest = json.loads((out / "manifest.json").read_text())
    assert [r["skipped"] for r in manifest["results"]] == [True]

    ev = tmp_path / "eval"
    result = CliRunner().invoke(
        app,
        [
            *("evaluate", "--data", str(chain["pack"]), "--simulation", str(out)),
            *("--out", str(ev), "--set", "camera_backend=given"),
        ],
    )
    assert result.exit_code == 0, result.output
    assert "overall" in result.output and row["clip_id"] in result.output
    with ShardReader(ev / "evaluate" / "shard-00000.parquet", EVALUATION) as reader:
        evaluation = next(reader.iter_rows())
    assert evaluation["clip_id"] == row["clip_id"] and np.isfinite(evaluation["psnr"])
    assert evaluation["cam_err"] == pytest.approx(0.0, abs=1e-9)


def _simulation_row(pack: dict, video: bytes, num_frames: int) -> dict:
    return {
        "clip_id": pack["clip_id"],
        "num_frames": num_frames,
        "width": pack["width"],
        "height": pack["height"],
        "fps": pack["fps"],
        "video": video,
        "preset": "tiny",
        "checkpoint": "",
        "checkpoint_step": 0,
        "sampling_steps": 1,
        "guidance_scale": 1.0,
        "seed": 0,
    }


def test_evaluate_identical_clip_is_perfect(chain, tmp_path: Path) -> None:
    pack = _pack_row(chain)
    sim = tmp_path / "sim.parquet"
    with ShardWriter(sim, SIMULATION, stage="test") as writer:
        writer.write_row(_simulation_row(pack, pack["target_video"], T))
    task = _task(
        tmp_path, "evaluate", "evaluate", {"pack": chain["pack"], "simulation": sim},
        {"camera_backend": "given"},
    )  # fmt: skip
    assert run_shard_task(task).rows == 1
    with ShardReader(task.output, EVALUATION) as reader:
        row = next(reader.iter_rows())
    assert row["psnr"] == float("inf") and row["psnr_hand"] == float("inf")
    assert row["ssim"] == pytest.approx(1.0)
    assert row["cam_err"] == pytest.approx(0.0, abs=1e-9)
    assert row["depth_err"] == pytest.approx(0.0, abs=1e-6)
    assert np.isfinite(row["psnr_baseline"]) and row["psnr_hand_baseline"] < 40
    assert row["note"] == "" and 0 < row["hand_fraction"] < 0.5
    assert overall([row])["psnr"] == float("inf") and "overall" in format_table([row])


def test_evaluate_rejects_a_generated_clip_of_another_length(chain) -> None:
    pack = _pack_row(chain)
    video = media.decode_rgb_video(pack["target_video"], PH, PW)[:5]
    row = _simulation_row(pack, media.encode_rgb_video(video, 16.0), 5)
    stage = get_stage("evaluate")()
    with pytest.raises(ClipRejected, match="generated video is \\(5, 32, 56, 3\\)"):
        stage.process({"pack": pack, "simulation": row})


def test_simulate_stage_checks_its_config() -> None:
    with pytest.raises(ConfigError, match="steps must be >= 1, got 0"):
        get_stage("simulate").from_params({"steps": 0})
    cfg = get_stage("evaluate").config_class
    assert dataclasses.asdict(cfg())["camera_backend"] == "none"


def test_train_runs_as_one_dask_task_on_a_gpu_worker(chain, tmp_path: Path) -> None:
    from distributed import LocalCluster

    config = TrainConfig(steps=1, preview_steps=0, optim=OptimConfig(warmup_steps=0))
    job = TrainJob((str(chain["pack"]),), str(tmp_path / "run"), config, sample_steps=0)
    with LocalCluster(
        n_workers=1,
        processes=False,
        threads_per_worker=1,
        resources={"GPU": 1},
        dashboard_address=None,
    ) as cluster:
        from egosim.stages.train.run import submit_training

        summary = submit_training(job, cluster.scheduler_address)
    assert summary["step"] == 1 and (tmp_path / "run" / "checkpoints").is_dir()


def test_training_data_too_big_for_tiny_is_refused(chain, tmp_path: Path) -> None:
    from egosim.model.errors import ModelConfigError
    from egosim.stages.train.run import check_data

    ds = PackDataset(chain["pack"])
    assert ds.sizes == [(T, PH, PW)]
    ds.sizes = [(61, 480, 832)]
    with pytest.raises(ModelConfigError, match=r"exceed 8192 tokens: pack at a training size"):
        check_data(ds, TrainConfig())
