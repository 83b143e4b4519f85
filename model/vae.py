"""Video autoencoders with one interface: ``encode`` (B,3,T,H,W) -> normalised (B,16,T',h,w).

- :class:`PackedVAE` (preset ``tiny``): deterministic and exactly invertible. It folds each latent
  frame's 4 pixel frames (frame 0 repeated 4x, the Wan layout) into 12 channels, pads to 16 and
  mixes them with a fixed orthogonal 16x16 matrix. No training, no weights, lossless up to float
  rounding (PSNR of uint8 round-trips is infinite; tested >= 28 dB). Spatial factor 1.
- :class:`WanVAE` (Wan presets): diffusers' ``AutoencoderKLWan`` loaded from ``<folder>/vae``,
  latents normalised with the config's ``latents_mean`` / ``latents_std`` as diffusers' Wan
  pipelines do. Frozen.
"""

from __future__ import annotations

from pathlib import Path

import torch
from torch import nn

from egosim.model.conditioning import fold_frames, unfold_frames
from egosim.model.errors import WeightsMismatchError
from egosim.model.presets import LATENT_CHANNELS, ModelPreset


class PackedVAE(nn.Module):
    """Lossless space-time packing autoencoder with the Wan latent layout (tiny preset)."""

    def __init__(self, seed: int = 0) -> None:
        super().__init__()
        # A fixed random orthogonal mix spreads the 12 packed values over all 16 channels so no
        # latent channel is constantly zero; orthogonality makes decode the exact transpose and
        # keeps the latent scale equal to the pixel scale (std about 0.5 for [-1, 1] video).
        g = torch.Generator().manual_seed(seed)
        q, r = torch.linalg.qr(torch.randn(LATENT_CHANNELS, LATENT_CHANNELS, generator=g))
        q = q * torch.sign(torch.diagonal(r)).unsqueeze(0)  # unique QR: positive diagonal of r
        self.register_buffer("mix", q, persistent=False)
        self.spatial_factor = 1
        self.temporal_factor = 4

    @torch.no_grad()
    def encode(self, video: torch.Tensor) -> torch.Tensor:
        """(B,3,T,H,W) in [-1,1] -> (B,16,T',H,W)."""
        packed = fold_frames(video.float())  # (B, 12, T', H, W)
        b, c, tl, h, w = packed.shape
        pad = packed.new_zeros(b, LATENT_CHANNELS - c, tl, h, w)
        z = torch.cat([packed, pad], dim=1)  # (B, 16, T', H, W)
        return torch.einsum("oc,bcthw->bothw", self.mix, z)

    @torch.no_grad()
    def decode(self, latent: torch.Tensor) -> torch.Tensor:
        """(B,16,T',H,W) -> (B,3,1+4(T'-1),H,W) in [-1,1]."""
        z = torch.einsum("oc,bothw->bcthw", self.mix, latent.float())  # mix^T
        return unfold_frames(z[:, :12]).clamp(-1.0, 1.0)


class WanVAE(nn.Module):
    """Frozen diffusers ``AutoencoderKLWan`` with Wan's latent normalisation."""

    def __init__(self, vae: nn.Module) -> None:
        super().__init__()
        self.vae = vae.eval().requires_grad_(False)
        cfg = vae.config
        self.register_buffer("mean", torch.tensor(cfg.latents_mean).view(1, -1, 1, 1, 1), False)
        self.register_buffer("std", torch.tensor(cfg.latents_std).view(1, -1, 1, 1, 1), False)
        self.spatial_factor = int(cfg.scale_factor_spatial)
        self.temporal_factor = int(cfg.scale_factor_temporal)

    @torch.no_grad()
    def encode(self, video: torch.Tensor) -> torch.Tensor:
        """(B,3,T,H,W) in [-1,1] -> normalised posterior mode (B,16,T',H/8,W/8)."""
        dtype = next(self.vae.parameters()).dtype
        z = self.vae.encode(video.to(dtype)).latent_dist.mode()
        return (z.float() - self.mean) / self.std

    @torch.no_grad()
    def decode(self, latent: torch.Tensor) -> torch.Tensor:
        """Normalised (B,16,T',h,w) -> (B,3,T,H,W) in [-1,1]."""
        dtype = next(self.vae.parameters()).dtype
        z = latent.float() * self.std + self.mean
        return self.vae.decode(z.to(dtype)).sample.float()


def build_vae(preset: ModelPreset, weights_dir: str | Path | None = None) -> nn.Module:
    """The preset's autoencoder; Wan presets load ``<weights_dir>/vae`` (diffusers format)."""
    if preset.vae.kind == "packed":
        return PackedVAE(seed=preset.vae.seed)
    if weights_dir is None:
        raise WeightsMismatchError(f"preset {preset.name!r} needs weights_dir with a vae/ folder")
    folder = Path(weights_dir) / "vae"
    if not (folder / "config.json").is_file():
        raise WeightsMismatchError(f"no diffusers VAE at {folder} (config.json missing)")
    from diffusers import AutoencoderKLWan

    vae = AutoencoderKLWan.from_pretrained(folder)
    if vae.config.z_dim != LATENT_CHANNELS:
        raise WeightsMismatchError(f"{folder}: z_dim must be {LATENT_CHANNELS}, got {vae.config}")
    return WanVAE(vae)
