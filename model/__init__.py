"""The observation model: a Wan2.1-Fun-InP video diffusion transformer at 52 input channels.

Public API (imported lazily, so ``import egosim.model`` does not load diffusers)::

    from egosim.model import PRESETS, TrainConfig, TrainingSample, build_model, sample
    from egosim.model.train import train  # not re-exported: the submodule `train` shadows it

- ``presets``: the preset table (``tiny``, ``wan2.1-fun-1.3b-inp``, ``wan2.1-fun-14b-inp``).
- ``network``: build / widen (36 -> 52) / load the transformer; ``build_model`` -> ModelBundle.
- ``conditioning``: channel layout, ``pack_mask`` (the one mask function), ``TrainingSample``.
- ``flow``: rectified flow matching; ``sampler``: Euler + CFG; ``train``: the loop.
- ``vae``, ``text``, ``lora``, ``metrics``, ``errors``.
"""

from __future__ import annotations

import importlib
from typing import Any

_EXPORTS = {
    "PRESETS": "presets",
    "ModelPreset": "presets",
    "get_preset": "presets",
    "list_presets": "presets",
    "ModelBundle": "network",
    "build_model": "network",
    "build_transformer": "network",
    "load_transformer": "network",
    "widen_patch_embedding": "network",
    "Conditions": "conditioning",
    "TrainingSample": "conditioning",
    "pack_mask": "conditioning",
    "FlowMatching": "flow",
    "sample": "sampler",
    "sample_latents": "sampler",
    "TrainConfig": "train",
    "TrainResult": "train",
    "LoRAConfig": "lora",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    """Import the submodule that defines ``name`` on first use."""
    if name not in _EXPORTS:
        raise AttributeError(f"module 'egosim.model' has no attribute {name!r}")
    return getattr(importlib.import_module(f"egosim.model.{_EXPORTS[name]}"), name)
