"""What a person watching a training run sees: a console progress bar, metrics files and previews.

:class:`TrainReporter` takes one record per optimizer step and sends it to

- ``run_dir/metrics.jsonl`` (one JSON line per step, always),
- a rich progress bar on stderr with loss, step time and samples/s (when ``progress``),
- TensorBoard event files in ``run_dir/tensorboard`` (``torch.utils.tensorboard``; open with
  ``tensorboard --logdir RUN/tensorboard``), previews included as images,
- Weights & Biases in offline mode (``run_dir/wandb``, sync later with ``wandb sync``) when
  ``wandb`` is importable and asked for.

Only rank 0 reports: other ranks get a reporter whose methods do nothing.
"""

from __future__ import annotations

import json
from pathlib import Path
from types import TracebackType
from typing import Any

import numpy as np

WANDB_MODES = ("auto", "offline", "off")  # auto: offline when wandb is importable


class TrainReporter:
    """Progress bar + metrics.jsonl + TensorBoard + W&B offline for one training call."""

    def __init__(
        self,
        run_dir: Path,
        total_steps: int,
        start_step: int,
        config: dict[str, Any],
        enabled: bool = True,
        progress: bool = True,
        tensorboard: bool = True,
        wandb: str = "auto",
    ) -> None:
        self.enabled = enabled
        self._log = None
        self._bar = None
        self._task = None
        self._tb = None
        self._wandb = None
        if not enabled:
            return
        self._log = (run_dir / "metrics.jsonl").open("a")
        if progress and total_steps > start_step:
            from rich.console import Console
            from rich.progress import (
                BarColumn,
                MofNCompleteColumn,
                Progress,
                TextColumn,
                TimeRemainingColumn,
            )

            self._bar = Progress(
                TextColumn("train"),
                BarColumn(),
                MofNCompleteColumn(),
                TextColumn("{task.fields[stats]}"),
                TimeRemainingColumn(),
                console=Console(stderr=True),
            )
            self._task = self._bar.add_task(
                "train", total=total_steps, completed=start_step, stats=""
            )
            self._bar.start()
        if tensorboard:
            from torch.utils.tensorboard import SummaryWriter

            self._tb = SummaryWriter(
                log_dir=str(run_dir / "tensorboard"), purge_step=start_step + 1
            )
        if wandb != "off":
            self._wandb = _start_wandb(run_dir, config, required=wandb == "offline")

    def step(self, record: dict[str, Any]) -> None:
        """Report one optimizer step (``record`` has ``step`` and numeric metrics)."""
        if not self.enabled:
            return
        self._log.write(json.dumps(record) + "\n")
        self._log.flush()
        step = int(record["step"])
        scalars = {k: v for k, v in record.items() if k != "step" and isinstance(v, int | float)}
        if self._tb is not None:
            for key, value in scalars.items():
                self._tb.add_scalar(f"train/{key}", value, step)
        if self._wandb is not None:
            self._wandb.log({f"train/{k}": v for k, v in scalars.items()}, step=step)
        if self._bar is not None:
            stats = (
                f"loss {record['loss']:.4f}  {record['step_seconds']:.2f} s/step  "
                f"{record['samples_per_second']:.2f} samples/s"
            )
            self._bar.update(self._task, completed=step, stats=stats)

    def image(self, tag: str, image: np.ndarray, step: int) -> None:
        """Log an RGB uint8 image (H, W, 3), e.g. a preview grid."""
        if self._tb is not None:
            self._tb.add_image(tag, image, step, dataformats="HWC")
        if self._wandb is not None:
            import wandb

            self._wandb.log({tag: wandb.Image(image)}, step=step)

    def close(self) -> None:
        """Stop the bar and flush every sink."""
        if self._bar is not None:
            self._bar.stop()
        if self._tb is not None:
            self._tb.close()
        if self._wandb is not None:
            self._wandb.finish()
        if self._log is not None:
            self._log.close()
        self._bar = self._tb = self._wandb = self._log = None

    def __enter__(self) -> TrainReporter:
        return self

    def __exit__(
        self,
        kind: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()


def _start_wandb(run_dir: Path, config: dict[str, Any], required: bool) -> Any:
    """An offline W&B run in ``run_dir/wandb``; None without wandb (an error when required)."""
    try:
        import wandb
    except ImportError:
        if required:
            from egosim.model.errors import ModelConfigError

            raise ModelConfigError("wandb='offline' but wandb is not installed") from None
        return None
    (run_dir / "wandb").mkdir(parents=True, exist_ok=True)
    return wandb.init(
        mode="offline", dir=str(run_dir), project="egosim", name=run_dir.name, config=config
    )
