"""Export the processed clips of a run as a ``LeRobotDataset`` v3.0 (robotics users' own tools).

One episode per clip. From the run folder (``OUT/<step>/shard-*.parquet``):

- ``ingest`` (clips): the RGB video -> video key ``observation.images.head``; per frame
  ``timestamp`` (seconds from the clip's start), ``observation.camera_pose`` (``x, y, z, qx, qy,
  qz, qw``: ``world_from_cam``, OpenCV axes, the cleaned ``poses`` step's when present), the
  constant ``observation.camera_intrinsics`` (``fx, fy, cx, cy``), ``observation.hand_joints``
  (``2 * 21 * 3`` world metres, the ``hands`` step's when present, else the clip's) and
  ``observation.hand_valid`` (2 flags) and ``observation.hand_lifted`` (2 flags: the valid hand's
  3D is trusted, the ``hands`` step's ``hand_lifted``; else equal to ``hand_valid``);
- ``keypoints``: the skeleton video -> ``observation.images.skeleton`` (the hand condition);
- ``scene_render``: the scene video -> ``observation.images.scene`` (the scene condition);
- ``captions``: the episode's task (else the clip's ``text``, else ``""``).

Condition steps that the run lacks are left out; a clip missing from a present step is skipped
and reported. Videos are copied byte for byte (H.264 MP4, one file per episode: ``file_index``
= episode index, ``from_timestamp`` 0), so nothing is re-encoded. A LeRobot dataset has one fps
and one frame size per video key: clips that differ from the first exported clip are skipped
and reported. The layout is the one :mod:`~egosim.stages.ingest.lerobot_source` reads;
``meta/stats.json`` (normalisation statistics) is not written. The episodes table carries an
extra column ``egosim/clip_id``.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from egosim.pipeline.geometry import xyzw_from_matrix
from egosim.pipeline.shards import find_shards, open_shard
from egosim.schemas import CAPTIONS, CLIPS, HANDS, KEYPOINTS, POSES, SCENE_RENDER, ShardSchema

HEAD_KEY = "observation.images.head"  # RGB video key
CONDITION_KEYS = {  # step -> (schema, video column, video key)
    "keypoints": (KEYPOINTS, "skeleton_video", "observation.images.skeleton"),
    "scene_render": (SCENE_RENDER, "scene_video", "observation.images.scene"),
}
DATA_PATH = "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
VIDEO_PATH = "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4"
CHUNKS_SIZE = 1000  # files per chunk folder, LeRobot's default


@dataclass
class ExportReport:
    """What :func:`export_lerobot` wrote and what it skipped (clip id -> reason)."""

    episodes: int = 0  # episodes written
    frames: int = 0  # frames written over all episodes
    video_keys: list[str] = field(default_factory=list)  # video features of the dataset
    skipped: dict[str, str] = field(default_factory=dict)  # clip id -> why it was left out


def _rows(run: Path, step: str, schema: ShardSchema) -> Iterator[dict[str, Any]]:
    for path in find_shards([run / step], step):
        with open_shard(path, schema) as reader:
            yield from reader.iter_rows()


def _index(run: Path, step: str, schema: ShardSchema, columns: list[str]) -> dict[str, dict]:
    """``clip_id -> {column: value}`` of a step, empty when the run has no such step."""
    if not (run / step).is_dir():
        return {}
    return {r["clip_id"]: {c: r[c] for c in columns} for r in _rows(run, step, schema)}


def _pose7(world_from_cam: np.ndarray) -> np.ndarray:
    """``(T, 4, 4)`` -> ``(T, 7)`` x, y, z, qx, qy, qz, qw."""
    quat = xyzw_from_matrix(world_from_cam[:, :3, :3])  # (T, 4)
    return np.concatenate([world_from_cam[:, :3, 3], quat], axis=1)


@dataclass
class _StepRows:
    """The rows of the run's other steps an episode reads, by clip id (empty: no such step)."""

    conditions: dict[str, dict[str, dict]]  # condition step -> clip id -> {video column: bytes}
    captions: dict[str, dict]  # clip id -> {"text": ...}
    poses: dict[str, dict]  # clip id -> {"world_from_cam": ...} (cleaned poses)
    hands: dict[str, dict]  # clip id -> {"hand_joints": ..., "hand_valid": ..., "hand_lifted"}

    @classmethod
    def read(cls, run: Path) -> _StepRows:
        """Index the condition, captions, poses and hands steps of ``run``."""
        return cls(
            conditions={
                step: _index(run, step, schema, [column])
                for step, (schema, column, _) in CONDITION_KEYS.items()
                if (run / step).is_dir()
            },
            captions=_index(run, "captions", CAPTIONS, ["text"]),
            poses=_index(run, "poses", POSES, ["world_from_cam"]),
            hands=_index(run, "hands", HANDS, ["hand_joints", "hand_valid", "hand_lifted"]),
        )

    def missing(self, clip: dict[str, Any]) -> str | None:
        """Why ``clip`` cannot be an episode (a condition row or camera poses lacking), or None."""
        cid = clip["clip_id"]
        missing = [s for s, rows in self.conditions.items() if cid not in rows]
        if missing:
            return f"no {', '.join(missing)} row"
        if clip["world_from_cam"] is None and cid not in self.poses:
            return "no camera poses"
        return None


def export_lerobot(run: Path, out: Path, robot_type: str = "egosim") -> ExportReport:
    """Write the clips of run folder ``run`` as a LeRobot v3.0 dataset at ``out`` (see above).

    Raises :class:`FileExistsError` when ``out`` holds a dataset already and
    :class:`FileNotFoundError` when ``run`` has no ``ingest`` shards.
    """
    run, out = Path(run), Path(out)
    if (out / "meta" / "info.json").exists():
        raise FileExistsError(f"{out} already holds a LeRobot dataset (meta/info.json)")
    find_shards([run / "ingest"], "ingest")  # raises FileNotFoundError when there are none
    steps = _StepRows.read(run)
    video_keys = [HEAD_KEY] + [CONDITION_KEYS[s][2] for s in steps.conditions]
    report = ExportReport(video_keys=video_keys)
    tasks: list[str] = []
    episodes: list[dict[str, Any]] = []
    fps = size = None
    for clip in _rows(run, "ingest", CLIPS):
        cid = clip["clip_id"]
        reason = steps.missing(clip)
        if reason is not None:
            report.skipped[cid] = reason
            continue
        t, h, w = int(clip["num_frames"]), int(clip["height"]), int(clip["width"])
        fps = float(clip["fps"]) if fps is None else fps
        size = (h, w) if size is None else size
        if abs(float(clip["fps"]) - fps) > 1e-6 or (h, w) != size:
            report.skipped[cid] = (
                f"{clip['fps']:g} fps {h}x{w}, the dataset is {fps:g} fps {size[0]}x{size[1]}"
            )
            continue
        ep = report.episodes
        chunk, file = ep // CHUNKS_SIZE, ep % CHUNKS_SIZE
        task = (steps.captions.get(cid) or {}).get("text") or clip.get("text") or ""
        if task not in tasks:
            tasks.append(task)
        table = _frames_table(clip, steps, ep, report.frames, tasks.index(task))
        data = out / DATA_PATH.format(chunk_index=chunk, file_index=file)
        data.parent.mkdir(parents=True, exist_ok=True)
        pq.write_table(table, data)
        entry: dict[str, Any] = {
            "episode_index": ep,
            "tasks": [task],
            "length": t,
            "data/chunk_index": chunk,
            "data/file_index": file,
            "dataset_from_index": report.frames,
            "dataset_to_index": report.frames + t,
            "egosim/clip_id": cid,
        }
        entry |= _write_videos(out, _episode_videos(clip, steps), chunk, file, t / fps)
        episodes.append(entry)
        report.episodes += 1
        report.frames += t
    if not episodes:
        raise FileNotFoundError(f"no clip of {run} could be exported: {report.skipped}")
    _write_meta(out, episodes, tasks, video_keys, fps or 0.0, size or (0, 0), robot_type)
    return report


def _frames_table(
    clip: dict[str, Any], steps: _StepRows, episode: int, first_index: int, task_index: int
) -> pa.Table:
    """The episode's per-frame table: timestamps, indexes, camera pose and intrinsics, hands.

    Poses are the cleaned ``poses`` step's when it has the clip, else the clip's own; hand
    joints the ``hands`` step's, else the clip's (zeros and not valid when neither has them).
    """
    cid, t = clip["clip_id"], int(clip["num_frames"])
    cams = steps.poses.get(cid, {}).get("world_from_cam") or clip["world_from_cam"]
    world_from_cam = np.asarray(cams, dtype=np.float64).reshape(t, 4, 4)
    hand = steps.hands.get(cid) or clip
    joints = hand.get("hand_joints")
    valid = hand.get("hand_valid")
    joints = np.zeros((t, 126)) if joints is None else np.asarray(joints).reshape(t, 126)
    valid = np.zeros((t, 2), bool) if valid is None else np.asarray(valid, bool).reshape(t, 2)
    lifted = hand.get("hand_lifted")  # only the hands step says; a clip's labels are 3D
    lifted = valid if lifted is None else np.asarray(lifted, bool).reshape(t, 2)
    stamps = np.asarray(clip["timestamps"], dtype=np.float64)
    f32 = pa.float32()
    return pa.table(
        {
            "timestamp": pa.array((stamps - stamps[0]).astype(np.float32)),
            "frame_index": pa.array(np.arange(t, dtype=np.int64)),
            "episode_index": pa.array(np.full(t, episode, dtype=np.int64)),
            "index": pa.array(np.arange(first_index, first_index + t, dtype=np.int64)),
            "task_index": pa.array(np.full(t, task_index, dtype=np.int64)),
            "observation.camera_pose": pa.array(
                _pose7(world_from_cam).astype(np.float32).tolist(), pa.list_(f32, 7)
            ),
            "observation.camera_intrinsics": pa.array(
                np.tile(np.asarray(clip["intrinsics"], np.float32), (t, 1)).tolist(),
                pa.list_(f32, 4),
            ),
            "observation.hand_joints": pa.array(
                joints.astype(np.float32).tolist(), pa.list_(f32, 126)
            ),
            "observation.hand_valid": pa.array(valid.tolist(), pa.list_(pa.bool_(), 2)),
            "observation.hand_lifted": pa.array(lifted.tolist(), pa.list_(pa.bool_(), 2)),
        }
    )


def _episode_videos(clip: dict[str, Any], steps: _StepRows) -> dict[str, bytes]:
    """Video key -> the episode's MP4 bytes: the clip's video and each condition step's."""
    videos = {HEAD_KEY: clip["video"]}
    for step, rows in steps.conditions.items():
        _, column, key = CONDITION_KEYS[step]
        videos[key] = rows[clip["clip_id"]][column]
    return videos


def _write_videos(
    out: Path, videos: dict[str, bytes], chunk: int, file: int, seconds: float
) -> dict[str, Any]:
    """Copy each video to its file; returns the episode-table entries that locate them."""
    entry: dict[str, Any] = {}
    for key, payload in videos.items():
        path = out / VIDEO_PATH.format(video_key=key, chunk_index=chunk, file_index=file)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(payload)
        entry |= {
            f"videos/{key}/chunk_index": chunk,
            f"videos/{key}/file_index": file,
            f"videos/{key}/from_timestamp": 0.0,
            f"videos/{key}/to_timestamp": seconds,
        }
    return entry


def _write_meta(
    out: Path,
    episodes: list[dict[str, Any]],
    tasks: list[str],
    video_keys: list[str],
    fps: float,
    size: tuple[int, int],
    robot_type: str,
) -> None:
    h, w = size
    video = {
        "dtype": "video",
        "shape": [h, w, 3],
        "names": ["height", "width", "channels"],
        "info": {"video.fps": fps, "video.height": h, "video.width": w, "video.codec": "h264",
                 "video.pix_fmt": "yuv420p", "video.is_depth_map": False, "has_audio": False},
    }  # fmt: skip
    features: dict[str, Any] = {key: video for key in video_keys}
    features |= {
        "observation.camera_pose": {
            "dtype": "float32",
            "shape": [7],
            "names": ["x", "y", "z", "qx", "qy", "qz", "qw"],
        },
        "observation.camera_intrinsics": {
            "dtype": "float32",
            "shape": [4],
            "names": ["fx", "fy", "cx", "cy"],
        },
        "observation.hand_joints": {"dtype": "float32", "shape": [126], "names": None},
        "observation.hand_valid": {"dtype": "bool", "shape": [2], "names": ["left", "right"]},
        "observation.hand_lifted": {"dtype": "bool", "shape": [2], "names": ["left", "right"]},
    }
    for name in ("timestamp",):
        features[name] = {"dtype": "float32", "shape": [1], "names": None}
    for name in ("frame_index", "episode_index", "index", "task_index"):
        features[name] = {"dtype": "int64", "shape": [1], "names": None}
    total = sum(e["length"] for e in episodes)
    info = {
        "codebase_version": "v3.0",
        "robot_type": robot_type,
        "total_episodes": len(episodes),
        "total_frames": total,
        "total_tasks": len(tasks),
        "chunks_size": CHUNKS_SIZE,
        "fps": int(fps) if float(fps).is_integer() else fps,  # LeRobot writes an integer
        "splits": {"train": f"0:{len(episodes)}"},
        "data_path": DATA_PATH,
        "video_path": VIDEO_PATH,
        "features": features,
    }
    meta = out / "meta"
    (meta / "episodes" / "chunk-000").mkdir(parents=True, exist_ok=True)
    pq.write_table(pa.Table.from_pylist(episodes), meta / "episodes/chunk-000/file-000.parquet")
    pq.write_table(
        pa.table({"task_index": list(range(len(tasks))), "task": tasks}), meta / "tasks.parquet"
    )
    (meta / "info.json").write_text(json.dumps(info, indent=2))
