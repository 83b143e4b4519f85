"""Train the observation model on pack or latents shards: one process, torchrun ranks, or Dask.

``train`` reads every clip of the data set, so it is not a :class:`ClipStage`: it is a library
function (:func:`run_training`) on a picklable :class:`TrainJob`, called by ``egosim train``
directly or submitted with :func:`submit_training` to a Dask scheduler as one task that asks for
``resources={"GPU": 1}`` (so it lands only on a worker started with ``--resources GPU=1``).

Under ``torchrun --nproc_per_node N -m egosim.pipeline.cli train ...`` every rank runs
:func:`run_training`: each indexes the shards (no rank loads the data set), trains its share of
every batch with FSDP2 (:mod:`egosim.model.distributed`), and rank 0 writes the files below.

The data: :func:`~egosim.stages.common.latents_dataset.open_training_data` gives precomputed
latents (a run with an ``encode/`` step) or pack samples (encoded on the fly).

Run directory (see :mod:`egosim.model.train` for the first ones)::

    RUN/config.json, metrics.jsonl, tensorboard/, checkpoints/, previews/, lora/   the loop
    RUN/data.json        shards and clip ids trained on
    RUN/sample.mp4       a sample generated from the first clip after training (pack data)
    RUN/summary.json     steps, wall time, loss curve summary
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from egosim.model.conditioning import Conditions
from egosim.model.distributed import init_distributed, shutdown_distributed
from egosim.model.errors import ModelConfigError
from egosim.model.train import TrainConfig, train
from egosim.pipeline.media import write_video_file
from egosim.stages.common.latents_dataset import LatentsDataset, open_training_data
from egosim.stages.common.pack_dataset import PackDataset


@dataclass(frozen=True)
class TrainJob:
    """One training run: data, run directory and the model's training config."""

    data: tuple[str, ...]  # pack/latents shard files, folders of them, or run folders
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


def check_data(dataset: PackDataset | LatentsDataset, config: TrainConfig) -> None:
    """Raise :class:`ModelConfigError` when the samples cannot train this config as packed."""
    from egosim.model.conditioning import latent_frames
    from egosim.model.presets import get_preset

    preset = get_preset(config.preset)
    if isinstance(dataset, LatentsDataset):
        dataset.check_preset(config.preset)  # latents of other encoders: refused up front
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
    """Train ``job.config`` on the job's data; returns the summary also written to summary.json.

    Under torchrun every rank calls this (collectively); rank 0 writes the run's files and the
    returned summary has ``rank`` and ``world_size``.
    """
    start = time.perf_counter()
    run_dir = Path(job.out)
    ctx = init_distributed(job.config.device)
    try:
        dataset = open_training_data(job.data)
        check_data(dataset, job.config)
        if ctx.is_main:
            run_dir.mkdir(parents=True, exist_ok=True)
            data = {"shards": [str(p) for p in dataset.shards], "clip_ids": dataset.clip_ids}
            (run_dir / "data.json").write_text(json.dumps(data, indent=2))
        result = train(job.config, dataset, run_dir, resume=job.resume, ctx=ctx)
        _sample_video(job, dataset, result.bundle, ctx.is_main)
        summary = {
            "run_dir": str(run_dir),
            "preset": job.config.preset,
            "clips": len(dataset),
            "step": result.step,
            "resumed_from": result.resumed_from,
            "seconds": time.perf_counter() - start,
            "samples_per_second": result.samples_per_second,
            "peak_memory_mb": result.peak_memory_mb,
            "world_size": ctx.world_size,
            "rank": ctx.rank,
            "loss_curve": [],
            "config": asdict(job.config),
        }
        if ctx.is_main:
            with (run_dir / "metrics.jsonl").open() as log:
                curve = [json.loads(line)["loss"] for line in log if line.strip()]
            summary["loss_curve"] = loss_summary(curve)
            (run_dir / "summary.json").write_text(json.dumps(summary, indent=2, default=str))
    finally:
        shutdown_distributed(ctx)
    return summary


def _sample_video(
    job: TrainJob, dataset: PackDataset | LatentsDataset, bundle: Any, write: bool
) -> None:
    """RUN/sample.mp4 from the first clip (pack data only: latents carry no conditions video).

    Every rank samples (a sharded model needs all of them); ``write`` says who writes.
    """
    from egosim.model.sampler import sample

    if not job.sample_steps or not len(dataset):
        return
    first = dataset[0]
    if not isinstance(first, Conditions):
        return
    video = sample(bundle, first, steps=job.sample_steps, seed=job.config.seed)
    if write:
        write_video_file(Path(job.out) / "sample.mp4", video, fps=8.0)


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
