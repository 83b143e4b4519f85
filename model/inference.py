"""Load a trained model for generation: a run directory or checkpoint file -> ModelBundle.

The checkpoint carries its resolved :class:`~egosim.model.train.TrainConfig`, so the same preset,
fine-tuning layout (full or LoRA) and weights folder are rebuilt before its weights are loaded;
a caller that names a different preset gets a :class:`CheckpointMismatchError` naming both.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

import torch

from egosim.model.errors import CheckpointMismatchError
from egosim.model.lora import LoRAConfig
from egosim.model.network import ModelBundle, build_model
from egosim.model.train import (
    TrainConfig,
    _resolve_device,
    _trainable,
    latest_checkpoint,
    load_checkpoint,
    read_checkpoint,
    setup_model,
)


@dataclass
class LoadedModel:
    """A model ready to sample, and where its weights came from."""

    bundle: ModelBundle  # preset, denoiser (eval mode) and VAE
    checkpoint: Path | None  # checkpoint file, None for an untrained (freshly built) model
    step: int  # training step of the checkpoint (0 when none)
    ema: bool  # True when the EMA weights were loaded


def resolve_checkpoint(path: str | Path) -> Path:
    """A checkpoint file, or the latest ``checkpoints/step_*.safetensors`` of a run directory."""
    path = Path(path)
    if path.is_file():
        return path
    found = latest_checkpoint(path) if path.is_dir() else None
    if found is None:
        raise FileNotFoundError(
            f"no checkpoint at {path} (a .safetensors checkpoint or a run directory)"
        )
    return found


def config_from_dict(values: dict) -> TrainConfig:
    """Rebuild a :class:`TrainConfig` from its ``dataclasses.asdict`` form (checkpoint, JSON)."""
    names = {f.name for f in dataclasses.fields(TrainConfig)}
    kw = {k: v for k, v in values.items() if k in names}
    if isinstance(kw.get("lora"), dict):
        lora = dict(kw["lora"])
        lora["targets"] = tuple(lora.get("targets", ()))
        kw["lora"] = LoRAConfig(**lora)
    for key in ("betas", "dropout_targets"):
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
    dev = _resolve_device(device)
    if checkpoint is None:
        bundle = build_model(preset or "tiny", weights_dir)
        bundle.denoiser.to(dev).eval()
        bundle.vae.to(dev)
        return LoadedModel(bundle, None, 0, False)
    path = resolve_checkpoint(checkpoint)
    payload = read_checkpoint(path)  # safetensors only: a pickle is refused, never loaded
    config = config_from_dict(payload["config"])
    if preset is not None and preset != config.preset:
        raise CheckpointMismatchError(
            f"checkpoint {path} was written by preset {config.preset!r}; asked for {preset!r}"
        )
    overrides = {"device": device}
    if weights_dir is not None:
        overrides["weights_dir"] = weights_dir
    config = dataclasses.replace(config, **overrides)
    bundle = setup_model(config, dev)
    payload = load_checkpoint(path, config, bundle, payload)
    ema = use_ema and payload.get("ema") is not None
    if ema:
        with torch.no_grad():
            for name, param in _trainable(bundle).items():
                param.copy_(payload["ema"][name])
    bundle.denoiser.eval()
    return LoadedModel(bundle, path, int(payload["step"]), ema)
