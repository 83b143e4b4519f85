"""The frozen encoders whose outputs the ``encode`` stage precomputes, loaded from local folders.

What each one computes (so that training from the stored features equals training on the fly):

- **VAE**: the preset's autoencoder (``model/vae.py``: the packed VAE of ``tiny``, diffusers'
  ``AutoencoderKLWan`` from ``<weights_dir>/vae`` for Wan presets), applied by
  :func:`egosim.model.conditioning.encode_batch`, the function training itself calls: target
  latent ``(16, T', h, w)`` and the 36 condition channels.
- **Text** (:class:`UMT5Features`): as diffusers' ``WanPipeline._get_t5_prompt_embeds``: the
  prompt is cleaned (``ftfy.fix_text`` when ftfy is installed, HTML unescaped twice, whitespace
  collapsed), tokenised with ``padding="max_length"``, ``max_length=512``, ``truncation`` and
  special tokens (the EOS), run through ``UMT5EncoderModel`` with its attention mask, and the
  last hidden states of the real tokens (mask 1) are kept. Wan zero-pads them to 512 rows;
  ``text.pad_tokens`` does that at training time, so only the real rows are stored.
- **Image** (:class:`CLIPImageFeatures`): as diffusers' ``WanImageToVideoPipeline.encode_image``:
  the hand-free first frame through the folder's ``CLIPImageProcessor`` (resize, centre crop 224,
  CLIP normalisation) and ``CLIPVisionModel``; the features are ``hidden_states[-2]``, the
  penultimate layer (257 tokens x 1280 for ViT-H/14).

Folders follow the diffusers Wan layout (``vae/``, ``text_encoder/``, ``tokenizer/``,
``image_encoder/``, ``image_processor/`` under one root); :class:`EncoderFolders` lets the text
and image parts come from other folders (a Wan2.1-Fun folder may hold only the transformer and
VAE). Nothing is downloaded.

:func:`write_tiny_wan_folder` writes tiny random models of every class in that layout
(``from_config`` with small widths, matching the ``tiny-wan`` preset) for tests and benchmarks.
"""

from __future__ import annotations

import html
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from egosim.model.conditioning import LatentSample, TrainingSample, encode_batch
from egosim.model.errors import ModelConfigError, WeightsMismatchError
from egosim.model.presets import ModelPreset, get_preset
from egosim.model.vae import build_vae

TEXT_SUBFOLDERS = ("text_encoder", "tokenizer")  # diffusers Wan layout: UMT5 and its tokenizer
IMAGE_SUBFOLDERS = ("image_encoder", "image_processor")  # CLIP vision model and preprocessing
CLIP_FEATURE_LAYER = -2  # hidden_states index Wan's image branch reads (penultimate layer)
DTYPES = {"float32": torch.float32, "bfloat16": torch.bfloat16, "float16": torch.float16}


def clean_prompt(text: str) -> str:
    """Wan's prompt cleaning (diffusers ``prompt_clean``): ftfy if installed, unescape, spaces."""
    try:
        import ftfy  # optional, as in diffusers; changes only mis-encoded text
    except ImportError:
        pass
    else:
        text = ftfy.fix_text(text)
    text = html.unescape(html.unescape(text)).strip()
    return re.sub(r"\s+", " ", text).strip()


class UMT5Features:
    """Prompt -> UMT5 features of its real tokens ``(length, d_model)``, as Wan computes them."""

    def __init__(self, model: nn.Module, tokenizer: Any, max_tokens: int = 512) -> None:
        self.model = model.eval().requires_grad_(False)
        self.tokenizer = tokenizer
        self.max_tokens = max_tokens
        self.dim = int(model.config.d_model)

    @torch.no_grad()
    def __call__(self, prompts: list[str]) -> list[torch.Tensor]:
        """One float32 CPU tensor ``(length_i, dim)`` per prompt (EOS included, no padding)."""
        tok = self.tokenizer(
            [clean_prompt(p) for p in prompts],
            padding="max_length",
            max_length=self.max_tokens,
            truncation=True,
            add_special_tokens=True,
            return_attention_mask=True,
            return_tensors="pt",
        )
        lengths = tok.attention_mask.gt(0).sum(dim=1).tolist()  # real tokens per prompt
        device = next(self.model.parameters()).device
        hidden = self.model(tok.input_ids.to(device), tok.attention_mask.to(device))
        states = hidden.last_hidden_state.float().cpu()  # (B, max_tokens, dim)
        return [states[i, :n].clone() for i, n in enumerate(lengths)]


class CLIPImageFeatures:
    """RGB uint8 image -> CLIP vision penultimate hidden states ``(tokens, hidden)``."""

    def __init__(self, model: nn.Module, processor: Any) -> None:
        self.model = model.eval().requires_grad_(False)
        self.processor = processor
        self.dim = int(model.config.hidden_size)

    @torch.no_grad()
    def __call__(self, images: list[np.ndarray]) -> torch.Tensor:
        """``(B, tokens, hidden)`` float32 on CPU for B ``(H, W, 3)`` uint8 images."""
        param = next(self.model.parameters())
        pixels = self.processor(images=[np.asarray(i) for i in images], return_tensors="pt")
        values = pixels["pixel_values"].to(param.device, param.dtype)  # (B, 3, 224, 224)
        out = self.model(pixel_values=values, output_hidden_states=True)
        return out.hidden_states[CLIP_FEATURE_LAYER].float().cpu()


@dataclass(frozen=True)
class EncoderFolders:
    """Where each frozen encoder is read from (diffusers layout; ``None``: not needed)."""

    weights_dir: Path | None = None  # diffusers Wan root: vae/ (and the defaults below)
    text_encoder: Path | None = None  # UMT5EncoderModel folder (config.json + safetensors)
    tokenizer: Path | None = None  # its tokenizer folder
    image_encoder: Path | None = None  # CLIPVisionModel folder
    image_processor: Path | None = None  # CLIPImageProcessor folder

    @classmethod
    def from_root(
        cls, weights_dir: str | Path | None, **overrides: str | Path | None
    ) -> EncoderFolders:
        """Folders under ``weights_dir`` by the diffusers layout, ``overrides`` (non-empty) win."""
        root = Path(weights_dir) if weights_dir else None
        values: dict[str, Path | None] = {"weights_dir": root}
        for name in (*TEXT_SUBFOLDERS, *IMAGE_SUBFOLDERS):
            given = overrides.pop(name, None)
            values[name] = Path(given) if given else (root / name if root else None)
        if overrides:
            raise ModelConfigError(f"unknown encoder folders {sorted(overrides)}")
        return cls(**values)


def _folder(path: Path | None, what: str, preset: ModelPreset) -> Path:
    if path is None:
        raise WeightsMismatchError(
            f"preset {preset.name!r} needs a {what} folder (weights_dir or its own folder)"
        )
    if not path.is_dir():
        raise WeightsMismatchError(f"preset {preset.name!r}: no {what} folder at {path}")
    return path


def load_text_features(
    preset: ModelPreset, folders: EncoderFolders, device: torch.device, dtype: torch.dtype
) -> UMT5Features:
    """UMT5 encoder + tokenizer from local folders, checked against the preset's text width."""
    from transformers import AutoTokenizer, UMT5EncoderModel

    model_dir = _folder(folders.text_encoder, "text_encoder (UMT5)", preset)
    tok_dir = _folder(folders.tokenizer, "tokenizer", preset)
    model = UMT5EncoderModel.from_pretrained(model_dir, dtype=dtype, local_files_only=True)
    if model.config.d_model != preset.transformer.text_dim:
        raise WeightsMismatchError(
            f"{model_dir}: UMT5 d_model is {model.config.d_model}, preset {preset.name!r} "
            f"takes text_dim {preset.transformer.text_dim}"
        )
    tokenizer = AutoTokenizer.from_pretrained(tok_dir, local_files_only=True)
    return UMT5Features(model.to(device), tokenizer, preset.text.max_tokens)


def load_image_features(
    preset: ModelPreset, folders: EncoderFolders, device: torch.device, dtype: torch.dtype
) -> CLIPImageFeatures:
    """CLIP vision model + image processor from local folders, checked against ``image_dim``."""
    from transformers import AutoImageProcessor, CLIPVisionModel

    model_dir = _folder(folders.image_encoder, "image_encoder (CLIP vision)", preset)
    proc_dir = _folder(folders.image_processor, "image_processor", preset)
    model = CLIPVisionModel.from_pretrained(model_dir, dtype=dtype, local_files_only=True)
    if model.config.hidden_size != preset.transformer.image_dim:
        raise WeightsMismatchError(
            f"{model_dir}: CLIP hidden_size is {model.config.hidden_size}, preset "
            f"{preset.name!r} takes image_dim {preset.transformer.image_dim}"
        )
    processor = AutoImageProcessor.from_pretrained(proc_dir, local_files_only=True)
    return CLIPImageFeatures(model.to(device), processor)


@dataclass
class FrozenEncoders:
    """The preset's frozen parts: VAE, and UMT5 / CLIP where the preset reads their features."""

    preset: ModelPreset  # the preset they feed
    vae: nn.Module  # encode (B,3,T,H,W) -> (B,16,T',h,w)
    text: UMT5Features | None  # None: the preset's text encoder trains (tiny's hashed table)
    image: CLIPImageFeatures | None  # None: the preset has no image branch

    def encode(self, samples: list[TrainingSample], clip_ids: list[str]) -> list[LatentSample]:
        """Pixel samples -> latent samples (latents by :func:`encode_batch`, features on CPU)."""
        enc = encode_batch(self.vae, samples)
        texts = self.text([s.prompt for s in samples]) if self.text else [None] * len(samples)
        images = (
            list(self.image([np.asarray(s.first_frame) for s in samples]))
            if self.image
            else [None] * len(samples)
        )
        return [
            LatentSample(
                x0=enc.x0[i].float().cpu(),
                condition=enc.condition[i].float().cpu(),
                prompt=s.prompt,
                text_embedding=texts[i],
                image_embedding=images[i],
                clip_id=clip_ids[i],
            )
            for i, s in enumerate(samples)
        ]


def load_encoders(
    preset: ModelPreset | str,
    folders: EncoderFolders,
    device: torch.device | str = "cpu",
    dtype: str = "float32",
) -> FrozenEncoders:
    """The frozen encoders of ``preset`` from local folders (the VAE always in float32).

    ``dtype`` applies to the text and image encoders (``float32``, ``bfloat16``, ``float16``).
    Raises :class:`WeightsMismatchError` naming a missing folder or a width the preset does not
    take.
    """
    preset = get_preset(preset) if isinstance(preset, str) else preset
    if dtype not in DTYPES:
        raise ModelConfigError(f"encoder dtype must be one of {sorted(DTYPES)}, got {dtype!r}")
    device = torch.device(device)
    vae = build_vae(preset, folders.weights_dir).to(device)
    text = None
    if preset.text.kind == "precomputed":
        text = load_text_features(preset, folders, device, DTYPES[dtype])
    image = None
    if preset.transformer.image_dim is not None:
        image = load_image_features(preset, folders, device, DTYPES[dtype])
    return FrozenEncoders(preset=preset, vae=vae, text=text, image=image)


# --- tiny random models of every class, for tests and benchmarks --------------------------------

TINY_VAE_CONFIG = {  # AutoencoderKLWan at test width: 4x spatial stages of width 8, same layout
    "base_dim": 8,
    "z_dim": 16,
    "dim_mult": [1, 1, 1, 1],
    "num_res_blocks": 1,
    "attn_scales": [],
    "temperal_downsample": [False, True, True],
}
_TOKEN_CHARS = "abcdefghijklmnopqrstuvwxyz0123456789 .,;:!?'-"  # tiny tokenizer: one id per char


def build_tiny_vae(seed: int = 0) -> nn.Module:
    """A random ``AutoencoderKLWan`` (x8 spatial, x4 temporal, z_dim 16) at test width."""
    from diffusers import AutoencoderKLWan

    torch.manual_seed(seed)
    return AutoencoderKLWan.from_config(TINY_VAE_CONFIG).eval()


def build_tiny_umt5(d_model: int, seed: int = 0) -> nn.Module:
    """A random 2-layer ``UMT5EncoderModel`` of width ``d_model`` over the tiny vocabulary."""
    from transformers import UMT5Config, UMT5EncoderModel

    torch.manual_seed(seed)
    config = UMT5Config(
        vocab_size=64,  # >= the tiny tokenizer's 3 special + 45 character ids
        d_model=d_model,
        d_kv=8,
        d_ff=2 * d_model,
        num_layers=2,
        num_heads=4,
        relative_attention_num_buckets=8,
        relative_attention_max_distance=32,
        pad_token_id=0,
        eos_token_id=1,
    )
    return UMT5EncoderModel(config).eval()


def build_tiny_tokenizer() -> Any:
    """A character-level fast tokenizer with T5's conventions (pad 0, EOS 1 appended, unk 2)."""
    from tokenizers import Regex, Tokenizer, models, normalizers, pre_tokenizers, processors
    from transformers import PreTrainedTokenizerFast

    vocab = {"<pad>": 0, "</s>": 1, "<unk>": 2}
    vocab.update({c: i + 3 for i, c in enumerate(_TOKEN_CHARS)})
    tok = Tokenizer(models.WordLevel(vocab, unk_token="<unk>"))
    tok.normalizer = normalizers.Lowercase()
    tok.pre_tokenizer = pre_tokenizers.Split(Regex("."), behavior="isolated")
    tok.post_processor = processors.TemplateProcessing(
        single="$A </s>", special_tokens=[("</s>", 1)]
    )
    return PreTrainedTokenizerFast(
        tokenizer_object=tok,
        pad_token="<pad>",
        eos_token="</s>",
        unk_token="<unk>",
        model_max_length=512,
    )


def build_tiny_clip_vision(hidden_size: int, seed: int = 0) -> nn.Module:
    """A random 2-layer ``CLIPVisionModel`` at 224 px, patch 14 (257 tokens, as ViT-H/14)."""
    from transformers import CLIPVisionConfig, CLIPVisionModel

    torch.manual_seed(seed)
    config = CLIPVisionConfig(
        hidden_size=hidden_size,
        intermediate_size=2 * hidden_size,
        num_hidden_layers=2,
        num_attention_heads=4,
        image_size=224,
        patch_size=14,
    )
    return CLIPVisionModel(config).eval()


def build_tiny_image_processor() -> Any:
    """CLIP's standard preprocessing (shortest edge 224, centre crop 224, CLIP mean/std)."""
    try:  # the PIL backend, which transformers falls back to without torchvision
        from transformers import CLIPImageProcessorPil as Processor
    except ImportError:  # pragma: no cover (older transformers)
        from transformers import CLIPImageProcessor as Processor
    return Processor()


def write_tiny_wan_folder(folder: str | Path, preset: str = "tiny-wan", seed: int = 0) -> Path:
    """Write tiny random Wan-architecture weights in the diffusers layout under ``folder``.

    ``transformer/`` (the preset at the published 36 input channels: loading widens it to 52),
    ``vae/``, ``text_encoder/``, ``tokenizer/``, ``image_encoder/``, ``image_processor/``; all
    safetensors or JSON. Widths match ``preset`` (text_dim, image_dim).
    """
    from egosim.model.network import build_transformer, save_transformer_folder
    from egosim.model.presets import PRETRAINED_IN_CHANNELS

    spec = get_preset(preset)
    if spec.vae.kind != "wan" or spec.transformer.image_dim is None:
        raise ModelConfigError(f"preset {preset!r} is not a Wan image-conditioned preset")
    root = Path(folder)
    torch.manual_seed(seed)
    save_transformer_folder(build_transformer(spec, PRETRAINED_IN_CHANNELS), root)
    build_tiny_vae(seed).save_pretrained(root / "vae", safe_serialization=True)
    build_tiny_umt5(spec.transformer.text_dim, seed).save_pretrained(root / "text_encoder")
    build_tiny_tokenizer().save_pretrained(root / "tokenizer")
    build_tiny_clip_vision(spec.transformer.image_dim, seed).save_pretrained(root / "image_encoder")
    build_tiny_image_processor().save_pretrained(root / "image_processor")
    return root
