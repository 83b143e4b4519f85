"""Convert a HaMeR checkpoint (``.ckpt``, ``.pth``) to regressor weights, without unpickling.

A ``torch.save`` file is a zip holding ``<name>/data.pkl`` (a pickle of the saved tree, where
each tensor is a call of ``torch._utils._rebuild_tensor_v2`` on a storage named by a persistent
id) and ``<name>/data/<key>`` (each storage's raw little-endian bytes).
:func:`read_checkpoint_state_dict` walks ``data.pkl`` with
:func:`~egosim.stages.hands.convert_pickle.read_pickle`: the ``state_dict``'s tensors become
numpy arrays built from the storage bytes, offset, size and stride (other storages, e.g.
optimizer states, are not read); nothing named in the file is imported or called.
``torch.load(weights_only=True)`` would also refuse arbitrary code, but it
refuses a Lightning checkpoint whole when its ``hyper_parameters`` hold a config object (HaMeR's
hold a ``yacs`` ``CfgNode``) unless that class is imported and allow-listed; here such objects
become inert markers outside the ``state_dict``, and the ``state_dict`` must be tensors only.

:func:`hamer_to_regressor` maps HaMeR's parameter names (``backbone.*``: a ViTPose ViT on
256 x 192 crops, patch convolution padded by 2; ``mano_head.*``: the MANO transformer-decoder
head) to :class:`~egosim.stages.hands.regressor_backend.HandRegressor` with ``head="mano"``:

- ``backbone.patch_embed.proj``, ``backbone.blocks.N.*``, ``backbone.last_norm`` -> the same
  names without ``backbone.``;
- ``backbone.pos_embed (1, 1 + N, C)`` -> ``pos_embed (1, N, C)`` as ViTPose uses it:
  ``pos_embed[:, 1:] + pos_embed[:, :1]`` (its class-token slot is added to every patch);
- ``mano_head.*`` -> ``mano_head.*`` (the same module tree);
- ``mano.*`` (the MANO layer's arrays, licence-gated: convert ``MANO_RIGHT.pkl`` with
  :mod:`egosim.stages.hands.convert_mano` instead) and ``discriminator.*`` (training only) are
  dropped; a ``refine_net.*`` (WiLoR) is refused: WiLoR's refinement network is not
  implemented.

The sizes are read from the weights; the numbers of attention heads are not in them and come
from arguments (HaMeR: ViT-H, 16 heads; decoder 8 heads).
"""

from __future__ import annotations

import dataclasses
import re
import zipfile
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch

from egosim.pipeline.stage import ConfigError
from egosim.stages.hands.convert_pickle import GlobalRef, Opaque, UnsafePickleError, read_pickle
from egosim.stages.hands.regressor_backend import (
    HandRegressor,
    RegressorSpec,
    RegressorWeightsError,
    save_regressor,
)

STORAGE_DTYPES = {  # torch storage class -> numpy dtype of its bytes ("bf16": bfloat16)
    "FloatStorage": "<f4",
    "DoubleStorage": "<f8",
    "HalfStorage": "<f2",
    "BFloat16Storage": "bf16",
    "LongStorage": "<i8",
    "IntStorage": "<i4",
    "ShortStorage": "<i2",
    "CharStorage": "i1",
    "ByteStorage": "u1",
    "BoolStorage": "?",
}


class CheckpointConvertError(ConfigError):
    """A checkpoint cannot be read or mapped; the message names the file and the problem."""


@dataclasses.dataclass(frozen=True)
class HamerLayout:
    """What a HaMeR checkpoint does not say about itself (its ``model_config.yaml`` does)."""

    num_heads: int = 16  # ViT attention heads (ViT-H)
    decoder_heads: int = 8  # MANO head decoder attention heads
    image_size: int = 256  # square crop side
    crop_columns: int = 32  # columns cut from each side: the ViT sees 256 x 192
    patch_padding: int = 2  # ViTPose's patch convolution padding
    box_scale: float = 2.0  # HaMeR demo's rescale of keypoint boxes


@dataclasses.dataclass(frozen=True)
class StorageRef:
    """A torch storage named by a persistent id: its file key, dtype and element count."""

    key: str
    dtype: str  # numpy dtype of its bytes, or "bf16"
    numel: int


@dataclasses.dataclass(frozen=True)
class TensorRef:
    """A tensor of a checkpoint, not yet read: a strided view of a storage."""

    storage: StorageRef
    offset: int
    size: tuple[int, ...]
    stride: tuple[int, ...]


def _rebuild_tensor(args: tuple) -> TensorRef:
    """``torch._utils._rebuild_tensor_v2(storage, offset, size, stride, ...)``, checked against
    the storage's length; read later, only if it is kept."""
    if len(args) < 4 or not isinstance(args[0], StorageRef):
        raise UnsafePickleError("_rebuild_tensor_v2 without a storage")
    storage, offset = args[0], int(args[1])
    size, stride = tuple(int(n) for n in args[2]), tuple(int(n) for n in args[3])
    if len(size) != len(stride) or offset < 0 or min(size, default=1) < 0:
        raise UnsafePickleError(f"tensor size {size} / stride {stride} / offset {offset}")
    last = offset + sum((n - 1) * st for n, st in zip(size, stride, strict=True))
    if 0 not in size and (min(stride, default=0) < 0 or last >= storage.numel):
        raise UnsafePickleError(f"tensor {size} at {offset} runs past its storage")
    return TensorRef(storage, offset, size, stride)


def _rebuild_parameter(args: tuple) -> Any:
    return args[0]  # (tensor, requires_grad, backward_hooks)


TORCH_REDUCERS = {
    ("torch._utils", "_rebuild_tensor_v2"): _rebuild_tensor,
    ("torch._utils", "_rebuild_parameter"): _rebuild_parameter,
}


def _storage_ref(pid: Any) -> StorageRef:
    """The persistent id ``('storage', torch.XStorage, key, location, numel)`` of a storage."""
    if not (isinstance(pid, tuple) and len(pid) == 5 and pid[0] == "storage"):
        raise UnsafePickleError(f"persistent id {pid!r} is not a torch storage")
    kind = pid[1]
    if not isinstance(kind, GlobalRef) or kind.name not in STORAGE_DTYPES:
        raise UnsafePickleError(f"storage type {kind} is not read")
    return StorageRef(str(pid[2]), STORAGE_DTYPES[kind.name], int(pid[4]))


def _storage_array(raw: bytes, dtype: str) -> np.ndarray:
    if dtype == "bf16":  # bfloat16 is the top half of a float32
        bits = np.frombuffer(raw, dtype="<u2").astype(np.uint32) << 16
        return bits.view(np.float32)
    return np.frombuffer(raw, dtype=dtype)


def _tensor_array(ref: TensorRef, storage: np.ndarray) -> np.ndarray:
    """The array of ``ref`` from its storage's elements (a copy)."""
    if len(storage) < ref.storage.numel:
        raise UnsafePickleError(f"storage {ref.storage.key} holds {len(storage)} elements")
    if 0 in ref.size:
        return np.zeros(ref.size, dtype=storage.dtype)
    strides = tuple(st * storage.itemsize for st in ref.stride)
    view = np.lib.stride_tricks.as_strided(storage[ref.offset :], shape=ref.size, strides=strides)
    return np.array(view)


def _state_dict_refs(tree: Any, source: str) -> dict[str, TensorRef]:
    """The tensors of a checkpoint tree's ``state_dict`` (Lightning), ``model``, or the tree
    itself; every value must be a tensor."""
    state = tree
    if isinstance(tree, dict):
        for key in ("state_dict", "model"):
            if isinstance(tree.get(key), dict):
                state = tree[key]
                break
    if not isinstance(state, dict):
        raise CheckpointConvertError(f"{source}: no state_dict in the checkpoint")
    bad = sorted(str(k) for k, v in state.items() if not isinstance(v, TensorRef))
    if bad:
        kinds = {type(state[k]).__name__ for k in bad}
        origins = {state[k].origin for k in bad if isinstance(state[k], Opaque)}
        raise CheckpointConvertError(
            f"{source}: state_dict entries {bad[:5]} are not tensors ({kinds} {origins or ''})"
        )
    return {str(k): v for k, v in state.items()}


def read_checkpoint_state_dict(path: str | Path) -> dict[str, np.ndarray]:
    """The ``state_dict`` arrays of a ``torch.save`` zip, rebuilt without unpickling; only the
    storages its tensors use are read (not, say, optimizer states). Objects other than tensors
    outside the ``state_dict`` (a Lightning checkpoint's hyper-parameters) are never built."""
    path = Path(path)
    try:
        archive = zipfile.ZipFile(path)
    except (OSError, zipfile.BadZipFile) as exc:
        raise CheckpointConvertError(
            f"{path}: not a torch.save zip ({exc}); the legacy (pre-1.6) format is not read"
        ) from exc
    with archive:
        pkls = [n for n in archive.namelist() if n.endswith("/data.pkl") or n == "data.pkl"]
        if len(pkls) != 1:
            raise CheckpointConvertError(f"{path}: expected one data.pkl, found {pkls}")
        prefix = pkls[0][: -len("data.pkl")]
        if f"{prefix}byteorder" in archive.namelist():
            order = archive.read(f"{prefix}byteorder").decode().strip()
            if order != "little":
                raise CheckpointConvertError(f"{path}: {order}-endian storages are not read")
        try:
            tree = read_pickle(
                archive.read(pkls[0]),
                reducers=TORCH_REDUCERS,
                persistent_load=_storage_ref,
                allow_unknown=True,
            )
            refs = _state_dict_refs(tree, str(path))
            storages: dict[str, np.ndarray] = {}
            state = {}
            for key, ref in refs.items():
                if ref.storage.key not in storages:
                    raw = archive.read(f"{prefix}data/{ref.storage.key}")
                    storages[ref.storage.key] = _storage_array(raw, ref.storage.dtype)
                state[key] = _tensor_array(ref, storages[ref.storage.key])
        except (UnsafePickleError, KeyError) as exc:
            raise CheckpointConvertError(f"{path}: {exc}") from exc
    return state


def _count(state: Mapping[str, np.ndarray], pattern: str) -> int:
    found = {int(m.group(1)) for k in state if (m := re.match(pattern, k))}
    return max(found) + 1 if found else 0


def _spec_from_state(state: Mapping[str, np.ndarray], layout: HamerLayout) -> RegressorSpec:
    """The :class:`RegressorSpec` whose sizes match a HaMeR state dict."""
    proj = state["backbone.patch_embed.proj.weight"]  # (C, 3, p, p)
    hidden, patch = int(proj.shape[0]), int(proj.shape[2])
    layers = _count(state, r"backbone\.blocks\.(\d+)\.")
    fc1 = state["backbone.blocks.0.mlp.fc1.weight"]  # (hidden * ratio, hidden)
    dec = "mano_head.transformer."
    embed = state[dec + "to_token_embedding.weight"]  # (dim, token_dim)
    if embed.shape[1] != 1:
        raise CheckpointConvertError(
            f"the MANO head's input token has {embed.shape[1]} values; only HaMeR's zero token "
            "(TRANSFORMER_INPUT: zero) is implemented"
        )
    if state["mano_head.decpose.weight"].shape[0] != 6 * 16:
        raise CheckpointConvertError("the MANO head must predict 6D rotations (JOINT_REP: 6d)")
    inner = state[dec + "transformer.layers.0.0.fn.to_qkv.weight"].shape[0] // 3
    if inner % layout.decoder_heads:
        raise CheckpointConvertError(f"decoder width {inner} not divisible by decoder_heads")
    return RegressorSpec(
        image_size=layout.image_size,
        patch_size=patch,
        hidden_size=hidden,
        num_layers=layers,
        num_heads=layout.num_heads,
        mlp_ratio=fc1.shape[0] / hidden,
        box_scale=layout.box_scale,
        crop_columns=layout.crop_columns,
        patch_padding=layout.patch_padding,
        head="mano",
        decoder_dim=int(embed.shape[0]),
        decoder_depth=_count(state, re.escape(dec) + r"transformer\.layers\.(\d+)\."),
        decoder_heads=layout.decoder_heads,
        decoder_dim_head=inner // layout.decoder_heads,
        decoder_mlp=int(state[dec + "transformer.layers.0.2.fn.net.0.weight"].shape[0]),
        num_betas=int(state["mano_head.decshape.weight"].shape[0]),
    )


def hamer_to_regressor(
    state: Mapping[str, np.ndarray], layout: HamerLayout = HamerLayout(), source: str = ""
) -> tuple[HandRegressor, list[str]]:
    """A :class:`HandRegressor` (head ``mano``, no MANO layer attached) holding a HaMeR state
    dict (map in the module docstring), and the dropped key prefixes."""
    if any(k.startswith("refine_net.") for k in state):
        raise CheckpointConvertError(
            f"{source}: a WiLoR checkpoint (refine_net.*): its refinement network is not "
            "implemented; only HaMeR's MANO head is"
        )
    try:
        spec = _spec_from_state(state, layout)
    except KeyError as exc:
        raise CheckpointConvertError(f"{source}: not a HaMeR checkpoint (no {exc})") from exc
    except RegressorWeightsError as exc:
        raise CheckpointConvertError(f"{source}: {exc}") from exc
    mapped, dropped = {}, set()
    for key, value in state.items():
        if key.startswith("backbone."):
            mapped[key[len("backbone.") :]] = value
        elif key.startswith("mano_head."):
            mapped[key] = value
        else:  # e.g. mano.* (MANO's arrays: their own file), discriminator.* (training)
            dropped.add(key.split(".")[0] + ".")
    pos = mapped.get("pos_embed")
    rows, cols = spec.grid
    if pos is not None and pos.shape[1] == rows * cols + 1:
        mapped["pos_embed"] = pos[:, 1:] + pos[:, :1]  # ViTPose adds the class slot to all
    elif pos is not None and pos.shape[1] != rows * cols:
        raise CheckpointConvertError(
            f"{source}: pos_embed has {pos.shape[1]} positions; image_size {spec.image_size}, "
            f"crop_columns {spec.crop_columns} and patch_padding {spec.patch_padding} give a "
            f"{rows} x {cols} grid"
        )
    mapped.pop("cls_token", None)  # ViTPose keeps it unused
    model = HandRegressor(spec)
    try:
        model.load_state_dict(
            {k: torch.from_numpy(np.ascontiguousarray(v)) for k, v in mapped.items()},
            strict=True,
        )
    except RuntimeError as exc:
        raise CheckpointConvertError(f"{source}: does not map onto the regressor: {exc}") from exc
    return model, sorted(dropped)


def convert_hamer_checkpoint(
    path: str | Path, out_dir: str | Path, layout: HamerLayout = HamerLayout()
) -> list[str]:
    """Convert the HaMeR checkpoint ``path`` to the weights folder ``out_dir`` (``config.json``
    + ``model.safetensors``; the MANO file is converted separately); the dropped prefixes."""
    state = read_checkpoint_state_dict(path)
    model, dropped = hamer_to_regressor(state, layout, str(path))
    save_regressor(model, out_dir)
    return dropped
