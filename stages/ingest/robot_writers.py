"""Write robot episodes in AgiBot World's and LeRobot's on-disk layouts from known arrays.

The inverse of :mod:`~egosim.stages.ingest.agibot_source` and
:mod:`~egosim.stages.ingest.lerobot_source`, so that those readers are tested against ground
truth (tests render the frames with the synthetic world and script the end-effector path). The
layouts are the ones documented in the readers' module docstrings; what a real dataset would
hold beyond what the readers use (depth, other cameras, actions' own streams, statistics) is
written only where the format requires it. ``drop_keys`` and ``state_rows`` make malformed
episodes on purpose.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import av
import h5py
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from egosim.pipeline.geometry import xyzw_from_matrix
from egosim.pipeline.media import write_video_file


@dataclass
class RobotEpisodeArrays:
    """Ground truth of one episode, in egosim's conventions (OpenCV axes, metres, seconds)."""

    frames: np.ndarray  # (T, H, W, 3) uint8 RGB of the head camera
    fps: float  # frames per second
    intrinsics: np.ndarray  # (4,) fx, fy, cx, cy in pixels of the frames
    world_from_cam: np.ndarray  # (T, 4, 4) camera-to-world
    world_from_ee: np.ndarray  # (T, G, 4, 4) end-effector poses (G = 2 for AgiBot, 1 LeRobot)
    gripper_state: np.ndarray  # (T, G) raw gripper readings
    task: str = "pick up the cube"  # task name / instruction
    actions: list[str] = field(default_factory=list)  # AgiBot action texts (sub-steps)
    joint_positions: np.ndarray | None = None  # (T, J) joint states (None: zeros for AgiBot)
    joint_names: list[str] = field(default_factory=list)  # LeRobot names of the J columns


def write_agibot_episode(
    root: Path,
    task: str,
    episode: str,
    ep: RobotEpisodeArrays,
    camera: str = "head",
    drop_keys: tuple[str, ...] = (),
    state_rows: int | None = None,
) -> Path:
    """Write ``ep`` as AgiBot World task ``task`` episode ``episode`` under ``root``.

    Returns the ``proprio_stats.h5`` path. ``drop_keys`` leaves those proprio keys out;
    ``state_rows`` keeps only that many state rows (a length mismatch with the video).
    """
    root = Path(root)
    t = len(ep.frames) if state_rows is None else state_rows
    video = root / "observations" / task / episode / "videos" / f"{camera}_color.mp4"
    video.parent.mkdir(parents=True, exist_ok=True)
    write_video_file(video, ep.frames, ep.fps)
    cam_dir = root / "parameters" / task / episode / "parameters" / "camera"
    cam_dir.mkdir(parents=True, exist_ok=True)
    fx, fy, cx, cy = (float(v) for v in ep.intrinsics)
    h, w = ep.frames.shape[1:3]
    intr = {"intrinsic": {"fx": fx, "fy": fy, "ppx": cx, "ppy": cy, "width": w, "height": h}}
    (cam_dir / f"{camera}_intrinsic_params.json").write_text(json.dumps(intr))
    extr = [
        {
            "extrinsic": {
                "rotation_matrix": pose[:3, :3].tolist(),
                "translation_vector": pose[:3, 3].tolist(),
            }
        }
        for pose in ep.world_from_cam
    ]
    (cam_dir / f"{camera}_extrinsic_params_aligned.json").write_text(json.dumps(extr))
    proprio = root / "proprio_stats" / task / episode / "proprio_stats.h5"
    proprio.parent.mkdir(parents=True, exist_ok=True)
    stamps = np.round(1.7e18 + np.arange(len(ep.frames)) / ep.fps * 1e9).astype(np.int64)
    data = {
        "timestamp": stamps,
        "state/end/position": ep.world_from_ee[:, :, :3, 3],  # (T, 2, 3)
        "state/end/orientation": xyzw_from_matrix(ep.world_from_ee[:, :, :3, :3]),  # (T, 2, 4)
        "state/effector/position": ep.gripper_state,  # (T, 2)
        "state/joint/position": np.zeros((len(ep.frames), 14))
        if ep.joint_positions is None
        else ep.joint_positions,
    }
    with h5py.File(proprio, "w") as f:
        for key, value in data.items():
            if key not in drop_keys:
                f.create_dataset(key, data=np.asarray(value)[:t])
    info_path = root / "task_info" / f"task_{task}.json"
    info_path.parent.mkdir(parents=True, exist_ok=True)
    entries = json.loads(info_path.read_text()) if info_path.is_file() else []
    actions = [
        {"start_frame": 0, "end_frame": len(ep.frames) - 1, "action_text": a, "skill": "Pick"}
        for a in ep.actions
    ]
    entries.append(
        {
            "episode_id": int(episode),
            "task_name": ep.task,
            "init_scene_text": "",
            "label_info": {"action_config": actions},
        }
    )
    info_path.write_text(json.dumps(entries))
    return proprio


def write_av1_file(path: Path, frames: np.ndarray, fps: float) -> None:
    """Write ``(T, H, W, 3)`` uint8 RGB frames as an AV1 MP4 (SVT-AV1, LeRobot's default codec)."""
    with av.open(str(path), "w", format="mp4") as container:
        stream = container.add_stream("libsvtav1", rate=round(fps))
        stream.width, stream.height = int(frames.shape[2]), int(frames.shape[1])
        stream.pix_fmt = "yuv420p"
        for frame in frames:
            container.mux(stream.encode(av.VideoFrame.from_ndarray(frame, format="rgb24")))
        container.mux(stream.encode())


STATE_NAMES = ["x", "y", "z", "qx", "qy", "qz", "qw", "gripper"]  # observation.state layout
CAMERA_POSE_NAMES = ["x", "y", "z", "qx", "qy", "qz", "qw"]  # observation.camera_pose layout


def _state_vector(ep: RobotEpisodeArrays) -> np.ndarray:
    """``observation.state`` rows ``(T, 8)``: the first gripper's pose and its reading."""
    pose = ep.world_from_ee[:, 0]  # (T, 4, 4)
    return np.concatenate(
        [pose[:, :3, 3], xyzw_from_matrix(pose[:, :3, :3]), ep.gripper_state[:, :1]], axis=1
    ).astype(np.float32)  # (T, 8)


def _episode_frames_table(
    ep: RobotEpisodeArrays, index: int, offset: int, fps: float, task_index: int, camera_pose: bool
) -> pa.Table:
    """One row per state of episode ``index``, whose first row is dataset row ``offset``."""
    t = len(ep.world_from_ee)
    state = _state_vector(ep)  # (T, 8)
    columns = {
        "observation.state": pa.array(state.tolist(), pa.list_(pa.float32(), 8)),
        "action": pa.array(state.tolist(), pa.list_(pa.float32(), 8)),
        "timestamp": pa.array((np.arange(t) / fps).astype(np.float32)),
        "frame_index": pa.array(np.arange(t, dtype=np.int64)),
        "episode_index": pa.array(np.full(t, index, dtype=np.int64)),
        "index": pa.array(np.arange(offset, offset + t, dtype=np.int64)),
        "task_index": pa.array(np.full(t, task_index, dtype=np.int64)),
    }
    if ep.joint_positions is not None:
        q = np.asarray(ep.joint_positions, np.float32)
        columns["observation.joint_positions"] = pa.array(
            q.tolist(), pa.list_(pa.float32(), q.shape[1])
        )
    if camera_pose:
        cam = ep.world_from_cam
        cam7 = np.concatenate([cam[:, :3, 3], xyzw_from_matrix(cam[:, :3, :3])], axis=1)
        columns["observation.camera_pose"] = pa.array(
            cam7.astype(np.float32).tolist(), pa.list_(pa.float32(), 7)
        )
    return pa.table(columns)


def _episode_meta_row(
    ep: RobotEpisodeArrays, index: int, offset: int, video_offset: int, fps: float, video_key: str
) -> dict[str, Any]:
    """Episode ``index``'s row of ``meta/episodes``: its data rows and its span of the video."""
    t, n_video = len(ep.world_from_ee), len(ep.frames)  # states, video frames
    return {
        "episode_index": index,
        "tasks": [ep.task],
        "length": t,
        "data/chunk_index": 0,
        "data/file_index": 0,
        "dataset_from_index": offset,
        "dataset_to_index": offset + t,
        f"videos/{video_key}/chunk_index": 0,
        f"videos/{video_key}/file_index": 0,
        f"videos/{video_key}/from_timestamp": video_offset / fps,
        f"videos/{video_key}/to_timestamp": (video_offset + n_video) / fps,
    }


def _features(
    first: RobotEpisodeArrays,
    video_key: str,
    fps: float,
    codec: str,
    names: list[str],
    camera_pose: bool,
) -> dict[str, object]:
    """``info.json``'s ``features``, sized from the ``first`` episode."""
    h, w = first.frames.shape[1:3]
    features: dict[str, object] = {
        video_key: {
            "dtype": "video",
            "shape": [h, w, 3],
            "names": ["height", "width", "channels"],
            "info": {"video.fps": fps, "video.height": h, "video.width": w, "video.codec": codec},
        },
        "observation.state": {"dtype": "float32", "shape": [8], "names": names},
        "action": {"dtype": "float32", "shape": [8], "names": names},
        "timestamp": {"dtype": "float32", "shape": [1], "names": None},
        "frame_index": {"dtype": "int64", "shape": [1], "names": None},
        "episode_index": {"dtype": "int64", "shape": [1], "names": None},
        "index": {"dtype": "int64", "shape": [1], "names": None},
        "task_index": {"dtype": "int64", "shape": [1], "names": None},
    }
    if first.joint_positions is not None:
        features["observation.joint_positions"] = {
            "dtype": "float32",
            "shape": [first.joint_positions.shape[1]],
            "names": list(first.joint_names) or None,
        }
    if camera_pose:
        features["observation.camera_pose"] = {
            "dtype": "float32",
            "shape": [7],
            "names": CAMERA_POSE_NAMES,
        }
    return features


def _write_v3_files(
    root: Path,
    info: dict[str, Any],
    episodes: list[RobotEpisodeArrays],
    tables: list[pa.Table],
    ep_rows: list[dict[str, Any]],
    tasks: list[str],
    video_key: str,
    fps: float,
    write_video: Callable[[Path, np.ndarray, float], None],
) -> None:
    """v3.0: every episode in one data file and one video; episodes and tasks as Parquet."""
    meta = root / "meta"
    info["data_path"] = "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
    info["video_path"] = "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4"
    data = root / info["data_path"].format(chunk_index=0, file_index=0)
    data.parent.mkdir(parents=True, exist_ok=True)
    pq.write_table(pa.concat_tables(tables), data)
    video = root / info["video_path"].format(video_key=video_key, chunk_index=0, file_index=0)
    video.parent.mkdir(parents=True, exist_ok=True)
    write_video(video, np.concatenate([e.frames for e in episodes]), fps)
    (meta / "episodes" / "chunk-000").mkdir(parents=True, exist_ok=True)
    pq.write_table(pa.Table.from_pylist(ep_rows), meta / "episodes/chunk-000/file-000.parquet")
    task_table = {"task_index": list(range(len(tasks))), "task": tasks}
    pq.write_table(pa.table(task_table), meta / "tasks.parquet")


def _write_v2_files(
    root: Path,
    info: dict[str, Any],
    episodes: list[RobotEpisodeArrays],
    tables: list[pa.Table],
    ep_rows: list[dict[str, Any]],
    tasks: list[str],
    video_key: str,
    fps: float,
    write_video: Callable[[Path, np.ndarray, float], None],
) -> None:
    """v2.x: one data file and one video per episode; episodes and tasks as JSON lines."""
    meta = root / "meta"
    info["data_path"] = "data/chunk-{episode_chunk:03d}/episode_{episode_index:06d}.parquet"
    info["video_path"] = (
        "videos/chunk-{episode_chunk:03d}/{video_key}/episode_{episode_index:06d}.mp4"
    )
    for index, (ep, table) in enumerate(zip(episodes, tables, strict=True)):
        data = root / info["data_path"].format(episode_chunk=0, episode_index=index)
        data.parent.mkdir(parents=True, exist_ok=True)
        pq.write_table(table, data)
        video = root / info["video_path"].format(
            episode_chunk=0, video_key=video_key, episode_index=index
        )
        video.parent.mkdir(parents=True, exist_ok=True)
        write_video(video, ep.frames, fps)
    lines = [
        json.dumps(
            {"episode_index": r["episode_index"], "tasks": r["tasks"], "length": r["length"]}
        )
        for r in ep_rows
    ]
    (meta / "episodes.jsonl").write_text("\n".join(lines) + "\n")
    task_lines = [json.dumps({"task_index": i, "task": s}) for i, s in enumerate(tasks)]
    (meta / "tasks.jsonl").write_text("\n".join(task_lines) + "\n")


def write_lerobot_dataset(
    root: Path,
    episodes: list[RobotEpisodeArrays],
    version: str = "v3.0",
    video_key: str = "observation.images.head",
    camera_pose: bool = True,
    state_names: list[str] | None = None,
    codec: str = "h264",
) -> Path:
    """Write ``episodes`` (one gripper each) as a LeRobot dataset under ``root``; returns ``root``.

    ``version`` ``"v3.0"`` packs every episode in one data file and one video file (located by
    ``from_timestamp``); ``"v2.1"`` writes one of each per episode. ``observation.state`` holds
    ``x, y, z, qx, qy, qz, qw, gripper`` (``state_names`` renames them: a joint-space dataset);
    ``camera_pose`` adds the per-frame ``observation.camera_pose`` (world_from_cam).
    ``codec`` is ``"h264"`` or ``"av1"`` (LeRobot's default; integer fps only).
    """
    if codec not in ("h264", "av1"):
        raise ValueError(f"codec must be 'h264' or 'av1', got {codec!r}")
    write_video = write_av1_file if codec == "av1" else write_video_file
    root = Path(root)
    fps = float(episodes[0].fps)
    tasks = sorted({e.task for e in episodes})
    tables, offset, video_offset, ep_rows = [], 0, 0, []
    for index, ep in enumerate(episodes):
        task_index = tasks.index(ep.task)
        tables.append(_episode_frames_table(ep, index, offset, fps, task_index, camera_pose))
        ep_rows.append(_episode_meta_row(ep, index, offset, video_offset, fps, video_key))
        offset += len(ep.world_from_ee)
        video_offset += len(ep.frames)
    features = _features(
        episodes[0], video_key, fps, codec, state_names or STATE_NAMES, camera_pose
    )
    info: dict[str, Any] = {
        "codebase_version": version,
        "robot_type": "synthetic",
        "total_episodes": len(episodes),
        "total_frames": offset,
        "total_tasks": len(tasks),
        "chunks_size": 1000,
        "fps": fps,
        "splits": {"train": f"0:{len(episodes)}"},
        "features": features,
    }
    meta = root / "meta"
    meta.mkdir(parents=True, exist_ok=True)
    if version.startswith("v3"):
        _write_v3_files(root, info, episodes, tables, ep_rows, tasks, video_key, fps, write_video)
    else:
        _write_v2_files(root, info, episodes, tables, ep_rows, tasks, video_key, fps, write_video)
    (meta / "info.json").write_text(json.dumps(info, indent=2))
    return root
