"""Memory plan: parameter counts against the meta-device model, the per-block activation count
against the tensors a real diffusers Wan block saves, the sequence length, the plan's terms,
the docs table (golden), and `egosim presets`."""

from __future__ import annotations

import dataclasses
import re
from collections.abc import Iterator
from pathlib import Path

import pytest
import torch
from typer.testing import CliRunner

from egosim.model.errors import ModelConfigError
from egosim.model.memory_plan import (
    GIB,
    TrainSetup,
    block_activation_bytes,
    default_plans,
    format_table,
    latent_shape,
    parameter_count,
    plan_memory,
    sequence_length,
)
from egosim.model.network import build_transformer, count_parameters
from egosim.model.presets import PRESETS, TextSpec
from egosim.pipeline.cli import app

DOC = Path(__file__).resolve().parents[1] / "docs" / "memory_plan.md"


@pytest.fixture(autouse=True)
def _one_thread() -> Iterator[None]:
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.mark.parametrize("name", sorted(PRESETS))
@pytest.mark.parametrize("in_channels", [36, 52])
def test_parameter_counts_match_the_meta_model(name: str, in_channels: int) -> None:
    preset = PRESETS[name]
    counted = parameter_count(preset.transformer, in_channels)
    model = build_transformer(preset, in_channels, device="meta")
    assert counted.total == count_parameters(model)
    assert counted.per_block == count_parameters(model.blocks[0])
    assert counted.root == count_parameters(model) - sum(count_parameters(b) for b in model.blocks)
    if in_channels == 36 and preset.published_param_count is not None:
        assert counted.total == preset.published_param_count


def _saved_bytes(spec, batch: int, frames: int, height: int, width: int, text: int) -> int:
    """Bytes of the distinct tensors one bf16 Wan block saves for backward (weights, the block's
    own inputs and the shared rotary tables excluded), via torch's saved-tensor hooks."""
    preset = dataclasses.replace(PRESETS["tiny"], transformer=spec, text=TextSpec("hashed", 512))
    torch.manual_seed(0)
    model = build_transformer(preset, 52).to(torch.bfloat16)
    block = model.blocks[0]
    captured: dict = {}
    block.register_forward_pre_hook(lambda _m, args: captured.setdefault("args", args))
    with torch.no_grad():
        model(
            hidden_states=torch.randn(batch, 52, frames, height, width, dtype=torch.bfloat16),
            timestep=torch.full((batch,), 500.0),
            encoder_hidden_states=torch.randn(batch, text, spec.text_dim, dtype=torch.bfloat16),
            encoder_hidden_states_image=torch.randn(
                batch, 257, spec.image_dim, dtype=torch.bfloat16
            ),
        )
    args = [
        a.detach().requires_grad_(True) if torch.is_tensor(a) and a.is_floating_point() else a
        for a in captured["args"]
    ]
    excluded = {p.untyped_storage().data_ptr() for p in block.parameters()}
    excluded |= {a.untyped_storage().data_ptr() for a in args if torch.is_tensor(a)}
    excluded |= {t.untyped_storage().data_ptr() for t in args[3]}  # rotary (cos, sin)
    saved: list[torch.Tensor] = []
    with torch.autograd.graph.saved_tensors_hooks(lambda t: saved.append(t) or t, lambda t: t):
        block(*args)
    seen, total = set(), 0
    for t in saved:
        ptr = t.untyped_storage().data_ptr()
        if ptr not in excluded and ptr not in seen:
            seen.add(ptr)
            total += t.untyped_storage().nbytes()
    return total


@pytest.mark.parametrize(
    ("heads", "head_dim", "ffn", "frames", "height", "width", "text"),
    [(4, 16, 96, 2, 14, 18, 512), (6, 16, 200, 3, 10, 12, 512), (2, 40, 120, 2, 8, 22, 512)],
)
def test_block_activation_count_matches_what_a_block_saves(
    heads: int, head_dim: int, ffn: int, frames: int, height: int, width: int, text: int
) -> None:
    d = heads * head_dim
    spec = dataclasses.replace(
        PRESETS["tiny"].transformer,
        num_attention_heads=heads,
        attention_head_dim=head_dim,
        ffn_dim=ffn,
        num_layers=1,
        image_dim=24,
        added_kv_proj_dim=d,
    )
    batch = 2
    tokens = frames * (height // 2) * (width // 2)
    measured = _saved_bytes(spec, batch, frames, height, width, text)
    predicted = batch * block_activation_bytes(spec, tokens, text, 257)
    assert predicted == measured  # exact: the count is tensor by tensor


def test_latent_and_sequence_length_at_the_default_clip() -> None:
    wan = PRESETS["wan2.1-fun-14b-inp"]
    assert latent_shape(wan, 61, 480, 832) == (16, 16, 60, 104)  # 1 + 60/4 frames, /8
    assert sequence_length(wan, 61, 480, 832) == 16 * 30 * 52  # (1, 2, 2) patches
    assert latent_shape(PRESETS["tiny"], 9, 32, 32) == (16, 3, 32, 32)  # packed VAE: /1
    with pytest.raises(ModelConfigError, match=r"1 \+ 4k, got 60.*multiples of 16, got 481x832"):
        latent_shape(wan, 60, 481, 832)


def test_plan_terms() -> None:
    name = "wan2.1-fun-14b-inp"
    one = plan_memory(name, TrainSetup(batch_per_gpu=1))
    four = plan_memory(name, TrainSetup(batch_per_gpu=4))
    single = plan_memory(name, TrainSetup(num_gpus=1))
    spec = PRESETS[name].transformer
    p = one.params.total
    assert one.tokens == 24_960
    assert one.model_states == -(-p // 8) * 16  # fp32 master + grad + 2 AdamW moments, / 8
    assert single.model_states == p * 16
    assert plan_memory(name, TrainSetup(ema=True)).model_states == -(-p // 8) * 20
    assert one.checkpoints == spec.num_layers * 24_960 * spec.inner_dim * 2  # bf16 per block
    assert four.checkpoints == 4 * one.checkpoints and four.block == 4 * one.block
    assert four.model_states == one.model_states and four.gathered == one.gathered
    assert one.total == (
        one.model_states + one.gathered + one.checkpoints + one.block + one.outside + one.overhead
    )
    with pytest.raises(ModelConfigError, match="image-conditioned"):
        plan_memory("tiny")
    with pytest.raises(ModelConfigError, match="num_gpus must be >= 1, got 0"):
        TrainSetup(num_gpus=0)


def test_docs_table_is_current() -> None:
    """docs/memory_plan.md holds the tables `egosim presets --memory` prints (regenerate with
    `egosim presets --memory --markdown [--gpus 1]`, pasted between the markers)."""
    text = DOC.read_text()
    for marker, plans in (
        ("plan", default_plans()),
        ("plan-1gpu", [p for p in default_plans(1) if p.preset == "wan2.1-fun-1.3b-inp"]),
    ):
        match = re.search(rf"<!-- {marker}:begin -->\n(.*?)\n<!-- {marker}:end -->", text, re.S)
        assert match, f"docs/memory_plan.md lacks the {marker} markers"
        assert match[1].strip() == format_table(plans).strip()


def test_presets_cli_lists_every_preset() -> None:
    runner = CliRunner()
    result = runner.invoke(app, ["presets"])
    assert result.exit_code == 0, result.output
    for name, preset in PRESETS.items():
        line = next(ln for ln in result.output.splitlines() if ln.startswith(name + " "))
        total = parameter_count(preset.transformer, 52).total
        assert f"{total:,}" in line
    assert "16x16x60x104" in result.output and "24,960" in result.output
    assert "original" in result.output  # the Wan presets take either key layout
    result = runner.invoke(app, ["presets", "--memory", "--markdown"])
    assert result.exit_code == 0, result.output
    assert format_table(default_plans()) in result.output
    gib = plan_memory("wan2.1-fun-14b-inp", TrainSetup(batch_per_gpu=4)).total / GIB
    assert f"**{gib:.1f}**" in result.output
