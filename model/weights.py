"""Published transformer weights: read a folder, name its key layout, convert, check, export.

Wan2.1-Fun-InP transformers are published in two key layouts of the same tensors:

- ``diffusers``: diffusers' ``WanTransformer3DModel`` names (``blocks.0.attn1.to_q.weight``,
  ``condition_embedder.text_embedder.linear_1.weight``, ``proj_out.weight`` ...), as in a
  ``transformer/`` folder of a diffusers pipeline;
- ``original``: the Wan / VideoX-Fun ``WanModel`` names (``blocks.0.self_attn.q.weight``,
  ``text_embedding.0.weight``, ``head.head.weight`` ...), as in the VideoX-Fun
  ``Wan2.1-Fun-*-InP`` folders (``diffusion_pytorch_model*.safetensors``).

The two differ by names only: every tensor has the same shape and orientation in both (no fused
or transposed tensor), so converting is a rename through one key map (:data:`TOP_MODULES`,
:data:`BLOCK_MODULES`, :data:`TOP_PARAMS`, :data:`BLOCK_PARAMS`), done once, when the folder is
read (:func:`read_weights_folder`). One trap: the original block calls its norms in the order
``norm1, norm3, norm2``, so its affine cross-attention norm is ``norm3`` where diffusers has
``norm2``; its other two norms have no parameters. Keys saved with ComfyUI's
``model.diffusion_model.`` prefix are read too.

Only safetensors headers are read to inspect a folder (names, shapes, dtypes), so
:func:`check_weights_folder` is instant on a 14B folder; tensors are read when loading. Pickled
files (``.pth``, ``.bin``, ``.ckpt``) are listed, never opened.
"""

from __future__ import annotations

import json
import math
import os
import re
import shutil
import uuid
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import torch

from egosim.model.errors import ModelError, WeightsMismatchError
from egosim.model.presets import (
    EGOSIM_IN_CHANNELS,
    PRESETS,
    PRETRAINED_IN_CHANNELS,
    ModelPreset,
    get_preset,
)

LAYOUT_DIFFUSERS = "diffusers"  # diffusers' WanTransformer3DModel key names
LAYOUT_ORIGINAL = "original"  # Wan / VideoX-Fun WanModel key names
LAYOUT_UNKNOWN = "unknown"  # neither (refused when loading)

# Prefixes some tools put before every key (ComfyUI saves `model.diffusion_model.`); stripped
# when every key of the folder carries the same one.
KNOWN_PREFIXES = ("model.diffusion_model.", "diffusion_model.")

# Keys diffusers itself drops when it loads Wan checkpoints (no parameter of the model).
IGNORED_DIFFUSERS_KEYS = ("norm_added_q.weight",)

# Files that are pickles: never opened (a pickle can run code).
PICKLE_SUFFIXES = (".pth", ".pt", ".bin", ".ckpt", ".pkl")

# Original (Wan / VideoX-Fun) module -> diffusers module, outside the blocks. Each maps its
# `.weight` and `.bias`. Sequential indices skip the parameter-free activations (GELU, SiLU).
TOP_MODULES = {
    "patch_embedding": "patch_embedding",
    "text_embedding.0": "condition_embedder.text_embedder.linear_1",
    "text_embedding.2": "condition_embedder.text_embedder.linear_2",
    "time_embedding.0": "condition_embedder.time_embedder.linear_1",
    "time_embedding.2": "condition_embedder.time_embedder.linear_2",
    "time_projection.1": "condition_embedder.time_proj",
    "img_emb.proj.0": "condition_embedder.image_embedder.norm1",
    "img_emb.proj.1": "condition_embedder.image_embedder.ff.net.0.proj",
    "img_emb.proj.3": "condition_embedder.image_embedder.ff.net.2",
    "img_emb.proj.4": "condition_embedder.image_embedder.norm2",
    "head.head": "proj_out",
}
# Original -> diffusers module inside `blocks.N.`.
BLOCK_MODULES = {
    "self_attn.q": "attn1.to_q",
    "self_attn.k": "attn1.to_k",
    "self_attn.v": "attn1.to_v",
    "self_attn.o": "attn1.to_out.0",
    "self_attn.norm_q": "attn1.norm_q",
    "self_attn.norm_k": "attn1.norm_k",
    "cross_attn.q": "attn2.to_q",
    "cross_attn.k": "attn2.to_k",
    "cross_attn.v": "attn2.to_v",
    "cross_attn.o": "attn2.to_out.0",
    "cross_attn.norm_q": "attn2.norm_q",
    "cross_attn.norm_k": "attn2.norm_k",
    "cross_attn.k_img": "attn2.add_k_proj",
    "cross_attn.v_img": "attn2.add_v_proj",
    "cross_attn.norm_k_img": "attn2.norm_added_k",
    "norm3": "norm2",  # the affine cross-attention norm (see the module docstring)
    "ffn.0": "ffn.net.0.proj",
    "ffn.2": "ffn.net.2",
}
# Bare parameters (no `.weight`): the adaLN modulation tables, (1, 2, D) and (1, 6, D).
TOP_PARAMS = {"head.modulation": "scale_shift_table"}
BLOCK_PARAMS = {"modulation": "scale_shift_table"}

_LEAVES = ("weight", "bias")
_BLOCK = re.compile(r"blocks\.(\d+)\.(.+)")


def _invert(table: dict[str, str]) -> dict[str, str]:
    inverse = {v: k for k, v in table.items()}
    if len(inverse) != len(table):  # a constant table: caught by the tests, never by users
        raise ModelError(f"key map is not one-to-one: {table}")
    return inverse


_INVERSE = (
    _invert(TOP_MODULES),
    _invert(BLOCK_MODULES),
    _invert(TOP_PARAMS),
    _invert(BLOCK_PARAMS),
)


def _rename(
    key: str,
    top: dict[str, str],
    block: dict[str, str],
    top_params: dict[str, str],
    block_params: dict[str, str],
) -> str | None:
    match = _BLOCK.fullmatch(key)
    prefix, rest, modules, params = "", key, top, top_params
    if match:
        prefix, rest, modules, params = f"blocks.{match[1]}.", match[2], block, block_params
    if rest in params:
        return prefix + params[rest]
    module, _, leaf = rest.rpartition(".")
    if leaf in _LEAVES and module in modules:
        return f"{prefix}{modules[module]}.{leaf}"
    return None


def original_to_diffusers_key(key: str) -> str | None:
    """The diffusers name of an original-layout (Wan / VideoX-Fun) key, or None if unknown."""
    return _rename(key, TOP_MODULES, BLOCK_MODULES, TOP_PARAMS, BLOCK_PARAMS)


def diffusers_to_original_key(key: str) -> str | None:
    """The original-layout name of a diffusers key, or None if it has none."""
    return _rename(key, *_INVERSE)


def _convert(
    state: dict[str, torch.Tensor], rename: Callable[[str], str | None], direction: str
) -> dict[str, torch.Tensor]:
    out, unknown = {}, []
    for key, value in state.items():
        new = rename(key)
        if new is None:
            unknown.append(key)
        else:
            out[new] = value
    if unknown:
        raise WeightsMismatchError(
            f"{direction}: {len(unknown)} keys have no mapping: {sorted(unknown)[:8]}"
        )
    return out


def original_to_diffusers(state: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """Rename an original-layout state dict to diffusers names (tensors unchanged)."""
    return _convert(state, original_to_diffusers_key, "original -> diffusers")


def diffusers_to_original(state: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """Rename a diffusers state dict to original (Wan / VideoX-Fun) names (tensors unchanged).

    Keys diffusers drops on load (``norm_added_q``) are dropped here too.
    """
    kept = {k: v for k, v in state.items() if not k.endswith(IGNORED_DIFFUSERS_KEYS)}
    return _convert(kept, diffusers_to_original_key, "diffusers -> original")


@dataclass(frozen=True)
class TensorEntry:
    """Where one tensor of a weights folder lives and what its header says."""

    file: Path  # the safetensors file holding it
    stored_key: str  # its name in that file, as stored (either layout, prefix included)
    shape: tuple[int, ...]  # shape from the header
    dtype: str  # safetensors dtype name from the header ("BF16", "F32", ...)


@dataclass(frozen=True)
class WeightsFolder:
    """A transformer weights folder as read from its safetensors headers (no tensor loaded)."""

    folder: Path  # the folder the files were read from (`<given>/transformer` when it exists)
    files: tuple[Path, ...]  # its safetensors files, sorted
    other_files: tuple[Path, ...]  # its other files (config, index, pickles: never opened)
    layout: str  # LAYOUT_DIFFUSERS or LAYOUT_ORIGINAL
    prefix: str  # key prefix stripped from every key ("" when none)
    tensors: dict[str, TensorEntry]  # diffusers name -> entry (ignored keys left out)

    @property
    def shapes(self) -> dict[str, tuple[int, ...]]:
        """Diffusers name -> shape of every tensor."""
        return {k: e.shape for k, e in self.tensors.items()}

    def parameter_count(self) -> int:
        """Number of values over every tensor."""
        return sum(math.prod(e.shape) for e in self.tensors.values())

    def dtype_counts(self) -> dict[str, int]:
        """Header dtype -> number of values stored in it."""
        counts: Counter[str] = Counter()
        for e in self.tensors.values():
            counts[e.dtype] += math.prod(e.shape)
        return dict(counts.most_common())

    def load_state_dict(self, dtype: torch.dtype | None = None) -> dict[str, torch.Tensor]:
        """Every tensor, under its diffusers name, on CPU (cast to ``dtype`` when given)."""
        from safetensors import safe_open

        by_file: dict[Path, list[tuple[str, TensorEntry]]] = {}
        for name, entry in self.tensors.items():
            by_file.setdefault(entry.file, []).append((name, entry))
        state: dict[str, torch.Tensor] = {}
        for path, entries in sorted(by_file.items()):
            with safe_open(path, framework="pt", device="cpu") as f:
                for name, entry in entries:
                    t = f.get_tensor(entry.stored_key)
                    state[name] = t if dtype is None else t.to(dtype)
        return state


def transformer_folder(folder: str | Path) -> Path:
    """``folder/transformer`` when it exists (a diffusers pipeline folder), else ``folder``."""
    folder = Path(folder)
    sub = folder / "transformer"
    return sub if sub.is_dir() else folder


SAFETENSORS_MAX_HEADER = 100_000_000  # bytes; the safetensors format's own cap on its header


def read_safetensors_header(path: Path) -> dict[str, tuple[tuple[int, ...], str]]:
    """Tensor name -> (shape, dtype) from a safetensors file's header, reading nothing else.

    The format (huggingface/safetensors, "Format") is an 8-byte little-endian header length,
    then that many bytes of JSON: ``{name: {"dtype", "shape", "data_offsets": [begin, end]}}``
    plus an optional ``__metadata__``. ``safe_open`` would map the whole file (33 GB for the
    14B model, refused on a login node with little memory); this reads the header bytes only,
    and checks that the file is long enough for the data it declares (a truncated download).
    """
    try:
        size = path.stat().st_size
        with path.open("rb") as f:
            length = int.from_bytes(f.read(8), "little")
            if not 2 <= length <= min(SAFETENSORS_MAX_HEADER, size - 8):
                raise WeightsMismatchError(
                    f"{path}: not a safetensors file (header length {length}, file {size} bytes)"
                )
            header = json.loads(f.read(length))
    except (OSError, ValueError) as exc:
        raise WeightsMismatchError(f"{path}: not a readable safetensors file ({exc})") from exc
    if not isinstance(header, dict):
        raise WeightsMismatchError(f"{path}: safetensors header is not a JSON object")
    out: dict[str, tuple[tuple[int, ...], str]] = {}
    data_end = 0
    for name, info in header.items():
        if name == "__metadata__":
            continue
        try:
            shape = tuple(int(d) for d in info["shape"])
            dtype = str(info["dtype"])
            data_end = max(data_end, int(info["data_offsets"][1]))
        except (KeyError, TypeError, ValueError, IndexError) as exc:
            raise WeightsMismatchError(f"{path}: bad header entry for {name!r} ({exc})") from exc
        out[name] = (shape, dtype)
    if 8 + length + data_end > size:
        raise WeightsMismatchError(
            f"{path}: truncated: its header declares {8 + length + data_end} bytes, the file "
            f"has {size}"
        )
    return out


def _read_headers(files: list[Path]) -> dict[str, tuple[Path, tuple[int, ...], str]]:
    found: dict[str, tuple[Path, tuple[int, ...], str]] = {}
    for path in files:
        for key, (shape, dtype) in read_safetensors_header(path).items():
            if key in found:
                raise WeightsMismatchError(
                    f"tensor {key!r} is in both {found[key][0].name} and {path.name}"
                )
            found[key] = (path, shape, dtype)
    return found


def _common_prefix(keys: list[str]) -> str:
    for prefix in KNOWN_PREFIXES:
        if keys and all(k.startswith(prefix) for k in keys):
            return prefix
    return ""


def _misfit_message(folder: Path, headers: dict, misfits: list[str], closest: str) -> str:
    per_file: dict[str, list[str]] = {}
    for key in misfits:
        per_file.setdefault(headers[key][0].name, []).append(key)
    where = "; ".join(
        f"{name}: {len(keys)} keys such as {sorted(keys)[:5]}"
        for name, keys in sorted(per_file.items())
    )
    return (
        f"{folder}: the safetensors keys fit neither the diffusers nor the original (Wan / "
        f"VideoX-Fun) layout of a Wan transformer; closest is {closest}, which does not know "
        f"{where}"
    )


def read_weights_folder(folder: str | Path) -> WeightsFolder:
    """Read the safetensors headers of a transformer folder and name its layout.

    Accepts a diffusers pipeline folder (its ``transformer/`` is read) or a folder of
    ``*.safetensors`` in either layout (sharded or not). Raises :class:`WeightsMismatchError`
    naming the folder when it has no safetensors file (listing any pickles it skipped), and
    naming each file and its unknown keys when the keys fit neither layout.
    """
    folder = transformer_folder(folder)
    if not folder.is_dir():
        raise WeightsMismatchError(f"no .safetensors files in {folder}: no such folder")
    files = sorted(folder.glob("*.safetensors"))
    others = sorted(p for p in folder.iterdir() if p.is_file() and p not in files)
    if not files:
        pickles = [p.name for p in others if p.suffix in PICKLE_SUFFIXES]
        extra = f" (pickle files {pickles} are never opened: save them as safetensors)"
        message = f"no .safetensors files in {folder}" + (extra if pickles else "")
        raise WeightsMismatchError(message)
    headers = _read_headers(files)
    prefix = _common_prefix(list(headers))
    stripped = {k[len(prefix) :]: k for k in headers}
    as_diffusers = [
        k
        for k in stripped
        if k.endswith(IGNORED_DIFFUSERS_KEYS) or (diffusers_to_original_key(k) is not None)
    ]
    as_original = [k for k in stripped if original_to_diffusers_key(k) is not None]
    if len(as_diffusers) == len(stripped):
        layout = LAYOUT_DIFFUSERS
        names = {k: k for k in stripped if not k.endswith(IGNORED_DIFFUSERS_KEYS)}
    elif len(as_original) == len(stripped):
        layout = LAYOUT_ORIGINAL
        names = {k: original_to_diffusers_key(k) for k in stripped}
    else:
        closest, fits = (
            (LAYOUT_DIFFUSERS, set(as_diffusers))
            if len(as_diffusers) >= len(as_original)
            else (LAYOUT_ORIGINAL, set(as_original))
        )
        misfits = [stripped[k] for k in stripped if k not in fits]
        raise WeightsMismatchError(_misfit_message(folder, headers, misfits, closest))
    tensors = {}
    for key, name in names.items():
        path, shape, dtype = headers[stripped[key]]
        tensors[name] = TensorEntry(path, stripped[key], shape, dtype)
    return WeightsFolder(folder, tuple(files), tuple(others), layout, prefix, tensors)


def infer_dims(shapes: dict[str, tuple[int, ...]]) -> dict[str, int | tuple[int, ...] | None]:
    """Architecture numbers read off diffusers-named shapes (None where a tensor is absent)."""

    def dim(key: str, axis: int) -> int | None:
        shape = shapes.get(key)
        return None if shape is None or len(shape) <= axis else shape[axis]

    patch = shapes.get("patch_embedding.weight")
    patch_size = tuple(patch[2:]) if patch is not None and len(patch) == 5 else None
    blocks = {int(m[1]) for k in shapes if (m := _BLOCK.fullmatch(k))}
    out = dim("proj_out.weight", 0)
    if out is not None and patch_size:
        out //= math.prod(patch_size)
    return {
        "in_channels": dim("patch_embedding.weight", 1),
        "inner_dim": dim("patch_embedding.weight", 0),
        "patch_size": patch_size,
        "num_layers": len(blocks),
        "ffn_dim": dim("blocks.0.ffn.net.0.proj.weight", 0),
        "text_dim": dim("condition_embedder.text_embedder.linear_1.weight", 1),
        "freq_dim": dim("condition_embedder.time_embedder.linear_1.weight", 1),
        "image_dim": dim("condition_embedder.image_embedder.norm1.weight", 0),
        "added_kv_proj_dim": dim("blocks.0.attn2.add_k_proj.weight", 1),
        "out_channels": out,
    }


@dataclass
class WeightsReport:
    """What a weights folder holds and which presets it fits (from headers only)."""

    weights: WeightsFolder  # the folder as read
    dims: dict  # architecture numbers (infer_dims)
    fits: list[str]  # presets whose architecture the folder fits (widening 36 -> 52 allowed)
    problems: dict[str, str] = field(default_factory=dict)  # preset -> why it does not fit

    def format(self) -> str:
        """A human-readable report."""
        w = self.weights
        lines = [f"folder: {w.folder}", "files:"]
        for path in (*w.files, *w.other_files):
            note = "" if path in w.files else "  (not read)"
            lines.append(f"  {path.name}  {path.stat().st_size / 2**20:,.1f} MiB{note}")
        dtypes = ", ".join(f"{d} {n:,}" for d, n in w.dtype_counts().items())
        prefix = f" (key prefix {w.prefix!r} stripped)" if w.prefix else ""
        lines += [
            f"layout: {w.layout}{prefix}",
            f"tensors: {len(w.tensors)}; parameters: {w.parameter_count():,}; dtype: {dtypes}",
            "dims: " + ", ".join(f"{k}={v}" for k, v in self.dims.items()),
        ]
        for name in PRESETS:
            if name in self.fits:
                stored = self.dims["in_channels"]
                how = f" (patch embedding widened {stored} -> 52)" if stored != 52 else ""
                lines.append(f"fits preset {name}{how}")
            elif name in self.problems:
                lines.append(f"not {name}: {self.problems[name]}")
        return "\n".join(lines)


def fit_problem(preset: ModelPreset, shapes: dict[str, tuple[int, ...]]) -> str | None:
    """Why ``shapes`` (diffusers names) cannot load into ``preset`` at 52 channels, or None."""
    from egosim.model.network import check_weight_shapes

    try:
        check_weight_shapes(preset, shapes, EGOSIM_IN_CHANNELS)
    except WeightsMismatchError as exc:
        return str(exc).removeprefix(f"preset {preset.name!r}: ")
    return None


def check_weights_folder(folder: str | Path, presets: list[str] | None = None) -> WeightsReport:
    """Inspect a weights folder (headers only) and test it against ``presets`` (default: all).

    Raises :class:`WeightsMismatchError` when the folder has no safetensors or its keys fit
    neither layout; a folder that reads but fits no preset is a report with empty ``fits``.
    """
    weights = read_weights_folder(folder)
    shapes = weights.shapes
    report = WeightsReport(weights, infer_dims(shapes), [])
    for name in presets or list(PRESETS):
        problem = fit_problem(get_preset(name), shapes)
        if problem is None:
            report.fits.append(name)
        else:
            report.problems[name] = problem
    return report


def expected_layout(preset: ModelPreset) -> str:
    """The weights a preset loads, in words (for ``egosim presets``)."""
    if preset.vae.kind != "wan":
        return "none needed (initialised); optional diffusers transformer folder"
    return (
        f"local folder: transformer in the diffusers or original (Wan / VideoX-Fun) layout, "
        f"safetensors, in_channels {PRETRAINED_IN_CHANNELS} (widened to {EGOSIM_IN_CHANNELS}); "
        "vae/ in diffusers format (AutoencoderKLWan)"
    )


EXPORT_RECORD = "egosim_export.json"  # provenance file written beside the exported weights


def export_transformer(
    run: str | Path, out: str | Path, use_ema: bool = True, dtype: torch.dtype | None = None
) -> Path:
    """Write a trained run's transformer as a diffusers folder ``out``; returns ``out``.

    ``run``: a run directory (its latest checkpoint) or a checkpoint file. EMA weights are
    used when the checkpoint has them and ``use_ema``; LoRA adapters are merged. ``out`` then
    loads with ``WanTransformer3DModel.from_pretrained(out)`` (and with
    :func:`egosim.model.network.load_transformer`). It is written to a temporary folder beside
    it and renamed, so a failed export leaves nothing under ``out``; an existing ``out`` is
    refused. ``out/egosim_export.json`` records the checkpoint, step, preset and EMA choice.
    """
    from egosim.model.inference import load_trained
    from egosim.model.lora import merge_lora
    from egosim.model.network import build_transformer

    out = Path(out)
    if out.exists():
        raise WeightsMismatchError(f"export folder {out} already exists; choose a new --out")
    loaded = load_trained(run, device="cpu", use_ema=use_ema)
    trained = loaded.bundle.denoiser.transformer
    merge_lora(trained)  # LoRA runs: adapters folded into the base weights, in place
    state = {k: v.detach() for k, v in trained.state_dict().items()}
    # A fresh plain module of the same architecture: whatever wrapped the trained one is gone.
    preset = loaded.bundle.preset
    plain = build_transformer(preset, trained.config.in_channels, device="meta")
    expected, got = set(plain.state_dict()), set(state)
    if expected != got:
        raise WeightsMismatchError(
            f"{loaded.checkpoint}: trained transformer does not reduce to a plain "
            f"WanTransformer3DModel; missing {sorted(expected - got)[:5]}, extra "
            f"{sorted(got - expected)[:5]}"
        )
    if dtype is not None:
        state = {k: v.to(dtype) for k, v in state.items()}
    plain.load_state_dict(state, strict=True, assign=True)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(f"{out.name}.tmp-{uuid.uuid4().hex[:8]}")
    try:
        plain.save_pretrained(tmp, safe_serialization=True)
        record = {
            "checkpoint": str(loaded.checkpoint),
            "step": loaded.step,
            "preset": preset.name,
            "ema": loaded.ema,
            "in_channels": int(trained.config.in_channels),
            "dtype": str(next(iter(state.values())).dtype).removeprefix("torch."),
        }
        (tmp / EXPORT_RECORD).write_text(json.dumps(record, indent=2) + "\n")
        os.replace(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return out
