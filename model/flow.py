"""The noise process: rectified flow matching (no network, no loop).

``x_t = (1 - t) x_0 + t e`` with ``e ~ N(0, I)``; the network predicts the velocity
``v = dx_t/dt = e - x_0``; t = 0 is data, t = 1 is noise. A timestep shift
``s(t) = shift t / (1 + (shift - 1) t)`` (SD3 / Wan) moves time towards the noisy end for
shift > 1; training draws ``t = s(u)`` with u uniform (or logit-normal) and sampling integrates
on the shifted grid ``s(linspace(1, 0, steps + 1))``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch

from egosim.model.errors import ModelConfigError


@dataclass(frozen=True)
class FlowMatching:
    """Rectified-flow noise process with a timestep shift."""

    shift: float = 1.0  # timestep shift (1.0: none; Wan uses 3-5 at 480p)
    time_sampling: str = "uniform"  # "uniform" or "logit_normal" (SD3's default density)

    def __post_init__(self) -> None:
        problems = []
        if not self.shift > 0:
            problems.append(f"shift must be > 0, got {self.shift}")
        if self.time_sampling not in ("uniform", "logit_normal"):
            problems.append(f"time_sampling must be uniform|logit_normal, got {self.time_sampling}")
        if problems:
            raise ModelConfigError("FlowMatching: " + "; ".join(problems))

    def shift_time(self, t: torch.Tensor) -> torch.Tensor:
        """Apply the shift ``s(t) = shift t / (1 + (shift - 1) t)`` (identity at shift 1)."""
        return self.shift * t / (1.0 + (self.shift - 1.0) * t)

    def sample_time(self, n: int, generator: torch.Generator) -> torch.Tensor:
        """Training times (n,) in (0, 1), shifted."""
        if self.time_sampling == "uniform":
            u = torch.rand(n, generator=generator)
        else:
            u = torch.sigmoid(torch.randn(n, generator=generator))
        return self.shift_time(u)

    @staticmethod
    def interpolate(x0: torch.Tensor, noise: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        """``x_t = (1 - t) x_0 + t e``; t (B,) broadcast over the other axes."""
        tb = t.view(-1, *([1] * (x0.ndim - 1))).to(x0)
        return (1.0 - tb) * x0 + tb * noise

    @staticmethod
    def target(x0: torch.Tensor, noise: torch.Tensor) -> torch.Tensor:
        """Velocity target ``e - x_0``."""
        return noise - x0

    def loss(
        self,
        velocity_fn: Callable[[torch.Tensor, torch.Tensor], torch.Tensor],
        x0: torch.Tensor,
        generator: torch.Generator,
    ) -> torch.Tensor:
        """Mean squared velocity error of ``velocity_fn(x_t, t)`` at random (t, e).

        Noise and times come from ``generator`` only, so a run is reproducible from its state.
        """
        t = self.sample_time(x0.shape[0], generator).to(x0.device)
        noise = torch.randn(x0.shape, generator=generator).to(x0)
        pred = velocity_fn(self.interpolate(x0, noise, t), t)
        return torch.mean((pred.float() - self.target(x0, noise).float()) ** 2)

    def sampling_times(self, steps: int) -> torch.Tensor:
        """Integration grid (steps + 1,) from 1 (noise) down to 0 (data), shifted."""
        if steps < 1:
            raise ModelConfigError(f"steps must be >= 1, got {steps}")
        return self.shift_time(torch.linspace(1.0, 0.0, steps + 1, dtype=torch.float64))
