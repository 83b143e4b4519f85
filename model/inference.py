"""Load a trained model for generation: a run directory or checkpoint file -> ModelBundle.

The checkpoint carries its resolved :class:`~egosim.model.train.TrainConfig`, so the same preset,
fine-tuning layout (full or LoRA) and weights folder are rebuilt before its weights are loaded;
a caller that names a different preset gets a :class:`CheckpointMismatchError` naming both.

Checkpoints are folders (format 3, written by any number of ranks, read here in one process);
single-file ``.safetensors`` checkpoints of an older egosim (format 2) still load for sampling.
A file that is a pickle is refused before a byte of it is interpreted.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

import torch

from egosim.model.checkpoint import load_tree
from egosim.model.distributed import resolve_device
from egosim.model.errors import CheckpointMismatchError
from egosim.model.lora import LoRAConfig
from egosim.model.network import ModelBundle, build_model
from egosim.model.train import (
    OptimConfig,
    TrainConfig,
    _trainable,
    latest_checkpoint,
    load_weights,
    read_state,
    setup_model,
)

LEGACY_FORMAT = 2  # single-file checkpoints (model/checkpoint.py save_tree) of older runs


@dataclass
class LoadedModel:
    """A model ready to sample, and where its weights came from."""

    bundle: ModelBundle  # preset, denoiser (eval mode) and VAE
    checkpoint: Path | None  # checkpoint file, None for an untrained (freshly built) model
    step: int  # training step of the checkpoint (0 when none)
    ema: bool  # True when the EMA weights were loaded


def resolve_checkpoint(path: str | Path) -> Path:
    """A checkpoint folder or file, or the latest checkpoint of a run directory."""
    path = Path(path)
    if path.is_file() or (path / "state.json").is_file():
        return path
    found = latest_checkpoint(path) if path.is_dir() else None
    if found is None:
        raise FileNotFoundError(
            f"no checkpoint at {path} (a checkpoint folder, a .safetensors checkpoint or a run "
            "directory)"
        )
    return found


OPTIM_KEYS = ("lr", "warmup_steps", "weight_decay", "betas", "grad_clip")  # flat before optim


def config_from_dict(values: dict) -> TrainConfig:
    """Rebuild a :class:`TrainConfig` from its ``dataclasses.asdict`` form (checkpoint, JSON).

    Configs saved before the ``optim`` group (flat ``lr``, ``warmup_steps``, ...) are read into
    it, so older checkpoints still load for sampling.
    """
    names = {f.name for f in dataclasses.fields(TrainConfig)}
    optim = dict(values.get("optim") or {k: values[k] for k in OPTIM_KEYS if k in values})
    if "betas" in optim:
        optim["betas"] = tuple(optim["betas"])
    kw = {k: v for k, v in values.items() if k in names and k != "optim"}
    kw["optim"] = OptimConfig(**optim)
    if isinstance(kw.get("lora"), dict):
        lora = dict(kw["lora"])
        lora["targets"] = tuple(lora.get("targets", ()))
        kw["lora"] = LoRAConfig(**lora)
    for key in ("dropout_targets",):
        if key in kw:
            kw[key] = tuple(kw[key])
    return TrainConfig(**kw)


def load_trained(
    checkpoint: str | Path | None,
    preset: str | None = None,
    device: str = "auto",
    use_ema: bool = True,
    weights_dir: str | None = None,
) -> LoadedModel:
    """Build the checkpoint's model and load its weights (EMA weights when present and wanted).

    ``checkpoint`` None builds ``preset`` untrained (from ``weights_dir`` when given): useful for
    smoke runs. ``preset``, when given, must be the checkpoint's preset. A pickled checkpoint
    raises :class:`~egosim.model.checkpoint.UnsafeCheckpointError` without being unpickled.
    """
    dev = resolve_device(device)
    if checkpoint is None:
        bundle = build_model(preset or "tiny", weights_dir)
        bundle.denoiser.to(dev).eval()
        bundle.vae.to(dev)
        return LoadedModel(bundle, None, 0, False)
    path = resolve_checkpoint(checkpoint)
    # A file is a format-2 checkpoint (a pickle is refused by load_tree, never loaded).
    legacy = _read_legacy(path) if path.is_file() else None
    config = config_from_dict(legacy["config"] if legacy else read_state(path)["config"])
    if preset is not None and preset != config.preset:
        raise CheckpointMismatchError(
            f"checkpoint {path} was written by preset {config.preset!r}; asked for {preset!r}"
        )
    overrides = {"device": device}
    if weights_dir is not None:
        overrides["weights_dir"] = weights_dir
    config = dataclasses.replace(config, **overrides)
    bundle = setup_model(config, torch.device("cpu"))
    if legacy is None:
        meta, ema = load_weights(path, config, bundle, use_ema)
        step = int(meta["step"])
    else:
        ema = _load_legacy(path, legacy, bundle, use_ema)
        step = int(legacy["step"])
    bundle.denoiser.to(dev).eval()
    bundle.vae.to(dev)
    return LoadedModel(bundle, path, step, ema)


def _read_legacy(path: Path) -> dict:
    """The payload of a format-2 single-file checkpoint (refuses pickles, never unpickles)."""
    payload, version = load_tree(path)
    if version != LEGACY_FORMAT or not isinstance(payload, dict) or "model" not in payload:
        raise CheckpointMismatchError(
            f"{path} is not an egosim checkpoint (format {version}; this code reads folders "
            f"and format-{LEGACY_FORMAT} files)"
        )
    return payload


def _load_legacy(path: Path, payload: dict, bundle: ModelBundle, use_ema: bool) -> bool:
    """Copy a format-2 payload's weights (EMA when present and wanted) into ``bundle``."""
    ema = use_ema and payload.get("ema") is not None
    source = payload["ema"] if ema else payload["model"]
    trainable = _trainable(bundle)
    if set(source) != set(trainable):
        missing = sorted(set(trainable) ^ set(source))[:3]
        raise CheckpointMismatchError(
            f"{path}: checkpoint tensors do not match the model's trainable weights ({missing})"
        )
    with torch.no_grad():
        for name, param in trainable.items():
            param.copy_(source[name])
    return ema
