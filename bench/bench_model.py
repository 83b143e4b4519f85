"""Model benchmarks: tiny-preset training throughput and peak memory on one CPU core."""

from __future__ import annotations

import os
import resource
import tempfile
import time

import numpy as np
import torch

from egosim.model.conditioning import TrainingSample
from egosim.model.network import build_model
from egosim.model.presets import get_preset
from egosim.model.sampler import sample
from egosim.model.train import TrainConfig, train


def _samples(n: int, t: int, h: int, w: int) -> list[TrainingSample]:
    out = []
    for i in range(n):
        rng = np.random.default_rng(i)
        v = rng.integers(0, 256, (t, h, w, 3), dtype=np.uint8)
        out.append(
            TrainingSample(
                target_video=v,
                scene_video=v,
                visibility=(rng.random((t, h, w)) > 0.3).astype(np.uint8),
                skeleton_video=v,
                first_frame=v[0],
                prompt=f"move object {i}",
            )
        )
    return out


def bench_train_tiny(steps: int = 10, batch_size: int = 4) -> list[dict]:
    """Tiny preset at its default clip size (9 x 32 x 32) on one core and one torch thread.

    Training samples/s (forward + backward + AdamW) against sampling samples/s per Euler step
    (forward only, the same size); peak memory (process max RSS) against the RSS before
    training (torch and diffusers imported, model built).
    """
    previous = os.sched_getaffinity(0) if hasattr(os, "sched_getaffinity") else None
    if previous is not None:
        os.sched_setaffinity(0, {min(previous)})
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        preset = get_preset("tiny")
        data = _samples(8, preset.num_frames, preset.height, preset.width)
        bundle = build_model("tiny")
        rss_before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
        sample(bundle, data[:batch_size], steps=1)  # warm-up
        t0 = time.perf_counter()
        sample(bundle, data[:batch_size], steps=5)
        forward_sps = batch_size * 5 / (time.perf_counter() - t0)
        cfg = TrainConfig(
            steps=steps,
            batch_size=batch_size,
            warmup_steps=2,
            checkpoint_every=0,
            preview_steps=0,
            device="cpu",
        )
        with tempfile.TemporaryDirectory() as run_dir:
            result = train(cfg, data, run_dir)
    finally:
        torch.set_num_threads(threads)
        if previous is not None:
            os.sched_setaffinity(0, previous)
    return [
        {
            "name": "tiny model train (9x32x32 clips, 1 core)",
            "value": result.samples_per_second,
            "unit": "samples/s",
            "baseline": "tiny model sampling, one Euler step (forward only)",
            "baseline_value": forward_sps,
        },
        {
            "name": "tiny model train peak memory",
            "value": result.peak_memory_mb,
            "unit": "MiB",
            "baseline": "process RSS before training (imports + model)",
            "baseline_value": rss_before,
        },
    ]


if __name__ == "__main__":
    for row in bench_train_tiny():
        print(row)
