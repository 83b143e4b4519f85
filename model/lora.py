"""Low-rank adapters through peft, saved in the layout diffusers' ``load_lora_weights`` reads.

DWM's recipe (appendix A): rank 64, alpha 64, LoRA on the attention projections and the
feed-forward layers of every transformer block, the input projection (here the widened 52-channel
patch embedding) trained fully, everything else frozen.

The adapters are peft ``LoraLayer`` modules injected by diffusers' ``PeftAdapterMixin.add_adapter``
(``WanTransformer3DModel`` has it), under peft's default adapter name, so parameter names are
peft's (``blocks.0.attn1.to_q.lora_A.default.weight``, base weights under ``base_layer``).

:func:`save_lora` writes a folder a diffusers user loads with
``WanPipeline.load_lora_weights(folder)`` (or ``transformer.load_lora_adapter``)::

    folder/pytorch_lora_weights.safetensors   transformer.blocks.N.<layer>.lora_A/lora_B.weight,
                                              with the peft LoraConfig (rank, alpha) in its header
    folder/patch_embedding.safetensors        the fully trained patch embedding (weight, bias);
                                              diffusers' LoRA loader takes LoRA keys only, so it
                                              is a file of its own, loaded into the transformer
                                              before the adapters (:func:`load_patch_embedding`)
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from torch import nn

from egosim.model.errors import ModelConfigError

ADAPTER = "default"  # peft adapter name (the one diffusers' loaders use when none is given)
LORA_WEIGHTS = "pytorch_lora_weights.safetensors"  # diffusers' default LoRA file name
PATCH_EMBEDDING_WEIGHTS = "patch_embedding.safetensors"  # the fully trained input projection

# Linear layers of WanTransformerBlock that get adapters: self- and cross-attention projections
# (query, key, value, output; the image branch's added key/value on Wan I2V presets) and the MLP.
DEFAULT_TARGETS = (
    "to_q",
    "to_k",
    "to_v",
    "to_out.0",
    "add_k_proj",
    "add_v_proj",
    "ffn.net.0.proj",
    "ffn.net.2",
)


@dataclass(frozen=True)
class LoRAConfig:
    """Which layers get adapters and how big they are."""

    rank: int = 64  # adapter rank r (DWM: 64)
    alpha: float = 64.0  # scale numerator: the update is (alpha / r) B A x (DWM: alpha = 64)
    targets: tuple[str, ...] = DEFAULT_TARGETS  # module-name suffixes inside transformer blocks
    train_patch_embedding: bool = True  # also train the (widened) input projection fully

    def __post_init__(self) -> None:
        problems = []
        if self.rank < 1:
            problems.append(f"rank must be >= 1, got {self.rank}")
        if not self.alpha > 0:
            problems.append(f"alpha must be > 0, got {self.alpha}")
        if not self.targets:
            problems.append("targets must name at least one layer, got ()")
        if problems:
            raise ModelConfigError("LoRAConfig: " + "; ".join(problems))

    def target_pattern(self) -> str:
        """peft ``target_modules`` regex: the target suffixes inside ``blocks.<i>.`` only."""
        names = "|".join(re.escape(t) for t in self.targets)
        return rf"blocks\.\d+\.(?:.*\.)?(?:{names})"

    def peft_config(self) -> Any:
        """The equivalent ``peft.LoraConfig`` (B initialised to zero: starts as the base model)."""
        from peft import LoraConfig

        return LoraConfig(
            r=self.rank,
            lora_alpha=self.alpha,
            target_modules=self.target_pattern(),
            lora_dropout=0.0,
            init_lora_weights=True,
        )


def apply_lora(model: nn.Module, config: LoRAConfig) -> list[str]:
    """Inject adapters into a Wan transformer in place and freeze the rest; returns wrapped names.

    Only Linear layers inside ``blocks.`` whose names end with a target get adapters. With
    ``train_patch_embedding`` the ``patch_embedding`` stays trainable.
    """
    from peft.tuners.lora import LoraLayer

    model.requires_grad_(False)
    try:
        model.add_adapter(config.peft_config(), adapter_name=ADAPTER)
    except ValueError as exc:  # peft: "Target modules ... not found in the base model"
        raise ModelConfigError(
            f"LoRA matched no layer for targets {config.targets}: {exc}"
        ) from exc
    wrapped = [n for n, m in model.named_modules() if isinstance(m, LoraLayer)]
    if config.train_patch_embedding:
        model.patch_embedding.requires_grad_(True)
    return wrapped


def lora_state_dict(model: nn.Module) -> dict[str, torch.Tensor]:
    """Adapter weights in diffusers' naming, unprefixed: ``blocks.0.attn1.to_q.lora_A.weight``."""
    from peft import get_peft_model_state_dict

    state = get_peft_model_state_dict(model, adapter_name=ADAPTER)
    return {k: v.detach().to("cpu").contiguous() for k, v in state.items()}


def save_lora(
    model: nn.Module,
    folder: str | Path,
    state: dict[str, torch.Tensor] | None = None,
    patch_embedding: dict[str, torch.Tensor] | None = None,
) -> Path:
    """Write the adapters (and the trained patch embedding) for diffusers; returns the folder.

    ``state``/``patch_embedding``: the full tensors when the caller gathered them (FSDP);
    default: read from ``model``.
    """
    from diffusers import WanPipeline
    from safetensors.torch import save_file

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    state = lora_state_dict(model) if state is None else state
    WanPipeline.save_lora_weights(
        folder,
        transformer_lora_layers=state,
        weight_name=LORA_WEIGHTS,
        safe_serialization=True,
        transformer_lora_adapter_metadata=model.peft_config[ADAPTER].to_dict(),
    )
    if patch_embedding is None and model.patch_embedding.weight.requires_grad:
        patch_embedding = {
            k: v.detach().to("cpu").contiguous()
            for k, v in model.patch_embedding.state_dict().items()
        }
    if patch_embedding:
        save_file(
            {f"patch_embedding.{k}": v for k, v in patch_embedding.items()},
            folder / PATCH_EMBEDDING_WEIGHTS,
        )
    return folder


def load_patch_embedding(transformer: nn.Module, folder: str | Path) -> bool:
    """Load ``folder/patch_embedding.safetensors`` into ``transformer`` (False when absent).

    The transformer must already have the trained width (52 input channels for egosim).
    """
    from safetensors.torch import load_file

    path = Path(folder) / PATCH_EMBEDDING_WEIGHTS
    if not path.is_file():
        return False
    tensors = load_file(str(path))
    state = {k.removeprefix("patch_embedding."): v for k, v in tensors.items()}
    want = {k: tuple(v.shape) for k, v in transformer.patch_embedding.state_dict().items()}
    got = {k: tuple(v.shape) for k, v in state.items()}
    if want != got:
        raise ModelConfigError(f"{path}: patch embedding {got} does not fit the model's {want}")
    with torch.no_grad():
        transformer.patch_embedding.load_state_dict(state)
    return True


def merge_lora(model: nn.Module) -> int:
    """Fold every adapter into its base layer and remove it, in place; returns how many."""
    from peft.tuners.lora import LoraLayer

    n = 0
    for name, module in list(model.named_modules()):
        if isinstance(module, LoraLayer):
            module.merge()
            parent_name, _, child = name.rpartition(".")
            setattr(model.get_submodule(parent_name), child, module.get_base_layer())
            n += 1
    return n
