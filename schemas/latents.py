"""The ``latents`` schema: what the frozen encoders make of one pack row (the ``encode`` stage).

One row per clip holds everything a training step needs in latent space, so training never runs
the VAE, the text encoder or the image encoder:

- ``x0``: the VAE latent of the target video, ``(16, T', h, w)``;
- ``condition``: the 36 condition channels exactly as ``egosim.model.conditioning.
  condition_latents`` lays them out (packed mask 4, scene latent 16, skeleton latent 16),
  ``(36, T', h, w)``;
- ``text_features``: UMT5 last hidden states of the prompt's real tokens only, ``(text_length,
  text_dim)`` (Wan zero-pads to 512 tokens; the reader pads); null for presets whose text
  encoder trains (``tiny``'s hashed table reads ``prompt``);
- ``image_features``: CLIP penultimate hidden states of the first frame, ``(image_tokens,
  image_dim)`` (257 x 1280 for ViT-H/14); null for presets without Wan's image branch.

Tensors are raw little-endian, C-order bytes of the row's ``dtype`` (``float32``, ``bfloat16``
or ``float16``); their shapes are columns, so a validator checks every byte length and that every
value is finite. :func:`decode_tensor` turns them back into float32 numpy arrays (bfloat16 is
exact: it is the upper half of a float32).

Versions: 1 (first). A reader of another version raises ``SchemaCompatibilityError``; re-run
``encode`` (latents are derived data, recomputed from the pack).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import pyarrow as pa

from egosim.schemas.base import Column, ShardSchema

LATENT_CHANNELS = 16  # channels of one video latent (the model's LATENT_CHANNELS)
CONDITION_CHANNELS = 36  # packed mask 4 + scene latent 16 + skeleton latent 16
STORAGE_DTYPES = {"float32": 4, "bfloat16": 2, "float16": 2}  # name -> bytes per value


def tensor_nbytes(shape: tuple[int, ...], dtype: str) -> int:
    """Bytes of a tensor of ``shape`` stored as ``dtype`` (one of :data:`STORAGE_DTYPES`)."""
    return int(np.prod(shape, dtype=np.int64)) * STORAGE_DTYPES[dtype]


def decode_tensor(data: bytes, shape: tuple[int, ...], dtype: str) -> np.ndarray:
    """Raw bytes of ``dtype`` -> a writable float32 array of ``shape`` (exact for every dtype).

    Raises ValueError naming the sizes when the byte count does not match the shape.
    """
    if dtype not in STORAGE_DTYPES:
        raise ValueError(f"dtype must be one of {sorted(STORAGE_DTYPES)}, got {dtype!r}")
    want = tensor_nbytes(shape, dtype)
    if len(data) != want:
        raise ValueError(f"{len(data)} bytes, a {dtype} tensor of shape {shape} needs {want}")
    if dtype == "bfloat16":
        # bfloat16 is the upper 16 bits of a float32: widening is a shift, exact.
        half = np.frombuffer(data, dtype="<u2").astype(np.uint32) << 16
        return half.view(np.float32).reshape(shape)
    raw = np.frombuffer(data, dtype="<f4" if dtype == "float32" else "<f2")
    return raw.astype(np.float32).reshape(shape)  # astype copies: writable


def _tensor_problems(row: Mapping[str, Any], column: str, shape: tuple[int, ...]) -> list[str]:
    data = row[column]
    try:
        values = decode_tensor(data, shape, row["dtype"])
    except ValueError as exc:
        return [f"{column}: {exc}"]
    if not np.all(np.isfinite(values)):
        return [f"{column} has non-finite values"]
    return []


def _check_latents(row: Mapping[str, Any]) -> list[str]:
    problems: list[str] = []
    t, h, w = row["num_frames"], row["height"], row["width"]
    tl, lh, lw = row["latent_frames"], row["latent_height"], row["latent_width"]
    if t < 1 or (t - 1) % 4:
        problems.append(f"num_frames must be 1 + 4k (the latent layout), got {t}")
    elif tl != 1 + (t - 1) // 4:
        problems.append(f"latent_frames must be 1 + (num_frames - 1) / 4 = {1 + (t - 1) // 4}")
    if min(h, w, lh, lw) < 1:
        problems.append(f"sizes must be positive, got {h}x{w} pixels, {lh}x{lw} latent")
    elif h % lh or w % lw or h // lh != w // lw:
        problems.append(
            f"pixel size {h}x{w} must be one integer factor times the latent size {lh}x{lw}"
        )
    if row["dtype"] not in STORAGE_DTYPES:
        problems.append(f"dtype must be one of {sorted(STORAGE_DTYPES)}, got {row['dtype']!r}")
        return problems
    if problems:
        return problems
    problems += _tensor_problems(row, "x0", (LATENT_CHANNELS, tl, lh, lw))
    problems += _tensor_problems(row, "condition", (CONDITION_CHANNELS, tl, lh, lw))
    for tensor, count, dim in (
        ("text_features", "text_length", "text_dim"),
        ("image_features", "image_tokens", "image_dim"),
    ):
        present = [row[c] is not None for c in (tensor, count, dim)]
        if any(present) and not all(present):
            problems.append(f"{tensor}, {count} and {dim} must all be set or all be null")
        elif all(present):
            if row[count] < 1 or row[dim] < 1:
                problems.append(f"{count} and {dim} must be >= 1, got {row[count]}, {row[dim]}")
            else:
                problems += _tensor_problems(row, tensor, (row[count], row[dim]))
    if row["text_length"] is not None and row["text_length"] > row["text_max_tokens"]:
        problems.append(
            f"text_length {row['text_length']} exceeds text_max_tokens {row['text_max_tokens']}"
        )
    return problems


LATENTS = ShardSchema(
    name="latents",
    version=1,
    doc=(
        "One training sample per clip in latent space: target latent, the 36 condition channels, "
        "text and image features of the frozen encoders, prompt."
    ),
    columns=(
        Column("clip_id", pa.string(), "Clip id, joins with the pack shard it was encoded from."),
        Column("num_frames", pa.int32(), "Pixel frames T of the packed sample (1 + 4k)."),
        Column("height", pa.int32(), "Pixel frame height H of the packed sample."),
        Column("width", pa.int32(), "Pixel frame width W of the packed sample."),
        Column("fps", pa.float64(), "Frames per second of the packed sample."),
        Column("preset", pa.string(), "Model preset whose frozen encoders made the row."),
        Column("latent_frames", pa.int32(), "Latent frames T' = 1 + (T - 1) / 4."),
        Column("latent_height", pa.int32(), "Latent height h = H / the VAE's spatial factor."),
        Column("latent_width", pa.int32(), "Latent width w = W / the VAE's spatial factor."),
        Column(
            "dtype",
            pa.string(),
            "Storage dtype of every tensor column: 'float32', 'bfloat16' or 'float16' "
            "(little-endian, C order).",
        ),
        Column("x0", pa.binary(), "(16, T', h, w) normalised VAE latent of the target video."),
        Column(
            "condition",
            pa.binary(),
            "(36, T', h, w) condition channels: packed visibility mask 4 (1 = known), scene "
            "latent 16 (unseen pixels 0, frame 0 = first frame), skeleton latent 16.",
        ),
        Column("prompt", pa.string(), "Text prompt of the clip."),
        Column(
            "text_max_tokens",
            pa.int32(),
            "Sequence length the text features are zero-padded to in training (Wan: 512).",
        ),
        Column(
            "text_features",
            pa.binary(),
            "(text_length, text_dim) UMT5 last hidden states of the real tokens (attention "
            "mask 1), no padding rows; null when the preset's text encoder trains.",
            True,
        ),
        Column("text_length", pa.int32(), "Real tokens of the prompt (EOS included).", True),
        Column("text_dim", pa.int32(), "Width of the text features (UMT5-XXL: 4096).", True),
        Column(
            "image_features",
            pa.binary(),
            "(image_tokens, image_dim) CLIP vision penultimate hidden states of the first frame "
            "(Wan's image branch); null for presets without it.",
            True,
        ),
        Column("image_tokens", pa.int32(), "Image feature tokens (ViT-H/14 at 224: 257).", True),
        Column("image_dim", pa.int32(), "Width of the image features (ViT-H/14: 1280).", True),
    ),
    validators=(_check_latents,),
)
