"""``egosim export dwm``: packed samples in DWM's processed-data layout, resampled as DWM expects.

DWM (snuvclab/dwm, ``training/cogvideox/static_hand_utils.py``) resolves a sample from a
relative video path ``<group>/videos/<stem>.mp4`` listed one per line in a dataset file: the
static-scene video ``<group>/videos_static/<stem>.mp4``, the hand video
``<group>/videos_hands/<stem>.mp4`` and the prompt ``<group>/prompts_rewrite/<stem>.txt`` (its
dataset's default ``prompt_subdir``; ``prompts/`` holds the caption before rewriting). Its clips
are 49 frames at 8 fps, 720x480 (``data_processing/custom``: ffmpeg ``fps=8``, scale with pad or
crop, then the last frame cloned up to 49 frames); its loader takes every frame of a 49-frame
file. This export writes, under ``OUT``:

- ``<group>/videos/<clip_id>.mp4``: the target (real) video;
- ``<group>/videos_static/<clip_id>.mp4``: the scene render (for a static camera it repeats the
  inpainted first frame: DWM's fixed-camera recipe);
- ``<group>/videos_hands/<clip_id>.mp4``: the hand skeleton video (DWM renders HaMeR hand meshes;
  egosim's hand condition is the skeleton);
- ``<group>/prompts/<clip_id>.txt`` and ``<group>/prompts_rewrite/<clip_id>.txt``: the prompt
  (the same text: egosim does not rewrite captions);
- ``<group>/metadata/<clip_id>.json``: what the resampling did (source frame per output frame,
  frames padded, resize mode and box);
- ``dataset_files/<group>.txt``: one ``<group>/videos/<clip_id>.mp4`` line per clip (the index;
  pass ``OUT`` as DWM's ``data_root``).

**Time**: output frame ``k`` (time ``k / fps``) shows the source frame on screen at that time,
``floor(k * fps_src / fps)`` (sample and hold; 16 -> 8 fps keeps every second frame, a slower
source repeats frames). Frames exist while ``k / fps`` is inside the source's duration
(``T / fps_src``); a shorter clip is padded by repeating its last frame (``short: pad``, DWM's
``tpad=stop_mode=clone``) or skipped (``short: reject``). **Space**: the frames are scaled
to fit ``width x height`` and padded with black (``pad``) or scaled to cover and centre-cropped
(``crop``). DWM's ``auto`` compares the two losses, which are equal for every aspect ratio (both
are ``1 - min(a, A) / max(a, A)`` for aspect ratios ``a``, ``A``), and keeps ``pad`` on a tie:
``pad`` is the default here.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Literal

import cv2
import numpy as np

from egosim.pipeline.export.files import (
    ExportResult,
    PackSample,
    iter_pack_samples,
    prepare_out,
    safe_path,
    write_atomic,
    write_text,
    write_video,
)
from egosim.pipeline.media import DEFAULT_CRF
from egosim.pipeline.stage import ConfigError
from egosim.schemas.ids import id_problems


@dataclass(frozen=True)
class DwmConfig:
    """Options of the DWM export (defaults: DWM's clip format)."""

    fps: float = 8.0  # output frame rate (DWM: 8)
    num_frames: int = 49  # output frames per clip (DWM: 49)
    height: int = 480  # output frame height in pixels (DWM: 480)
    width: int = 720  # output frame width in pixels (DWM: 720)
    resize: Literal["pad", "crop"] = "pad"  # fit inside and pad black, or cover and centre-crop
    short: Literal["pad", "reject"] = "pad"  # a clip shorter than num_frames at fps
    group: str = "egosim"  # DWM sample-group folder (and dataset file name)
    crf: int = DEFAULT_CRF  # H.264 constant rate factor of every video (0-51, lower = better)
    overwrite: bool = False  # write into an OUT that already holds this group's dataset file

    def __post_init__(self) -> None:
        problems = []
        if not (np.isfinite(self.fps) and self.fps > 0):
            problems.append(f"fps must be > 0, got {self.fps}")
        if self.num_frames < 1:
            problems.append(f"num_frames must be >= 1, got {self.num_frames}")
        if self.height < 2 or self.width < 2:
            problems.append(f"height and width must be >= 2, got {self.height}x{self.width}")
        if self.resize not in ("pad", "crop"):
            problems.append(f"resize must be 'pad' or 'crop', got {self.resize!r}")
        if self.short not in ("pad", "reject"):
            problems.append(f"short must be 'pad' or 'reject', got {self.short!r}")
        problems += [f"group: {p}" for p in id_problems(self.group, "group name")]
        if not 0 <= self.crf <= 51:
            problems.append(f"crf must be in 0..51, got {self.crf}")
        if problems:
            raise ConfigError("dwm: " + "; ".join(problems))


@dataclass(frozen=True)
class Resampling:
    """How one clip was brought to DWM's format (written to ``metadata/<clip_id>.json``)."""

    source_fps: float  # frame rate of the packed sample
    source_frames: int  # frames of the packed sample
    source_indices: list[int]  # (num_frames,) source frame shown in each output frame
    padded_frames: int  # output frames that repeat the last one (the clip was shorter)
    resize: str  # "pad" or "crop"
    scale: float  # source pixels -> output pixels
    box: list[int]  # x0, y0, width, height of the scaled frame in the output (pad) or of the
    # output window in the scaled frame (crop)


def frame_indices(num_source: int, source_fps: float, fps: float) -> list[int]:
    """Source frame shown at each output time ``k / fps`` inside the source's duration."""
    count = int(np.floor(num_source * fps / source_fps + 1e-9))
    k = np.arange(count)
    return np.minimum(np.floor(k * source_fps / fps + 1e-9), num_source - 1).astype(int).tolist()


def _resize_plan(h: int, w: int, config: DwmConfig) -> tuple[float, int, int, list[int]]:
    """``(scale, scaled_h, scaled_w, box)`` of fitting (pad) or covering (crop) the output."""
    sy, sx = config.height / h, config.width / w
    if config.resize == "pad":
        scale = min(sx, sy)
        sh = min(config.height, max(1, round(h * scale)))
        sw = min(config.width, max(1, round(w * scale)))
        box = [(config.width - sw) // 2, (config.height - sh) // 2, sw, sh]
    else:
        scale = max(sx, sy)
        sh, sw = max(config.height, round(h * scale)), max(config.width, round(w * scale))
        box = [(sw - config.width) // 2, (sh - config.height) // 2, config.width, config.height]
    return scale, sh, sw, box


def _resize(
    frames: np.ndarray, plan: tuple[float, int, int, list[int]], config: DwmConfig
) -> np.ndarray:
    """``(T, h, w, 3)`` -> ``(T, height, width, 3)`` by the plan (black bars for pad)."""
    scale, sh, sw, (x0, y0, bw, bh) = plan
    interp = cv2.INTER_AREA if scale < 1 else cv2.INTER_LINEAR
    out = np.zeros((len(frames), config.height, config.width, 3), dtype=np.uint8)
    for i, frame in enumerate(frames):
        scaled = cv2.resize(frame, (sw, sh), interpolation=interp)  # (sh, sw, 3)
        if config.resize == "pad":
            out[i, y0 : y0 + bh, x0 : x0 + bw] = scaled
        else:
            out[i] = scaled[y0 : y0 + bh, x0 : x0 + bw]
    return out


def resample(sample: PackSample, config: DwmConfig) -> tuple[dict[str, np.ndarray], Resampling]:
    """The sample's target, scene and skeleton videos in DWM's rate, length and size.

    Raises ``ValueError`` naming the clip when it is too short and ``short`` is ``reject``.
    """
    t, h, w = sample.target.shape[:3]
    indices = frame_indices(t, sample.fps, config.fps)[: config.num_frames]
    padded = config.num_frames - len(indices)
    if padded and config.short == "reject":
        raise ValueError(
            f"clip {sample.clip_id!r}: {t} frames at {sample.fps:g} fps give {len(indices)} "
            f"frames at {config.fps:g} fps, fewer than num_frames {config.num_frames}"
        )
    indices += [indices[-1]] * padded
    plan = _resize_plan(h, w, config)
    videos = {
        name: _resize(video[indices], plan, config)
        for name, video in (
            ("videos", sample.target),
            ("videos_static", sample.scene),
            ("videos_hands", sample.skeleton),
        )
    }
    info = Resampling(
        source_fps=sample.fps,
        source_frames=t,
        source_indices=[int(i) for i in indices],
        padded_frames=padded,
        resize=config.resize,
        scale=float(plan[0]),
        box=[int(v) for v in plan[3]],
    )
    return videos, info


def export_dwm(run: Path, out: Path, config: DwmConfig | None = None) -> ExportResult:
    """Export the pack shards of ``run`` in DWM's layout at ``out`` (see module doc).

    The dataset file ``dataset_files/<group>.txt`` is written last; rows that do not decode,
    and (with ``short: reject``) clips too short, are skipped and listed in the result.
    """
    config = config or DwmConfig()
    index_name = f"dataset_files/{config.group}.txt"
    out = prepare_out(out, index_name, config.overwrite)
    result = ExportResult(out=out, index=safe_path(out, "dataset_files", f"{config.group}.txt"))
    lines = []
    for item in iter_pack_samples(run):
        if isinstance(item, tuple):
            result.skipped[item[0]] = item[1]
            continue
        cid, group = item.clip_id, config.group
        try:
            videos, info = resample(item, config)
        except ValueError as exc:
            result.skipped[cid] = str(exc)
            continue
        for folder, frames in videos.items():
            write_video(safe_path(out, group, folder, f"{cid}.mp4"), frames, config.fps, config.crf)
        for folder in ("prompts", "prompts_rewrite"):
            write_text(safe_path(out, group, folder, f"{cid}.txt"), item.prompt)
        meta = json.dumps({"clip_id": cid, **asdict(info)}, indent=2) + "\n"
        write_atomic(safe_path(out, group, "metadata", f"{cid}.json"), meta.encode("utf-8"))
        lines.append(f"{group}/videos/{cid}.mp4")
        result.written.append(cid)
    write_atomic(result.index, "".join(f"{line}\n" for line in lines).encode("utf-8"))
    return result
