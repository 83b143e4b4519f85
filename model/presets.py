"""Named model sizes in one table (`PRESETS`): the transformer, autoencoder and text encoder specs.

The Wan presets copy the published Wan2.1-Fun-InP transformer configs (diffusers key names, as in
diffusers' ``scripts/convert_wan_to_diffusers.py`` for the I2V models, which Fun-InP shares):

=====================  =====  =====  ======  =====  ========  =========  ============
preset                 dim    heads  layers  ffn    text_dim  image_dim  added_kv_dim
=====================  =====  =====  ======  =====  ========  =========  ============
wan2.1-fun-1.3b-inp    1536   12     30      8960   4096      1280       1536
wan2.1-fun-14b-inp     5120   40     40      13824  4096      1280       5120
=====================  =====  =====  ======  =====  ========  =========  ============

Both are published with ``in_channels=36`` (noisy latent 16 + mask 4 + masked-video latent 16);
EgoSim widens the patch embedding to 52 (+ skeleton-video latent 16), see ``network.py``.
"""

from __future__ import annotations

from dataclasses import dataclass

from egosim.model.errors import ModelConfigError, UnknownPresetError

LATENT_CHANNELS = 16  # channels of one video latent (Wan VAE z_dim)
MASK_CHANNELS = 4  # packed inpainting-mask channels (4 pixel frames per latent frame)
PRETRAINED_IN_CHANNELS = 36  # Wan-Fun-InP input: noisy 16 + mask 4 + masked video 16
EGOSIM_IN_CHANNELS = 52  # EgoSim input: noisy 16 + mask 4 + scene 16 + skeleton 16


@dataclass(frozen=True)
class TransformerSpec:
    """Constructor arguments of diffusers' ``WanTransformer3DModel`` (architecture only)."""

    num_attention_heads: int  # attention heads; inner dim = heads * head_dim
    attention_head_dim: int  # channels per head (Wan: 128)
    ffn_dim: int  # feed-forward hidden width
    num_layers: int  # transformer blocks
    text_dim: int  # width of the text features fed to cross-attention (UMT5: 4096)
    image_dim: int | None = None  # CLIP image-feature width (1280) or None: no image branch
    added_kv_proj_dim: int | None = None  # image cross-attention K/V input width, None: none
    patch_size: tuple[int, int, int] = (1, 2, 2)  # (t, h, w) patch of the latent
    freq_dim: int = 256  # sinusoidal timestep embedding width
    eps: float = 1e-6  # norm epsilon
    rope_max_seq_len: int = 1024  # rotary table length (positions per axis)

    @property
    def inner_dim(self) -> int:
        """Transformer width (heads * head_dim)."""
        return self.num_attention_heads * self.attention_head_dim

    def diffusers_kwargs(self, in_channels: int) -> dict:
        """Keyword arguments for ``WanTransformer3DModel(**kwargs)`` at ``in_channels``."""
        return {
            "patch_size": self.patch_size,
            "num_attention_heads": self.num_attention_heads,
            "attention_head_dim": self.attention_head_dim,
            "in_channels": in_channels,
            "out_channels": LATENT_CHANNELS,
            "text_dim": self.text_dim,
            "freq_dim": self.freq_dim,
            "ffn_dim": self.ffn_dim,
            "num_layers": self.num_layers,
            "cross_attn_norm": True,
            "qk_norm": "rms_norm_across_heads",
            "eps": self.eps,
            "image_dim": self.image_dim,
            "added_kv_proj_dim": self.added_kv_proj_dim,
            "rope_max_seq_len": self.rope_max_seq_len,
        }


@dataclass(frozen=True)
class VAESpec:
    """Which video autoencoder a preset uses and its compression factors."""

    kind: str  # "packed": deterministic invertible (tiny); "wan": diffusers AutoencoderKLWan
    temporal_factor: int = 4  # pixel frames per latent frame (the first frame stands alone)
    spatial_factor: int = 8  # pixels per latent cell along each image axis
    seed: int = 0  # seed of the packed VAE's fixed orthogonal channel mix


@dataclass(frozen=True)
class TextSpec:
    """How prompts become ``(L, text_dim)`` features."""

    kind: str  # "hashed": trainable hashed-token table (tiny); "precomputed": UMT5 files
    max_tokens: int  # sequence length L (zero-padded); Wan's image branch needs exactly 512
    vocab_size: int = 4096  # hash buckets of the hashed encoder (unused when precomputed)


@dataclass(frozen=True)
class ModelPreset:
    """One named model size: everything needed to build the network, VAE and text encoder."""

    name: str  # registry key
    transformer: TransformerSpec  # denoiser architecture
    vae: VAESpec  # autoencoder
    text: TextSpec  # prompt encoder
    sample_shift: float = 1.0  # default timestep shift for training and sampling
    num_frames: int = 61  # default clip length (1 + 4k so latent frames are whole)
    height: int = 480  # default frame height in pixels
    width: int = 832  # default frame width in pixels
    # Parameters at 36 input channels as published: the architecture check that the meta-device
    # build counts exactly this many (tests/test_model_network.py); None when not published.
    published_param_count: int | None = None
    notes: str = ""  # provenance of the numbers

    def __post_init__(self) -> None:
        problems = []
        if self.vae.kind not in ("packed", "wan"):
            problems.append(f"vae.kind must be 'packed' or 'wan', got {self.vae.kind!r}")
        if self.text.kind not in ("hashed", "precomputed"):
            problems.append(f"text.kind must be 'hashed' or 'precomputed', got {self.text.kind!r}")
        if self.transformer.image_dim is not None and self.text.max_tokens != 512:
            # diffusers' WanAttnProcessor splits image tokens off as `len - 512`.
            problems.append(
                f"image-conditioned presets need text.max_tokens=512, got {self.text.max_tokens}"
            )
        if (self.num_frames - 1) % self.vae.temporal_factor:
            problems.append(f"num_frames must be 1 + 4k, got {self.num_frames}")
        if problems:
            raise ModelConfigError(f"preset {self.name!r}: " + "; ".join(problems))

    @property
    def pixel_multiple(self) -> int:
        """Frame height and width must be multiples of this (VAE factor * patch)."""
        return self.vae.spatial_factor * self.transformer.patch_size[1]


PRESETS: dict[str, ModelPreset] = {
    # CPU-sized: 2 blocks of width 64; the packed VAE is lossless, with the Wan latent layout
    # (16 channels, first frame alone then groups of 4 frames) at full pixel resolution.
    "tiny": ModelPreset(
        name="tiny",
        transformer=TransformerSpec(
            # Width 256: each 2x2 token carries 4 x 16 x 4 = 256 input values (noise, mask,
            # scene, skeleton); at width 64 the model could not pass the scene render through
            # and lost to copying it (measured 18.6 vs 20.7 dB on held-out clips).
            num_attention_heads=4,
            attention_head_dim=64,
            ffn_dim=512,
            num_layers=2,
            text_dim=32,
            freq_dim=32,
            rope_max_seq_len=256,
        ),
        vae=VAESpec(kind="packed", spatial_factor=1),
        text=TextSpec(kind="hashed", max_tokens=16, vocab_size=2048),
        sample_shift=1.0,
        num_frames=9,
        height=32,
        width=32,
        notes="CPU test size; not a published model",
    ),
    # The Wan architecture at CPU test size: the Wan VAE layout (x8 spatial, x4 temporal), 512
    # precomputed text tokens and the CLIP image branch, with widths that tiny random encoders
    # (egosim.model.encoders.write_tiny_wan_folder) match: UMT5 d_model 32 = text_dim, CLIP
    # hidden size 32 = image_dim. Trains from random weights or a tiny random folder; it exists
    # to run the Wan code paths (encode stage, image/text features, widening) in tests.
    "tiny-wan": ModelPreset(
        name="tiny-wan",
        transformer=TransformerSpec(
            num_attention_heads=2,
            attention_head_dim=16,
            ffn_dim=64,
            num_layers=2,
            text_dim=32,
            image_dim=32,
            added_kv_proj_dim=32,  # = inner dim, as in the published I2V configs
            freq_dim=32,
        ),
        vae=VAESpec(kind="wan"),
        text=TextSpec(kind="precomputed", max_tokens=512),
        sample_shift=3.0,
        num_frames=9,
        height=64,
        width=64,
        notes="Wan architecture at CPU test size (tiny random encoders); not a published model",
    ),
    "wan2.1-fun-1.3b-inp": ModelPreset(
        name="wan2.1-fun-1.3b-inp",
        transformer=TransformerSpec(
            num_attention_heads=12,
            attention_head_dim=128,
            ffn_dim=8960,
            num_layers=30,
            text_dim=4096,
            image_dim=1280,
            added_kv_proj_dim=1536,
        ),
        vae=VAESpec(kind="wan"),
        text=TextSpec(kind="precomputed", max_tokens=512),
        sample_shift=3.0,
        published_param_count=1_564_428_608,
        notes=(
            "Wan2.1 1.3B (dim 1536, 12 heads, 30 layers, ffn 8960; T2V transformer 1,418,996,800"
            " params) + I2V extras (in 36, CLIP image_dim 1280, added K/V 1536)"
        ),
    ),
    "wan2.1-fun-14b-inp": ModelPreset(
        name="wan2.1-fun-14b-inp",
        transformer=TransformerSpec(
            num_attention_heads=40,
            attention_head_dim=128,
            ffn_dim=13824,
            num_layers=40,
            text_dim=4096,
            image_dim=1280,
            added_kv_proj_dim=5120,
        ),
        vae=VAESpec(kind="wan"),
        text=TextSpec(kind="precomputed", max_tokens=512),
        sample_shift=3.0,
        published_param_count=16_394_878_784,
        notes="Wan2.1 I2V-14B config (dim 5120, 40 heads, 40 layers, ffn 13824, in 36)",
    ),
}


def get_preset(name: str) -> ModelPreset:
    """The preset called ``name``; raises :class:`UnknownPresetError` listing the known names."""
    try:
        return PRESETS[name]
    except KeyError:
        raise UnknownPresetError(f"unknown preset {name!r}; known: {sorted(PRESETS)}") from None


def list_presets() -> list[str]:
    """Preset names, for a CLI to list."""
    return sorted(PRESETS)
