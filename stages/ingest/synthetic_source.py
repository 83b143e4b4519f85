"""Ingest backend for the built-in synthetic world (no input files needed)."""

from __future__ import annotations

from dataclasses import replace
from typing import Protocol

import numpy as np

from egosim.pipeline.records import Clip
from egosim.pipeline.stage import ClipRejected
from egosim.stages.world.clip import render_clip
from egosim.stages.world.config import VARIANTS, WorldConfig


class SyntheticFormat(Protocol):
    """Ingest parameters the synthetic source reads (an ``IngestConfig`` satisfies it)."""

    preset: str
    fps: float
    num_frames: int
    height: int
    width: int
    synthetic_count: int
    synthetic_mode: str
    synthetic_articulated_every: int
    synthetic_variant: str
    seed: int


def list_units(cfg: SyntheticFormat) -> list[str]:
    """One unit per generated clip: ``synthetic:<mode>:<seed>[:articulated][:<variant>]``.

    The variant is named only when it is not the default one, so default units are unchanged.
    """
    units = []
    for i in range(cfg.synthetic_count):
        every = cfg.synthetic_articulated_every
        articulated = every > 0 and i % every == every - 1
        suffix = ":articulated" if articulated else ""
        if cfg.synthetic_variant != "default":
            suffix += f":{cfg.synthetic_variant}"
        units.append(f"synthetic:{cfg.synthetic_mode}:{cfg.seed + i}{suffix}")
    return units


def render_unit(spec: str, cfg: SyntheticFormat) -> Clip:
    """Render the clip a unit spec (``<mode>:<seed>[:articulated][:<variant>]``) names.

    The world renders exactly ``num_frames`` frames at ``fps``, so the clip is one full window
    of its own source (``source_frame_indices`` 0..T-1).
    """
    parts = spec.split(":")
    try:
        mode, seed = parts[0], int(parts[1])
    except (IndexError, ValueError) as exc:
        raise ClipRejected(f"bad synthetic unit {spec!r}") from exc
    variants = [p for p in parts[2:] if p in VARIANTS]
    world = WorldConfig(
        seed=seed,
        mode=mode,
        height=cfg.height,
        width=cfg.width,
        num_frames=cfg.num_frames,
        fps=cfg.fps,
        articulated="articulated" in parts[2:],
        variant=variants[-1] if variants else "default",
    )
    kind = "art" if world.articulated else mode
    tag = "" if world.variant == "default" else f"{world.variant}-"
    clip = render_clip(world, clip_id=f"synth-{tag}{kind}-{seed:05d}")
    return replace(
        clip,
        source_fps=float(cfg.fps),
        source_num_frames=clip.num_frames,
        source_frame_indices=np.arange(clip.num_frames),
        clip_policy=f"full:{cfg.preset}" if cfg.preset else "full",
    ).check()
