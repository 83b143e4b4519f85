"""LoRA through peft: a trained run's adapters load into a tiny Wan with diffusers' own loader.

Tolerance: diffusers rebuilds the same peft layers from the saved tensors (and the LoRA config in
the file's header), so the outputs should agree to float32 rounding; we allow 1e-5 absolute on
outputs of magnitude ~1, and check that the adapters moved the output by far more than that.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors import safe_open

from egosim.model.conditioning import TrainingSample
from egosim.model.lora import LORA_WEIGHTS, PATCH_EMBEDDING_WEIGHTS, load_patch_embedding
from egosim.model.network import build_model
from egosim.model.train import TrainConfig, train
from egosim.pipeline.stage import build_config

OUTPUT_ATOL = 1e-5  # diffusers-loaded vs egosim-trained transformer outputs


def _sample(seed: int) -> TrainingSample:
    rng = np.random.default_rng(seed)
    target = rng.integers(0, 256, (5, 8, 8, 3), dtype=np.uint8)
    return TrainingSample(
        target_video=target,
        scene_video=target,
        visibility=np.ones((5, 8, 8), np.uint8),
        skeleton_video=np.zeros((5, 8, 8, 3), np.uint8),
        first_frame=target[0],
        prompt=f"move object {seed}",
    )


@pytest.fixture(scope="module")
def lora_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, torch.nn.Module]:
    """Two LoRA steps (rank 4, alpha 8: scale 2, so a loader ignoring alpha would be caught)."""
    torch.set_num_threads(1)
    config = build_config(
        TrainConfig,
        {
            "finetune": "lora",
            "lora.rank": "4",
            "lora.alpha": "8",
            "steps": "2",
            "optim.lr": "1e-2",
            "optim.warmup_steps": "0",
            "preview_steps": "0",
            "progress": "false",
            "tensorboard": "false",
        },
        "train",
    )
    run = tmp_path_factory.mktemp("lora") / "run"
    result = train(config, [_sample(0), _sample(1)], run)
    return run, result.bundle.denoiser.transformer.eval()


def _inputs(in_channels: int = 52) -> dict:
    g = torch.Generator().manual_seed(3)
    return {
        "hidden_states": torch.randn(1, in_channels, 2, 8, 8, generator=g),
        "timestep": torch.tensor([400.0]),
        "encoder_hidden_states": torch.randn(1, 16, 32, generator=g),
        "return_dict": False,
    }


def test_saved_lora_has_diffusers_keys_and_config(lora_run) -> None:
    run, _ = lora_run
    with safe_open(str(run / "lora" / LORA_WEIGHTS), framework="pt") as f:
        keys = list(f.keys())
        header = f.metadata()
        shape = f.get_slice("transformer.blocks.0.attn1.to_q.lora_A.weight").get_shape()
    assert keys and all(k.startswith("transformer.blocks.") for k in keys)
    assert all(".lora_A.weight" in k or ".lora_B.weight" in k for k in keys)
    # DWM's targets: self/cross attention q, k, v, out and both FFN layers, in every block
    for layer in ("attn1.to_q", "attn1.to_out.0", "attn2.to_v", "ffn.net.0.proj", "ffn.net.2"):
        assert f"transformer.blocks.1.{layer}.lora_B.weight" in keys, layer
    assert shape == [4, 256]  # rank 4 from --set lora.rank=4
    meta = json.loads(header["lora_adapter_metadata"])
    assert meta["transformer.r"] == 4 and meta["transformer.lora_alpha"] == 8
    with safe_open(str(run / "lora" / PATCH_EMBEDDING_WEIGHTS), framework="pt") as f:
        assert set(f.keys()) == {"patch_embedding.weight", "patch_embedding.bias"}


def test_diffusers_load_lora_weights_reproduces_the_trained_model(lora_run) -> None:
    from diffusers import WanPipeline

    run, trained = lora_run
    base = build_model("tiny", seed=TrainConfig().seed).denoiser.transformer.eval()
    inputs = _inputs()
    with torch.no_grad():
        before = base(**inputs)[0]
        assert load_patch_embedding(base, run / "lora")
        pipe = WanPipeline(
            tokenizer=None, text_encoder=None, vae=None, scheduler=None, transformer=base
        )
        pipe.load_lora_weights(run / "lora")  # diffusers' loader, default weight name
        loaded = base(**inputs)[0]
        ours = trained(**inputs)[0]
    assert float((loaded - ours).abs().max()) < OUTPUT_ATOL
    assert float((ours - before).abs().max()) > 100 * OUTPUT_ATOL  # training changed the output


def test_lora_config_is_checked() -> None:
    from egosim.model.errors import ModelConfigError
    from egosim.model.lora import LoRAConfig, apply_lora
    from egosim.pipeline.stage import ConfigError

    with pytest.raises(ConfigError, match="rank must be >= 1, got 0"):
        build_config(TrainConfig, {"lora.rank": "0"}, "train")
    with pytest.raises(ConfigError, match=r"parameter 'lora\.rank': .*got 'x'"):
        build_config(TrainConfig, {"lora.rank": "x"}, "train")
    model = build_model("tiny").denoiser.transformer
    with pytest.raises(ModelConfigError, match="LoRA matched no layer"):
        apply_lora(model, dataclasses.replace(LoRAConfig(), targets=("no_such_layer",)))
