"""Low-rank adapters on ``nn.Linear`` layers (peft is not installed; this is the whole of it).

DWM's recipe (appendix A): rank 64, alpha 64, LoRA on the diffusion transformer, and the input
projection (here the widened patch embedding) trained fully; everything else frozen.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import nn

from egosim.model.errors import ModelConfigError

# Linear layers of WanTransformerBlock that get adapters: attention projections and the MLP.
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
        if problems:
            raise ModelConfigError("LoRAConfig: " + "; ".join(problems))


class LoRALinear(nn.Module):
    """``base(x) + (alpha / r) * up(down(x))`` around a frozen ``nn.Linear``."""

    def __init__(self, base: nn.Linear, rank: int, alpha: float) -> None:
        super().__init__()
        self.base = base.requires_grad_(False)
        self.scale = alpha / rank
        kw = {"device": base.weight.device, "dtype": base.weight.dtype}
        self.down = nn.Linear(base.in_features, rank, bias=False, **kw)
        self.up = nn.Linear(rank, base.out_features, bias=False, **kw)
        # As in the LoRA paper: A (down) Kaiming-uniform, B (up) zero, so the wrapped layer starts
        # exactly equal to the base layer and only the update is learnt.
        nn.init.kaiming_uniform_(self.down.weight, a=math.sqrt(5))
        nn.init.zeros_(self.up.weight)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(..., in) -> (..., out)."""
        return self.base(x) + self.up(self.down(x)) * self.scale

    @torch.no_grad()
    def merged(self) -> nn.Linear:
        """A plain Linear with the update folded into its weight."""
        delta = (self.up.weight.float() @ self.down.weight.float()) * self.scale
        self.base.weight += delta.to(self.base.weight.dtype)
        return self.base


def apply_lora(model: nn.Module, config: LoRAConfig) -> list[str]:
    """Wrap matching Linear layers of ``model`` in place; freezes the rest. Returns wrapped names.

    Only names inside ``blocks.`` are matched (the transformer blocks). With
    ``train_patch_embedding`` the ``patch_embedding`` stays trainable.
    """
    model.requires_grad_(False)
    wrapped = []
    for name, module in list(model.named_modules()):
        if ".blocks." not in f".{name}" or not isinstance(module, nn.Linear):
            continue
        if not any(name.endswith(t) for t in config.targets):
            continue
        parent_name, _, child = name.rpartition(".")
        parent = model.get_submodule(parent_name)
        setattr(parent, child, LoRALinear(module, config.rank, config.alpha))
        wrapped.append(name)
    if not wrapped:
        raise ModelConfigError(f"LoRA matched no Linear layer for targets {config.targets}")
    if config.train_patch_embedding:
        for n, p in model.named_parameters():
            if "patch_embedding" in n:
                p.requires_grad_(True)
    return wrapped


def merge_lora(model: nn.Module) -> int:
    """Fold every adapter back into its base layer in place; returns how many were merged."""
    n = 0
    for name, module in list(model.named_modules()):
        if isinstance(module, LoRALinear):
            parent_name, _, child = name.rpartition(".")
            setattr(model.get_submodule(parent_name), child, module.merged())
            n += 1
    return n
