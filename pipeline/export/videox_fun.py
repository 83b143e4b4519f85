"""``egosim export videox-fun``: packed samples as a VideoX-Fun training folder.

VideoX-Fun's datasets (``videox_fun/data/dataset_image_video.py``: ``ImageVideoDataset``,
``ImageVideoControlDataset``) read a JSON list (``json.load``), one dict per sample, with
``file_path`` (the target video), ``text`` (the prompt), ``type`` (``"video"``) and, for control
training, ``control_file_path`` (the control video); relative paths are joined to the loader's
``data_root``. This export writes, under ``OUT``:

- ``metadata.json``: the list, paths relative to ``OUT`` (pass ``OUT`` as ``data_root``);
- ``videos/<clip_id>.mp4``: the target (real) video -> ``file_path``;
- ``control/<clip_id>.mp4``: the scene render (EgoSim's ego prior) -> ``control_file_path``;
- ``masks/<clip_id>.mp4``: the inpainting mask, **white = unobserved, to synthesise** (VideoX-Fun's
  ``mask_condition`` polarity; :func:`~egosim.pipeline.export.pack_rows.inpaint_mask_from_visible`
  of the pack's ``visible``) -> ``mask_file_path``;
- ``skeletons/<clip_id>.mp4``: the hand skeleton video -> ``skeleton_file_path``;
- ``first_frames/<clip_id>.png``: the hand-free first frame -> ``first_frame_file_path``;
- ``hand_masks/<clip_id>.mp4`` (white = hand or arm) -> ``hand_mask_file_path``, when packed.

The keys after ``control_file_path`` are egosim's (VideoX-Fun's loaders ignore unknown keys);
each entry also records ``clip_id``, ``num_frames``, ``height``, ``width`` and ``fps``. Videos
keep the pack's size, frame count and rate (H.264, CRF ``crf``; masks black/white).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from egosim.pipeline.export.files import (
    ExportResult,
    PackSample,
    iter_pack_samples,
    mask_as_rgb,
    prepare_out,
    safe_path,
    write_atomic,
    write_png,
    write_video,
)
from egosim.pipeline.export.pack_rows import inpaint_mask_from_visible
from egosim.pipeline.media import DEFAULT_CRF
from egosim.pipeline.stage import ConfigError

INDEX_NAME = "metadata.json"


@dataclass(frozen=True)
class VideoXFunConfig:
    """Options of the VideoX-Fun export."""

    crf: int = DEFAULT_CRF  # H.264 constant rate factor of every video (0-51, lower = better)
    absolute_paths: bool = False  # write absolute paths (for a loader run with data_root None)
    overwrite: bool = False  # write into an OUT that already holds a metadata.json

    def __post_init__(self) -> None:
        if not 0 <= self.crf <= 51:
            raise ConfigError(f"videox-fun: crf must be in 0..51, got {self.crf}")


def _entry(out: Path, sample: PackSample, config: VideoXFunConfig) -> dict[str, object]:
    """Write one sample's files; returns its metadata entry."""
    cid, fps, crf = sample.clip_id, sample.fps, config.crf

    def rel(path: Path) -> str:
        return str(path.resolve()) if config.absolute_paths else path.relative_to(out).as_posix()

    target = write_video(safe_path(out, "videos", f"{cid}.mp4"), sample.target, fps, crf)
    control = write_video(safe_path(out, "control", f"{cid}.mp4"), sample.scene, fps, crf)
    mask = inpaint_mask_from_visible(sample.visible)  # (T, H, W) 1 = synthesise
    masks = write_video(safe_path(out, "masks", f"{cid}.mp4"), mask_as_rgb(mask), fps, crf)
    skeleton = write_video(safe_path(out, "skeletons", f"{cid}.mp4"), sample.skeleton, fps, crf)
    first = write_png(safe_path(out, "first_frames", f"{cid}.png"), sample.first_frame)
    t, h, w = sample.target.shape[:3]
    entry: dict[str, object] = {
        "file_path": rel(target),
        "control_file_path": rel(control),
        "text": sample.prompt,
        "type": "video",
        "mask_file_path": rel(masks),
        "skeleton_file_path": rel(skeleton),
        "first_frame_file_path": rel(first),
        "clip_id": cid,
        "num_frames": t,
        "height": h,
        "width": w,
        "fps": fps,
    }
    if sample.hand_mask is not None:
        hand = safe_path(out, "hand_masks", f"{cid}.mp4")
        entry["hand_mask_file_path"] = rel(
            write_video(hand, mask_as_rgb(sample.hand_mask), fps, crf)
        )
    return entry


def export_videox_fun(run: Path, out: Path, config: VideoXFunConfig | None = None) -> ExportResult:
    """Export the pack shards of ``run`` as a VideoX-Fun folder at ``out`` (see module doc).

    ``run`` is a run folder, a folder of pack shards or one shard. ``metadata.json`` is written
    last. Rows that do not decode are skipped and listed in the result.
    """
    config = config or VideoXFunConfig()
    out = prepare_out(out, INDEX_NAME, config.overwrite)
    result = ExportResult(out=out, index=out / INDEX_NAME)
    entries = []
    for item in iter_pack_samples(run):
        if isinstance(item, tuple):
            result.skipped[item[0]] = item[1]
            continue
        entries.append(_entry(out, item, config))
        result.written.append(item.clip_id)
    text = json.dumps(entries, indent=2, ensure_ascii=False) + "\n"
    write_atomic(result.index, text.encode("utf-8"))
    return result
