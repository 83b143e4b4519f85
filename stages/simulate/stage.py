"""The ``simulate`` stage: generate each packed clip with a trained observation model.

A pack row is a state (scene render + visibility from the point cloud, the hand-free first
frame, a prompt) and an action (the hand-skeleton video); the model generates the egocentric
clip. Any other state and action works through :func:`generate` with a
:class:`~egosim.model.Conditions`. ``egosim simulate`` runs this stage on pack shards and also
writes each generated clip as an MP4.

The model is loaded once per stage instance (lazily, on the first clip) from ``checkpoint`` (a
run directory or a ``.safetensors`` checkpoint; a pickle is refused, never loaded); a ``preset``
that differs from the checkpoint's is an error.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np

from egosim.pipeline import media
from egosim.pipeline.records import PackRecord
from egosim.pipeline.stage import ClipStage, ConfigError, StageConfig
from egosim.schemas import ShardSchema
from egosim.schemas.pack import PACK, SIMULATION
from egosim.stages.common.packed import sample_from_pack_row

if TYPE_CHECKING:  # the model (torch + diffusers) is imported when a clip is generated
    from egosim.model.conditioning import Conditions
    from egosim.model.inference import LoadedModel


@dataclasses.dataclass(frozen=True)
class SimulateConfig(StageConfig):
    """Parameters of ``simulate``."""

    checkpoint: str = ""  # run dir or .safetensors checkpoint; "" = untrained preset (smoke runs)
    preset: str = ""  # expected preset; "" = the checkpoint's ("tiny" without a checkpoint)
    steps: int = 50  # Euler steps of the flow sampler (EgoSim: 50)
    guidance_scale: float = 1.0  # classifier-free guidance scale (EgoSim: 1.0)
    seed: int = 0  # noise seed (the same for every clip)
    device: str = "auto"  # torch device: auto (cuda if available), cpu, cuda[:n]
    use_ema: bool = True  # load the checkpoint's EMA weights when it has them
    weights_dir: str = ""  # diffusers weights folder for Wan presets ("" = the checkpoint's)
    crf: int = 10  # H.264 quality of the generated video (lower = better, bigger)

    def __post_init__(self) -> None:
        problems = []
        if self.steps < 1:
            problems.append(f"steps must be >= 1, got {self.steps}")
        if not self.guidance_scale > 0:
            problems.append(f"guidance_scale must be > 0, got {self.guidance_scale}")
        if not 0 <= self.crf <= 51:
            problems.append(f"crf must be in [0, 51], got {self.crf}")
        if not self.device or self.device.split(":")[0] not in ("auto", "cpu", "cuda", "mps"):
            problems.append(f"device must be auto, cpu or cuda[:n], got {self.device!r}")
        if problems:
            raise ConfigError("; ".join(problems))


def generate(
    model: LoadedModel,
    conditions: Conditions,
    steps: int = 50,
    guidance_scale: float = 1.0,
    seed: int = 0,
) -> np.ndarray:
    """Generate one clip ``(T, H, W, 3)`` uint8 from any state and action (``conditions``)."""
    from egosim.model.sampler import sample

    return sample(model.bundle, conditions, steps=steps, guidance_scale=guidance_scale, seed=seed)


class SimulateStage(ClipStage):
    """Generate each packed clip with a trained model: a video per clip."""

    name = "simulate"
    description = "generate a clip from a state and an action sequence (packed conditions)"
    version = 2  # 2: no wall-clock seconds in the shard (byte-reproducible; see the manifest)
    config_class = SimulateConfig
    inputs: ClassVar[Mapping[str, ShardSchema]] = {"pack": PACK}
    output = SIMULATION
    backends = ("flow_euler",)
    gpu = True
    config: SimulateConfig

    def __init__(self, config: StageConfig | None = None) -> None:
        super().__init__(config)
        self._model: LoadedModel | None = None

    @property
    def model(self) -> LoadedModel:
        """The loaded model (built on first use)."""
        if self._model is None:
            from egosim.model.inference import load_trained

            cfg = self.config
            self._model = load_trained(
                cfg.checkpoint or None,
                preset=cfg.preset or None,
                device=cfg.device,
                use_ema=cfg.use_ema,
                weights_dir=cfg.weights_dir or None,
            )
        return self._model

    def process(self, rows: Mapping[str, Mapping[str, Any]]) -> dict[str, Any]:
        """Generate one clip from its pack row."""
        cfg = self.config
        row = PackRecord.of(rows["pack"])
        conditions = sample_from_pack_row(row).conditions()
        model = self.model
        video = generate(model, conditions, cfg.steps, cfg.guidance_scale, cfg.seed)
        t, h, w = video.shape[:3]
        return {
            "clip_id": row.clip_id,
            "num_frames": t,
            "width": w,
            "height": h,
            "fps": row.fps,
            "video": media.encode_rgb_video(video, row.fps, cfg.crf),
            "preset": model.bundle.preset.name,
            "checkpoint": "" if model.checkpoint is None else str(model.checkpoint),
            "checkpoint_step": model.step,
            "sampling_steps": cfg.steps,
            "guidance_scale": cfg.guidance_scale,
            "seed": cfg.seed,
        }
