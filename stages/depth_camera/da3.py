"""Optional backend: Depth Anything 3 (``depth-anything-3`` package), weights from a local path.

The package's ``DepthAnything3.from_pretrained(path).inference(images, process_res=...)`` returns
a prediction with ``depth (N, h, w)``, ``conf (N, h, w)``, ``extrinsics (N, 3, 4)`` world-to-camera
(OpenCV axes) and ``intrinsics (N, 3, 3)`` at the processed resolution ``h x w``. This module is
the one place where that world-to-camera output is converted to the project's ``world_from_cam``
(:func:`world_from_cam_from_extrinsics`) and where its intrinsics and depth are rescaled to the
clip's size. The package is imported lazily: the rest of the stage runs without it.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from egosim.pipeline.geometry import invert_se3, scale_intrinsics


class Da3Error(RuntimeError):
    """The Depth Anything 3 backend cannot run (package or weights missing, bad output)."""


@dataclass(frozen=True)
class Da3Result:
    """Camera and first-frame depth from Depth Anything 3, at the clip's resolution."""

    intrinsics: np.ndarray  # (4,) fx, fy, cx, cy in pixels of the clip's frames
    world_from_cam: np.ndarray  # (T, 4, 4) camera-to-world in the model's scale
    depth0: np.ndarray  # (H, W) float32 z-depth of frame 0 in the same scale
    confidence0: np.ndarray  # (H, W) float32 in [0, 1]


def world_from_cam_from_extrinsics(extrinsics: np.ndarray) -> np.ndarray:
    """Convert world-to-camera ``(N, 3, 4)`` or ``(N, 4, 4)`` extrinsics to ``(N, 4, 4)``.

    Depth Anything 3 (like COLMAP) reports ``cam_from_world``: ``x_cam = R x_world + t``. The
    project stores ``world_from_cam``, its rigid inverse. Raises :class:`Da3Error` on bad shapes.
    """
    ext = np.asarray(extrinsics, dtype=np.float64)
    if ext.ndim != 3 or ext.shape[1:] not in ((3, 4), (4, 4)):
        raise Da3Error(f"extrinsics must be (N, 3, 4) or (N, 4, 4), got {ext.shape}")
    cam_from_world = np.tile(np.eye(4), (len(ext), 1, 1))
    cam_from_world[:, :3, :] = ext[:, :3, :]
    return invert_se3(cam_from_world)


def intrinsics_from_matrices(
    matrices: np.ndarray, processed_hw: tuple[int, int], clip_hw: tuple[int, int]
) -> np.ndarray:
    """Average ``(N, 3, 3)`` pinhole matrices at ``processed_hw`` and rescale to ``clip_hw``.

    Returns ``(fx, fy, cx, cy)`` in pixels of the clip's frames.
    """
    k = np.asarray(matrices, dtype=np.float64).reshape(-1, 3, 3).mean(0)
    vec = np.array([k[0, 0], k[1, 1], k[0, 2], k[1, 2]])
    (ph, pw), (h, w) = processed_hw, clip_hw
    return scale_intrinsics(vec, w / pw, h / ph)


def _load_model(weights: str, device: str) -> Any:
    try:
        from depth_anything_3.api import DepthAnything3
    except ImportError as exc:
        raise Da3Error(
            "backend 'da3' needs the depth-anything-3 package (pip install depth-anything-3)"
        ) from exc
    if not weights or not Path(weights).exists():
        raise Da3Error(f"backend 'da3' needs a local weights folder (da3_weights), got {weights!r}")
    return DepthAnything3.from_pretrained(weights).to(device).eval()


def run_da3(
    frames: np.ndarray, weights: str, device: str = "cpu", process_res: int = 504
) -> Da3Result:
    """Run Depth Anything 3 on ``frames (T, H, W, 3)`` uint8 RGB; see :class:`Da3Result`."""
    import torch

    model = _load_model(weights, device)
    t, h, w = frames.shape[:3]
    with torch.no_grad():
        pred = model.inference(list(frames), process_res=process_res)
    depth = np.asarray(pred.depth, dtype=np.float32)  # (T, ph, pw)
    if depth.ndim != 3 or len(depth) != t or pred.extrinsics is None or pred.intrinsics is None:
        raise Da3Error(f"unexpected Depth Anything 3 output: depth {depth.shape}")
    ph, pw = depth.shape[1:]
    conf = np.asarray(pred.conf, dtype=np.float32)[0]  # (ph, pw), unbounded scores
    scale = float(np.quantile(conf, 0.95)) or 1.0
    return Da3Result(
        intrinsics=intrinsics_from_matrices(pred.intrinsics, (ph, pw), (h, w)),
        world_from_cam=world_from_cam_from_extrinsics(pred.extrinsics),
        depth0=cv2.resize(depth[0], (w, h), interpolation=cv2.INTER_LINEAR),
        confidence0=np.clip(cv2.resize(conf / scale, (w, h)), 0.0, 1.0).astype(np.float32),
    )
