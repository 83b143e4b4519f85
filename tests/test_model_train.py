"""Training loop: exact resume, checkpoint checks, run directory, LoRA, and sampling."""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import torch

from egosim.model.conditioning import TrainingSample
from egosim.model.errors import CheckpointMismatchError, MissingEmbeddingError
from egosim.model.presets import PRESETS
from egosim.model.sampler import sample
from egosim.model.train import OptimConfig, TrainConfig, latest_checkpoint, sample_stream, train


@pytest.fixture(autouse=True)
def _one_thread() -> Iterator[None]:
    """Tiny models run faster on one thread, above all on a shared, loaded machine."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def make_sample(seed: int, t: int = 5, h: int = 8, w: int = 8) -> TrainingSample:
    rng = np.random.default_rng(seed)
    target = rng.integers(0, 256, (t, h, w, 3), dtype=np.uint8)
    vis = (rng.random((t, h, w)) > 0.3).astype(np.uint8)
    skeleton = np.zeros((t, h, w, 3), np.uint8)
    skeleton[:, seed % h] = 255
    return TrainingSample(
        target_video=target,
        scene_video=target,
        visibility=vis,
        skeleton_video=skeleton,
        first_frame=target[0],
        prompt=f"pick up object {seed}",
    )


DATA = [make_sample(i) for i in range(3)]
CFG = TrainConfig(
    progress=False,
    tensorboard=False,
    steps=4,
    batch_size=2,
    grad_accum=2,
    optim=OptimConfig(lr=1e-3, warmup_steps=2),
    checkpoint_every=2,
    ema_decay=0.9,
    preview_steps=2,
)


def test_resume_is_exact(tmp_path: Path) -> None:
    full = train(CFG, DATA, tmp_path / "full")
    first = train(CFG, DATA, tmp_path / "split", max_steps=2)
    second = train(CFG, DATA, tmp_path / "split")
    assert second.resumed_from == 2
    assert len(full.losses) == 4
    assert first.losses + second.losses == full.losses  # bit-for-bit
    a = dict(full.bundle.denoiser.named_parameters())
    for n, p in second.bundle.denoiser.named_parameters():
        assert torch.equal(p, a[n]), n


def test_resume_is_exact_for_plain_iterables(tmp_path: Path) -> None:
    class Stream:
        def __iter__(self) -> Iterator[TrainingSample]:
            return iter(DATA)

    cfg = dataclasses.replace(CFG, ema_decay=None, grad_accum=1)
    full = train(cfg, Stream(), tmp_path / "full")
    first = train(cfg, Stream(), tmp_path / "split", max_steps=2)
    second = train(cfg, Stream(), tmp_path / "split")
    assert first.losses + second.losses == full.losses


def test_run_directory(tmp_path: Path) -> None:
    result = train(dataclasses.replace(CFG, steps=2), DATA, tmp_path)
    resolved = json.loads((tmp_path / "config.json").read_text())
    assert resolved["train"]["preset"] == "tiny" and resolved["preset"]["name"] == "tiny"
    lines = [json.loads(x) for x in (tmp_path / "metrics.jsonl").read_text().splitlines()]
    assert [r["step"] for r in lines] == [1, 2]
    assert {"loss", "lr", "grad_norm", "samples_per_second", "peak_memory_mb"} <= set(lines[0])
    assert lines[0]["lr"] == pytest.approx(CFG.optim.lr / 2)  # warmup
    assert (tmp_path / "previews" / "step_00000002.png").stat().st_size > 0
    ckpt = latest_checkpoint(tmp_path)
    assert ckpt.name == "step_00000002" and ckpt.is_dir()
    assert {p.name for p in ckpt.iterdir()} == {
        "model.safetensors",
        "ema.safetensors",
        "optimizer.safetensors",
        "state.json",
        "rng-rank0.json",
    }
    assert np.isfinite(result.losses).all()


def test_checkpoint_from_another_preset_is_refused(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    tiny = PRESETS["tiny"]
    other = dataclasses.replace(
        tiny, name="tiny-wide", transformer=dataclasses.replace(tiny.transformer, ffn_dim=64)
    )
    monkeypatch.setitem(PRESETS, "tiny-wide", other)
    train(dataclasses.replace(CFG, preset="tiny-wide", steps=1), DATA, tmp_path)
    with pytest.raises(CheckpointMismatchError, match=r"'tiny-wide'.*'tiny'"):
        train(dataclasses.replace(CFG, steps=2), DATA, tmp_path)
    # same preset name, different trainable layout (LoRA vs full)
    with pytest.raises(CheckpointMismatchError, match="finetune"):
        train(dataclasses.replace(CFG, preset="tiny-wide", finetune="lora"), DATA, tmp_path)


def test_lora_training_only_moves_adapters_and_patch_embedding(tmp_path: Path) -> None:
    cfg = dataclasses.replace(CFG, finetune="lora", steps=2, ema_decay=None)
    result = train(cfg, DATA, tmp_path)
    den = result.bundle.denoiser
    trainable = {n for n, p in den.named_parameters() if p.requires_grad}
    assert any(".lora_A." in n for n in trainable) and any(".lora_B." in n for n in trainable)
    assert "transformer.patch_embedding.weight" in trainable
    assert not any(n.endswith("attn1.to_q.base_layer.weight") for n in trainable)
    assert (tmp_path / "lora" / "pytorch_lora_weights.safetensors").is_file()


def test_sample_makes_a_video_and_uses_guidance() -> None:
    from egosim.model.network import build_model

    bundle = build_model("tiny")
    s = DATA[0]
    video = sample(bundle, s, steps=3)
    assert video.shape == (5, 8, 8, 3) and video.dtype == np.uint8
    again = sample(bundle, s.conditions(), steps=3)
    assert np.array_equal(video, again)  # deterministic given the seed
    guided = sample(bundle, [s, DATA[1]], steps=3, guidance_scale=3.0)
    assert guided.shape == (2, 5, 8, 8, 3)


def test_sample_stream_orders() -> None:
    seq = list(range(5))
    a = sample_stream(seq, 0, 0)
    first = [next(a) for _ in range(12)]
    assert sorted(first[:5]) == seq and sorted(first[5:10]) == seq
    b = sample_stream(seq, 0, 7)
    assert [next(b) for _ in range(5)] == first[7:12]


def test_wan_presets_demand_precomputed_embeddings(tmp_path: Path) -> None:
    from egosim.model.network import EgoSimDenoiser, build_transformer
    from egosim.model.text import PrecomputedTextEncoder, prompt_key

    preset = PRESETS["wan2.1-fun-1.3b-inp"]
    text = PrecomputedTextEncoder(4096, 512, tmp_path)
    den = EgoSimDenoiser(preset, build_transformer(preset, device="meta"), text)
    with pytest.raises(MissingEmbeddingError, match="image_embedding"):
        den.image_context([None])
    with pytest.raises(MissingEmbeddingError, match=prompt_key("open the drawer")):
        text(["open the drawer"])
    torch.save(torch.ones(7, 4096), tmp_path / f"{prompt_key('open the drawer')}.pt")
    ctx = text(["open the drawer", ""])
    assert ctx.shape == (2, 512, 4096)
    assert ctx[0, :7].eq(1).all() and ctx[0, 7:].eq(0).all() and ctx[1].eq(0).all()


def test_progress_bar_tensorboard_and_wandb_guard(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    from egosim.model.errors import ModelConfigError

    cfg = dataclasses.replace(CFG, steps=2, progress=True, tensorboard=True, preview_steps=2)
    result = train(cfg, DATA, tmp_path)
    err = capsys.readouterr().err
    assert "2/2" in err and "samples/s" in err and "s/step" in err  # the rich bar, on stderr
    events = EventAccumulator(str(tmp_path / "tensorboard"))
    events.Reload()
    logged = [e.value for e in events.Scalars("train/loss")]
    np.testing.assert_allclose(logged, result.losses, rtol=1e-6)  # float32 in the event file
    assert [e.step for e in events.Scalars("train/lr")] == [1, 2]
    assert events.Images("preview")[-1].step == 2
    # W&B: "auto" is off without wandb installed; asking for it then is an error
    try:
        import wandb  # noqa: F401
    except ImportError:
        with pytest.raises(ModelConfigError, match="wandb is not installed"):
            train(dataclasses.replace(cfg, wandb="offline", steps=3), DATA, tmp_path)
    with pytest.raises(ModelConfigError, match="wandb must be one of"):
        dataclasses.replace(cfg, wandb="online")


def test_old_single_file_checkpoint_is_not_resumed(tmp_path: Path) -> None:
    from egosim.model.checkpoint import save_tree

    save_tree(tmp_path / "checkpoints" / "step_00000001.safetensors", {"model": {}}, 2)
    with pytest.raises(CheckpointMismatchError, match=r"format 2.*--fresh"):
        train(CFG, DATA, tmp_path)


def test_configs_saved_with_flat_optimiser_names_still_load() -> None:
    """Runs saved before the ``optim`` group wrote lr, warmup_steps, ... at the top level."""
    import dataclasses

    from egosim.model.inference import config_from_dict

    saved = dataclasses.asdict(CFG)
    flat = {k: v for k, v in saved.items() if k != "optim"}
    flat.update({"lr": 3e-4, "warmup_steps": 5, "betas": [0.8, 0.95], "grad_clip": 0.5})
    old = config_from_dict(flat)
    assert old.optim == OptimConfig(lr=3e-4, warmup_steps=5, betas=(0.8, 0.95), grad_clip=0.5)
    assert config_from_dict(saved) == CFG  # the current layout round-trips


def test_truncated_checkpoint_file_is_refused_before_loading(tmp_path: Path) -> None:
    from egosim.model.distributed import DistContext, load_tensors, save_tensors

    one = DistContext(0, 1, 0, torch.device("cpu"))
    save_tensors(tmp_path, {"model": {"w": torch.arange(64.0)}}, one)
    target = {"model": {"w": torch.zeros(64)}}
    load_tensors(tmp_path, target, one)
    assert torch.equal(target["model"]["w"], torch.arange(64.0))
    file = tmp_path / "model.safetensors"
    file.write_bytes(file.read_bytes()[:-8])  # a copy cut short
    with pytest.raises(CheckpointMismatchError, match="truncated"):
        load_tensors(tmp_path, {"model": {"w": torch.zeros(64)}}, one)
