"""Sampling: Euler integration of the flow ODE with classifier-free guidance, then VAE decode."""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
import torch

from egosim.model.conditioning import (
    Conditions,
    assemble_input,
    collate,
    condition_latents,
    null_conditions,
    tensor_to_video,
)
from egosim.model.flow import FlowMatching
from egosim.model.network import ModelBundle

DEFAULT_STEPS = 50  # EgoSim: 50 flow-matching steps
DEFAULT_GUIDANCE = 1.0  # EgoSim: CFG scale 1.0 (a single conditional pass)


@torch.no_grad()
def euler_sample(
    velocity_fn: Callable[[torch.Tensor, torch.Tensor], torch.Tensor],
    noise: torch.Tensor,
    flow: FlowMatching,
    steps: int = DEFAULT_STEPS,
) -> torch.Tensor:
    """Integrate ``dx/dt = v(x, t)`` from t = 1 (``noise``) to t = 0 with Euler steps.

    ``velocity_fn(x, t)`` gets t as a (B,) tensor; returns the t = 0 sample, shape of ``noise``.
    """
    times = flow.sampling_times(steps)
    x = noise.float()
    b = x.shape[0]
    for i in range(steps):
        t, t_next = float(times[i]), float(times[i + 1])
        v = velocity_fn(x, torch.full((b,), t, device=x.device)).float()
        x = x + (t_next - t) * v  # dt < 0: towards the data end
    return x


@torch.no_grad()
def sample_latents(
    bundle: ModelBundle,
    conditions: Sequence[Conditions],
    steps: int = DEFAULT_STEPS,
    guidance_scale: float = DEFAULT_GUIDANCE,
    guidance_targets: tuple[str, ...] = ("text",),
    shift: float | None = None,
    seed: int = 0,
) -> torch.Tensor:
    """Generate latents (B, 16, T', h, w) for a batch of conditions.

    Guidance: ``v = v_null + scale (v_cond - v_null)`` where the null branch zeroes
    ``guidance_targets``; at scale 1.0 only the conditional branch runs.
    """
    den = bundle.denoiser.eval()
    device = next(den.parameters()).device
    pix = collate(list(conditions))
    cond = condition_latents(bundle.vae, pix).to(device)  # (B, 36, T', h, w)
    context = den.encode_text(pix.prompts, pix.text_embeddings)  # (B, L, D)
    image_ctx = den.image_context(pix.image_embeddings)
    n_cond, n_ctx, n_img = null_conditions(cond, context, image_ctx, guidance_targets)
    flow = FlowMatching(shift=bundle.preset.sample_shift if shift is None else shift)
    g = torch.Generator().manual_seed(seed)
    noise = torch.randn((cond.shape[0], 16, *cond.shape[2:]), generator=g).to(device)

    def velocity(x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        v = den(assemble_input(x, cond), t, context, image_ctx)
        if guidance_scale == 1.0:
            return v
        v_null = den(assemble_input(x, n_cond), t, n_ctx, n_img)
        return v_null + guidance_scale * (v - v_null)

    return euler_sample(velocity, noise, flow, steps)


@torch.no_grad()
def sample(
    bundle: ModelBundle,
    conditions: Conditions | Sequence[Conditions],
    steps: int = DEFAULT_STEPS,
    guidance_scale: float = DEFAULT_GUIDANCE,
    guidance_targets: tuple[str, ...] = ("text",),
    shift: float | None = None,
    seed: int = 0,
) -> np.ndarray:
    """Generate videos: uint8 (T, H, W, 3) for one :class:`Conditions`, (B, T, H, W, 3) for many.

    A :class:`TrainingSample` works too (its target is ignored).
    """
    single = isinstance(conditions, Conditions)
    batch = [conditions] if single else list(conditions)
    latents = sample_latents(bundle, batch, steps, guidance_scale, guidance_targets, shift, seed)
    video = tensor_to_video(bundle.vae.decode(latents))  # (B, T, H, W, 3)
    return video[0] if single else video
