"""The training loop (library function, no CLI): AdamW, warmup, accumulation, clipping, EMA,
checkpoints that resume exactly, on one process or many (torchrun + FSDP2, model/distributed.py).

Run directory layout::

    run_dir/config.json           resolved TrainConfig + preset + world size + library versions
    run_dir/metrics.jsonl         one line per optimizer step (loss, lr, grad_norm, speed, memory)
    run_dir/tensorboard/          the same metrics and the previews as TensorBoard event files
    run_dir/checkpoints/step_XXXXXXXX/   one folder per checkpoint (format 3):
        model.safetensors         trainable weights, full tensors, keys ``model.<param name>``
        ema.safetensors           EMA of the trainable weights (``ema.<name>``), when on
        optimizer.safetensors     AdamW moments (``optimizer.<name>.exp_avg`` / ``.exp_avg_sq``)
        state.json                step, data position, config, AdamW step counts, shapes
        rng-rank<r>.json          each rank's torch / numpy / Python RNG states
    run_dir/previews/step_XXXXXXXX.png     rows: target, scene (masked), skeleton, generated
    run_dir/lora/                 (finetune=lora) adapters in diffusers' load_lora_weights layout

Batches: ``batch_size`` is per rank and per micro-batch; one optimizer step sees
``world_size * batch_size * grad_accum`` samples (the global batch).

Exact resume: every random draw of the loop (condition dropout, flow time, noise) comes from a
generator seeded by (seed, the sample's global position), so it depends neither on how samples
are spread over ranks nor on where a run was interrupted; the data position is one global
sample counter (indexable datasets are visited in a per-epoch seeded permutation, plain
iterables are replayed and skipped); the learning rate is a pure function of the step.
Reloading a checkpoint and going on gives the same losses as never stopping (bit-for-bit on one
CPU process; to float rounding when the number of ranks changes, since gradients are then
summed in another order).
"""

from __future__ import annotations

import base64
import dataclasses
import json
import random
import resource
import shutil
import sys
import time
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from egosim.model import distributed as parallel
from egosim.model.checkpoint import CHECKPOINT_SUFFIX, UnsafeCheckpointError
from egosim.model.conditioning import (
    GUIDANCE_TARGETS,
    Conditions,
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
from egosim.model.progress import WANDB_MODES, TrainReporter
from egosim.model.sampler import sample

CHECKPOINT_FORMAT = 3  # 3: a folder of DCP safetensors groups + state.json (2: one .safetensors)
STATE_FILE = "state.json"  # the JSON part of a checkpoint folder
CHECKPOINT_GROUPS = ("model", "ema", "optimizer")  # safetensors files of a checkpoint folder


@dataclass(frozen=True)
class OptimConfig:
    """AdamW and its learning-rate schedule (``--set optim.lr=1e-5``)."""

    lr: float = 1e-4  # peak learning rate (EgoSim / DWM: 1e-4 class)
    warmup_steps: int = 10  # linear warmup from lr/warmup to lr, then constant
    weight_decay: float = 0.0  # AdamW decoupled weight decay
    betas: tuple[float, float] = (0.9, 0.999)  # AdamW betas
    grad_clip: float = 1.0  # max global grad norm (<= 0: no clipping)

    def __post_init__(self) -> None:
        problems = []
        if not self.lr > 0:
            problems.append(f"lr must be > 0, got {self.lr}")
        if self.warmup_steps < 0:
            problems.append(f"warmup_steps must be >= 0, got {self.warmup_steps}")
        if self.weight_decay < 0:
            problems.append(f"weight_decay must be >= 0, got {self.weight_decay}")
        if len(self.betas) != 2 or not all(0 <= b < 1 for b in self.betas):
            problems.append(f"betas must be two values in [0, 1), got {self.betas}")
        if problems:
            raise ModelConfigError("OptimConfig: " + "; ".join(problems))

    def lr_at(self, step: int) -> float:
        """Learning rate of optimizer step ``step`` (0-based): linear warmup, then constant."""
        if self.warmup_steps and step < self.warmup_steps:
            return self.lr * (step + 1) / self.warmup_steps
        return self.lr


@dataclass(frozen=True)
class TrainConfig:
    """Everything a training run depends on (saved as the run's resolved config)."""

    preset: str = "tiny"  # model preset name (egosim.model.presets.PRESETS)
    steps: int = 100  # optimizer steps in total
    batch_size: int = 1  # samples per micro-batch on each rank
    grad_accum: int = 1  # micro-batches per optimizer step
    optim: OptimConfig = field(default_factory=OptimConfig)  # AdamW and the LR schedule
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
    mixed_precision: str = "auto"  # "auto" (bf16 on CUDA), "bf16" or "no"
    gradient_checkpointing: str = "auto"  # "auto" (on for CUDA), "on" or "off"
    device: str = "auto"  # "auto" (cuda:<local rank> if available), "cpu" or "cuda[:n]"
    weights_dir: str | None = None  # diffusers-format weights folder (required for Wan presets)
    text_embeddings_dir: str | None = None  # precomputed UMT5 features (Wan presets)
    progress: bool = True  # rich progress bar on stderr (rank 0)
    tensorboard: bool = True  # TensorBoard event files in RUN/tensorboard (rank 0)
    wandb: str = "auto"  # W&B offline run in RUN/wandb: "auto" (when installed), "offline", "off"

    def __post_init__(self) -> None:
        problems = []
        get_preset(self.preset)
        for name in ("steps", "batch_size", "grad_accum", "keep_checkpoints"):
            if getattr(self, name) < 1:
                problems.append(f"{name} must be >= 1, got {getattr(self, name)}")
        for name in ("checkpoint_every", "preview_every", "preview_steps"):
            if getattr(self, name) < 0:
                problems.append(f"{name} must be >= 0, got {getattr(self, name)}")
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
        if self.wandb not in WANDB_MODES:
            problems.append(f"wandb must be one of {WANDB_MODES}, got {self.wandb!r}")
        if problems:
            raise ModelConfigError("TrainConfig: " + "; ".join(problems))


@dataclass
class TrainResult:
    """What :func:`train` returns."""

    losses: list[float]  # loss of every optimizer step run in THIS call, in order
    step: int  # optimizer steps done in total (including resumed ones)
    run_dir: Path  # where config, metrics, checkpoints and previews are
    bundle: ModelBundle  # the trained model (EMA weights are in the checkpoint, not applied)
    resumed_from: int  # step the call started from (0: fresh)
    samples_per_second: float  # training throughput of this call, all ranks (optimizer steps)
    peak_memory_mb: float  # CUDA peak allocated, or the process's max RSS on CPU (this rank)
    world_size: int = 1  # ranks that trained


@dataclass
class TrainState:
    """The mutable state of a run: model, optimizer, EMA and position (what a checkpoint holds)."""

    bundle: ModelBundle  # preset, denoiser (sharded under FSDP) and VAE
    params: dict[str, torch.nn.Parameter]  # trainable parameters by name (DTensors under FSDP)
    optimizer: torch.optim.AdamW  # over ``params``
    ema: dict[str, torch.Tensor] | None  # EMA of ``params`` (same sharding), None when off
    step: int = 0  # optimizer steps done
    samples_seen: int = 0  # global sample position of the next micro-batch (all ranks)


# --- data ---------------------------------------------------------------------------------------


def sample_stream(dataset: Iterable[Any], seed: int, start: int) -> Iterator[Any]:
    """Endless stream of samples beginning at position ``start`` of the run's fixed order.

    Indexable datasets (``__len__`` + ``__getitem__``): a seeded permutation per epoch. Other
    iterables: their own order, re-iterated each epoch; resuming replays and skips ``start``.
    """
    if _indexable(dataset):
        data: Sequence = dataset  # type: ignore[assignment]
        if len(data) == 0:
            raise ModelConfigError("dataset is empty")
        k = start
        while True:
            yield from (
                data[i]
                for i in parallel.positions_to_indices(range(k, k + len(data)), len(data), seed)
            )
            k += len(data)
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


def _indexable(dataset: Any) -> bool:
    return hasattr(dataset, "__len__") and hasattr(dataset, "__getitem__")


class _Feed:
    """This rank's micro-batches: ``take(start)`` -> (global positions, samples)."""

    def __init__(
        self, dataset: Iterable[Any], config: TrainConfig, ctx: parallel.DistContext, start: int
    ):
        self.dataset, self.config, self.ctx = dataset, config, ctx
        self.stream: Iterator[Any] | None = None
        if not _indexable(dataset):
            if ctx.world_size > 1:
                raise ModelConfigError(
                    "training on several ranks needs an indexable dataset (len and [i], e.g. "
                    f"PackDataset); got {type(dataset).__name__}"
                )
            self.stream = sample_stream(dataset, config.seed, start)
        elif len(dataset) == 0:  # type: ignore[arg-type]
            raise ModelConfigError("dataset is empty")

    def take(self, start: int) -> tuple[range, list[Any]]:
        positions = parallel.rank_positions(start, self.config.batch_size, self.ctx)
        if self.stream is not None:
            return positions, [next(self.stream) for _ in positions]
        n = len(self.dataset)  # type: ignore[arg-type]
        indices = parallel.positions_to_indices(positions, n, self.config.seed)
        return positions, [self.dataset[i] for i in indices]  # type: ignore[index]


def sample_generator(seed: int, position: int) -> torch.Generator:
    """The generator of every random draw made for the sample at global ``position``."""
    a, b = np.random.SeedSequence([seed, position]).generate_state(2, dtype=np.uint32)
    return torch.Generator().manual_seed((int(a) << 32) | int(b))


# --- model and state ----------------------------------------------------------------------------


def _trainable(bundle: ModelBundle) -> dict[str, torch.nn.Parameter]:
    return {n: p for n, p in bundle.denoiser.named_parameters() if p.requires_grad}


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


def _use_bf16(config: TrainConfig, device: torch.device) -> bool:
    return device.type == "cuda" and config.mixed_precision in ("auto", "bf16")


def build_state(config: TrainConfig, ctx: parallel.DistContext) -> TrainState:
    """Model (sharded by FSDP2 when ranks > 1), AdamW over the trainable weights, EMA."""
    bundle = setup_model(config, ctx.device)
    if ctx.enabled:
        parallel.shard_denoiser(bundle.denoiser, ctx, bf16=_use_bf16(config, ctx.device))
    params = _trainable(bundle)
    optimizer = torch.optim.AdamW(
        list(params.values()),
        lr=config.optim.lr,
        betas=config.optim.betas,
        weight_decay=config.optim.weight_decay,
    )
    ema = _ema_copy(params) if config.ema_decay is not None else None
    return TrainState(bundle, params, optimizer, ema)


def _ema_copy(params: dict[str, torch.nn.Parameter]) -> dict[str, torch.Tensor]:
    return {n: p.detach().clone() for n, p in params.items()}


# --- checkpoints --------------------------------------------------------------------------------


def checkpoint_path(run_dir: str | Path, step: int) -> Path:
    """``run_dir/checkpoints/step_XXXXXXXX`` (a folder, format 3)."""
    return Path(run_dir) / "checkpoints" / f"step_{step:08d}"


def latest_checkpoint(run_dir: str | Path) -> Path | None:
    """Most recent checkpoint of a run directory (a ``step_*`` folder with its state.json), or None.

    A run of an older egosim may hold single-file ``step_*.safetensors`` checkpoints (format 2):
    the newest is returned when there is no folder (sampling reads it; resuming refuses it). A
    run directory that holds only pickled ``step_*.pt`` checkpoints is an
    :class:`UnsafeCheckpointError`: they are never loaded, and silently starting afresh would
    hide that.
    """
    folder = Path(run_dir) / "checkpoints"
    found = sorted(p.parent for p in folder.glob(f"step_*/{STATE_FILE}"))
    if found:
        return found[-1]
    single = sorted(folder.glob(f"step_*{CHECKPOINT_SUFFIX}"))
    if single:
        return single[-1]
    legacy = sorted(folder.glob("step_*.pt"))
    if legacy:
        raise UnsafeCheckpointError(
            f"{legacy[-1]}: pickled checkpoint of an older egosim; egosim loads only "
            f"safetensors checkpoints (step_*/{STATE_FILE}). Train afresh (--fresh)."
        )
    return None


def read_state(path: str | Path) -> dict:
    """The ``state.json`` of a checkpoint folder; raises :class:`CheckpointMismatchError`."""
    path = Path(path)
    file = path / STATE_FILE
    if not file.is_file():
        raise CheckpointMismatchError(
            f"{path} is not an egosim checkpoint folder (no {STATE_FILE})"
        )
    try:
        meta = json.loads(file.read_text())
    except (OSError, ValueError) as exc:
        raise CheckpointMismatchError(f"{file}: unreadable checkpoint state ({exc})") from exc
    if not isinstance(meta, dict) or meta.get("format") != CHECKPOINT_FORMAT:
        got = meta.get("format") if isinstance(meta, dict) else None
        raise CheckpointMismatchError(
            f"{file}: checkpoint format {got!r}, this code reads {CHECKPOINT_FORMAT}"
        )
    return meta


def check_checkpoint(meta: dict, config: TrainConfig, bundle: ModelBundle, where: Path) -> None:
    """Raise :class:`CheckpointMismatchError` if a checkpoint cannot continue this run."""
    if meta["preset"] != config.preset:
        raise CheckpointMismatchError(
            f"{where}: checkpoint was written by preset {meta['preset']!r}; this run uses "
            f"{config.preset!r}"
        )
    if meta["finetune"] != config.finetune:
        raise CheckpointMismatchError(
            f"{where}: checkpoint was trained with finetune={meta['finetune']!r}; this run uses "
            f"{config.finetune!r}"
        )
    want = {n: list(p.shape) for n, p in _trainable(bundle).items()}
    got = {n: list(s) for n, s in meta["shapes"].items()}
    for name in sorted(set(want) | set(got)):
        if want.get(name) != got.get(name):
            raise CheckpointMismatchError(
                f"{where}: checkpoint tensor {name!r} has shape {got.get(name)}, model expects "
                f"{want.get(name)} (None = absent)"
            )


def save_checkpoint(
    run_dir: Path, config: TrainConfig, state: TrainState, ctx: parallel.DistContext
) -> Path:
    """Write ``checkpoints/step_XXXXXXXX`` (collective: every rank calls it); returns the folder.

    The folder appears complete or not at all: it is written as ``step_X.partial`` and renamed
    by rank 0 after the shards are merged and ``state.json`` is written.
    """
    final = checkpoint_path(run_dir, state.step)
    partial = final.with_name(final.name + ".partial")
    if ctx.is_main:
        shutil.rmtree(partial, ignore_errors=True)
        partial.mkdir(parents=True)
    parallel.barrier(ctx)
    moments, counts = _optimizer_tensors(state)
    groups = {"model": dict(state.params), "ema": state.ema or {}, "optimizer": moments}
    parallel.save_tensors(partial, groups, ctx)
    (partial / f"rng-rank{ctx.rank}.json").write_text(json.dumps(_rng_state()))
    parallel.barrier(ctx)
    if ctx.is_main:
        meta = {
            "format": CHECKPOINT_FORMAT,
            "preset": config.preset,
            "finetune": config.finetune,
            "step": state.step,
            "samples_seen": state.samples_seen,
            "world_size": ctx.world_size,
            "global_batch": ctx.world_size * config.batch_size * config.grad_accum,
            "ema": state.ema is not None,
            "shapes": {n: list(p.shape) for n, p in state.params.items()},
            "optimizer_steps": counts,
            "config": dataclasses.asdict(config),
        }
        (partial / STATE_FILE).write_text(json.dumps(meta, indent=2))
        shutil.rmtree(final, ignore_errors=True)
        partial.rename(final)
        kept = sorted(p.parent for p in final.parent.glob(f"step_*/{STATE_FILE}"))
        for old in kept[: -config.keep_checkpoints]:
            shutil.rmtree(old)
    parallel.barrier(ctx)
    return final


def _optimizer_tensors(state: TrainState) -> tuple[dict[str, torch.Tensor], dict[str, float]]:
    """AdamW moments by ``<param>.exp_avg|exp_avg_sq`` and each parameter's step count."""
    moments: dict[str, torch.Tensor] = {}
    counts: dict[str, float] = {}
    for name, p in state.params.items():
        st = state.optimizer.state.get(p, {})
        moments[f"{name}.exp_avg"] = st.get("exp_avg", torch.zeros_like(p))
        moments[f"{name}.exp_avg_sq"] = st.get("exp_avg_sq", torch.zeros_like(p))
        counts[name] = float(st["step"]) if "step" in st else 0.0
    return moments, counts


def load_checkpoint(
    path: str | Path, config: TrainConfig, state: TrainState, ctx: parallel.DistContext
) -> dict:
    """Continue ``state`` from a checkpoint folder (collective); returns its state.json.

    Works whatever the number of ranks that wrote it: each rank reads the slices it owns.
    Raises :class:`CheckpointMismatchError` when it cannot continue this run.
    """
    path = Path(path)
    if path.is_file():
        raise CheckpointMismatchError(
            f"{path}: single-file checkpoint of an older egosim (format 2): it can be sampled "
            f"(egosim simulate --checkpoint) but not resumed; train afresh (--fresh)"
        )
    meta = read_state(path)
    check_checkpoint(meta, config, state.bundle, path)
    moments = {
        f"{n}.{k}": torch.zeros_like(p)
        for n, p in state.params.items()
        for k in ("exp_avg", "exp_avg_sq")
    }
    targets = {"model": dict(state.params), "optimizer": moments}
    if state.ema is not None and meta["ema"]:
        targets["ema"] = state.ema
    parallel.load_tensors(path, targets, ctx)
    if state.ema is not None and not meta["ema"]:
        state.ema = _ema_copy(state.params)  # EMA turned on at resume: starts at the weights
    for name, p in state.params.items():
        count = meta["optimizer_steps"][name]
        if count > 0:
            state.optimizer.state[p] = {
                "step": torch.tensor(count, dtype=torch.float32),
                "exp_avg": moments[f"{name}.exp_avg"],
                "exp_avg_sq": moments[f"{name}.exp_avg_sq"],
            }
    rng = path / f"rng-rank{ctx.rank}.json"
    if rng.is_file():
        _set_rng_state(json.loads(rng.read_text()))
    state.step, state.samples_seen = int(meta["step"]), int(meta["samples_seen"])
    return meta


def load_weights(
    path: str | Path, config: TrainConfig, bundle: ModelBundle, use_ema: bool
) -> tuple[dict, bool]:
    """Load a checkpoint folder's trainable weights (EMA ones when there and wanted) in one process.

    Returns (state.json, whether EMA weights were loaded).
    """
    path = Path(path)
    meta = read_state(path)
    check_checkpoint(meta, config, bundle, path)
    group = "ema" if use_ema and meta["ema"] else "model"
    parallel.load_tensors(
        path, {group: _trainable(bundle)}, parallel.DistContext(0, 1, 0, torch.device("cpu"))
    )
    return meta, group == "ema"


def _b64(t: torch.Tensor) -> str:
    return base64.b64encode(t.numpy().tobytes()).decode("ascii")


def _unb64(s: str) -> torch.Tensor:
    return torch.frombuffer(bytearray(base64.b64decode(s)), dtype=torch.uint8)


def _rng_state() -> dict:
    """This process's torch / numpy / Python RNG states as JSON-able values."""
    kind, keys, pos, has_gauss, gauss = np.random.get_state()
    version, internal, gauss_next = random.getstate()
    state = {
        "torch": _b64(torch.get_rng_state()),
        "numpy": [kind, keys.tolist(), int(pos), int(has_gauss), float(gauss)],
        "python": [version, list(internal), gauss_next],
    }
    if torch.cuda.is_available():
        state["cuda"] = [_b64(s) for s in torch.cuda.get_rng_state_all()]
    return state


def _set_rng_state(state: dict) -> None:
    torch.set_rng_state(_unb64(state["torch"]))
    kind, keys, pos, has_gauss, gauss = state["numpy"]
    np.random.set_state((kind, np.asarray(keys, dtype=np.uint32), pos, has_gauss, gauss))
    version, internal, gauss_next = state["python"]
    random.setstate((version, tuple(internal), gauss_next))
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all([_unb64(s) for s in state["cuda"]])


# --- the loop -----------------------------------------------------------------------------------


def _peak_memory_mb(device: torch.device) -> float:
    if device.type == "cuda":
        return torch.cuda.max_memory_allocated(device) / 2**20
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return rss / 2**20 if sys.platform == "darwin" else rss / 1024


def _write_config(
    run_dir: Path, config: TrainConfig, bundle: ModelBundle, ctx: parallel.DistContext
) -> None:
    resolved = {
        "train": dataclasses.asdict(config),
        "preset": dataclasses.asdict(bundle.preset),
        "device": str(ctx.device),
        "world_size": ctx.world_size,
        "global_batch": ctx.world_size * config.batch_size * config.grad_accum,
        "versions": {"torch": torch.__version__, "python": sys.version.split()[0]},
    }
    (run_dir / "config.json").write_text(json.dumps(resolved, indent=2, default=str))


def train(
    config: TrainConfig,
    dataset: Iterable[Any],
    run_dir: str | Path,
    resume: bool = True,
    max_steps: int | None = None,
    ctx: parallel.DistContext | None = None,
) -> TrainResult:
    """Train the preset's denoiser on ``dataset`` (TrainingSample or LatentSample items).

    ``resume``: continue from the run directory's latest checkpoint if there is one.
    ``max_steps``: stop once this many total steps are done (an interruption; the last step is
    checkpointed), default ``config.steps``. ``ctx``: the rank's place (default: one process,
    or torchrun's process group when launched by torchrun; see :func:`parallel.init_distributed`).
    """
    ctx = ctx or parallel.init_distributed(config.device)
    run_dir = Path(run_dir)
    if ctx.is_main:
        run_dir.mkdir(parents=True, exist_ok=True)
    parallel.barrier(ctx)
    state = build_state(config, ctx)
    ckpt = latest_checkpoint(run_dir) if resume else None
    resumed_from = load_checkpoint(ckpt, config, state, ctx)["step"] if ckpt is not None else 0
    if ctx.is_main:
        _write_config(run_dir, config, state.bundle, ctx)
    stop = min(config.steps, max_steps if max_steps is not None else config.steps)
    reporter = TrainReporter(
        run_dir,
        stop,
        state.step,
        dataclasses.asdict(config),
        enabled=ctx.is_main,
        progress=config.progress,
        tensorboard=config.tensorboard,
        wandb=config.wandb,
    )
    with reporter:
        losses, seconds, samples = _run_steps(config, dataset, run_dir, state, ctx, stop, reporter)
    if config.finetune == "lora" and state.step == stop:
        _export_lora(run_dir / "lora", state, ctx)
    return TrainResult(
        losses=losses,
        step=state.step,
        run_dir=run_dir,
        bundle=state.bundle,
        resumed_from=resumed_from,
        samples_per_second=samples / seconds if seconds > 0 else 0.0,
        peak_memory_mb=_peak_memory_mb(ctx.device),
        world_size=ctx.world_size,
    )


def _run_steps(
    config: TrainConfig,
    dataset: Iterable[Any],
    run_dir: Path,
    state: TrainState,
    ctx: parallel.DistContext,
    stop: int,
    reporter: TrainReporter,
) -> tuple[list[float], float, int]:
    """Optimizer steps until ``stop``: (losses, seconds spent in steps, samples trained on)."""
    preset = state.bundle.preset
    flow = FlowMatching(
        shift=preset.sample_shift if config.shift is None else config.shift,
        time_sampling=config.time_sampling,
    )
    feed = _Feed(dataset, config, ctx, state.samples_seen)
    global_batch = ctx.world_size * config.batch_size * config.grad_accum
    losses: list[float] = []
    seconds, samples = 0.0, 0
    state.bundle.denoiser.train()
    while state.step < stop:
        t0 = time.perf_counter()
        loss, grad_norm, lr = _optimizer_step(config, state, feed, flow, ctx)
        dt = time.perf_counter() - t0
        seconds += dt
        samples += global_batch
        losses.append(loss)
        reporter.step(
            {
                "step": state.step,
                "loss": loss,
                "lr": lr,
                "grad_norm": grad_norm,
                "samples_seen": state.samples_seen,
                "step_seconds": dt,
                "samples_per_second": global_batch / dt,
                "peak_memory_mb": _peak_memory_mb(ctx.device),
            }
        )
        last = state.step == stop
        if last or (config.checkpoint_every and state.step % config.checkpoint_every == 0):
            save_checkpoint(run_dir, config, state, ctx)
        due = last or (config.preview_every and state.step % config.preview_every == 0)
        if config.preview_steps and due:
            _preview(run_dir, config, state, dataset, ctx, reporter)
    return losses, seconds, samples


def _optimizer_step(
    config: TrainConfig,
    state: TrainState,
    feed: _Feed,
    flow: FlowMatching,
    ctx: parallel.DistContext,
) -> tuple[float, float, float]:
    """One optimizer step (``grad_accum`` micro-batches): (loss mean over ranks, grad norm, lr)."""
    lr = config.optim.lr_at(state.step)
    for group in state.optimizer.param_groups:
        group["lr"] = lr
    state.optimizer.zero_grad(set_to_none=True)
    den = state.bundle.denoiser
    step_loss = 0.0
    for micro in range(config.grad_accum):
        parallel.set_gradient_sync(den, micro == config.grad_accum - 1)
        positions, batch = feed.take(state.samples_seen)
        state.samples_seen += ctx.world_size * config.batch_size
        loss = _micro_step(state.bundle, flow, batch, positions, config, ctx.device)
        (loss / config.grad_accum).backward()
        step_loss += float(loss.detach()) / config.grad_accum
    params = list(state.params.values())
    grad_norm = (
        parallel.to_float(torch.nn.utils.clip_grad_norm_(params, config.optim.grad_clip))
        if config.optim.grad_clip > 0
        else float("nan")
    )
    state.optimizer.step()
    if state.ema is not None:
        with torch.no_grad():
            for n, p in state.params.items():
                state.ema[n].lerp_(p.detach(), 1.0 - config.ema_decay)
    state.step += 1
    return parallel.mean_over_ranks(step_loss, ctx), grad_norm, lr


def _micro_step(
    bundle: ModelBundle,
    flow: FlowMatching,
    batch: list[Any],
    positions: range,
    config: TrainConfig,
    device: torch.device,
) -> torch.Tensor:
    """Flow-matching loss of one micro-batch (mean over its samples and elements).

    Dropout, flow time and noise of each sample come from :func:`sample_generator` of its global
    position, drawn in that order.
    """
    den = bundle.denoiser
    enc = encode_batch(bundle.vae, batch)
    x0, cond = enc.x0.to(device), enc.condition.to(device)  # (B,16,T',h,w), (B,36,T',h,w)
    context = den.encode_text(enc.prompts, enc.text_embeddings)  # (B, L, D)
    image_ctx = den.image_context(enc.image_embeddings)
    gens = [sample_generator(config.seed, k) for k in positions]
    dropped = torch.cat([torch.rand(1, generator=g) for g in gens]) < config.cond_dropout  # (B,)
    t = torch.cat([flow.sample_time(1, g) for g in gens]).to(device)  # (B,)
    noise = torch.stack([torch.randn(x0.shape[1:], generator=g) for g in gens]).to(x0)
    cond, context, image_ctx = null_conditions(
        cond, context, image_ctx, config.dropout_targets, dropped
    )
    with torch.autocast(device.type, dtype=torch.bfloat16, enabled=_use_bf16(config, device)):
        pred = den(assemble_input(flow.interpolate(x0, noise, t), cond), t, context, image_ctx)
    return torch.mean((pred.float() - flow.target(x0, noise).float()) ** 2)


def _preview(
    run_dir: Path,
    config: TrainConfig,
    state: TrainState,
    dataset: Iterable[Any],
    ctx: parallel.DistContext,
    reporter: TrainReporter,
) -> None:
    """Generate the first clip of the run's order and write the preview grid (all ranks sample)."""
    first = next(sample_stream(dataset, config.seed, 0))
    if not isinstance(first, Conditions):
        return  # precomputed latents carry no pixels to show next to the generated clip
    generated = sample(state.bundle, first, steps=config.preview_steps, seed=config.seed)
    state.bundle.denoiser.train()
    if ctx.is_main:
        grid = preview_grid(first, generated)
        _write_png(run_dir / "previews" / f"step_{state.step:08d}.png", grid)
        reporter.image("preview", grid, state.step)


def preview_grid(sample_: TrainingSample, generated: np.ndarray) -> np.ndarray:
    """RGB uint8 grid: rows target, scene (masked), skeleton, generated; columns frames."""
    scene = np.asarray(sample_.scene_video) * np.asarray(sample_.visibility)[..., None]
    rows = [
        np.asarray(sample_.target_video),
        scene.astype(np.uint8),
        np.asarray(sample_.skeleton_video),
        generated,
    ]
    return np.concatenate([np.concatenate(list(r), axis=1) for r in rows], axis=0)


def _write_png(path: Path, rgb: np.ndarray) -> None:
    import cv2

    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))


def _export_lora(folder: Path, state: TrainState, ctx: parallel.DistContext) -> None:
    """Write the adapters for diffusers (full tensors gathered from FSDP shards; rank 0 writes)."""
    from egosim.model.lora import lora_state_dict, save_lora

    transformer = state.bundle.denoiser.transformer
    if not ctx.enabled:
        save_lora(transformer, folder, lora_state_dict(transformer))
        return
    from torch.distributed.checkpoint.state_dict import StateDictOptions, get_model_state_dict

    # Collective: every rank takes part in the gather; only rank 0 receives the full tensors.
    full = get_model_state_dict(
        transformer, options=StateDictOptions(full_state_dict=True, cpu_offload=True)
    )
    if ctx.is_main:
        adapters = {k.replace(".default.", "."): v for k, v in full.items() if ".lora_" in k}
        trained_patch = transformer.patch_embedding.weight.requires_grad
        patch = {
            k.removeprefix("patch_embedding."): v
            for k, v in full.items()
            if trained_patch and k.startswith("patch_embedding.")
        }
        save_lora(transformer, folder, adapters, patch or None)
    parallel.barrier(ctx)
