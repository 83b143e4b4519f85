"""Model benchmarks: tiny-preset training throughput and peak memory on CPU, 1 process and 2 ranks.

``python -m bench.run --only model`` runs both. The 2-rank figure launches this module under
``torchrun --standalone --nproc_per_node 2`` (gloo, FSDP2) and the 1-process baseline as a plain
subprocess running the same worker, in the same run.
"""

from __future__ import annotations

import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from egosim.model.conditioning import TrainingSample
from egosim.model.network import build_model
from egosim.model.presets import get_preset
from egosim.model.sampler import sample
from egosim.model.train import OptimConfig, TrainConfig, train


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
            optim=OptimConfig(warmup_steps=2),
            checkpoint_every=0,
            preview_steps=0,
            device="cpu",
            progress=False,
            tensorboard=False,
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


RANKS_STEPS = 6  # optimizer steps per run (the first, with allocator warm-up, is not timed)
RANKS_BATCH = 2  # samples per rank and micro-batch (2 ranks: a global batch of 4)


def _rank_worker(spec: Path) -> None:
    """One rank (or the single process): train tiny, rank 0 writes samples/s and peak memory."""
    import torch.distributed as dist

    from egosim.model.distributed import init_distributed, mean_over_ranks, shutdown_distributed

    torch.set_num_threads(1)
    job = json.loads(spec.read_text())
    ctx = init_distributed("cpu")
    preset = get_preset("tiny")
    data = _samples(8, preset.num_frames, preset.height, preset.width)
    cfg = TrainConfig(
        steps=RANKS_STEPS,
        batch_size=RANKS_BATCH,
        optim=OptimConfig(warmup_steps=2),
        checkpoint_every=0,
        preview_steps=0,
        device="cpu",
        progress=False,
        tensorboard=False,
        wandb="off",
    )
    with tempfile.TemporaryDirectory() as run_dir:
        result = train(cfg, data, run_dir, ctx=ctx)
        if ctx.is_main:
            lines = (Path(run_dir) / "metrics.jsonl").read_text().splitlines()
    rss = torch.tensor([result.peak_memory_mb])
    if ctx.enabled:
        dist.all_reduce(rss, op=dist.ReduceOp.MAX)
    mean_over_ranks(0.0, ctx)  # every rank reaches the reduction before rank 0 writes
    if ctx.is_main:
        timed = [json.loads(line) for line in lines][1:]  # step 1 (warm-up) left out
        seconds = sum(r["step_seconds"] for r in timed)
        samples = ctx.world_size * RANKS_BATCH * len(timed)
        out = {"samples_per_second": samples / seconds, "peak_rss_mb": float(rss.item())}
        Path(job["out"]).write_text(json.dumps(out))
    shutdown_distributed(ctx)


def _launch(ranks: int, folder: Path) -> dict:
    """Run :func:`_rank_worker` on ``ranks`` processes (1: a plain process, no torchrun)."""
    spec = folder / f"spec{ranks}.json"
    out = folder / f"out{ranks}.json"
    spec.write_text(json.dumps({"out": str(out)}))
    torchrun = ["-m", "torch.distributed.run", "--standalone", "--nproc_per_node", str(ranks)]
    launcher = [sys.executable, *(torchrun if ranks > 1 else []), "-m", "bench.bench_model"]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    root = Path(__file__).resolve().parents[1]
    done = subprocess.run(
        [*launcher, "--rank-worker", str(spec)],
        cwd=root,
        env=env,
        capture_output=True,
        text=True,
        timeout=900,
    )
    if done.returncode != 0:
        raise RuntimeError(f"{ranks}-rank training failed:\n{done.stderr[-4000:]}")
    return json.loads(out.read_text())


def bench_train_tiny_ranks() -> list[dict]:
    """Tiny training on 2 CPU ranks (torchrun, gloo, FSDP2) against 1 process, same batch per rank.

    Throughput counts all ranks' samples (2 ranks process twice the global batch); the ratio
    is the speed-up of adding a rank (2.0 = perfect on two free cores). Memory: the largest
    peak RSS of one rank against the single process's.
    """
    with tempfile.TemporaryDirectory() as tmp:
        one = _launch(1, Path(tmp))
        two = _launch(2, Path(tmp))
    size = "9x32x32 clips, batch 2 per rank"
    return [
        {
            "name": f"tiny train, 2 CPU ranks ({size})",
            "value": two["samples_per_second"],
            "unit": "samples/s",
            "baseline": "1 process, same batch per rank",
            "baseline_value": one["samples_per_second"],
        },
        {
            "name": "tiny train peak memory per rank, 2 ranks",
            "value": two["peak_rss_mb"],
            "unit": "MiB",
            "baseline": "1 process peak RSS",
            "baseline_value": one["peak_rss_mb"],
        },
    ]


if __name__ == "__main__":
    if len(sys.argv) == 3 and sys.argv[1] == "--rank-worker":
        _rank_worker(Path(sys.argv[2]))
    else:
        for row in (*bench_train_tiny(), *bench_train_tiny_ranks()):
            print(row)
