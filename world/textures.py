"""Procedural high-frequency textures, so that feature matching works on every surface.

A texture is a square ``(S, S, 3) uint8`` image sampled by surface coordinates in metres
(``texel_size`` metres per texel). It mixes multi-octave value noise through a colour palette,
random blobs of a second colour and, for some surfaces, a checker or stripe layer.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

# Named base colours (RGB 0..1); the name is what captions say.
COLOURS: dict[str, tuple[float, float, float]] = {
    "red": (0.80, 0.15, 0.12),
    "green": (0.20, 0.62, 0.22),
    "blue": (0.15, 0.30, 0.80),
    "yellow": (0.90, 0.80, 0.15),
    "orange": (0.95, 0.50, 0.10),
    "purple": (0.50, 0.20, 0.65),
    "cyan": (0.15, 0.70, 0.75),
    "pink": (0.92, 0.45, 0.65),
}


@dataclass(frozen=True)
class Texture:
    """A tiled texture image and its scale."""

    image: np.ndarray  # (S, S, 3) uint8 RGB albedo
    texel_size: float  # metres per texel on the surface


def value_noise(
    rng: np.random.Generator, size: int, octaves: int, base_cells: int, persistence: float = 0.75
) -> np.ndarray:
    """Multi-octave value noise ``(size, size)`` in [0, 1]; octave k has ``base_cells * 2**k``."""
    out = np.zeros((size, size), np.float32)
    total = 0.0
    for k in range(octaves):
        cells = min(base_cells * 2**k, size)
        grid = rng.random((cells + 1, cells + 1)).astype(np.float32)
        amp = persistence**k
        out += amp * cv2.resize(grid, (size, size), interpolation=cv2.INTER_CUBIC)
        total += amp
    out /= total
    lo, hi = np.percentile(out, [1, 99])
    return np.clip((out - lo) / max(hi - lo, 1e-6), 0.0, 1.0)


def make_texture(
    rng: np.random.Generator,
    base: tuple[float, float, float],
    size: int = 256,
    texel_size: float = 0.0015,
    contrast: float = 0.6,
) -> Texture:
    """A textured albedo around colour ``base``.

    Layers: multi-octave value noise modulating brightness, blobs of three other colours with
    radii from 3 mm to 3 cm (so that there are corners and blobs at every image scale), and for
    some surfaces a faint checker or stripe pattern, plus a per-texel grain.
    """
    base_c = np.asarray(base, np.float32)
    noise = value_noise(rng, size, octaves=6, base_cells=int(rng.integers(3, 7)))  # (S, S)
    shade = 1.0 - contrast + contrast * 1.5 * noise  # (S, S)
    img = base_c[None, None] * shade[..., None]  # (S, S, 3)
    others = np.stack(
        [base_c * 0.35, np.clip(base_c * 0.5 + 0.5, 0, 1), rng.uniform(0.05, 0.95, 3)]
    ).astype(np.float32)  # (3, 3) darker, lighter, contrasting
    r_min = max(1.0, 0.003 / texel_size)
    r_max = max(r_min + 1.0, min(0.03 / texel_size, size / 6))
    mean_r2 = (r_max**2 - r_min**2) / (2.0 * np.log(r_max / r_min))  # E[r^2], log-uniform r
    count = int(0.45 * size * size / (np.pi * mean_r2))
    radii = np.exp(rng.uniform(np.log(r_min), np.log(r_max), count))  # (count,)
    centres = rng.integers(0, size, (count, 2)).tolist()
    squash = rng.uniform(0.4, 1.0, count)
    angles = rng.uniform(0.0, 180.0, count).tolist()
    axes_a = np.maximum(1, np.rint(radii)).astype(int).tolist()
    axes_b = np.maximum(1, np.rint(radii * squash)).astype(int).tolist()
    label = np.full((size, size), 255, np.uint8)
    for k, (centre, a, b, angle) in enumerate(zip(centres, axes_a, axes_b, angles, strict=True)):
        cv2.ellipse(label, centre, (a, b), angle, 0, 360, k % 3, -1)
    spots = label < 3
    img[spots] = others[label[spots]] * shade[spots][:, None]
    layer = int(rng.integers(0, 3))  # 0 none, 1 checker, 2 stripes
    if layer:
        period = int(rng.integers(8, 24))
        i, j = np.mgrid[0:size, 0:size]
        mask = ((i // period + j // period) % 2 if layer == 1 else (i + j) // period % 2) > 0
        img = np.where(mask[..., None], img * 0.85, img)
    grain = rng.normal(0.0, 0.05, (size, size, 1)).astype(np.float32)  # per-texel grain
    img = np.clip(img * (1.0 + grain), 0.0, 1.0)
    return Texture((img * 255.0 + 0.5).astype(np.uint8), texel_size)
