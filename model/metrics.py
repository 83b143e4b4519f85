"""Image metrics: PSNR, SSIM, and LPIPS when weights exist locally.

Videos are uint8 arrays (..., H, W, 3) or float arrays in [0, data_range]. The camera error
(Cam-ERR, Plücker rays) is geometry, not a model piece: ``egosim.pipeline.geometry.camera_error``
(``model/`` never imports ``pipeline/``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from torch.nn import functional as F  # noqa: N812 (the universal torch alias)

from egosim.model.errors import ModelConfigError


def _as_float(x: np.ndarray | torch.Tensor) -> torch.Tensor:
    return torch.as_tensor(np.asarray(x)).double()


def psnr(
    pred: np.ndarray | torch.Tensor, target: np.ndarray | torch.Tensor, data_range: float = 255.0
) -> float:
    """Peak signal-to-noise ratio in dB over all elements (inf when identical)."""
    a, b = _as_float(pred), _as_float(target)
    if a.shape != b.shape:
        raise ModelConfigError(f"psnr: shapes differ, got {tuple(a.shape)} and {tuple(b.shape)}")
    mse = float(torch.mean((a - b) ** 2))
    return float("inf") if mse == 0 else 10.0 * float(np.log10(data_range**2 / mse))


def ssim(
    pred: np.ndarray | torch.Tensor, target: np.ndarray | torch.Tensor, data_range: float = 255.0
) -> float:
    """Mean SSIM (Wang et al. 2004: 11x11 Gaussian window, sigma 1.5, K1 0.01, K2 0.03).

    Inputs (..., H, W, C) or (..., H, W); computed per channel and image, averaged; the window
    is applied 'valid' (no padding), as in the reference implementation.
    """
    a, b = _as_float(pred), _as_float(target)
    if a.shape != b.shape:
        raise ModelConfigError(f"ssim: shapes differ, got {tuple(a.shape)} and {tuple(b.shape)}")
    if a.ndim == 2:
        a, b = a[..., None], b[..., None]
    h, w, c = a.shape[-3:]
    if min(h, w) < 11:
        raise ModelConfigError(f"ssim needs frames of at least 11x11 pixels, got {h}x{w}")
    a = a.reshape(-1, h, w, c).permute(0, 3, 1, 2).reshape(-1, 1, h, w)  # (N*C, 1, H, W)
    b = b.reshape(-1, h, w, c).permute(0, 3, 1, 2).reshape(-1, 1, h, w)
    x = torch.arange(11, dtype=torch.float64) - 5.0
    g = torch.exp(-(x**2) / (2 * 1.5**2))
    g = g / g.sum()
    win = (g[:, None] * g[None, :]).view(1, 1, 11, 11)
    mu_a, mu_b = F.conv2d(a, win), F.conv2d(b, win)
    s_aa = F.conv2d(a * a, win) - mu_a**2
    s_bb = F.conv2d(b * b, win) - mu_b**2
    s_ab = F.conv2d(a * b, win) - mu_a * mu_b
    c1, c2 = (0.01 * data_range) ** 2, (0.03 * data_range) ** 2
    num = (2 * mu_a * mu_b + c1) * (2 * s_ab + c2)
    den = (mu_a**2 + mu_b**2 + c1) * (s_aa + s_bb + c2)
    return float((num / den).mean())


def lpips_distance(
    pred: np.ndarray, target: np.ndarray, weights: str | Path | None = None
) -> float | None:
    """LPIPS (AlexNet) when the ``lpips`` package and its weights are available locally, else None.

    Nothing is downloaded: ``weights`` must point at a local ``alex.pth`` (LPIPS linear layers)
    and torchvision's AlexNet weights must already be cached; otherwise the metric is skipped.
    """
    try:
        import lpips  # type: ignore[import-not-found]
    except ImportError:
        return None
    if weights is None or not Path(weights).is_file():
        return None
    try:
        model = lpips.LPIPS(net="alex", pretrained=True, model_path=str(weights), verbose=False)
    except Exception:  # backbone weights not cached locally: skip rather than download
        return None
    a = torch.as_tensor(np.asarray(pred)).float().permute(0, 3, 1, 2) / 127.5 - 1
    b = torch.as_tensor(np.asarray(target)).float().permute(0, 3, 1, 2) / 127.5 - 1
    with torch.no_grad():
        return float(model(a, b).mean())
