"""``egosim export egosim-csv``: packed samples in the official EgoSim release's layout.

The official EgoSim code reads a metadata CSV (``csv.DictReader`` / ``pandas.read_csv``) with the
columns ``video, ego_prior_video, hand_keypoint_video, first_frame, prompt, video_id``; paths are
relative to its ``dataset_root``, and the mask video is found **next to the ego prior** as
``pc_mask_video.mp4`` (its data pipeline's ``generate_metadata.py`` writes one folder per clip).
This export writes, under ``OUT`` (pass ``OUT`` as ``dataset_root``):

- ``metadata.csv`` with exactly those columns, in that order, one row per clip;
- ``<clip_id>/video.mp4``: the target (real) video;
- ``<clip_id>/rendered_scene.mp4``: the scene render (``ego_prior_video``);
- ``<clip_id>/pc_mask_video.mp4``: the point-cloud mask, **white = a scene point landed**
  (the pack's ``visible``; EgoSim renders it from the point cloud in mask mode);
- ``<clip_id>/skeleton_3d.mp4``: the hand skeleton video (``hand_keypoint_video``);
- ``<clip_id>/hand_inpaint.png``: the hand-free first frame (``first_frame``);
- ``<clip_id>/caption.txt``: the prompt.

Videos keep the pack's size, frame count and rate (EgoSim's own clips are 61 frames at 16 fps,
the ``egosim`` ingest preset; pack with ``num_frames: 61`` and the clip size to match).
"""

from __future__ import annotations

import csv
import io
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
    write_text,
    write_video,
)
from egosim.pipeline.media import DEFAULT_CRF
from egosim.pipeline.stage import ConfigError

INDEX_NAME = "metadata.csv"
COLUMNS = ("video", "ego_prior_video", "hand_keypoint_video", "first_frame", "prompt", "video_id")
# File names inside a clip's folder, as EgoSim's data pipeline writes them.
FILES = {
    "video": "video.mp4",
    "ego_prior_video": "rendered_scene.mp4",
    "mask": "pc_mask_video.mp4",
    "hand_keypoint_video": "skeleton_3d.mp4",
    "first_frame": "hand_inpaint.png",
    "caption": "caption.txt",
}


@dataclass(frozen=True)
class EgoSimCsvConfig:
    """Options of the EgoSim CSV export."""

    crf: int = DEFAULT_CRF  # H.264 constant rate factor of every video (0-51, lower = better)
    overwrite: bool = False  # write into an OUT that already holds a metadata.csv

    def __post_init__(self) -> None:
        if not 0 <= self.crf <= 51:
            raise ConfigError(f"egosim-csv: crf must be in 0..51, got {self.crf}")


def _row(out: Path, sample: PackSample, config: EgoSimCsvConfig) -> dict[str, str]:
    """Write one clip's folder; returns its CSV row (paths relative to ``out``)."""
    cid, fps, crf = sample.clip_id, sample.fps, config.crf

    def path(key: str) -> Path:
        return safe_path(out, cid, FILES[key])

    write_video(path("video"), sample.target, fps, crf)
    write_video(path("ego_prior_video"), sample.scene, fps, crf)
    write_video(path("mask"), mask_as_rgb(sample.visible), fps, crf)
    write_video(path("hand_keypoint_video"), sample.skeleton, fps, crf)
    write_png(path("first_frame"), sample.first_frame)
    write_text(path("caption"), sample.prompt)
    return {
        "video": f"{cid}/{FILES['video']}",
        "ego_prior_video": f"{cid}/{FILES['ego_prior_video']}",
        "hand_keypoint_video": f"{cid}/{FILES['hand_keypoint_video']}",
        "first_frame": f"{cid}/{FILES['first_frame']}",
        "prompt": sample.prompt,
        "video_id": cid,
    }


def export_egosim_csv(run: Path, out: Path, config: EgoSimCsvConfig | None = None) -> ExportResult:
    """Export the pack shards of ``run`` in EgoSim's CSV layout at ``out`` (see module doc).

    ``metadata.csv`` is written last; rows that do not decode are skipped and listed.
    """
    config = config or EgoSimCsvConfig()
    out = prepare_out(out, INDEX_NAME, config.overwrite)
    result = ExportResult(out=out, index=out / INDEX_NAME)
    rows = []
    for item in iter_pack_samples(run):
        if isinstance(item, tuple):
            result.skipped[item[0]] = item[1]
            continue
        rows.append(_row(out, item, config))
        result.written.append(item.clip_id)
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=list(COLUMNS), lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    write_atomic(result.index, buffer.getvalue().encode("utf-8"))
    return result
