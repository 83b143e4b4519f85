"""The denoising network: diffusers' ``WanTransformer3DModel`` at 52 input channels + text encoder.

Building, widening 36 -> 52 input channels, and loading a local diffusers-format weights folder
with shape checks live here; the noise process is ``flow.py`` and the loop ``train.py``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import torch
from diffusers import WanTransformer3DModel
from diffusers.models.transformers.transformer_wan import WanRotaryPosEmbed
from torch import nn

from egosim.model.errors import MissingEmbeddingError, WeightsMismatchError
from egosim.model.presets import (
    EGOSIM_IN_CHANNELS,
    ModelPreset,
    get_preset,
)
from egosim.model.text import HashedTextEncoder, PrecomputedTextEncoder
from egosim.model.vae import build_vae
from egosim.model.weights import IGNORED_DIFFUSERS_KEYS, read_weights_folder

IMAGE_TOKENS = 257  # CLIP ViT-H/14 tokens Wan's image branch takes (CLS + 16 x 16 patches)


def build_transformer(
    preset: ModelPreset | str,
    in_channels: int = EGOSIM_IN_CHANNELS,
    device: torch.device | str | None = None,
) -> WanTransformer3DModel:
    """A freshly initialised transformer of the preset at ``in_channels``.

    Pass ``device="meta"`` to build without allocating (parameter counts, then loading). Weights
    use diffusers' default initialisation (PyTorch layer defaults, ``scale_shift_table`` ~
    N(0, 1/dim)); a from-scratch tiny model needs nothing more.
    """
    preset = get_preset(preset) if isinstance(preset, str) else preset
    with torch.device(device or "cpu"):
        return WanTransformer3DModel(**preset.transformer.diffusers_kwargs(in_channels))


def widen_patch_embedding(
    transformer: WanTransformer3DModel, in_channels: int = EGOSIM_IN_CHANNELS
) -> WanTransformer3DModel:
    """Widen the patch embedding to ``in_channels`` in place; new input channels get zero weights.

    Zero weights on the appended channels make the widened model compute exactly what the
    pretrained one did, whatever those channels hold, so a pretrained inpainting model starts as
    it was (DWM's identity-with-prior argument) and gradients still reach the new weights.
    """
    old = transformer.patch_embedding
    if old.in_channels == in_channels:
        return transformer
    if old.in_channels > in_channels:
        raise WeightsMismatchError(
            f"cannot narrow patch_embedding from {old.in_channels} to {in_channels} channels"
        )
    new = nn.Conv3d(
        in_channels,
        old.out_channels,
        kernel_size=old.kernel_size,
        stride=old.stride,
        device=old.weight.device,
        dtype=old.weight.dtype,
    )
    with torch.no_grad():
        new.weight.zero_()
        new.weight[:, : old.in_channels] = old.weight
        new.bias.copy_(old.bias)
    transformer.patch_embedding = new
    transformer.register_to_config(in_channels=in_channels)
    return transformer


def check_weight_shapes(
    preset: ModelPreset, shapes: dict[str, tuple[int, ...]], in_channels: int
) -> None:
    """Raise :class:`WeightsMismatchError` naming the first tensor that does not fit the preset.

    ``patch_embedding.weight`` may have the pretrained 36 (or any smaller) input channels: it is
    widened on load.
    """
    model = build_transformer(preset, in_channels, device="meta")
    expected = {k: tuple(v.shape) for k, v in model.state_dict().items()}
    for key, want in expected.items():
        if key not in shapes:
            raise WeightsMismatchError(f"preset {preset.name!r}: weights folder lacks {key!r}")
        got = shapes[key]
        widenable = key == "patch_embedding.weight" and got[1] <= want[1]
        if widenable and got[0] == want[0] and got[2:] == want[2:]:
            continue
        if got != want:
            raise WeightsMismatchError(
                f"preset {preset.name!r}: tensor {key!r} has shape {got} in the weights folder, "
                f"the preset expects {want}"
            )
    extra = sorted(
        k for k in shapes if k not in expected and not k.endswith(IGNORED_DIFFUSERS_KEYS)
    )
    if extra:
        raise WeightsMismatchError(
            f"preset {preset.name!r}: weights folder has tensors the preset lacks: {extra[:5]}"
        )


def load_transformer(
    preset: ModelPreset | str,
    folder: str | Path,
    in_channels: int = EGOSIM_IN_CHANNELS,
    dtype: torch.dtype | None = None,
) -> WanTransformer3DModel:
    """Load a transformer folder into the preset's architecture (on CPU).

    The folder may use diffusers' key names or the original Wan / VideoX-Fun ones (converted
    by ``egosim.model.weights``). Shapes are checked before any tensor is read; a 36-channel
    patch embedding is widened with zero-initialised new channels. ``dtype`` casts (default:
    keep the stored dtype).
    """
    preset = get_preset(preset) if isinstance(preset, str) else preset
    weights = read_weights_folder(folder)  # headers only; original keys renamed to diffusers'
    shapes = weights.shapes
    check_weight_shapes(preset, shapes, in_channels)
    stored_in = shapes["patch_embedding.weight"][1]
    model = build_transformer(preset, stored_in, device="meta")
    model.load_state_dict(weights.load_state_dict(dtype), strict=True, assign=True)
    # Rotary tables are non-persistent buffers: rebuild them (they stayed on the meta device).
    spec = preset.transformer
    model.rope = WanRotaryPosEmbed(spec.attention_head_dim, spec.patch_size, spec.rope_max_seq_len)
    return widen_patch_embedding(model, in_channels)


class EgoSimDenoiser(nn.Module):
    """Velocity network: Wan transformer on the 52-channel input plus the prompt encoder."""

    def __init__(self, preset: ModelPreset, transformer: WanTransformer3DModel, text: nn.Module):
        super().__init__()
        self.preset = preset
        self.transformer = transformer
        self.text_encoder = text

    @property
    def needs_image_context(self) -> bool:
        """Whether the preset has Wan's CLIP image branch (Wan presets)."""
        return self.preset.transformer.image_dim is not None

    def encode_text(
        self, prompts: list[str], given: list[torch.Tensor | None] | None = None
    ) -> torch.Tensor:
        """Prompts -> (B, L, text_dim) on the model's device; "" is the null prompt (zeros)."""
        device = next(self.transformer.parameters()).device
        if isinstance(self.text_encoder, HashedTextEncoder):
            return self.text_encoder(prompts).to(device)
        return self.text_encoder(prompts, given).to(device)

    def image_context(self, given: list[torch.Tensor | None]) -> torch.Tensor | None:
        """Per-sample CLIP features -> (B, 257, image_dim), or None for presets without them."""
        if not self.needs_image_context:
            return None
        if any(g is None for g in given):
            raise MissingEmbeddingError(
                f"preset {self.preset.name!r} needs image_embedding (CLIP, "
                f"({IMAGE_TOKENS}, {self.preset.transformer.image_dim})) on every sample"
            )
        device = next(self.transformer.parameters()).device
        return torch.stack([g.float() for g in given]).to(device)

    def forward(
        self,
        x: torch.Tensor,
        t: torch.Tensor,
        context: torch.Tensor,
        image_context: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """Predict the flow velocity ``e - x_0``.

        x: (B, 52, T', h, w) assembled input; t: (B,) flow time in [0, 1] (Wan is fed 1000 t,
        its timestep convention); context: (B, L, text_dim); image_context: (B, 257, 1280) or
        None. Returns (B, 16, T', h, w).
        """
        dtype = self.transformer.patch_embedding.weight.dtype
        out = self.transformer(
            hidden_states=x.to(dtype),  # (B, 52, T', h, w)
            timestep=t * 1000.0,  # (B,)
            encoder_hidden_states=context.to(dtype),  # (B, L, text_dim)
            encoder_hidden_states_image=None if image_context is None else image_context.to(dtype),
            return_dict=False,
        )[0]
        return out  # (B, 16, T', h, w)


@dataclass
class ModelBundle:
    """Everything sampling and training need: the preset, the denoiser and the (frozen) VAE."""

    preset: ModelPreset  # the preset it was built from
    denoiser: EgoSimDenoiser  # trainable network (+ tiny text encoder)
    vae: nn.Module  # frozen autoencoder with encode/decode


def build_model(
    preset: ModelPreset | str,
    weights_dir: str | Path | None = None,
    text_embeddings_dir: str | Path | None = None,
    seed: int = 0,
    dtype: torch.dtype | None = None,
) -> ModelBundle:
    """Build (tiny: initialise; Wan: load) the network, text encoder and VAE of a preset.

    ``weights_dir``: diffusers-format folder with ``transformer/`` (and ``vae/`` for Wan
    presets); optional for ``tiny`` (loads a pretrained 36- or 52-channel tiny transformer).
    ``text_embeddings_dir``: folder of precomputed UMT5 features (Wan presets).
    """
    preset = get_preset(preset) if isinstance(preset, str) else preset
    if weights_dir is None and preset.vae.kind == "wan":
        raise WeightsMismatchError(f"preset {preset.name!r} needs a weights_dir (no download)")
    torch.manual_seed(seed)  # deterministic initialisation of everything built below
    if weights_dir is not None:
        transformer = load_transformer(preset, weights_dir, dtype=dtype)
    else:
        transformer = build_transformer(preset)
    spec = preset.text
    if spec.kind == "hashed":
        text: nn.Module = HashedTextEncoder(
            preset.transformer.text_dim, spec.max_tokens, spec.vocab_size
        )
    else:
        text = PrecomputedTextEncoder(
            preset.transformer.text_dim, spec.max_tokens, text_embeddings_dir
        )
    denoiser = EgoSimDenoiser(preset, transformer, text)
    vae = build_vae(preset, weights_dir)
    return ModelBundle(preset=preset, denoiser=denoiser, vae=vae)


def count_parameters(module: nn.Module) -> int:
    """Number of parameters (works on the meta device)."""
    return sum(p.numel() for p in module.parameters())


def save_transformer_folder(transformer: WanTransformer3DModel, folder: str | Path) -> Path:
    """Write a diffusers-format ``<folder>/transformer`` (config.json + safetensors)."""
    out = Path(folder) / "transformer"
    transformer.save_pretrained(out, safe_serialization=True)
    json.loads((out / "config.json").read_text())  # written and parseable
    return out
