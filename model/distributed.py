"""Many processes, one model: the process group, FSDP2 sharding, data positions and DCP checkpoints.

``torchrun --nproc_per_node N -m egosim.pipeline.cli train ...`` starts N processes; each calls
:func:`init_distributed`, which reads torchrun's environment (``RANK``, ``WORLD_SIZE``,
``LOCAL_RANK``) and joins the process group (NCCL on CUDA, gloo on CPU). Without torchrun the
context is a single process and nothing here touches ``torch.distributed``: one process stays
the default and runs exactly the code it always ran.

- Sharding (:func:`shard_denoiser`): FSDP2 ``fully_shard`` on every transformer block, then on
  the transformer as the root; the prompt encoder, when it has parameters (tiny's hashed table),
  is its own FSDP root because it runs outside the transformer's forward. On CUDA the parameters
  are all-gathered in bf16 and gradients reduced in fp32 (``MixedPrecisionPolicy``). Activation
  checkpointing stays diffusers' per-block ``enable_gradient_checkpointing`` (non-reentrant
  ``torch.utils.checkpoint``), which composes with the per-block FSDP units.
- Data (:func:`rank_positions`): the run visits one global order of sample positions; every
  micro-batch takes the next ``world_size * batch_size`` positions and rank r keeps its own
  contiguous slice, so N ranks with batch b see exactly the samples one process with batch N*b
  sees, and each rank reads (decodes) only its own samples.
- Checkpoints (:func:`save_tensors`, :func:`load_tensors`): ``torch.distributed.checkpoint``
  with its Hugging Face storage, i.e. safetensors files, never pickles. Each rank writes its
  shards, rank 0 consolidates them into one full-tensor file per group (``model.safetensors``,
  ``ema.safetensors``, ``optimizer.safetensors``), and a load reads only the slices the loading
  rank owns: a checkpoint written by N ranks loads on M ranks (or one process).
"""

from __future__ import annotations

import os
import shutil
import warnings
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import torch
import torch.distributed as dist
from torch import nn

from egosim.model.errors import CheckpointMismatchError, ModelConfigError, WeightsMismatchError

# DCP says so on every single-process save/load; one process is the intended default here.
_SINGLE_PROCESS_WARNING = r"torch\.distributed is disabled, unavailable or uninitialized"
SHARDED_DIR = "sharded"  # DCP's per-rank shard folder inside a checkpoint (removed once merged)

# FSDP2 warns that the root returns a view (an in-place op on it would skip the all-gather); the
# loop only reads the transformer output, out of place.
warnings.filterwarnings("ignore", message=r"FSDP2-wrapped module .* returned a view tensor")


@dataclass(frozen=True)
class DistContext:
    """Where this process stands: its rank, the number of ranks and its device."""

    rank: int  # global rank (0 in a single process)
    world_size: int  # number of ranks (1 in a single process)
    local_rank: int  # rank on this machine (selects the CUDA device)
    device: torch.device  # the device this rank computes on

    @property
    def enabled(self) -> bool:
        """True when a process group is in use (more than one rank, or torchrun with one)."""
        return dist.is_available() and dist.is_initialized()

    @property
    def is_main(self) -> bool:
        """True on rank 0: the rank that logs, writes previews and merges checkpoints."""
        return self.rank == 0


def launched_by_torchrun() -> bool:
    """Whether torchrun (or another launcher with its environment) started this process."""
    return "WORLD_SIZE" in os.environ and "RANK" in os.environ


def resolve_device(name: str, local_rank: int = 0) -> torch.device:
    """``auto`` -> ``cuda:<local_rank>`` when CUDA is available, else ``cpu``; others as given."""
    if name == "auto":
        return torch.device(f"cuda:{local_rank}" if torch.cuda.is_available() else "cpu")
    device = torch.device(name)
    if device.type == "cuda" and device.index is None:
        return torch.device(f"cuda:{local_rank}")
    return device


def init_distributed(device: str = "auto") -> DistContext:
    """Join torchrun's process group (when launched by torchrun) and pick this rank's device.

    Without torchrun: a single-process context and no process group. Backend: NCCL when the
    device is CUDA, gloo otherwise. An already initialised group (a test harness) is reused.
    """
    if not launched_by_torchrun():
        return DistContext(0, 1, 0, resolve_device(device))
    rank, world = int(os.environ["RANK"]), int(os.environ["WORLD_SIZE"])
    local_rank = int(os.environ.get("LOCAL_RANK", "0"))
    dev = resolve_device(device, local_rank)
    if dev.type == "cuda":
        torch.cuda.set_device(dev)
    if not dist.is_initialized():
        backend = "nccl" if dev.type == "cuda" else "gloo"
        dist.init_process_group(backend, device_id=dev if dev.type == "cuda" else None)
    if dist.get_world_size() != world or dist.get_rank() != rank:
        raise ModelConfigError(
            f"process group has rank {dist.get_rank()} of {dist.get_world_size()}, the "
            f"environment says rank {rank} of {world}"
        )
    return DistContext(rank, world, local_rank, dev)


def shutdown_distributed(ctx: DistContext) -> None:
    """Leave the process group (no-op in a single process)."""
    if ctx.enabled:
        dist.barrier()
        dist.destroy_process_group()


def barrier(ctx: DistContext) -> None:
    """Wait for every rank (no-op in a single process)."""
    if ctx.enabled:
        dist.barrier()


def mean_over_ranks(value: float, ctx: DistContext) -> float:
    """The mean of ``value`` over all ranks (``value`` itself in a single process)."""
    if not ctx.enabled:
        return value
    t = torch.tensor([value], dtype=torch.float64, device=_collective_device(ctx))
    dist.all_reduce(t, op=dist.ReduceOp.SUM)
    return float(t.item()) / ctx.world_size


def _collective_device(ctx: DistContext) -> torch.device:
    return ctx.device if dist.get_backend() == "nccl" else torch.device("cpu")


def to_float(x: torch.Tensor) -> float:
    """A scalar tensor (a DTensor is gathered first, e.g. FSDP's grad norm) as a float."""
    full = getattr(x, "full_tensor", None)
    return float((full() if full is not None else x).item())


def local_tensor(x: torch.Tensor) -> torch.Tensor:
    """The rank's own shard of a DTensor, or the tensor itself."""
    return x.to_local() if hasattr(x, "to_local") else x


def shard_denoiser(denoiser: nn.Module, ctx: DistContext, bf16: bool) -> None:
    """FSDP2 in place: each transformer block, then the transformer; the prompt encoder alone.

    ``bf16``: all-gather parameters in bf16 and reduce gradients in fp32 (CUDA); otherwise the
    parameters stay in their dtype. Call after the trainable parameters are chosen (LoRA
    injected) and before the optimizer is built: FSDP2 replaces parameters by DTensors.
    """
    from torch.distributed.device_mesh import init_device_mesh
    from torch.distributed.fsdp import MixedPrecisionPolicy, fully_shard

    mesh = init_device_mesh(ctx.device.type, (ctx.world_size,))
    policy = (
        MixedPrecisionPolicy(param_dtype=torch.bfloat16, reduce_dtype=torch.float32)
        if bf16
        else MixedPrecisionPolicy()
    )
    transformer = denoiser.transformer
    for block in transformer.blocks:
        fully_shard(block, mesh=mesh, mp_policy=policy)
    fully_shard(transformer, mesh=mesh, mp_policy=policy)
    text = denoiser.text_encoder
    if any(True for _ in text.parameters()):
        # Called outside the transformer's forward (encode_text), so it is a root of its own.
        fully_shard(text, mesh=mesh, mp_policy=MixedPrecisionPolicy())


def fsdp_modules(denoiser: nn.Module) -> list[nn.Module]:
    """The FSDP roots of a sharded denoiser (empty when it is not sharded)."""
    from torch.distributed.fsdp import FSDPModule

    roots = [denoiser.transformer, denoiser.text_encoder]
    return [m for m in roots if isinstance(m, FSDPModule)]


def set_gradient_sync(denoiser: nn.Module, enabled: bool) -> None:
    """Turn FSDP's gradient reduce-scatter on (last micro-batch) or off (accumulating)."""
    for module in fsdp_modules(denoiser):
        module.set_requires_gradient_sync(enabled)


def rank_positions(start: int, batch_size: int, ctx: DistContext) -> range:
    """Global sample positions of this rank's part of the micro-batch that begins at ``start``.

    The micro-batch covers ``[start, start + world_size * batch_size)``; rank r takes the r-th
    contiguous slice of ``batch_size`` positions.
    """
    first = start + ctx.rank * batch_size
    return range(first, first + batch_size)


def epoch_order(n: int, seed: int, epoch: int) -> list[int]:
    """The run's fixed permutation of ``n`` samples for ``epoch`` (the same on every rank)."""
    g = torch.Generator().manual_seed(seed * 1_000_003 + epoch)
    return torch.randperm(n, generator=g).tolist()


def positions_to_indices(positions: range, n: int, seed: int) -> Iterator[int]:
    """Dataset indices of global sample positions (epoch e visits ``epoch_order(n, seed, e)``)."""
    cached: tuple[int, list[int]] | None = None
    for k in positions:
        epoch, pos = divmod(k, n)
        if cached is None or cached[0] != epoch:
            cached = (epoch, epoch_order(n, seed, epoch))
        yield cached[1][pos]


# --- checkpoints through torch.distributed.checkpoint (safetensors storage) -------------------


def save_tensors(
    folder: Path, groups: dict[str, dict[str, torch.Tensor]], ctx: DistContext
) -> None:
    """Write each group of tensors (plain or FSDP-sharded) as ``folder/<group>.safetensors``.

    Keys are ``<group>.<name>``. Every rank calls this with its own shards; rank 0 merges the
    shards into full tensors. Collective: every rank must call it with the same keys.
    """
    from torch.distributed.checkpoint import HuggingFaceStorageWriter, save

    names = [g for g, tensors in groups.items() if tensors]
    flat: dict[str, torch.Tensor] = {}
    files: dict[str, int] = {}
    for index, group in enumerate(names, start=1):
        for name, tensor in groups[group].items():
            flat[f"{group}.{name}"] = tensor.detach()
            files[f"{group}.{name}"] = index
    writer = HuggingFaceStorageWriter(
        str(folder),
        fqn_to_index_mapping=files,
        save_distributed=ctx.enabled,
        enable_consolidation=ctx.enabled,
    )
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=_SINGLE_PROCESS_WARNING)
        save(flat, storage_writer=writer, no_dist=not ctx.enabled)
    barrier(ctx)
    if ctx.is_main:
        shutil.rmtree(folder / SHARDED_DIR, ignore_errors=True)
        for index, group in enumerate(names, start=1):
            (merged,) = folder.glob(f"*-{index:05d}-of-{len(names):05d}.safetensors")
            merged.rename(folder / f"{group}.safetensors")
        for index_file in folder.glob("*.index.json"):
            index_file.unlink()  # names the files before renaming; the reader does not use it
    barrier(ctx)


def load_tensors(
    folder: Path, targets: dict[str, dict[str, torch.Tensor]], ctx: DistContext
) -> None:
    """Fill ``targets`` (group -> name -> tensor, plain or sharded) in place from ``folder``.

    Each rank reads only the slices its shards cover, whatever the number of ranks that wrote
    the checkpoint. Raises :class:`CheckpointMismatchError` naming a tensor the checkpoint lacks.
    """
    from torch.distributed.checkpoint import HuggingFaceStorageReader, load

    from egosim.model.weights import read_safetensors_header

    flat = {
        f"{group}.{name}": tensor.detach()
        for group, tensors in targets.items()
        for name, tensor in tensors.items()
    }
    stored: dict[str, list[int]] = {}
    for path in sorted(folder.glob("*.safetensors")):
        try:  # headers only; also refuses a truncated file before DCP reads it
            header = read_safetensors_header(path)
        except WeightsMismatchError as exc:
            raise CheckpointMismatchError(str(exc)) from exc
        stored.update({key: list(shape) for key, (shape, _) in header.items()})
    for key, tensor in flat.items():
        if key not in stored:
            raise CheckpointMismatchError(f"{folder}: checkpoint has no tensor {key!r}")
        if stored[key] != list(tensor.shape):
            raise CheckpointMismatchError(
                f"{folder}: tensor {key!r} is {stored[key]}, the model expects {list(tensor.shape)}"
            )
    given = dict(flat)
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=_SINGLE_PROCESS_WARNING)
        load(flat, storage_reader=HuggingFaceStorageReader(str(folder)), no_dist=not ctx.enabled)
    with torch.no_grad():
        for key, tensor in given.items():
            if flat[key] is not tensor:  # the loader may hand back a new tensor: copy it in
                tensor.copy_(flat[key])
