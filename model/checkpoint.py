"""Checkpoints as tensors, never pickles: safetensors files plus JSON.

Training checkpoints (format 3, :mod:`egosim.model.train`) are folders written through
``torch.distributed.checkpoint``'s safetensors storage (:mod:`egosim.model.distributed`): one
``.safetensors`` file per tensor group plus ``state.json``. This module holds what every
checkpoint reader shares: :func:`refuse_pickle` (a file, or each file of a folder, that starts
like a pickle or a ``torch.save`` zip is refused with :class:`UnsafeCheckpointError` naming it,
before anything is unpickled) and the single-file tree format of older egosim runs (format 2)
and other tensor trees: :func:`save_tree` writes any nesting of dicts, lists and tuples whose
leaves are tensors, numpy arrays, ``None``, bools, ints, floats or strings as one
``.safetensors`` file: every tensor is a named safetensors entry and the structure is a JSON
document in the file header (metadata key ``egosim.tree``), with tensors replaced by
``{"__tensor__": name}``. :func:`load_tree` reads it back. Neither ever calls pickle, so loading
a file cannot run code.
"""

from __future__ import annotations

import json
import os
import uuid
from pathlib import Path
from typing import Any

import numpy as np
import torch
from safetensors import SafetensorError, safe_open
from safetensors.torch import save_file

from egosim.model.errors import ModelError

TREE_KEY = "egosim.tree"  # safetensors metadata key holding the JSON structure
FORMAT_KEY = "egosim.checkpoint_format"  # safetensors metadata key: layout version of the tree
CHECKPOINT_SUFFIX = ".safetensors"  # file suffix of every egosim checkpoint

# First bytes of files that torch.save / pickle write: a zip archive (torch >= 1.6) or a raw
# pickle stream (protocol 2..5 starts with 0x80 and the protocol number).
_PICKLE_MAGIC = (b"PK\x03\x04", b"\x80\x02", b"\x80\x03", b"\x80\x04", b"\x80\x05")


class UnsafeCheckpointError(ModelError):
    """A checkpoint file is a pickle (``torch.save``) or not a readable safetensors file."""


def _encode(value: Any, tensors: dict[str, torch.Tensor], path: str) -> Any:
    """JSON-able form of ``value``; tensors move into ``tensors`` under a unique name."""
    if value is None or isinstance(value, bool | int | float | str):
        return value
    if isinstance(value, torch.Tensor | np.ndarray):
        kind = "__tensor__" if isinstance(value, torch.Tensor) else "__ndarray__"
        tensor = torch.from_numpy(np.ascontiguousarray(value)) if kind == "__ndarray__" else value
        name = f"t{len(tensors):06d}:{path}"
        # Own contiguous CPU copy: safetensors refuses views and tensors sharing storage.
        tensors[name] = tensor.detach().to("cpu").contiguous().clone()
        return {kind: name}
    if isinstance(value, tuple):
        return {"__tuple__": [_encode(v, tensors, f"{path}.{i}") for i, v in enumerate(value)]}
    if isinstance(value, list):
        return [_encode(v, tensors, f"{path}.{i}") for i, v in enumerate(value)]
    if isinstance(value, dict):
        items = []
        for key, item in value.items():
            if not isinstance(key, str | int) or isinstance(key, bool):
                raise TypeError(f"checkpoint key {key!r} at {path!r} is not a str or int")
            items.append([key, _encode(item, tensors, f"{path}.{key}")])
        return {"__dict__": items}
    raise TypeError(f"checkpoint value at {path!r} has unsupported type {type(value).__name__}")


def _decode(value: Any, tensors: dict[str, torch.Tensor], where: str) -> Any:
    """Inverse of :func:`_encode`."""
    if isinstance(value, list):
        return [_decode(v, tensors, where) for v in value]
    if not isinstance(value, dict):
        return value
    if len(value) != 1:
        raise UnsafeCheckpointError(f"{where}: malformed checkpoint structure {sorted(value)}")
    ((tag, body),) = value.items()
    if tag in ("__tensor__", "__ndarray__"):
        if body not in tensors:
            raise UnsafeCheckpointError(f"{where}: checkpoint names missing tensor {body!r}")
        return tensors[body] if tag == "__tensor__" else tensors[body].numpy()
    if tag == "__tuple__":
        return tuple(_decode(v, tensors, where) for v in body)
    if tag == "__dict__":
        return {k: _decode(v, tensors, where) for k, v in body}
    raise UnsafeCheckpointError(f"{where}: unknown checkpoint tag {tag!r}")


def save_tree(path: str | Path, tree: Any, format_version: int = 1) -> None:
    """Write ``tree`` as one safetensors file, atomically (temporary file, then rename)."""
    path = Path(path)
    tensors: dict[str, torch.Tensor] = {}
    structure = _encode(tree, tensors, "")
    metadata = {TREE_KEY: json.dumps(structure), FORMAT_KEY: str(format_version)}
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f"{path.name}.tmp-{uuid.uuid4().hex[:8]}")
    try:
        save_file(tensors, tmp, metadata=metadata)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def refuse_pickle(path: str | Path) -> None:
    """Raise :class:`UnsafeCheckpointError` if ``path`` starts like a pickle or torch.save zip.

    A checkpoint folder (format 3) is checked file by file (its ``*.safetensors``).
    """
    path = Path(path)
    if path.is_dir():
        for file in sorted(path.glob(f"*{CHECKPOINT_SUFFIX}")):
            refuse_pickle(file)
        return
    try:
        with path.open("rb") as f:
            head = f.read(4)
    except OSError as exc:
        raise UnsafeCheckpointError(f"{path}: cannot read checkpoint ({exc})") from exc
    if any(head.startswith(m) for m in _PICKLE_MAGIC):
        raise UnsafeCheckpointError(
            f"{path}: is a pickle (torch.save) file; egosim loads only safetensors checkpoints "
            "and never unpickles, since a pickle can run code. Re-save its tensors with "
            "safetensors from a trusted environment."
        )


def load_tree(path: str | Path) -> tuple[Any, int]:
    """Read a file written by :func:`save_tree`: ``(tree, format_version)``; never unpickles."""
    path = Path(path)
    refuse_pickle(path)
    try:
        with safe_open(str(path), framework="pt", device="cpu") as f:
            metadata = f.metadata() or {}
            tensors = {name: f.get_tensor(name) for name in f.keys()}  # noqa: SIM118
    except (SafetensorError, OSError, ValueError) as exc:
        raise UnsafeCheckpointError(f"{path}: not a safetensors checkpoint ({exc})") from exc
    if TREE_KEY not in metadata:
        raise UnsafeCheckpointError(f"{path}: safetensors file without egosim checkpoint data")
    try:
        structure = json.loads(metadata[TREE_KEY])
        version = int(metadata.get(FORMAT_KEY, "0"))
    except ValueError as exc:
        raise UnsafeCheckpointError(f"{path}: unreadable checkpoint header ({exc})") from exc
    return _decode(structure, tensors, str(path)), version
