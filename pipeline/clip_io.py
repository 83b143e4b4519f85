"""Convert between decoded :class:`Clip` records and rows of the ``clips`` schema.

Also the Python API for notebooks and tests: :func:`read_clips` streams a shard as decoded clips,
one at a time, and :func:`write_clips` writes clips back as a shard.
"""

from __future__ import annotations

import itertools
from collections.abc import Iterable, Iterator, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from egosim.pipeline import media
from egosim.pipeline.records import NUM_HAND_JOINTS, Clip, ClipValueError
from egosim.pipeline.shards import ShardWriter, open_shard, shard_file_name
from egosim.schemas import CLIPS


def row_from_clip(clip: Clip, crf: int = media.DEFAULT_CRF) -> dict[str, Any]:
    """Encode a clip as one ``clips`` row (videos compressed, arrays flattened)."""
    clip.check()
    t, h, w = clip.num_frames, clip.height, clip.width
    depths = [d for d in (clip.depth, clip.static_depth) if d is not None]
    unit = max(media.depth_unit_for(d) for d in depths) if depths else None
    n_obj = None if clip.object_poses is None else int(clip.object_poses.shape[1])
    return {
        "clip_id": clip.clip_id,
        "source": clip.source,
        "source_uri": clip.source_uri,
        "fps": float(clip.fps),
        "num_frames": t,
        "width": w,
        "height": h,
        "timestamps": np.asarray(clip.timestamps, dtype=np.float64).tolist(),
        "intrinsics": np.asarray(clip.intrinsics, dtype=np.float64).tolist(),
        "video": media.encode_rgb_video(clip.frames, clip.fps, crf),
        "world_from_cam": _opt(clip.world_from_cam, lambda a: a.reshape(t, 16).tolist()),
        "depth": _opt(clip.depth, lambda a: media.encode_depth_video(a, unit)),
        "depth_unit_m": unit,
        "static_video": _opt(
            clip.static_frames, lambda a: media.encode_rgb_video(a, clip.fps, crf)
        ),
        "static_depth": _opt(clip.static_depth, lambda a: media.encode_depth_video(a, unit)),
        "first_frame_clean": _opt(clip.first_frame_clean, media.encode_png),
        "hand_joints": _opt(
            clip.hand_joints, lambda a: a.astype(np.float32).reshape(t, -1).tolist()
        ),
        "hand_valid": _opt(clip.hand_valid, lambda a: a.astype(bool).tolist()),
        "hand_confidence": _opt(
            clip.hand_confidence, lambda a: a.astype(np.float32).reshape(t, -1).tolist()
        ),
        "hand_mask": _opt(clip.hand_mask, media.encode_mask_video),
        "embodiment_mask": _opt(clip.embodiment_mask, media.encode_mask_video),
        "object_mask": _opt(clip.object_mask, media.encode_mask_video),
        "num_objects": n_obj,
        "object_poses": _opt(clip.object_poses, lambda a: a.reshape(-1, 16).tolist()),
        "text": clip.text,
        "source_fps": _opt(clip.source_fps, float),
        "source_num_frames": _opt(clip.source_num_frames, int),
        "source_frame_indices": _opt(
            clip.source_frame_indices, lambda a: np.asarray(a, dtype=np.int64).tolist()
        ),
        "clip_policy": clip.clip_policy,
        "gripper_opening": _opt(clip.gripper_opening, lambda a: a.astype(np.float32).tolist()),
        "source_crop": _opt(clip.source_crop, lambda a: np.asarray(a, dtype=np.float64).tolist()),
    }


# The columns every clips row needs to become a Clip (the schema's non-nullable ones). A stage
# that declares a subset of the clips columns and calls clip_from_row lists these too.
CLIP_REQUIRED_COLUMNS: tuple[str, ...] = tuple(c.name for c in CLIPS.columns if not c.nullable)


def clip_from_row(row: Mapping[str, Any]) -> Clip:
    """Decode one ``clips`` row into a :class:`Clip` (every video it holds decoded).

    An optional column absent from ``row`` (a stage that read a subset of the columns, see
    ``ClipStage.columns``) is treated like null; a missing required column
    (:data:`CLIP_REQUIRED_COLUMNS`) raises :class:`ClipValueError` naming the clip and columns.
    """
    cid = row.get("clip_id", "?")
    missing = [name for name in CLIP_REQUIRED_COLUMNS if name not in row]
    if missing:
        raise ClipValueError(
            f"clip {cid!r}: the row lacks required clips column(s) {missing} (a stage reading "
            "a subset of columns must declare clip_io.CLIP_REQUIRED_COLUMNS)"
        )

    def get(key: str) -> Any:
        # not row.get: a DeclaredRow raises there for a column its stage did not declare
        return row[key] if key in row else None  # noqa: SIM401

    t, h, w = row["num_frames"], row["height"], row["width"]
    unit = get("depth_unit_m")

    def video(key: str) -> np.ndarray | None:
        data = get(key)
        return None if data is None else media.decode_rgb_video(data, h, w, f"clip {cid} {key}")

    def lossless(key: str) -> np.ndarray | None:
        data = get(key)
        return None if data is None else media.decode_lossless_video(data, f"clip {cid} {key}")

    def depth(key: str) -> np.ndarray | None:
        data = get(key)
        return None if data is None else media.decode_depth_video(data, unit, f"clip {cid} {key}")

    n_obj = get("num_objects")
    clip = Clip(
        clip_id=cid,
        source=row["source"],
        source_uri=row["source_uri"],
        fps=float(row["fps"]),
        timestamps=np.asarray(row["timestamps"], dtype=np.float64),
        intrinsics=np.asarray(row["intrinsics"], dtype=np.float64),
        frames=video("video"),
        world_from_cam=_opt(get("world_from_cam"), lambda v: _arr(v).reshape(t, 4, 4)),
        depth=depth("depth"),
        static_frames=video("static_video"),
        static_depth=depth("static_depth"),
        first_frame_clean=_opt(
            get("first_frame_clean"), lambda b: media.decode_png(b, f"clip {cid} first frame")
        ),
        hand_joints=_opt(
            get("hand_joints"), lambda v: _arr(v, np.float32).reshape(t, 2, NUM_HAND_JOINTS, 3)
        ),
        hand_valid=_opt(get("hand_valid"), lambda v: np.asarray(v, dtype=bool)),
        hand_confidence=_opt(
            get("hand_confidence"), lambda v: _arr(v, np.float32).reshape(t, 2, -1)
        ),
        hand_mask=lossless("hand_mask"),
        embodiment_mask=lossless("embodiment_mask"),
        object_mask=lossless("object_mask"),
        # num_objects left unread: the object count follows from the poses' length
        object_poses=_opt(
            get("object_poses"), lambda v: _arr(v).reshape(t, -1 if n_obj is None else n_obj, 4, 4)
        ),
        text=get("text"),
        source_fps=_opt(get("source_fps"), float),
        source_num_frames=_opt(get("source_num_frames"), int),
        source_frame_indices=_opt(get("source_frame_indices"), lambda v: _arr(v, np.int64)),
        clip_policy=get("clip_policy"),
        gripper_opening=_opt(get("gripper_opening"), lambda v: _arr(v, np.float32).reshape(t, 2)),
        source_crop=_opt(get("source_crop"), lambda v: _arr(v, np.float64)),
    )
    return clip.check()


def read_clips(path: Path) -> Iterator[Clip]:
    """Stream the clips of a ``clips`` shard, decoded, one at a time."""
    with open_shard(path, CLIPS) as reader:
        for row in reader.iter_rows():
            yield clip_from_row(row)


def write_clips(
    path: Path, clips: Iterable[Clip], stage: str = "api", params: Mapping[str, Any] | None = None
) -> int:
    """Write clips as a ``clips`` shard (atomically); returns the number written."""
    count = 0
    with ShardWriter(path, CLIPS, stage=stage, params=dict(params or {})) as writer:
        for clip in clips:
            writer.write_row(row_from_clip(clip))
            count += 1
    return count


def write_clip_shards(
    folder: Path,
    clips: Iterable[Clip],
    per_shard: int,
    stage: str = "api",
    params: Mapping[str, Any] | None = None,
) -> list[tuple[Path, int]]:
    """Write clips as ``folder/shard-NNNNN.parquet``, ``per_shard`` clips each (``egosim synth``).

    Clips are consumed lazily, one at a time; returns ``(path, clips written)`` per shard.
    """
    if per_shard < 1:
        raise ValueError(f"per_shard must be >= 1, got {per_shard}")
    written: list[tuple[Path, int]] = []
    remaining = iter(clips)
    while (first := next(remaining, None)) is not None:
        path = Path(folder) / shard_file_name(len(written))
        batch = itertools.chain([first], itertools.islice(remaining, per_shard - 1))
        written.append((path, write_clips(path, batch, stage=stage, params=params)))
    return written


def _opt(value: Any, fn: Any) -> Any:
    return None if value is None else fn(value)


def _arr(value: Any, dtype: Any = np.float64) -> np.ndarray:
    return np.asarray(value, dtype=dtype)
