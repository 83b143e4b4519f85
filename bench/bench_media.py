"""Media codec throughput at the default clip size (61 x 480 x 832)."""

from __future__ import annotations

import time

import cv2
import numpy as np

from egosim.pipeline import media


def _frames() -> np.ndarray:
    v, u = np.mgrid[0:480, 0:832].astype(np.float32)
    rng = np.random.default_rng(0)
    noise = rng.integers(0, 40, (480, 832, 1), dtype=np.uint8)
    frames = []
    for t in range(61):
        luma = 127 + 90 * np.sin(u / 23 + v / 31 + 0.1 * t) * np.cos(v / 47 - 0.05 * t)
        frames.append(np.clip(luma[..., None] * [1.0, 0.9, 0.8] + noise, 0, 255))
    return np.stack(frames).astype(np.uint8)


def bench_video_codecs() -> list[dict]:
    """H.264 encode and decode frames/s against per-frame PNG (lossless) in the same run."""
    frames = _frames()
    t0 = time.perf_counter()
    data = media.encode_rgb_video(frames, 16.0)
    enc = time.perf_counter() - t0
    t0 = time.perf_counter()
    media.decode_rgb_video(data, 480, 832)
    dec = time.perf_counter() - t0
    t0 = time.perf_counter()
    pngs = [cv2.imencode(".png", f)[1] for f in frames]
    png_enc = time.perf_counter() - t0
    t0 = time.perf_counter()
    for p in pngs:
        cv2.imdecode(p, cv2.IMREAD_COLOR)
    png_dec = time.perf_counter() - t0
    n = len(frames)
    png_bytes = sum(len(p) for p in pngs)
    return [
        {
            "name": "h264 encode",
            "value": n / enc,
            "unit": "frames/s",
            "baseline": "png encode (cv2)",
            "baseline_value": n / png_enc,
        },
        {
            "name": "h264 decode",
            "value": n / dec,
            "unit": "frames/s",
            "baseline": "png decode (cv2)",
            "baseline_value": n / png_dec,
        },
        {
            "name": "h264 clip size",
            "value": len(data) / 2**20,
            "unit": "MiB",
            "baseline": "png frames",
            "baseline_value": png_bytes / 2**20,
        },
    ]
