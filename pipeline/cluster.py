"""Dask clusters for the runner: the local cluster, GPU workers from dask-cuda, SLURM jobs.

- :func:`local_cluster` is what ``egosim run`` starts when no ``--scheduler`` is given. With
  CUDA devices and `dask-cuda <https://docs.rapids.ai/api/dask-cuda/>`_ installed (the ``cuda``
  extra), the GPU workers come from ``dask_cuda.LocalCUDACluster``: one worker per GPU, each
  pinned to its device (``CUDA_VISIBLE_DEVICES`` rotated by dask-cuda) and declaring the
  resource ``GPU: 1``; CPU workers (no device, no ``GPU`` resource) are added to the same
  cluster for the CPU stages. Without dask-cuda (or without GPUs) the cluster is the hand-built
  ``SpecCluster`` of Nanny workers, its first ``gpu_workers`` declaring ``GPU: 1``.
  :func:`plan_local_cluster` makes that choice and is what tests check.
- :func:`slurm_cluster` builds a ``dask_jobqueue.SLURMCluster`` from a :class:`SlurmConfig`:
  each SLURM job runs one worker process; with ``gpus=1`` the job books one GPU
  (``--gres=gpu:1``) and its worker declares ``GPU: 1``, so GPU steps land only there.
  :func:`slurm_job_script` returns the ``sbatch`` script a job would run without submitting it
  (``egosim cluster slurm --print-job-script``).

``egosim run --scheduler tcp://HOST:PORT`` is unchanged: any dask.distributed cluster whose GPU
workers declare ``GPU`` works, including one started by ``egosim cluster slurm``.
"""

from __future__ import annotations

import dataclasses
import importlib.util
import logging
import os
import re
from dataclasses import dataclass, field
from typing import Any, Literal

from egosim.pipeline.stage import StageError

GPU_RESOURCE = "GPU"  # worker resource that GPU steps ask for (workflow `resources: {GPU: 1}`)
MAX_LOCAL_WORKERS = 8  # default local cluster size: min(cores, this)


class ClusterError(StageError):
    """A cluster could not be planned or built from the options given; says which and why."""


@dataclass(frozen=True)
class LocalClusterPlan:
    """What :func:`local_cluster` will start."""

    kind: Literal["dask-cuda", "spec"]  # dask-cuda GPU workers, or the hand-built SpecCluster
    gpu_workers: int  # workers declaring GPU: 1 (one per device)
    cpu_workers: int  # workers without a GPU resource


def dask_cuda_available() -> bool:
    """True when the optional ``dask_cuda`` package can be imported."""
    return importlib.util.find_spec("dask_cuda") is not None


def visible_gpus() -> int:
    """Number of CUDA devices torch sees (0 on a CPU-only build or machine)."""
    import torch

    return int(torch.cuda.device_count())


def default_workers() -> int:
    """Default local cluster size: one worker per core, at most :data:`MAX_LOCAL_WORKERS`."""
    return max(1, min(os.cpu_count() or 1, MAX_LOCAL_WORKERS))


def plan_local_cluster(
    n_workers: int | None,
    gpu_workers: int | None,
    gpus: int,
    have_dask_cuda: bool,
) -> LocalClusterPlan:
    """Choose the local cluster: dask-cuda when it is installed and a GPU worker is wanted.

    ``n_workers`` is the cluster size (default :func:`default_workers`, raised to the GPU count
    if that is larger), ``gpu_workers`` how many of them hold a GPU (default ``gpus``, the
    devices visible). Raises :class:`ClusterError` for negative counts or more GPU workers than
    workers.
    """
    want_gpus = gpus if gpu_workers is None else gpu_workers
    if want_gpus < 0 or (n_workers is not None and n_workers < 1):
        raise ClusterError(
            f"workers must be >= 1 and GPU workers >= 0, got {n_workers} and {gpu_workers}"
        )
    total = max(default_workers(), want_gpus) if n_workers is None else n_workers
    if want_gpus > total:
        raise ClusterError(f"{want_gpus} GPU workers asked for a cluster of {total} workers")
    kind: Literal["dask-cuda", "spec"] = "dask-cuda" if want_gpus and have_dask_cuda else "spec"
    if kind == "dask-cuda" and want_gpus > gpus:
        raise ClusterError(f"{want_gpus} GPU workers asked for, but {gpus} CUDA device(s) visible")
    return LocalClusterPlan(kind=kind, gpu_workers=want_gpus, cpu_workers=total - want_gpus)


def _cpu_worker_spec(nanny: type, hide_gpus: bool) -> dict[str, Any]:
    """Spec of one CPU worker: one thread, quiet logs; ``hide_gpus`` leaves it no CUDA device."""
    options: dict[str, Any] = {"nthreads": 1, "silence_logs": logging.WARNING}
    if hide_gpus:
        options["env"] = {"CUDA_VISIBLE_DEVICES": ""}
    return {"cls": nanny, "options": options}


def local_cluster(
    n_workers: int | None = None,
    gpu_workers: int | None = None,
    dashboard_address: str | None = None,
) -> Any:
    """Start the local cluster that :func:`plan_local_cluster` chooses; see the module doc.

    ``dashboard_address`` is the scheduler's dashboard (``":8787"``; None: no dashboard).
    """
    from distributed import Nanny, Scheduler, SpecCluster

    plan = plan_local_cluster(n_workers, gpu_workers, visible_gpus(), dask_cuda_available())
    if plan.kind == "dask-cuda":
        from dask_cuda import LocalCUDACluster

        cluster = LocalCUDACluster(
            n_workers=plan.gpu_workers,
            CUDA_VISIBLE_DEVICES=list(range(plan.gpu_workers)),
            threads_per_worker=1,
            resources={GPU_RESOURCE: 1},
            dashboard_address=dashboard_address,
            silence_logs=logging.WARNING,
        )
        # SpecCluster's documented way to grow a cluster with other workers: add their specs,
        # then scale to the new size (the cluster starts what its spec lacks).
        for i in range(plan.cpu_workers):
            cluster.worker_spec[f"cpu-{i}"] = _cpu_worker_spec(Nanny, hide_gpus=True)
        cluster.scale(len(cluster.worker_spec))
        return cluster
    workers: dict[str, dict[str, Any]] = {}
    for i in range(plan.gpu_workers + plan.cpu_workers):
        if i < plan.gpu_workers:
            options: dict[str, Any] = {
                "nthreads": 1,
                "silence_logs": logging.WARNING,
                "resources": {GPU_RESOURCE: 1},
                "env": {"CUDA_VISIBLE_DEVICES": str(i)},
            }
            workers[f"gpu-{i}"] = {"cls": Nanny, "options": options}
        else:
            workers[f"cpu-{i}"] = _cpu_worker_spec(Nanny, hide_gpus=plan.gpu_workers > 0)
    scheduler = {"cls": Scheduler, "options": {"dashboard_address": dashboard_address}}
    return SpecCluster(
        workers=workers, scheduler=scheduler, silence_logs=logging.WARNING, asynchronous=False
    )


_MEMORY = re.compile(r"^\d+(\.\d+)?\s*([KMGT]i?B|[KMGT])$", re.IGNORECASE)
_WALLTIME = re.compile(r"^(\d+-)?\d{1,2}(:\d{2}){1,2}$")


@dataclass(frozen=True)
class SlurmConfig:
    """One SLURM worker job of ``egosim cluster slurm`` (each job runs one Dask worker)."""

    cores: int = 4  # CPU cores per job (the worker gets this many threads)
    memory: str = "16GB"  # memory per job, Dask's notation: "16GB", "64GiB"
    gpus: int = 0  # GPUs per job: 0 (CPU worker) or 1 (worker declares GPU: 1)
    walltime: str = "04:00:00"  # job time limit: HH:MM:SS or D-HH:MM:SS
    jobs: int = 1  # jobs (workers) to request when the cluster starts
    partition: str = ""  # SLURM partition (--partition), "" = the site's default
    account: str = ""  # SLURM account (--account), "" = none
    job_name: str = "egosim-worker"  # SLURM job name (-J)
    local_directory: str = ""  # worker scratch folder on the node ("" = Dask's default)
    log_directory: str = ""  # folder of the jobs' stdout/stderr files ("" = submit folder)
    python: str = ""  # Python that runs the worker ("" = the one running egosim)
    job_extra: tuple[str, ...] = ()  # extra "#SBATCH" directives, e.g. "--constraint=a100"
    prologue: tuple[str, ...] = ()  # shell lines run before the worker (module load, venv)
    dashboard_address: str = ":8787"  # scheduler dashboard ("" = any free port)
    extra: dict[str, Any] = field(default_factory=dict)  # more SLURMCluster keyword arguments

    def __post_init__(self) -> None:
        problems = []
        if self.cores < 1:
            problems.append(f"cores must be >= 1, got {self.cores}")
        if not _MEMORY.match(self.memory.strip()):
            problems.append(f"memory must look like 16GB or 64GiB, got {self.memory!r}")
        if self.gpus not in (0, 1):
            problems.append(
                f"gpus is GPUs per job and must be 0 or 1 (one worker per GPU: ask for more "
                f"jobs instead), got {self.gpus}"
            )
        if not _WALLTIME.match(self.walltime):
            problems.append(f"walltime must be HH:MM:SS or D-HH:MM:SS, got {self.walltime!r}")
        if self.jobs < 0:
            problems.append(f"jobs must be >= 0, got {self.jobs}")
        if problems:
            raise ClusterError("SLURM cluster: " + "; ".join(problems))

    def cluster_kwargs(self) -> dict[str, Any]:
        """Keyword arguments of ``dask_jobqueue.SLURMCluster`` for this config."""
        directives = [*self.job_extra]
        worker_args: list[str] = []
        if self.gpus:
            directives.append(f"--gres=gpu:{self.gpus}")
            worker_args += ["--resources", f"{GPU_RESOURCE}={self.gpus}"]
        kwargs: dict[str, Any] = {
            "cores": self.cores,
            "processes": 1,
            "memory": self.memory,
            "walltime": self.walltime,
            "job_name": self.job_name,
            "job_extra_directives": directives,
            "worker_extra_args": worker_args,
            "job_script_prologue": list(self.prologue),
            "scheduler_options": {"dashboard_address": self.dashboard_address or ":0"},
        }
        optional = {
            "queue": self.partition,
            "account": self.account,
            "local_directory": self.local_directory,
            "log_directory": self.log_directory,
            "python": self.python,
        }
        kwargs.update({k: v for k, v in optional.items() if v})
        return {**kwargs, **self.extra}


def slurm_cluster(config: SlurmConfig) -> Any:
    """A ``dask_jobqueue.SLURMCluster`` for ``config`` (scheduler started, no job submitted)."""
    from dask_jobqueue import SLURMCluster

    return SLURMCluster(**config.cluster_kwargs())


def slurm_job_script(config: SlurmConfig) -> str:
    """The ``sbatch`` script of one worker job, generated by dask-jobqueue; nothing is submitted.

    A scheduler is started (its dashboard on any free port, and closed again) so that the
    script names a real address.
    """
    cluster = slurm_cluster(dataclasses.replace(config, dashboard_address=""))
    try:
        return str(cluster.job_script())
    finally:
        cluster.close()
