"""Per-GPU memory of full fine-tuning, computed from parameter, optimizer and activation sizes.

Setting (the EgoSim recipe, issue 14): full fine-tuning with AdamW, FSDP2
(``fully_shard`` per transformer block and on the root) over ``num_gpus`` GPUs, bf16 compute with
fp32 master weights, gradients and moments, and activation checkpointing per block. Nothing is
allocated: parameter counts come from the preset's spec (:func:`parameter_count`, checked
against the model built on the meta device by ``tests/test_memory_plan.py``), activations from
the sequence length and a per-token count of what one diffusers ``WanTransformerBlock`` saves for
backward (:data:`BLOCK_BYTES_PER_TOKEN`, checked against the tensors a real block saves).

Per GPU, with ``P`` parameters (``P_b`` per block, ``P_r`` outside the blocks), ``N`` GPUs, ``B``
samples per GPU, ``S`` tokens per sample, ``L`` blocks of width ``D``:

- sharded model states: ``P/N * (4 master + 4 grad + 8 AdamW exp_avg/exp_avg_sq)`` bytes
  (+ ``4 P/N`` with an fp32 EMA);
- unsharded, transient: bf16 all-gathered parameters of the root and of ``1 + prefetch`` blocks
  (``2 (P_r + (1 + prefetch) P_b)``), and the gradients of the root and one block before their
  reduce-scatter (bf16, then an fp32 copy to reduce: ``6 (P_r + P_b)``);
- checkpointed block inputs: ``L * B * S * D * 2`` (one bf16 hidden state per block);
- the one block being recomputed in backward: ``B * block_activation_bytes`` plus its backward
  working set (two fp32 ``(B, S, D)`` gradients of the residual stream);
- outside the blocks: patch-embedding input, rotary tables, embedded text/image context, head;
- a fixed runtime overhead (CUDA context, NCCL and cuBLAS workspaces, allocator slack): an
  assumption, stated as ``overhead_gib``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

from egosim.model.errors import ModelConfigError
from egosim.model.presets import (
    EGOSIM_IN_CHANNELS,
    LATENT_CHANNELS,
    ModelPreset,
    TransformerSpec,
    get_preset,
)

GIB = 2**30

# What one diffusers 0.42 WanTransformerBlock (image-conditioned, bf16 weights and inputs, SDPA
# attention that keeps no S x S matrix) saves for backward, in bytes, counted tensor by tensor
# and checked against torch's saved-tensor hooks in tests/test_memory_plan.py:
# per token of the video: 68 per channel of width D (the block keeps fp32 copies around its
# three LayerNorms and adaLN modulations, bf16 q/k/v/outputs of three attentions, the linear
# inputs), 4 per FFN channel (bf16 GELU input and output), 12 per head (fp32 log-sum-exp of
# self-, text- and image-attention) and 28 (fp32 norm statistics);
BLOCK_BYTES_PER_TOKEN_D = 68
BLOCK_BYTES_PER_TOKEN_FFN = 4
BLOCK_BYTES_PER_TOKEN_HEAD = 12
BLOCK_BYTES_PER_TOKEN = 28
# per context token (text and image): 16 per channel and 4 (fp32 norm statistics of the
# cross-attention key norms, bf16 keys and values); per sample: 32 per channel (modulation).
BLOCK_BYTES_PER_CONTEXT_TOKEN_D = 16
BLOCK_BYTES_PER_CONTEXT_TOKEN = 4
BLOCK_BYTES_PER_SAMPLE_D = 32


@dataclass(frozen=True)
class ParameterCount:
    """Parameters of a transformer, split as FSDP2 wraps it."""

    total: int  # every parameter
    per_block: int  # one transformer block (all blocks are alike)
    root: int  # outside the blocks: patch embedding, condition embedders, head

    @property
    def blocks(self) -> int:
        """Parameters in all blocks together."""
        return self.total - self.root


def parameter_count(spec: TransformerSpec, in_channels: int = EGOSIM_IN_CHANNELS) -> ParameterCount:
    """Parameters of ``WanTransformer3DModel`` with ``spec`` at ``in_channels``, from the spec.

    Linear layers count ``in * out + out``; the adaLN tables ``6 D`` per block and ``2 D`` in the
    head; RMS norms over the heads ``D``; affine LayerNorms ``2 x width``.
    """
    d, f = spec.inner_dim, spec.ffn_dim
    patch = math.prod(spec.patch_size)

    def linear(i: int, o: int) -> int:
        return i * o + o

    root = (
        in_channels * patch * d + d  # patch embedding (Conv3d)
        + linear(spec.freq_dim, d) + linear(d, d)  # time embedder
        + linear(d, 6 * d)  # time projection to the 6 block modulations
        + linear(spec.text_dim, d) + linear(d, d)  # text embedder
        + linear(d, LATENT_CHANNELS * patch) + 2 * d  # head: proj_out + scale_shift_table
    )  # fmt: skip
    if spec.image_dim is not None:
        i = spec.image_dim
        root += 2 * i + linear(i, i) + linear(i, d) + 2 * d  # norm1, ff (GELU), norm2
    attention = 4 * linear(d, d) + 2 * d  # q, k, v, out + RMS norms of q and k
    cross = attention
    if spec.added_kv_proj_dim is not None:
        cross += 2 * linear(spec.added_kv_proj_dim, d) + d  # image K, V + RMS norm of K
    block = 6 * d + attention + cross + 2 * d + linear(d, f) + linear(f, d)  # + affine norm2
    return ParameterCount(root + spec.num_layers * block, block, root)


def latent_shape(
    preset: ModelPreset, num_frames: int, height: int, width: int
) -> tuple[int, int, int, int]:
    """``(C, T', h, w)`` of a clip's latent: the first frame alone, then groups of 4 frames."""
    vae = preset.vae
    problems = []
    if (num_frames - 1) % vae.temporal_factor:
        problems.append(f"num_frames must be 1 + {vae.temporal_factor}k, got {num_frames}")
    if height % preset.pixel_multiple or width % preset.pixel_multiple:
        problems.append(
            f"height and width must be multiples of {preset.pixel_multiple}, got {height}x{width}"
        )
    if problems:
        raise ModelConfigError(f"preset {preset.name!r}: " + "; ".join(problems))
    frames = (num_frames - 1) // vae.temporal_factor + 1
    return (LATENT_CHANNELS, frames, height // vae.spatial_factor, width // vae.spatial_factor)


def sequence_length(preset: ModelPreset, num_frames: int, height: int, width: int) -> int:
    """Transformer tokens of one clip: latent cells divided by the patch size."""
    _, t, h, w = latent_shape(preset, num_frames, height, width)
    pt, ph, pw = preset.transformer.patch_size
    return (t // pt) * (h // ph) * (w // pw)


def block_activation_bytes(
    spec: TransformerSpec, tokens: int, text_tokens: int, image_tokens: int
) -> int:
    """Bytes one image-conditioned Wan block saves for backward, per sample (bf16 compute)."""
    d = spec.inner_dim
    per_token = (
        BLOCK_BYTES_PER_TOKEN_D * d
        + BLOCK_BYTES_PER_TOKEN_FFN * spec.ffn_dim
        + BLOCK_BYTES_PER_TOKEN_HEAD * spec.num_attention_heads
        + BLOCK_BYTES_PER_TOKEN
    )
    per_context = BLOCK_BYTES_PER_CONTEXT_TOKEN_D * d + BLOCK_BYTES_PER_CONTEXT_TOKEN
    context = text_tokens + image_tokens
    return tokens * per_token + context * per_context + BLOCK_BYTES_PER_SAMPLE_D * d


@dataclass(frozen=True)
class TrainSetup:
    """The training run a plan is for (defaults: the paper's 14B recipe, batch 1)."""

    num_gpus: int = 8  # FSDP2 shards parameters, gradients and optimizer states over these
    batch_per_gpu: int = 1  # samples per GPU per micro-batch
    num_frames: int = 61  # clip length in pixel frames (1 + 4k)
    height: int = 480  # frame height in pixels
    width: int = 832  # frame width in pixels
    in_channels: int = EGOSIM_IN_CHANNELS  # transformer input channels (52: widened)
    text_tokens: int = 512  # UMT5 tokens (Wan pads to 512)
    image_tokens: int = 257  # CLIP image tokens (Wan's image branch)
    prefetch_blocks: int = 1  # blocks FSDP2 all-gathers ahead of the one computing
    ema: bool = False  # keep an fp32 EMA of the (sharded) weights
    overhead_gib: float = 2.0  # CUDA context, NCCL/cuBLAS workspaces, allocator slack (assumed)

    def __post_init__(self) -> None:
        bad = [
            f"{f.name} must be >= 1, got {getattr(self, f.name)}"
            for f in fields(self)
            if f.name in ("num_gpus", "batch_per_gpu", "num_frames", "height", "width")
            and getattr(self, f.name) < 1
        ]
        if self.prefetch_blocks < 0:
            bad.append(f"prefetch_blocks must be >= 0, got {self.prefetch_blocks}")
        if self.overhead_gib < 0:
            bad.append(f"overhead_gib must be >= 0, got {self.overhead_gib}")
        if bad:
            raise ModelConfigError("TrainSetup: " + "; ".join(bad))


# Bytes per parameter of each training state (mixed precision as FSDP2 runs it).
MASTER_BYTES = 4  # fp32 sharded parameters (the optimizer's copy)
GRAD_BYTES = 4  # fp32 sharded gradients (reduce-scatter in fp32)
ADAM_BYTES = 8  # fp32 exp_avg + exp_avg_sq
COMPUTE_BYTES = 2  # bf16 all-gathered parameters, activations
UNSHARDED_GRAD_BYTES = 6  # a block's bf16 gradient + its fp32 copy for the reduce-scatter


@dataclass(frozen=True)
class MemoryPlan:
    """Per-GPU memory of one training step, in bytes, by component."""

    preset: str  # preset name
    setup: TrainSetup  # the run it is for
    params: ParameterCount  # parameter counts
    tokens: int  # tokens per sample
    model_states: int  # sharded master weights + gradients + AdamW moments (+ EMA)
    gathered: int  # all-gathered bf16 parameters and unsharded gradients (transient)
    checkpoints: int  # checkpointed block inputs of every block
    block: int  # the recomputed block's saved tensors + its backward working set
    outside: int  # activations outside the blocks (patch embedding, context, rope, head)
    overhead: int  # fixed runtime overhead (assumed)

    @property
    def activations(self) -> int:
        """Every activation term."""
        return self.checkpoints + self.block + self.outside

    @property
    def total(self) -> int:
        """Peak estimate: every term together."""
        return self.model_states + self.gathered + self.activations + self.overhead


def plan_memory(preset: ModelPreset | str, setup: TrainSetup | None = None) -> MemoryPlan:
    """Per-GPU memory of full fine-tuning ``preset`` under ``setup`` (see the module docstring)."""
    preset = get_preset(preset) if isinstance(preset, str) else preset
    setup = setup or TrainSetup()
    spec = preset.transformer
    if spec.image_dim is None:
        raise ModelConfigError(
            f"preset {preset.name!r}: the activation count is for image-conditioned Wan blocks"
        )
    params = parameter_count(spec, setup.in_channels)
    n, b, d = setup.num_gpus, setup.batch_per_gpu, spec.inner_dim
    tokens = sequence_length(preset, setup.num_frames, setup.height, setup.width)
    state_bytes = MASTER_BYTES + GRAD_BYTES + ADAM_BYTES + (MASTER_BYTES if setup.ema else 0)
    model_states = math.ceil(params.total / n) * state_bytes
    gathered = COMPUTE_BYTES * (params.root + (1 + setup.prefetch_blocks) * params.per_block)
    gathered += UNSHARDED_GRAD_BYTES * (params.root + params.per_block)
    checkpoints = spec.num_layers * b * tokens * d * COMPUTE_BYTES
    block = b * block_activation_bytes(spec, tokens, setup.text_tokens, setup.image_tokens)
    block += 2 * b * tokens * d * 4  # backward: fp32 gradient of the residual stream, twice
    patch = math.prod(spec.patch_size)
    out_values = LATENT_CHANNELS * patch
    outside = (
        b
        * (
            tokens * patch * setup.in_channels * COMPUTE_BYTES  # patch-embedding input
            + (setup.text_tokens + setup.image_tokens) * d * COMPUTE_BYTES  # embedded context
            + tokens * (10 * d + 8 * out_values)  # head: fp32 norm in/out, bf16 input, fp32 output
        )
        + 2 * tokens * spec.attention_head_dim * 4
    )  # rotary cos and sin tables (fp32, shared)
    overhead = int(setup.overhead_gib * GIB)
    return MemoryPlan(
        preset.name, setup, params, tokens, model_states, gathered, checkpoints, block, outside,
        overhead,
    )  # fmt: skip


def format_table(plans: list[MemoryPlan]) -> str:
    """A Markdown table of plans, GiB per GPU by component."""
    head = (
        "| preset | GPUs | batch/GPU | tokens | params | model states | gathered | "
        "block inputs | block | outside | overhead | **total** |"
    )
    lines = [head, "|" + " --- |" * 12]
    for p in plans:
        cells = [
            p.preset,
            str(p.setup.num_gpus),
            str(p.setup.batch_per_gpu),
            f"{p.tokens:,}",
            f"{p.params.total / 1e9:.3f} B",
            *(
                f"{v / GIB:.1f}"
                for v in (p.model_states, p.gathered, p.checkpoints, p.block, p.outside, p.overhead)
            ),
            f"**{p.total / GIB:.1f}**",
        ]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


PLAN_PRESETS = ("wan2.1-fun-1.3b-inp", "wan2.1-fun-14b-inp")  # presets of the docs table
PLAN_BATCHES = (1, 2, 3, 4)  # batch sizes per GPU of the docs table


def default_plans(num_gpus: int = 8) -> list[MemoryPlan]:
    """The docs table: both Wan presets at 61x480x832, batch 1-4 per GPU, on ``num_gpus``."""
    return [
        plan_memory(name, TrainSetup(num_gpus=num_gpus, batch_per_gpu=b))
        for name in PLAN_PRESETS
        for b in PLAN_BATCHES
    ]
