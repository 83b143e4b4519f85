"""Training from precomputed latents: ``LatentSample`` through ``encode_batch``, the latents
dataset, ``open_training_data``, and training that equals training on the fly.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from egosim.model.conditioning import LatentSample, TrainingSample, encode_batch
from egosim.model.encoders import EncoderFolders, load_encoders
from egosim.model.errors import SampleError
from egosim.model.network import build_model
from egosim.model.train import OptimConfig, TrainConfig, train
from egosim.model.vae import PackedVAE
from egosim.pipeline import media
from egosim.pipeline.shards import ShardWriter
from egosim.schemas.captions import CAPTIONS
from egosim.stages.common.latents_dataset import (
    LatentsDataset,
    TrainingDataError,
    open_training_data,
)
from egosim.stages.common.pack_dataset import PackDataset
from tests.test_encode import _encode_run, pack_row, wan_folder, write_pack

__all__ = ["wan_folder"]  # the module fixture, shared with test_encode


def _latent(
    clip_id: str = "c", grid: tuple[int, int, int] = (3, 4, 6), seed: int = 0
) -> LatentSample:
    g = torch.Generator().manual_seed(seed)
    return LatentSample(
        x0=torch.randn(16, *grid, generator=g),
        condition=torch.randn(36, *grid, generator=g),
        prompt="p",
        text_embedding=torch.randn(5, 32, generator=g).to(torch.bfloat16),
        image_embedding=torch.randn(257, 32, generator=g),
        clip_id=clip_id,
    )


def test_latent_sample_checks_shapes_and_names_the_clip() -> None:
    with pytest.raises(SampleError, match=r"'bad'.*x0 must be.*condition must be"):
        LatentSample(
            x0=torch.zeros(12, 3, 4, 4),
            condition=torch.zeros(36, 2, 4, 4),
            prompt="",
            clip_id="bad",
        )
    with pytest.raises(SampleError, match="image_embedding must be"):
        LatentSample(
            x0=torch.zeros(16, 3, 4, 4),
            condition=torch.zeros(36, 3, 4, 4),
            prompt="",
            image_embedding=torch.zeros(257),
        )


def test_encode_batch_passes_latents_through() -> None:
    a, b = _latent("a", seed=0), _latent("b", seed=1)
    enc = encode_batch(PackedVAE(), [a, b])
    assert enc.x0.shape == (2, 16, 3, 4, 6) and enc.condition.shape == (2, 36, 3, 4, 6)
    assert torch.equal(enc.x0[1], b.x0) and torch.equal(enc.condition[0], a.condition)
    assert enc.text_embeddings[0].dtype == torch.float32  # bf16 widened exactly
    assert torch.equal(enc.text_embeddings[0], a.text_embedding.float())
    assert torch.equal(enc.image_embeddings[1], b.image_embedding)
    assert enc.prompts == ["p", "p"]


def test_encode_batch_refuses_mixed_kinds_and_sizes() -> None:
    v = np.zeros((5, 8, 8, 3), np.uint8)
    pixel = TrainingSample(
        target_video=v,
        scene_video=v,
        visibility=np.ones((5, 8, 8), np.uint8),
        skeleton_video=v,
        first_frame=v[0],
        prompt="",
    )
    with pytest.raises(SampleError, match="mixes precomputed latents and pixel samples"):
        encode_batch(PackedVAE(), [_latent(), pixel])
    with pytest.raises(SampleError, match=r"differ in \(T', h, w\).*'a', 'b'"):
        encode_batch(PackedVAE(), [_latent("a"), _latent("b", grid=(2, 4, 6))])


@pytest.fixture(scope="module")
def tiny_runs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """A pack shard of 2 clips at 9x32x32 (tiny's size) and its encode run (tiny preset)."""
    tmp = tmp_path_factory.mktemp("tiny")
    pack = write_pack(
        tmp / "pack" / "shard-00000.parquet",
        [pack_row(f"c{i}", h=32, w=32, seed=i) for i in range(2)],
    )
    run = _encode_run(tmp / "encoded", pack, preset="tiny")
    return {"pack": pack, "pack_dir": tmp, "run": run}


def test_open_training_data_picks_the_kind(tiny_runs: dict[str, Path], tmp_path: Path) -> None:
    latents = open_training_data(tiny_runs["run"])  # a run folder with encode/
    assert isinstance(latents, LatentsDataset) and len(latents) == 2
    assert latents.clip_ids == ["c0", "c1"] and latents.sizes == [(9, 32, 32)] * 2
    assert latents.presets == ["tiny", "tiny"]
    latents.check_preset("tiny")
    with pytest.raises(TrainingDataError, match=r"2 clip.*'c0'.*encoded for preset 'tiny'"):
        latents.check_preset("tiny-wan")
    assert latents.shards == sorted((tiny_runs["run"] / "encode").glob("shard-*.parquet"))
    assert isinstance(open_training_data(latents.shards), LatentsDataset)  # shard files
    pack = open_training_data([tiny_runs["pack_dir"]])  # a run folder with pack/
    assert isinstance(pack, PackDataset) and pack.clip_ids == latents.clip_ids
    with pytest.raises(IndexError, match="out of range"):
        latents[2]
    with pytest.raises(TrainingDataError, match="mix pack and latents"):
        open_training_data([tiny_runs["pack"], *latents.shards])
    captions = tmp_path / "captions" / "shard-00000.parquet"
    with ShardWriter(captions, CAPTIONS, stage="caption"):
        pass
    with pytest.raises(TrainingDataError, match="'captions'"):
        open_training_data(captions)
    (tmp_path / "empty").mkdir()
    with pytest.raises(TrainingDataError, match="no pack or latents shards"):
        open_training_data(tmp_path / "empty")


def test_a_folder_made_by_egosim_stage_opens(tiny_runs, tmp_path: Path) -> None:
    """`egosim stage` writes shard-00000.rejects.parquet beside its output: not a shard."""
    from egosim.pipeline.runner import plan_stage, run_tasks_here

    output = tmp_path / "run" / "encode" / "shard-00000.parquet"
    task = plan_stage("encode", {"preset": "tiny"}, output, inputs={"pack": tiny_runs["pack"]})
    run_tasks_here([task])
    assert (output.parent / "shard-00000.rejects.parquet").is_file()
    for path in (tmp_path / "run", output.parent):
        data = open_training_data(path)
        assert isinstance(data, LatentsDataset) and data.clip_ids == ["c0", "c1"]


def _config(**kw) -> TrainConfig:
    base = {
        "steps": 2,
        "optim": OptimConfig(warmup_steps=1),
        "preview_steps": 0,
        "cond_dropout": 0.0,
        "checkpoint_every": 0,
    }
    return TrainConfig(**{**base, **kw})


def test_tiny_training_from_latents_equals_training_on_the_fly(tiny_runs, tmp_path: Path) -> None:
    fly = train(_config(), PackDataset(tiny_runs["pack"]), tmp_path / "fly")
    pre = train(_config(), open_training_data(tiny_runs["run"]), tmp_path / "pre")
    assert len(pre.losses) == 2 and np.all(np.isfinite(pre.losses))
    assert pre.losses == fly.losses  # float32 latents of a deterministic VAE: bit-exact


def _train_tiny_wan_from_latents(run: Path, folder: Path, out: Path):
    data = open_training_data(run)
    assert isinstance(data, LatentsDataset)
    optim = OptimConfig(lr=1e-2, warmup_steps=1)
    config = _config(preset="tiny-wan", steps=1, weights_dir=str(folder), optim=optim)
    return data, config, train(config, data, out)


def test_tiny_wan_trains_one_step_with_features_from_the_shard(
    wan_folder: Path, tmp_path: Path
) -> None:
    pack = write_pack(tmp_path / "pack.parquet", [pack_row("c0", seed=0)])
    run = _encode_run(tmp_path / "run", pack, preset="tiny-wan", weights_dir=str(wan_folder))
    data, config, pre = _train_tiny_wan_from_latents(run, wan_folder, tmp_path / "pre")
    assert np.isfinite(pre.losses[0])
    stored = data[0]
    assert stored.text_embedding.shape[1] == 32 and stored.image_embedding.shape == (257, 32)
    # The image branch was trained: its key projection (input: the CLIP features) moved.
    init = build_model("tiny-wan", str(wan_folder), seed=config.seed).denoiser
    key = "transformer.blocks.0.attn2.add_k_proj.weight"
    before, after = (
        dict(init.named_parameters())[key],
        dict(pre.bundle.denoiser.named_parameters())[key],
    )
    assert not torch.allclose(before, after.detach().cpu())
    # On the fly: pixel sample, frozen encoders run inside the step; the same loss.
    enc = load_encoders("tiny-wan", EncoderFolders.from_root(wan_folder))
    pixel = PackDataset(pack)[0]
    (features,) = enc.encode([pixel], ["c0"])
    sample = TrainingSample(
        **{
            f: getattr(pixel, f)
            for f in ("target_video", "scene_video", "visibility", "skeleton_video")
        },
        first_frame=pixel.first_frame,
        prompt=pixel.prompt,
        text_embedding=features.text_embedding,
        image_embedding=features.image_embedding,
    )
    fly = train(config, [sample], tmp_path / "fly")
    assert fly.losses == pytest.approx(pre.losses, rel=1e-6, abs=0)  # float32 storage: same inputs


@pytest.mark.slow
def test_wan_clip_size_pack_encodes_and_trains_one_step(wan_folder: Path, tmp_path: Path) -> None:
    """Done-when: a 61x480x832 pack (a synthetic-world clip) -> encode with tiny random Wan
    encoders -> one training step of tiny-wan on the latents shard (5-13 min on one shared core:
    the tiny random Wan VAE takes about 1 s per 480x832 frame on CPU, three videos per clip)."""
    from egosim.world import WorldConfig, render_clip

    t, h, w = 61, 480, 832
    clip = render_clip(WorldConfig(seed=0, height=h, width=w, num_frames=t))
    skeleton = np.repeat(clip.hand_mask[..., None], 3, axis=-1) * np.uint8(255)
    row = {
        **pack_row("world-0", t=1 + 4, h=16, w=16),  # the non-video columns
        "clip_id": "world-0",
        "num_frames": t,
        "height": h,
        "width": w,
        "frame_indices": list(range(t)),
        "intrinsics": [float(v) for v in clip.intrinsics],
        "target_video": media.encode_rgb_video(clip.frames, 16.0),
        "scene_video": media.encode_rgb_video(clip.static_frames, 16.0),
        "visible": media.encode_mask_video((clip.static_depth > 0).astype(np.uint8)),
        "skeleton_video": media.encode_rgb_video(skeleton, 16.0),
        "first_frame": media.encode_png(clip.first_frame_clean),
        "prompt": "the right hand picks up the box",
    }
    pack = write_pack(tmp_path / "pack.parquet", [row])
    run = _encode_run(
        tmp_path / "run",
        pack,
        preset="tiny-wan",
        weights_dir=str(wan_folder),
        storage_dtype="bfloat16",
    )
    data, _, result = _train_tiny_wan_from_latents(run, wan_folder, tmp_path / "train")
    assert data.sizes == [(t, h, w)] and data.latent_sizes == [(16, 60, 104)]
    assert data[0].image_embedding.shape == (257, 32)
    assert data[0].text_embedding.shape == (len("the right hand picks up the box") + 1, 32)
    assert result.step == 1 and np.isfinite(result.losses[0])


def test_training_refuses_latents_of_another_preset(tiny_runs: dict[str, Path]) -> None:
    from egosim.stages.train.run import check_data

    latents = open_training_data(tiny_runs["run"])
    check_data(latents, _config())  # tiny latents, tiny training: fine
    with pytest.raises(TrainingDataError, match="encoded for preset 'tiny'"):
        check_data(latents, _config(preset="tiny-wan"))
