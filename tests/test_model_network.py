"""Building presets (meta device, parameter counts), 36 -> 52 widening, weights-folder checks,
and LoRA."""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator
from pathlib import Path

import pytest
import torch

from egosim.model.conditioning import assemble_input
from egosim.model.errors import UnknownPresetError, WeightsMismatchError
from egosim.model.lora import LoRAConfig, apply_lora, merge_lora
from egosim.model.network import (
    build_model,
    build_transformer,
    count_parameters,
    load_transformer,
    save_transformer_folder,
)
from egosim.model.presets import PRESETS, get_preset


@pytest.fixture(autouse=True)
def _one_thread() -> Iterator[None]:
    """Tiny models run faster on one thread, above all on a shared, loaded machine."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


# Wan2.1 T2V-1.3B transformer (16 input channels, no image branch): 1,418,996,800 parameters, the
# count other public code pins for the released checkpoint (as it pins 126,892,531 for the VAE).
# The InP counts are what the published Fun-InP / I2V configs (in 36, CLIP image_dim 1280, added
# K/V) give with diffusers' WanTransformer3DModel; no exact published figure was found offline.
WAN_T2V_1_3B_PARAMS = 1_418_996_800
WAN_FUN_1_3B_INP_PARAMS = 1_564_428_608
WAN_FUN_14B_INP_PARAMS = 16_394_878_784


def _inputs(model: torch.nn.Module, in_channels: int, seed: int = 0) -> dict:
    g = torch.Generator().manual_seed(seed)
    cfg = model.config
    return {
        "hidden_states": torch.randn(2, in_channels, 3, 8, 8, generator=g),
        "timestep": torch.tensor([100.0, 700.0]),
        "encoder_hidden_states": torch.randn(2, 16, cfg.text_dim, generator=g),
        "return_dict": False,
    }


def test_wan_presets_build_on_meta_with_published_counts() -> None:
    p13 = get_preset("wan2.1-fun-1.3b-inp")
    base = dataclasses.replace(p13.transformer, image_dim=None, added_kv_proj_dim=None)
    t2v = build_transformer(dataclasses.replace(p13, transformer=base), 16, device="meta")
    assert count_parameters(t2v) == WAN_T2V_1_3B_PARAMS
    for name, published in (
        ("wan2.1-fun-1.3b-inp", WAN_FUN_1_3B_INP_PARAMS),
        ("wan2.1-fun-14b-inp", WAN_FUN_14B_INP_PARAMS),
    ):
        preset = get_preset(name)
        assert preset.published_param_count == published
        m36 = build_transformer(preset, 36, device="meta")
        m52 = build_transformer(preset, 52, device="meta")
        assert m52.patch_embedding.weight.is_meta
        assert count_parameters(m36) == published
        # widening adds exactly 16 input channels x inner_dim x (1*2*2) weights
        assert count_parameters(m52) - published == 16 * preset.transformer.inner_dim * 4


def test_unknown_preset() -> None:
    with pytest.raises(UnknownPresetError, match="known"):
        get_preset("wan-huge")


def test_widening_keeps_a_pretrained_model_unchanged(tmp_path: Path) -> None:
    torch.manual_seed(0)
    pretrained = build_transformer("tiny", in_channels=36).eval()
    with torch.no_grad():  # give every weight a non-trivial value, as after pretraining
        for p in pretrained.parameters():
            p.add_(0.05 * torch.randn_like(p))
    save_transformer_folder(pretrained, tmp_path)
    widened = load_transformer("tiny", tmp_path).eval()
    assert widened.patch_embedding.in_channels == 52 and widened.config.in_channels == 52
    inp = _inputs(pretrained, 36)
    with torch.no_grad():
        ref = pretrained(**inp)[0]
        zeros = torch.zeros(2, 16, 3, 8, 8)
        out0 = widened(**{**inp, "hidden_states": assemble_input(inp["hidden_states"], zeros)})[0]
        other = torch.randn(2, 16, 3, 8, 8)
        out1 = widened(**{**inp, "hidden_states": assemble_input(inp["hidden_states"], other)})[0]
    torch.testing.assert_close(out0, ref, rtol=0, atol=1e-6)
    torch.testing.assert_close(out1, ref, rtol=0, atol=1e-6)  # new weights are exactly zero
    # the new channels do get gradients (they can learn the skeleton condition)
    widened.train()
    out = widened(**{**inp, "hidden_states": assemble_input(inp["hidden_states"], other)})[0]
    out.square().mean().backward()
    assert widened.patch_embedding.weight.grad[:, 36:].abs().sum() > 0


def test_wrong_shaped_folder_names_the_tensor(tmp_path: Path) -> None:
    spec = dataclasses.replace(PRESETS["tiny"].transformer, ffn_dim=96)
    other = build_transformer(dataclasses.replace(PRESETS["tiny"], transformer=spec), 36)
    save_transformer_folder(other, tmp_path)
    with pytest.raises(WeightsMismatchError, match=r"blocks\.0\.ffn\.net\.0\.proj\.weight"):
        load_transformer("tiny", tmp_path)
    with pytest.raises(WeightsMismatchError, match=r"no \.safetensors"):
        load_transformer("tiny", tmp_path / "empty")


def test_wan_preset_needs_a_weights_folder() -> None:
    with pytest.raises(WeightsMismatchError, match="weights_dir"):
        build_model("wan2.1-fun-1.3b-inp")


def test_lora_starts_identical_and_merges() -> None:
    bundle = build_model("tiny")
    model = bundle.denoiser.transformer.eval()
    inp = _inputs(model, 52)
    with torch.no_grad():
        ref = model(**inp)[0]
    wrapped = apply_lora(model, LoRAConfig(rank=4, alpha=4))
    assert any(n.endswith("attn1.to_q") for n in wrapped)
    trainable = {n for n, p in model.named_parameters() if p.requires_grad}
    assert trainable and all(
        (".lora_A." in n or ".lora_B." in n or n.startswith("patch_embedding")) for n in trainable
    )
    assert "patch_embedding.weight" in trainable  # DWM: input projection trained too
    with torch.no_grad():
        torch.testing.assert_close(model(**inp)[0], ref, rtol=0, atol=0)  # B = 0 at start
        for n, p in model.named_parameters():
            if ".lora_B." in n:  # peft's up projection (zero at start)
                p.normal_(0, 0.1)
        adapted = model(**inp)[0]
        assert not torch.allclose(adapted, ref)
        assert merge_lora(model) == len(wrapped)
        torch.testing.assert_close(model(**inp)[0], adapted, rtol=1e-4, atol=1e-5)


def test_wan_vae_count_and_wrapper(tmp_path: Path) -> None:
    from diffusers import AutoencoderKLWan

    from egosim.model.vae import build_vae

    with torch.device("meta"):
        full = AutoencoderKLWan()  # Wan2.1 VAE defaults
    assert count_parameters(full) == 126_892_531  # the released Wan2.1 VAE
    torch.manual_seed(0)
    AutoencoderKLWan(base_dim=8, dim_mult=[1, 1, 1, 1], num_res_blocks=1).save_pretrained(
        tmp_path / "vae"
    )
    vae = build_vae(get_preset("wan2.1-fun-1.3b-inp"), tmp_path)
    z = vae.encode(torch.rand(1, 3, 5, 16, 16) * 2 - 1)
    assert z.shape == (1, 16, 2, 2, 2)  # 1 + 4k frames -> 1 + k; 8x spatial
    assert vae.decode(z).shape == (1, 3, 5, 16, 16)
