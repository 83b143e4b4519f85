"""The ``encode`` stage: what the frozen encoders make of each pack row, stored as ``latents``.

Per clip: the VAE latent of the target video and the 36 condition channels (computed by
``egosim.model.conditioning.encode_batch``, the function training calls on the fly, so the two
agree exactly), UMT5 features of the prompt and CLIP features of the hand-free first frame when
the preset reads them (``egosim.model.encoders`` says how each follows diffusers' Wan
pipelines). Training on a ``latents`` shard then never runs a frozen encoder.

Backends follow the preset: ``packed`` (``tiny``: its lossless packed VAE; the hashed text
encoder trains, so no text features, and there is no image branch) and ``wan`` (Wan presets:
``AutoencoderKLWan`` from ``<weights_dir>/vae``, UMT5 and CLIP from the diffusers-layout folders
under ``weights_dir`` or the folders given one by one). Nothing is downloaded.

The encoders are loaded once per stage instance, on the first clip. A clip whose frame size the
preset cannot take (not a multiple of its VAE factor times the patch size) is rejected with its
size; so is a pack row that does not decode.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any, ClassVar

from egosim.pipeline.records import PackRecord
from egosim.pipeline.stage import ClipRejected, ClipStage, ConfigError, StageConfig
from egosim.schemas import ShardSchema
from egosim.schemas.latents import LATENTS, STORAGE_DTYPES
from egosim.schemas.pack import PACK
from egosim.stages.common.packed import sample_from_pack_row

if TYPE_CHECKING:  # torch, diffusers and transformers load with the encoders
    import torch

    from egosim.model.encoders import FrozenEncoders

ENCODER_DTYPES = ("float32", "bfloat16", "float16")  # text/image encoder weight dtypes


@dataclasses.dataclass(frozen=True)
class EncodeConfig(StageConfig):
    """Parameters of ``encode``."""

    preset: str = "tiny"  # model preset whose frozen encoders run (egosim.model.presets)
    weights_dir: str = ""  # diffusers-layout Wan folder (vae/, text_encoder/, ...); Wan presets
    text_encoder_dir: str = ""  # UMT5EncoderModel folder; "" = <weights_dir>/text_encoder
    tokenizer_dir: str = ""  # UMT5 tokenizer folder; "" = <weights_dir>/tokenizer
    image_encoder_dir: str = ""  # CLIPVisionModel folder; "" = <weights_dir>/image_encoder
    image_processor_dir: str = ""  # CLIPImageProcessor folder; "" = <weights_dir>/image_processor
    device: str = "auto"  # torch device: auto (cuda if available), cpu, cuda[:n]
    encoder_dtype: str = "float32"  # UMT5 / CLIP weights dtype (float32|bfloat16|float16)
    storage_dtype: str = "float32"  # dtype of the stored tensors (float32|bfloat16|float16)

    def __post_init__(self) -> None:
        from egosim.model.errors import UnknownPresetError
        from egosim.model.presets import get_preset

        problems = []
        try:
            preset = get_preset(self.preset)
        except UnknownPresetError as exc:
            problems.append(str(exc))
        else:
            if preset.vae.kind == "wan" and not self.weights_dir:
                problems.append(
                    f"preset {self.preset!r} needs weights_dir (a folder with vae/), got ''"
                )
        if self.encoder_dtype not in ENCODER_DTYPES:
            problems.append(
                f"encoder_dtype must be one of {ENCODER_DTYPES}, got {self.encoder_dtype!r}"
            )
        if self.storage_dtype not in STORAGE_DTYPES:
            problems.append(
                f"storage_dtype must be one of {tuple(STORAGE_DTYPES)}, got {self.storage_dtype!r}"
            )
        if not self.device or self.device.split(":")[0] not in ("auto", "cpu", "cuda", "mps"):
            problems.append(f"device must be auto, cpu or cuda[:n], got {self.device!r}")
        if problems:
            raise ConfigError("; ".join(problems))


def tensor_bytes(tensor: torch.Tensor, dtype: str) -> bytes:
    """A tensor as raw little-endian C-order bytes of ``dtype`` (rounded to nearest even).

    The inverse is :func:`egosim.schemas.latents.decode_tensor`.
    """
    import torch

    t = tensor.detach().cpu().contiguous()
    if dtype == "bfloat16":
        return t.to(torch.bfloat16).view(torch.int16).numpy().astype("<i2").tobytes()
    if dtype == "float16":
        return t.to(torch.float16).numpy().astype("<f2").tobytes()
    if dtype == "float32":
        return t.to(torch.float32).numpy().astype("<f4").tobytes()
    raise ValueError(f"dtype must be one of {sorted(STORAGE_DTYPES)}, got {dtype!r}")


class EncodeStage(ClipStage):
    """Precompute VAE latents and text / image features of packed clips."""

    name = "encode"
    description = "precompute VAE latents, UMT5 text and CLIP image features of packed clips"
    config_class = EncodeConfig
    inputs: ClassVar[Mapping[str, ShardSchema]] = {"pack": PACK}
    output = LATENTS
    backends = ("packed", "wan")  # chosen by the preset's VAE kind
    gpu = True
    config: EncodeConfig

    def __init__(self, config: StageConfig | None = None) -> None:
        super().__init__(config)
        self._encoders: FrozenEncoders | None = None

    @property
    def encoders(self) -> FrozenEncoders:
        """The preset's frozen encoders (loaded on first use)."""
        if self._encoders is None:
            from egosim.model.distributed import resolve_device
            from egosim.model.encoders import EncoderFolders, load_encoders

            cfg = self.config
            folders = EncoderFolders.from_root(
                cfg.weights_dir or None,
                text_encoder=cfg.text_encoder_dir,
                tokenizer=cfg.tokenizer_dir,
                image_encoder=cfg.image_encoder_dir,
                image_processor=cfg.image_processor_dir,
            )
            self._encoders = load_encoders(
                cfg.preset, folders, resolve_device(cfg.device), cfg.encoder_dtype
            )
        return self._encoders

    def process(self, rows: Mapping[str, Mapping[str, Any]]) -> dict[str, Any]:
        """Encode one pack row into a latents row (or reject it with the reason)."""
        from egosim.model.presets import get_preset

        cfg = self.config
        row = PackRecord.of(rows["pack"])
        cid = row.clip_id
        t, h, w = row.size
        preset = get_preset(cfg.preset)
        m = preset.pixel_multiple
        if h % m or w % m:
            raise ClipRejected(
                f"frame size {h}x{w} is not a multiple of {m} (preset {preset.name!r}: VAE "
                f"factor {preset.vae.spatial_factor} x patch {preset.transformer.patch_size[1]})"
                "; pack at a size it takes"
            )
        sample = sample_from_pack_row(row)
        (latent,) = self.encoders.encode([sample], [cid])
        _, tl, lh, lw = latent.x0.shape
        dtype = cfg.storage_dtype
        text, image = latent.text_embedding, latent.image_embedding
        return {
            "clip_id": cid,
            "num_frames": t,
            "height": h,
            "width": w,
            "fps": row.fps,
            "preset": preset.name,
            "latent_frames": int(tl),
            "latent_height": int(lh),
            "latent_width": int(lw),
            "dtype": dtype,
            "x0": tensor_bytes(latent.x0, dtype),
            "condition": tensor_bytes(latent.condition, dtype),
            "prompt": latent.prompt,
            "text_max_tokens": preset.text.max_tokens,
            "text_features": None if text is None else tensor_bytes(text, dtype),
            "text_length": None if text is None else int(text.shape[0]),
            "text_dim": None if text is None else int(text.shape[1]),
            "image_features": None if image is None else tensor_bytes(image, dtype),
            "image_tokens": None if image is None else int(image.shape[0]),
            "image_dim": None if image is None else int(image.shape[1]),
        }
