"""What every exporter of packed samples shares: reading pack rows, writing files atomically.

Exporters read a run's ``pack`` shards (one training sample per clip, at the model's size and
frame count: :mod:`egosim.schemas.pack`), decode each row with the one pack decoder
(:func:`~egosim.pipeline.export.pack_rows.decode_pack_row`), and write plain files another
tool's loader reads: H.264 MP4 videos (masks as black/white RGB video, since those loaders read
masks as video), PNG images, text and an index (JSON, CSV or a list). Every file is written to a
temporary name in its folder and renamed, the index last, so a killed export never leaves an
index that names a missing or half-written file. Paths built from clip ids are checked to stay
under the output folder. A row that cannot be decoded is skipped and reported, not fatal.
"""

from __future__ import annotations

import os
import uuid
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from egosim.pipeline import media
from egosim.pipeline.export.pack_rows import PackRowError, decode_pack_row
from egosim.pipeline.export.run_index import ExportError, RunIndex
from egosim.pipeline.shards import SHARD_GLOB, ShardReader, find_shards
from egosim.schemas.ids import id_problems, path_under
from egosim.schemas.pack import PACK


@dataclass(frozen=True)
class PackSample:
    """One decoded pack row: the sample's videos at the pack's size, rate and frame count."""

    clip_id: str  # clip id (a valid id: letters, digits, '.', '_', '-')
    fps: float  # frames per second of the sample
    prompt: str  # text prompt
    target: np.ndarray  # (T, H, W, 3) uint8 real frames
    scene: np.ndarray  # (T, H, W, 3) uint8 scene render
    visible: np.ndarray  # (T, H, W) uint8 {0, 1}, 1 = a scene point landed
    skeleton: np.ndarray  # (T, H, W, 3) uint8 hand skeleton video
    first_frame: np.ndarray  # (H, W, 3) uint8 hand-free first frame
    hand_mask: np.ndarray | None  # (T, H, W) uint8 {0, 1}, 1 = hand or arm; None when absent


@dataclass
class ExportResult:
    """What an export wrote and what it left out."""

    out: Path  # the output folder
    index: Path  # the index file the tool reads (metadata.json, metadata.csv, dataset file)
    written: list[str] = field(default_factory=list)  # clip ids exported, in order
    skipped: dict[str, str] = field(default_factory=dict)  # clip id -> why it was left out


def pack_shards(run: Path) -> list[Path]:
    """The ``pack`` shards of ``run``: a run folder, a folder of pack shards, or one shard.

    In a run folder the step is found by the schema its shards declare (any step name).
    """
    path = Path(run)
    if path.is_dir() and not any(path.glob(SHARD_GLOB)):
        index = RunIndex.open(path)
        step = index.step_of(PACK)
        if step is None:
            raise ExportError(f"{path}: no step wrote pack shards (steps: {index.steps})")
        return sorted((path / step).glob(SHARD_GLOB))
    try:
        return find_shards([path], "pack")
    except FileNotFoundError as exc:
        raise ExportError(str(exc)) from exc


def iter_pack_samples(run: Path) -> Iterator[PackSample | tuple[str, str]]:
    """Each pack row of ``run`` decoded, or ``(clip_id, reason)`` for a row that is not usable.

    A row is not usable when its media do not decode or disagree in size
    (:class:`~egosim.pipeline.export.pack_rows.PackRowError`), or its clip id repeats one
    already seen. Shards of another schema (or version) raise ``SchemaCompatibilityError``.
    """
    seen: set[str] = set()
    for shard in pack_shards(run):
        with ShardReader(shard, PACK) as reader:
            for row in reader.iter_rows():
                cid = str(row["clip_id"])
                problems = id_problems(cid)
                if problems:
                    yield cid, f"{shard.name}: clip id {cid!r}: {'; '.join(problems)}"
                    continue
                if cid in seen:
                    yield cid, f"{shard.name}: clip id {cid!r} repeats one already exported"
                    continue
                seen.add(cid)
                try:
                    videos = decode_pack_row(row)
                except (PackRowError, media.MediaError) as exc:
                    yield cid, f"{shard.name}: {exc}"
                    continue
                yield PackSample(
                    clip_id=cid,
                    fps=float(row["fps"]),
                    prompt=str(row["prompt"]),
                    target=videos["target"],
                    scene=videos["scene"],
                    visible=videos["visible"],
                    skeleton=videos["skeleton"],
                    first_frame=videos["first_frame"],
                    hand_mask=videos.get("hand_mask"),
                )


def safe_path(out: Path, *parts: str) -> Path:
    """``out / parts`` (parent folders made), refused when it would leave ``out``."""
    path = path_under(out, *parts)
    path.parent.mkdir(parents=True, exist_ok=True)
    return path


def write_atomic(path: Path, data: bytes) -> Path:
    """Write ``data`` to ``path`` through a temporary file in the same folder and a rename."""
    path = Path(path)
    tmp = path.with_name(f"{path.name}.tmp-{uuid.uuid4().hex[:8]}")
    try:
        tmp.write_bytes(data)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path


def write_video(path: Path, frames: np.ndarray, fps: float, crf: int) -> Path:
    """``(T, H, W, 3)`` uint8 RGB as an H.264 MP4 at ``fps`` (CRF ``crf``)."""
    return write_atomic(path, media.encode_rgb_video(np.ascontiguousarray(frames), fps, crf))


def mask_as_rgb(mask: np.ndarray) -> np.ndarray:
    """A ``{0, 1}`` mask ``(T, H, W)`` as black/white RGB frames ``(T, H, W, 3)`` (1 = 255)."""
    grey = (np.asarray(mask) > 0).astype(np.uint8) * 255  # (T, H, W)
    return np.repeat(grey[..., None], 3, axis=-1)


def write_png(path: Path, image: np.ndarray) -> Path:
    """An RGB or grey uint8 image as a PNG file (lossless)."""
    return write_atomic(path, media.encode_png(np.ascontiguousarray(image)))


def write_text(path: Path, text: str) -> Path:
    """UTF-8 text (a trailing newline added when missing)."""
    return write_atomic(path, (text if text.endswith("\n") else text + "\n").encode("utf-8"))


def prepare_out(out: Path, index_name: str, overwrite: bool) -> Path:
    """Make the output folder; refuse one that already holds an export unless ``overwrite``."""
    out = Path(out)
    if (out / index_name).exists() and not overwrite:
        raise ExportError(
            f"{out} already holds an export ({index_name}); choose another --out or overwrite"
        )
    out.mkdir(parents=True, exist_ok=True)
    return out
