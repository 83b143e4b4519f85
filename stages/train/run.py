"""Train the observation model on pack shards, locally or as one Dask task on a GPU worker.

``train`` reads every clip of the data set, so it is not a :class:`ClipStage`: it is a library
function (:func:`run_training`) on a picklable :class:`TrainJob`, called by ``egosim train``
directly or submitted with :func:`submit_training` to a Dask scheduler as one task that asks for
``resources={"GPU": 1}`` (so it lands only on a worker started with ``--resources GPU=1``).

Run directory (see :mod:`egosim.model.train` for the first four)::

    RUN/config.json, metrics.jsonl, checkpoints/, previews/   written by the training loop
    RUN/data.json        pack shards and clip ids trained on
    RUN/sample.mp4       a sample generated from the first clip after training
    RUN/summary.json     steps, wall time, loss curve summary
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from egosim.model.errors import ModelConfigError
from egosim.model.train import TrainConfig, train
from egosim.pipeline.media import write_video_file
from egosim.stages.common.pack_dataset import PackDataset


@dataclass(frozen=True)
class TrainJob:
    """One training run: data, run directory and the model's training config."""

    data: tuple[str, ...]  # pack shard files, folders of them, or run folders with pack/
    out: str  # run directory (created; resumed from its latest checkpoint when resume)
    config: TrainConfig  # the training loop's config (preset, steps, lr, ...)
    resume: bool = True  # continue from RUN's latest checkpoint when there is one
    sample_steps: int = 20  # Euler steps of RUN/sample.mp4 (0: no sample video)


def loss_summary(losses: list[float], windows: int = 5) -> list[dict[str, float]]:
    """Mean loss over ``windows`` equal consecutive parts of the run (the curve, compressed)."""
    if not losses:
        return []
    parts = np.array_split(np.asarray(losses, dtype=np.float64), min(windows, len(losses)))
    out, start = [], 0
    for part in parts:
        out.append(
            {"from_step": start + 1, "to_step": start + len(part), "loss": float(part.mean())}
        )
        start += len(part)
    return out


MAX_TINY_TOKENS = 8192  # tiny works at full pixel resolution: beyond this a CPU step takes minutes


def check_data(dataset: PackDataset, config: TrainConfig) -> None:
    """Raise :class:`ModelConfigError` when the samples cannot train this config as packed."""
    from egosim.model.conditioning import latent_frames
    from egosim.model.presets import get_preset

    preset = get_preset(config.preset)
    sizes = sorted(set(dataset.sizes))
    problems = []
    if config.batch_size > 1 and len(sizes) > 1:
        problems.append(
            f"batch_size {config.batch_size} needs samples of one size, the pack holds {sizes} "
            "(T, H, W): pack with one height/width/num_frames or use batch_size=1"
        )
    m = preset.pixel_multiple
    odd = [s for s in sizes if s[1] % m or s[2] % m]
    if odd:
        problems.append(
            f"preset {preset.name!r} needs height and width multiples of {m}, got {odd}"
        )
    if preset.vae.kind == "packed":
        patch = preset.transformer.patch_size
        big = [
            s
            for s in sizes
            if latent_frames(s[0]) * (s[1] // patch[1]) * (s[2] // patch[2]) > MAX_TINY_TOKENS
        ]
        if big:
            problems.append(
                f"preset {preset.name!r} works at full pixel resolution; samples {big} (T, H, W) "
                f"exceed {MAX_TINY_TOKENS} tokens: pack at a training size (e.g. pack params "
                "height=32 width=56 num_frames=9)"
            )
    if problems:
        raise ModelConfigError("training data: " + "; ".join(problems))


def run_training(job: TrainJob) -> dict[str, Any]:
    """Train ``job.config`` on the pack data; returns the summary also written to summary.json."""
    from egosim.model.sampler import sample

    start = time.perf_counter()
    run_dir = Path(job.out)
    dataset = PackDataset(job.data)
    check_data(dataset, job.config)
    run_dir.mkdir(parents=True, exist_ok=True)
    data = {"shards": [str(p) for p in dataset.shards], "clip_ids": dataset.clip_ids}
    (run_dir / "data.json").write_text(json.dumps(data, indent=2))
    result = train(job.config, dataset, run_dir, resume=job.resume)
    if job.sample_steps:
        first = dataset[0]
        video = sample(result.bundle, first, steps=job.sample_steps, seed=job.config.seed)
        write_video_file(run_dir / "sample.mp4", video, fps=8.0)
    curve = []
    with (run_dir / "metrics.jsonl").open() as log:
        curve = [json.loads(line)["loss"] for line in log if line.strip()]
    summary = {
        "run_dir": str(run_dir),
        "preset": job.config.preset,
        "clips": len(dataset),
        "step": result.step,
        "resumed_from": result.resumed_from,
        "seconds": time.perf_counter() - start,
        "samples_per_second": result.samples_per_second,
        "peak_memory_mb": result.peak_memory_mb,
        "loss_curve": loss_summary(curve),
        "config": asdict(job.config),
    }
    (run_dir / "summary.json").write_text(json.dumps(summary, indent=2, default=str))
    return summary


def submit_training(job: TrainJob, scheduler: str, gpu: bool = True) -> dict[str, Any]:
    """Run :func:`run_training` as one task on the Dask cluster at ``scheduler``.

    With ``gpu`` the task asks for ``{"GPU": 1}`` and waits for a worker that declares it. The
    data and run folders must be on a filesystem the worker shares.
    """
    from distributed import Client

    with Client(scheduler) as client:
        resources = {"GPU": 1} if gpu else None
        future = client.submit(run_training, job, resources=resources, pure=False)
        return future.result()
