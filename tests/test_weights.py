"""Published weights: the original <-> diffusers key map, layout detection and refusal, the
header-only folder check (`egosim weights check`), and exporting a trained run as a diffusers
folder (`egosim weights export`)."""

from __future__ import annotations

import dataclasses
import json
import math
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import torch
from diffusers import WanTransformer3DModel
from safetensors.torch import save_file
from typer.testing import CliRunner

from egosim.model.conditioning import TrainingSample, assemble_input
from egosim.model.errors import WeightsMismatchError
from egosim.model.inference import load_trained
from egosim.model.network import build_transformer, count_parameters, load_transformer
from egosim.model.presets import PRESETS, ModelPreset, TextSpec
from egosim.model.train import OptimConfig, TrainConfig, train
from egosim.model.weights import (
    EXPORT_RECORD,
    LAYOUT_DIFFUSERS,
    LAYOUT_ORIGINAL,
    check_weights_folder,
    diffusers_to_original,
    export_transformer,
    original_to_diffusers,
    read_weights_folder,
)
from egosim.pipeline.cli import app


@pytest.fixture(autouse=True)
def _one_thread() -> Iterator[None]:
    """Tiny models run faster on one thread, above all on a shared, loaded machine."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


# A tiny Fun-InP-shaped preset: the tiny transformer plus Wan's CLIP image branch (image_dim,
# added K/V), so every original-layout key family (img_emb, k_img, norm_k_img) is exercised.
TINY_INP = dataclasses.replace(
    PRESETS["tiny"],
    name="tiny-inp",
    transformer=dataclasses.replace(
        PRESETS["tiny"].transformer, image_dim=24, added_kv_proj_dim=256
    ),
    text=TextSpec(kind="hashed", max_tokens=512, vocab_size=64),
)

# Original (Wan / VideoX-Fun) names written out by hand from Wan's `WanModel` (wan/modules/
# model.py): the ground truth the key map must produce, including the norm2/norm3 swap.
ORIGINAL_NAMES = {
    "patch_embedding.weight": "patch_embedding.weight",
    "text_embedding.0.weight": "condition_embedder.text_embedder.linear_1.weight",
    "text_embedding.2.bias": "condition_embedder.text_embedder.linear_2.bias",
    "time_embedding.0.weight": "condition_embedder.time_embedder.linear_1.weight",
    "time_projection.1.weight": "condition_embedder.time_proj.weight",
    "img_emb.proj.0.weight": "condition_embedder.image_embedder.norm1.weight",
    "img_emb.proj.1.weight": "condition_embedder.image_embedder.ff.net.0.proj.weight",
    "img_emb.proj.3.bias": "condition_embedder.image_embedder.ff.net.2.bias",
    "img_emb.proj.4.weight": "condition_embedder.image_embedder.norm2.weight",
    "blocks.0.modulation": "blocks.0.scale_shift_table",
    "blocks.1.self_attn.q.weight": "blocks.1.attn1.to_q.weight",
    "blocks.0.self_attn.o.bias": "blocks.0.attn1.to_out.0.bias",
    "blocks.0.self_attn.norm_k.weight": "blocks.0.attn1.norm_k.weight",
    "blocks.0.cross_attn.v.weight": "blocks.0.attn2.to_v.weight",
    "blocks.0.cross_attn.k_img.weight": "blocks.0.attn2.add_k_proj.weight",
    "blocks.1.cross_attn.v_img.bias": "blocks.1.attn2.add_v_proj.bias",
    "blocks.0.cross_attn.norm_k_img.weight": "blocks.0.attn2.norm_added_k.weight",
    "blocks.0.norm3.weight": "blocks.0.norm2.weight",
    "blocks.1.norm3.bias": "blocks.1.norm2.bias",
    "blocks.0.ffn.0.weight": "blocks.0.ffn.net.0.proj.weight",
    "blocks.0.ffn.2.bias": "blocks.0.ffn.net.2.bias",
    "head.head.weight": "proj_out.weight",
    "head.modulation": "scale_shift_table",
}


def _randomised(preset: ModelPreset, in_channels: int, seed: int = 0) -> WanTransformer3DModel:
    """A model of ``preset`` whose every parameter is random (norm gains and tables too)."""
    torch.manual_seed(seed)
    model = build_transformer(preset, in_channels).eval()
    with torch.no_grad():
        for p in model.parameters():
            p.add_(0.1 * torch.randn_like(p))
    return model


def _inputs(model: WanTransformer3DModel, in_channels: int, seed: int = 1) -> dict:
    g = torch.Generator().manual_seed(seed)
    cfg = model.config
    inputs = {
        "hidden_states": torch.randn(2, in_channels, 3, 8, 8, generator=g),
        "timestep": torch.tensor([100.0, 700.0]),
        "encoder_hidden_states": torch.randn(2, 512, cfg.text_dim, generator=g),
        "return_dict": False,
    }
    if cfg.image_dim:
        inputs["encoder_hidden_states_image"] = torch.randn(2, 257, cfg.image_dim, generator=g)
    return inputs


def _write_original(model: WanTransformer3DModel, folder: Path, prefix: str = "") -> Path:
    """Save ``model`` in the original key layout, split over two shard files like a release."""
    state = diffusers_to_original(model.state_dict())
    keys = sorted(state)
    folder.mkdir(parents=True, exist_ok=True)
    half = len(keys) // 2
    for i, part in enumerate((keys[:half], keys[half:])):
        name = f"diffusion_pytorch_model-{i + 1:05d}-of-00002.safetensors"
        save_file({prefix + k: state[k].contiguous() for k in part}, folder / name)
    return folder


def test_key_map_matches_the_wan_names_and_diffusers_own_converter() -> None:
    model = _randomised(TINY_INP, 36)
    diffusers_state = model.state_dict()
    original = diffusers_to_original(diffusers_state)
    assert len(original) == len(diffusers_state)
    for orig_name, diff_name in ORIGINAL_NAMES.items():
        assert torch.equal(original[orig_name], diffusers_state[diff_name]), orig_name
    # Same tensors, same shapes: no fused or transposed tensor in Wan2.1.
    back = original_to_diffusers(original)
    assert back.keys() == diffusers_state.keys()
    assert all(back[k] is diffusers_state[k] for k in back)
    # An independent implementation (diffusers' single-file loader) agrees name for name.
    from diffusers.loaders.single_file_utils import convert_wan_transformer_to_diffusers

    theirs = convert_wan_transformer_to_diffusers(dict(original))
    assert theirs.keys() == diffusers_state.keys()
    assert all(torch.equal(theirs[k], diffusers_state[k]) for k in theirs)


@pytest.mark.parametrize("prefix", ["", "model.diffusion_model."])
def test_original_layout_folder_loads_and_matches_the_source_model(
    tmp_path: Path, prefix: str
) -> None:
    source = _randomised(TINY_INP, 36)
    folder = _write_original(source, tmp_path / "fun-inp", prefix)
    read = read_weights_folder(folder)
    assert read.layout == LAYOUT_ORIGINAL and read.prefix == prefix
    assert read.parameter_count() == count_parameters(source)
    inputs = _inputs(source, 36)
    with torch.no_grad():
        ref = source(**inputs)[0]
        # Converted at the published width: the same function (tolerance 1e-6: same ops).
        same = load_transformer(TINY_INP, folder, in_channels=36).eval()
        torch.testing.assert_close(same(**inputs)[0], ref, rtol=0, atol=1e-6)
        # Converted, then widened 36 -> 52: new channels have zero weights, whatever they hold.
        wide = load_transformer(TINY_INP, folder).eval()
        assert wide.config.in_channels == 52
        extra = torch.randn(2, 16, 3, 8, 8)
        widened_in = {**inputs, "hidden_states": assemble_input(inputs["hidden_states"], extra)}
        torch.testing.assert_close(wide(**widened_in)[0], ref, rtol=0, atol=1e-6)


def test_a_folder_of_neither_layout_is_refused_naming_file_and_keys(tmp_path: Path) -> None:
    state = diffusers_to_original(_randomised(TINY_INP, 36).state_dict())
    state["blocks.0.self_attn.qkv.weight"] = torch.zeros(3, 3)  # fused: no such key in Wan2.1
    state["pos_embed"] = torch.zeros(4)
    folder = tmp_path / "odd"
    folder.mkdir()
    save_file(state, folder / "model.safetensors")
    with pytest.raises(WeightsMismatchError) as info:
        load_transformer(TINY_INP, folder)
    message = str(info.value)
    assert "model.safetensors" in message and "closest is original" in message
    assert "blocks.0.self_attn.qkv.weight" in message and "pos_embed" in message
    # keys of both layouts in one folder are refused too
    mixed = tmp_path / "mixed"
    mixed.mkdir()
    save_file({"blocks.0.attn1.to_q.weight": torch.zeros(2)}, mixed / "a.safetensors")
    save_file({"blocks.0.self_attn.k.weight": torch.zeros(2)}, mixed / "b.safetensors")
    with pytest.raises(WeightsMismatchError, match=r"b\.safetensors.*self_attn\.k"):
        read_weights_folder(mixed)


def test_a_folder_of_pickles_is_refused_without_opening_them(tmp_path: Path) -> None:
    (tmp_path / "diffusion_pytorch_model.bin").write_bytes(b"\x80\x04 not opened")
    with pytest.raises(WeightsMismatchError, match=r"no \.safetensors.*diffusion_pytorch_model"):
        read_weights_folder(tmp_path)


def test_a_truncated_file_is_refused_before_loading(tmp_path: Path) -> None:
    build_transformer("tiny", 36).save_pretrained(tmp_path)
    path = tmp_path / "diffusion_pytorch_model.safetensors"
    with path.open("r+b") as f:
        f.truncate(path.stat().st_size - 10)  # a download cut short
    with pytest.raises(WeightsMismatchError, match=r"diffusion_pytorch_model.*truncated"):
        check_weights_folder(tmp_path)
    path.write_bytes(b"\xff" * 16)
    with pytest.raises(WeightsMismatchError, match="not a safetensors file"):
        read_weights_folder(tmp_path)


def _write_header_only(shapes: dict[str, tuple[int, ...]], path: Path) -> int:
    """A valid bf16 safetensors file whose data is a hole (sparse): only the header is real."""
    header, offset = {}, 0
    for name in sorted(shapes):
        size = 2 * math.prod(shapes[name])
        header[name] = {
            "dtype": "BF16",
            "shape": list(shapes[name]),
            "data_offsets": [offset, offset + size],
        }
        offset += size
    blob = json.dumps(header, separators=(",", ":")).encode()
    blob += b" " * (-len(blob) % 8)
    with path.open("wb") as f:
        f.write(len(blob).to_bytes(8, "little") + blob)
        f.truncate(8 + len(blob) + offset)  # no data written: the file is sparse
    return offset


def test_check_reads_only_headers_of_a_14b_folder(tmp_path: Path) -> None:
    meta = build_transformer("wan2.1-fun-14b-inp", 36, device="meta")
    shapes = {k: tuple(v.shape) for k, v in diffusers_to_original(meta.state_dict()).items()}
    folder = tmp_path / "Wan2.1-Fun-14B-InP"
    folder.mkdir()
    data_bytes = _write_header_only(shapes, folder / "diffusion_pytorch_model.safetensors")
    assert data_bytes > 30e9  # 16.4 B parameters in bf16, never written nor read
    start = time.perf_counter()
    report = check_weights_folder(folder)
    seconds = time.perf_counter() - start
    assert seconds < 20  # headers and a meta-device build per preset, no tensor read
    assert report.weights.layout == LAYOUT_ORIGINAL
    assert report.weights.parameter_count() == PRESETS["wan2.1-fun-14b-inp"].published_param_count
    assert report.weights.dtype_counts() == {"BF16": report.weights.parameter_count()}
    assert report.fits == ["wan2.1-fun-14b-inp"]
    assert report.dims["in_channels"] == 36 and report.dims["inner_dim"] == 5120
    assert report.dims["num_layers"] == 40 and report.dims["image_dim"] == 1280
    assert "the preset expects (1, 2, 1536)" in report.problems["wan2.1-fun-1.3b-inp"]
    result = CliRunner().invoke(app, ["weights", "check", str(folder)])
    assert result.exit_code == 0, result.output
    assert "layout: original" in result.output
    assert "fits preset wan2.1-fun-14b-inp (patch embedding widened 36 -> 52)" in result.output


def test_check_cli_exit_codes(tmp_path: Path) -> None:
    tiny = tmp_path / "tiny"
    build_transformer("tiny", 36).save_pretrained(tiny / "transformer")
    report = check_weights_folder(tiny)
    assert report.weights.layout == LAYOUT_DIFFUSERS and report.fits == ["tiny"]
    assert report.weights.dtype_counts() == {"F32": report.weights.parameter_count()}
    runner = CliRunner()
    assert runner.invoke(app, ["weights", "check", str(tiny)]).exit_code == 0
    # a folder that reads but fits no preset: exit 2 with the reason per preset
    spec = dataclasses.replace(PRESETS["tiny"].transformer, ffn_dim=96)
    other = tmp_path / "other"
    build_transformer(dataclasses.replace(PRESETS["tiny"], transformer=spec), 36).save_pretrained(
        other
    )
    result = runner.invoke(app, ["weights", "check", str(other)])
    assert result.exit_code == 2
    assert "fits no preset" in result.output and "ffn.net.0.proj.weight" in result.output
    # no safetensors at all: exit 2 naming the folder
    empty = tmp_path / "empty"
    empty.mkdir()
    result = runner.invoke(app, ["weights", "check", str(empty)])
    assert result.exit_code == 2 and "no .safetensors" in result.output


def _sample(seed: int) -> TrainingSample:
    rng = np.random.default_rng(seed)
    target = rng.integers(0, 256, (5, 8, 8, 3), dtype=np.uint8)
    return TrainingSample(
        target_video=target,
        scene_video=target,
        visibility=(rng.random((5, 8, 8)) > 0.3).astype(np.uint8),
        skeleton_video=np.zeros((5, 8, 8, 3), np.uint8),
        first_frame=target[0],
        prompt=f"move object {seed}",
    )


@pytest.mark.parametrize("finetune", ["full", "lora"])
def test_export_round_trips_a_trained_run(tmp_path: Path, finetune: str) -> None:
    config = TrainConfig(
        steps=2,
        optim=OptimConfig(lr=1e-2, warmup_steps=1),
        ema_decay=0.5,
        preview_steps=0,
        finetune=finetune,
    )
    if finetune == "lora":
        config = dataclasses.replace(config, lora=dataclasses.replace(config.lora, rank=4))
    run = tmp_path / "run"
    train(config, [_sample(0), _sample(1)], run)
    out = export_transformer(run, tmp_path / "export")
    exported = WanTransformer3DModel.from_pretrained(out).eval()
    record = json.loads((out / EXPORT_RECORD).read_text())
    assert record["step"] == 2 and record["ema"] is True and record["preset"] == "tiny"
    trained = load_trained(run, device="cpu").bundle.denoiser.transformer.eval()  # EMA weights
    inputs = _inputs(trained, 52)
    inputs["encoder_hidden_states"] = inputs["encoder_hidden_states"][:, :16]
    with torch.no_grad():
        ref = trained(**inputs)[0]
        # full: the same tensors; LoRA: adapters merged into the base weights (float rounding)
        torch.testing.assert_close(exported(**inputs)[0], ref, rtol=0, atol=1e-5)
        # and egosim's own loader reads the export as a tiny folder
        again = load_transformer("tiny", out).eval()
        torch.testing.assert_close(again(**inputs)[0], ref, rtol=0, atol=1e-5)
        # the weights moved away from the initialisation (the test would catch a stale export)
        fresh = build_transformer("tiny").eval()
        assert (fresh(**inputs)[0] - ref).abs().max() > 1e-3
    with pytest.raises(WeightsMismatchError, match="already exists"):
        export_transformer(run, out)


def test_export_cli(tmp_path: Path) -> None:
    config = TrainConfig(steps=1, preview_steps=0)
    run = tmp_path / "run"
    train(config, [_sample(0)], run)
    runner = CliRunner()
    result = runner.invoke(app, ["weights", "export", str(run), "--out", str(tmp_path / "x")])
    assert result.exit_code == 0, result.output
    assert (tmp_path / "x" / "config.json").is_file()
    result = runner.invoke(app, ["weights", "export", str(tmp_path / "nothing"), "--out", "y"])
    assert result.exit_code == 2 and "no checkpoint" in result.output
