"""The training loop (library function, no CLI): AdamW, warmup, accumulation, clipping, EMA,
checkpoints with optimizer and RNG state, and exact resume.

Run directory layout::

    run_dir/config.json           resolved TrainConfig + preset + library versions
    run_dir/metrics.jsonl         one line per optimizer step (loss, lr, grad_norm, speed, memory)
    run_dir/checkpoints/step_XXXXXXXX.safetensors   trainable weights, optimizer, EMA, RNG,
                                  data position (safetensors, never a pickle: model/checkpoint.py)
    run_dir/previews/step_XXXXXXXX.png     rows: target, scene (masked), skeleton, generated

Exact resume: every random draw of the loop (flow times, noise, condition dropout) comes from one
``torch.Generator`` whose state is checkpointed; the data position is a sample counter (indexable
datasets are visited in a per-epoch seeded permutation, plain iterables are replayed and
skipped); the learning rate is a pure function of the step. Reloading a checkpoint and going on
gives the same loss sequence as never stopping (tested bit-for-bit on CPU).
"""

from __future__ import annotations

import dataclasses
import json
import random
import resource
import sys
import time
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from egosim.model.checkpoint import CHECKPOINT_SUFFIX, UnsafeCheckpointError, load_tree, save_tree
from egosim.model.conditioning import (
    GUIDANCE_TARGETS,
    TrainingSample,
    assemble_input,
    encode_batch,
    null_conditions,
)
from egosim.model.errors import CheckpointMismatchError, ModelConfigError
from egosim.model.flow import FlowMatching
from egosim.model.lora import LoRAConfig, apply_lora
from egosim.model.network import ModelBundle, build_model
from egosim.model.presets import get_preset
from egosim.model.sampler import sample

CHECKPOINT_FORMAT = 2  # bump when the checkpoint dict layout changes (2: safetensors, no pickle)


@dataclass(frozen=True)
class TrainConfig:
    """Everything a training run depends on (saved as the run's resolved config)."""

    preset: str = "tiny"  # model preset name (egosim.model.presets.PRESETS)
    steps: int = 100  # optimizer steps in total
    batch_size: int = 1  # samples per micro-batch
    grad_accum: int = 1  # micro-batches per optimizer step
    lr: float = 1e-4  # peak learning rate (EgoSim / DWM: 1e-4 class)
    warmup_steps: int = 10  # linear warmup from lr/warmup to lr, then constant
    weight_decay: float = 0.0  # AdamW decoupled weight decay
    betas: tuple[float, float] = (0.9, 0.999)  # AdamW betas
    grad_clip: float = 1.0  # max global grad norm (<= 0: no clipping)
    ema_decay: float | None = None  # EMA of trainable weights (None: off), e.g. 0.999
    finetune: str = "full"  # "full" (EgoSim) or "lora" (DWM)
    lora: LoRAConfig = field(default_factory=LoRAConfig)  # adapters when finetune == "lora"
    cond_dropout: float = 0.1  # per-sample probability of nulling `dropout_targets` (for CFG)
    dropout_targets: tuple[str, ...] = ("text",)  # which conditions dropout nulls
    shift: float | None = None  # timestep shift (None: the preset's sample_shift)
    time_sampling: str = "uniform"  # flow-time density: "uniform" or "logit_normal"
    seed: int = 0  # seeds initialisation, data order, noise, times and dropout
    checkpoint_every: int = 50  # save every N steps (and always at the last step); 0: only last
    keep_checkpoints: int = 2  # most recent checkpoints kept on disk
    preview_every: int = 0  # write a preview png every N steps (0: only at the last step)
    preview_steps: int = 10  # Euler steps for previews (sampling default 50); 0: no previews
    mixed_precision: str = "auto"  # "auto" (bf16 autocast on CUDA), "bf16" or "no"
    gradient_checkpointing: str = "auto"  # "auto" (on for CUDA), "on" or "off"
    device: str = "auto"  # "auto" (cuda if available), "cpu" or "cuda[:n]"
    weights_dir: str | None = None  # diffusers-format weights folder (required for Wan presets)
    text_embeddings_dir: str | None = None  # precomputed UMT5 features (Wan presets)

    def __post_init__(self) -> None:
        problems = []
        get_preset(self.preset)
        for name in ("steps", "batch_size", "grad_accum"):
            if getattr(self, name) < 1:
                problems.append(f"{name} must be >= 1, got {getattr(self, name)}")
        if not self.lr > 0:
            problems.append(f"lr must be > 0, got {self.lr}")
        if self.warmup_steps < 0:
            problems.append(f"warmup_steps must be >= 0, got {self.warmup_steps}")
        if self.ema_decay is not None and not 0 < self.ema_decay < 1:
            problems.append(f"ema_decay must be in (0, 1) or None, got {self.ema_decay}")
        if self.finetune not in ("full", "lora"):
            problems.append(f"finetune must be 'full' or 'lora', got {self.finetune!r}")
        if not 0 <= self.cond_dropout <= 1:
            problems.append(f"cond_dropout must be in [0, 1], got {self.cond_dropout}")
        bad = [t for t in self.dropout_targets if t not in GUIDANCE_TARGETS]
        if bad:
            problems.append(f"dropout_targets must be among {GUIDANCE_TARGETS}, got {bad}")
        if self.mixed_precision not in ("auto", "bf16", "no"):
            problems.append(f"mixed_precision must be auto|bf16|no, got {self.mixed_precision!r}")
        if self.gradient_checkpointing not in ("auto", "on", "off"):
            problems.append(
                f"gradient_checkpointing must be auto|on|off, got {self.gradient_checkpointing!r}"
            )
        if problems:
            raise ModelConfigError("TrainConfig: " + "; ".join(problems))

    def lr_at(self, step: int) -> float:
        """Learning rate of optimizer step ``step`` (0-based): linear warmup, then constant."""
        if self.warmup_steps and step < self.warmup_steps:
            return self.lr * (step + 1) / self.warmup_steps
        return self.lr


@dataclass
class TrainResult:
    """What :func:`train` returns."""

    losses: list[float]  # loss of every optimizer step run in THIS call, in order
    step: int  # optimizer steps done in total (including resumed ones)
    run_dir: Path  # where config, metrics, checkpoints and previews are
    bundle: ModelBundle  # the trained model (EMA weights are in the checkpoint, not applied)
    resumed_from: int  # step the call started from (0: fresh)
    samples_per_second: float  # training throughput of this call (optimizer steps only)
    peak_memory_mb: float  # CUDA peak allocated, or the process's max RSS on CPU


def sample_stream(dataset: Iterable[TrainingSample], seed: int, start: int) -> Iterator[Any]:
    """Endless stream of samples beginning at position ``start`` of the run's fixed order.

    Indexable datasets (``__len__`` + ``__getitem__``): a seeded permutation per epoch. Other
    iterables: their own order, re-iterated each epoch; resuming replays and skips ``start``.
    """
    if hasattr(dataset, "__len__") and hasattr(dataset, "__getitem__"):
        data: Sequence = dataset  # type: ignore[assignment]
        n = len(data)
        if n == 0:
            raise ModelConfigError("dataset is empty")
        k, perm_epoch, perm = start, -1, None
        while True:
            epoch, pos = divmod(k, n)
            if epoch != perm_epoch:
                g = torch.Generator().manual_seed(seed * 1_000_003 + epoch)
                perm, perm_epoch = torch.randperm(n, generator=g).tolist(), epoch
            yield data[perm[pos]]
            k += 1
    k = 0
    while True:
        empty = True
        for item in dataset:
            empty = False
            if k >= start:
                yield item
            k += 1
        if empty:
            raise ModelConfigError("dataset is empty")


def _resolve_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(name)


def _trainable(bundle: ModelBundle) -> dict[str, torch.nn.Parameter]:
    return {n: p for n, p in bundle.denoiser.named_parameters() if p.requires_grad}


def _rng_state() -> dict:
    state = {
        "torch": torch.get_rng_state(),
        "numpy": np.random.get_state(),
        "python": random.getstate(),
    }
    if torch.cuda.is_available():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def _set_rng_state(state: dict) -> None:
    torch.set_rng_state(state["torch"])
    np.random.set_state(state["numpy"])
    random.setstate(state["python"])
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])


def save_checkpoint(
    path: Path,
    config: TrainConfig,
    bundle: ModelBundle,
    optimizer: torch.optim.Optimizer,
    ema: dict[str, torch.Tensor] | None,
    generator: torch.Generator,
    step: int,
    samples_seen: int,
) -> None:
    """Write trainable weights, optimizer, EMA, RNG states and data position (atomically).

    One safetensors file (:func:`egosim.model.checkpoint.save_tree`): tensors as tensors, the
    rest (step, config, optimizer hyper-parameters, Python RNG state) as JSON in its header.
    """
    trainable = _trainable(bundle)
    payload = {
        "format": CHECKPOINT_FORMAT,
        "preset": config.preset,
        "finetune": config.finetune,
        "shapes": {n: tuple(p.shape) for n, p in trainable.items()},
        "model": {n: p.detach().cpu() for n, p in trainable.items()},
        "optimizer": optimizer.state_dict(),
        "ema": None if ema is None else {n: t.cpu() for n, t in ema.items()},
        "generator": generator.get_state(),
        "rng": _rng_state(),
        "step": step,
        "samples_seen": samples_seen,
        "config": dataclasses.asdict(config),
    }
    save_tree(path, payload, CHECKPOINT_FORMAT)


def read_checkpoint(path: str | Path) -> dict:
    """The payload dict of a checkpoint file (safetensors only; a pickle is refused)."""
    payload, _ = load_tree(path)
    if not isinstance(payload, dict) or "config" not in payload or "model" not in payload:
        raise CheckpointMismatchError(f"{path} is not an egosim training checkpoint")
    return payload


def check_checkpoint(payload: dict, config: TrainConfig, bundle: ModelBundle) -> None:
    """Raise :class:`CheckpointMismatchError` if a checkpoint cannot continue this run."""
    if payload.get("format") != CHECKPOINT_FORMAT:
        raise CheckpointMismatchError(
            f"checkpoint format {payload.get('format')!r}, this code reads {CHECKPOINT_FORMAT}"
        )
    if payload["preset"] != config.preset:
        raise CheckpointMismatchError(
            f"checkpoint was written by preset {payload['preset']!r}; this run uses "
            f"{config.preset!r}"
        )
    if payload["finetune"] != config.finetune:
        raise CheckpointMismatchError(
            f"checkpoint was trained with finetune={payload['finetune']!r}; this run uses "
            f"{config.finetune!r}"
        )
    want = {n: tuple(p.shape) for n, p in _trainable(bundle).items()}
    got = {n: tuple(s) for n, s in payload["shapes"].items()}
    for name in sorted(set(want) | set(got)):
        if want.get(name) != got.get(name):
            raise CheckpointMismatchError(
                f"checkpoint tensor {name!r} has shape {got.get(name)}, model expects "
                f"{want.get(name)} (None = absent)"
            )


def load_checkpoint(
    path: str | Path, config: TrainConfig, bundle: ModelBundle, payload: dict | None = None
) -> dict:
    """Read and check a checkpoint, load its trainable weights into ``bundle``; returns it.

    Raises :class:`UnsafeCheckpointError` for a pickle or an unreadable file (nothing is
    unpickled) and :class:`CheckpointMismatchError` when it cannot continue this run.
    ``payload``: the file's content when the caller has already read it.
    """
    if payload is None:
        payload = read_checkpoint(path)
    check_checkpoint(payload, config, bundle)
    trainable = _trainable(bundle)
    with torch.no_grad():
        for n, p in trainable.items():
            p.copy_(payload["model"][n])
    return payload


def latest_checkpoint(run_dir: str | Path) -> Path | None:
    """Most recent ``checkpoints/step_*.safetensors`` of a run directory, or None.

    A run directory that holds only pickled checkpoints of an older egosim (``step_*.pt``) is
    an :class:`UnsafeCheckpointError`: they are never loaded, and silently starting afresh
    would hide that.
    """
    folder = Path(run_dir) / "checkpoints"
    found = sorted(folder.glob(f"step_*{CHECKPOINT_SUFFIX}"))
    if found:
        return found[-1]
    legacy = sorted(folder.glob("step_*.pt"))
    if legacy:
        raise UnsafeCheckpointError(
            f"{legacy[-1]}: pickled checkpoint of an older egosim; egosim loads only "
            f"safetensors checkpoints (step_*{CHECKPOINT_SUFFIX}). Train afresh (--fresh)."
        )
    return None


def _write_preview(path: Path, sample_: TrainingSample, generated: np.ndarray) -> None:
    import cv2

    scene = np.asarray(sample_.scene_video) * np.asarray(sample_.visibility)[..., None]
    rows = [
        np.asarray(sample_.target_video),
        scene.astype(np.uint8),
        np.asarray(sample_.skeleton_video),
        generated,
    ]
    grid = np.concatenate([np.concatenate(list(r), axis=1) for r in rows], axis=0)
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), cv2.cvtColor(grid, cv2.COLOR_RGB2BGR))


def _peak_memory_mb(device: torch.device) -> float:
    if device.type == "cuda":
        return torch.cuda.max_memory_allocated(device) / 2**20
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return rss / 2**20 if sys.platform == "darwin" else rss / 1024


def setup_model(config: TrainConfig, device: torch.device) -> ModelBundle:
    """Build the preset, set what trains (full or LoRA) and the GPU-only memory options."""
    bundle = build_model(
        config.preset, config.weights_dir, config.text_embeddings_dir, seed=config.seed
    )
    den = bundle.denoiser
    if config.finetune == "lora":
        apply_lora(den.transformer, config.lora)
        den.text_encoder.requires_grad_(True)  # tiny's hashed table is never pretrained
    else:
        den.requires_grad_(True)
    den.to(device)
    bundle.vae.to(device)
    use_gc = config.gradient_checkpointing == "on" or (
        config.gradient_checkpointing == "auto" and device.type == "cuda"
    )
    if use_gc:
        den.transformer.enable_gradient_checkpointing()
    return bundle


def train(
    config: TrainConfig,
    dataset: Iterable[TrainingSample],
    run_dir: str | Path,
    resume: bool = True,
    max_steps: int | None = None,
) -> TrainResult:
    """Train the preset's denoiser on ``dataset`` (TrainingSample items), writing ``run_dir``.

    ``resume``: continue from the run directory's latest checkpoint if there is one.
    ``max_steps``: stop once this many total steps are done (an interruption; the last step is
    checkpointed), default ``config.steps``.
    """
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    device = _resolve_device(config.device)
    bundle = setup_model(config, device)
    den = bundle.denoiser
    params = list(_trainable(bundle).values())
    optimizer = torch.optim.AdamW(
        params, lr=config.lr, betas=config.betas, weight_decay=config.weight_decay
    )
    ema = (
        {n: p.detach().clone() for n, p in _trainable(bundle).items()}
        if config.ema_decay is not None
        else None
    )
    generator = torch.Generator().manual_seed(config.seed)
    step, samples_seen, resumed_from = 0, 0, 0
    ckpt = latest_checkpoint(run_dir) if resume else None
    if ckpt is not None:
        payload = load_checkpoint(ckpt, config, bundle)
        optimizer.load_state_dict(payload["optimizer"])
        if ema is not None and payload["ema"] is not None:
            ema = {n: t.to(device) for n, t in payload["ema"].items()}
        generator.set_state(payload["generator"])
        _set_rng_state(payload["rng"])
        step = resumed_from = payload["step"]
        samples_seen = payload["samples_seen"]

    preset = bundle.preset
    resolved = {
        "train": dataclasses.asdict(config),
        "preset": dataclasses.asdict(preset),
        "device": str(device),
        "versions": {"torch": torch.__version__, "python": sys.version.split()[0]},
    }
    (run_dir / "config.json").write_text(json.dumps(resolved, indent=2, default=str))

    flow = FlowMatching(
        shift=preset.sample_shift if config.shift is None else config.shift,
        time_sampling=config.time_sampling,
    )
    use_bf16 = device.type == "cuda" and config.mixed_precision in ("auto", "bf16")
    stream = sample_stream(dataset, config.seed, samples_seen)
    stop = min(config.steps, max_steps if max_steps is not None else config.steps)
    losses: list[float] = []
    n_samples, step_time = 0, 0.0
    den.train()
    with (run_dir / "metrics.jsonl").open("a") as log:
        while step < stop:
            lr = config.lr_at(step)
            for group in optimizer.param_groups:
                group["lr"] = lr
            optimizer.zero_grad(set_to_none=True)
            step_loss = 0.0
            t0 = time.perf_counter()
            for _ in range(config.grad_accum):
                batch = [next(stream) for _ in range(config.batch_size)]
                samples_seen += len(batch)
                loss = _micro_step(bundle, flow, batch, config, generator, device, use_bf16)
                (loss / config.grad_accum).backward()
                step_loss += float(loss.detach()) / config.grad_accum
            grad_norm = (
                float(torch.nn.utils.clip_grad_norm_(params, config.grad_clip))
                if config.grad_clip > 0
                else float("nan")
            )
            optimizer.step()
            if ema is not None:
                with torch.no_grad():
                    for n, p in _trainable(bundle).items():
                        ema[n].lerp_(p.detach(), 1.0 - config.ema_decay)
            step += 1
            n = config.batch_size * config.grad_accum
            n_samples += n
            dt = time.perf_counter() - t0
            step_time += dt
            losses.append(step_loss)
            record = {
                "step": step,
                "loss": step_loss,
                "lr": lr,
                "grad_norm": grad_norm,
                "samples_seen": samples_seen,
                "step_seconds": dt,
                "samples_per_second": n / dt,
                "peak_memory_mb": _peak_memory_mb(device),
            }
            log.write(json.dumps(record) + "\n")
            log.flush()
            last = step == stop
            if last or (config.checkpoint_every and step % config.checkpoint_every == 0):
                path = run_dir / "checkpoints" / f"step_{step:08d}{CHECKPOINT_SUFFIX}"
                save_checkpoint(path, config, bundle, optimizer, ema, generator, step, samples_seen)
                kept = sorted(path.parent.glob(f"step_*{CHECKPOINT_SUFFIX}"))
                for old in kept[: -config.keep_checkpoints]:
                    old.unlink()
            due = last or (config.preview_every and step % config.preview_every == 0)
            if config.preview_steps and due:
                first = next(sample_stream(dataset, config.seed, 0))
                generated = sample(bundle, first, steps=config.preview_steps, seed=config.seed)
                _write_preview(run_dir / "previews" / f"step_{step:08d}.png", first, generated)
                den.train()
    return TrainResult(
        losses=losses,
        step=step,
        run_dir=run_dir,
        bundle=bundle,
        resumed_from=resumed_from,
        samples_per_second=n_samples / step_time if step_time > 0 else 0.0,
        peak_memory_mb=_peak_memory_mb(device),
    )


def _micro_step(
    bundle: ModelBundle,
    flow: FlowMatching,
    batch: list[TrainingSample],
    config: TrainConfig,
    generator: torch.Generator,
    device: torch.device,
    use_bf16: bool,
) -> torch.Tensor:
    """Flow-matching loss of one micro-batch (encodes targets and conditions on the fly)."""
    den = bundle.denoiser
    enc = encode_batch(bundle.vae, batch)
    x0, cond = enc.x0.to(device), enc.condition.to(device)  # (B,16,T',h,w), (B,36,T',h,w)
    context = den.encode_text(enc.prompts, enc.text_embeddings)  # (B, L, D)
    image_ctx = den.image_context(enc.image_embeddings)
    dropped = torch.rand(len(batch), generator=generator) < config.cond_dropout
    cond, context, image_ctx = null_conditions(
        cond, context, image_ctx, config.dropout_targets, dropped
    )
    with torch.autocast(device.type, dtype=torch.bfloat16, enabled=use_bf16):
        return flow.loss(
            lambda x, t: den(assemble_input(x, cond), t, context, image_ctx), x0, generator
        )
