"""AgiBot World episodes read into a gripper-skeleton :class:`~egosim.pipeline.records.Clip`.

AgiBot World's released layout (Alpha/Beta; one episode per ``{task}/{episode}`` folder)::

    ROOT/task_info/task_{task}.json             [{"episode_id", "task_name", "init_scene_text",
                                                  "label_info": {"action_config": [
                                                  {"start_frame", "end_frame", "action_text"}]}}]
    ROOT/observations/{task}/{episode}/videos/{camera}_color.mp4        (camera "head" default)
    ROOT/parameters/{task}/{episode}/parameters/camera/{camera}_intrinsic_params.json
        {"intrinsic": {"fx", "fy", "ppx", "ppy"}}                      pixels of the video
    ROOT/parameters/{task}/{episode}/parameters/camera/{camera}_extrinsic_params_aligned.json
        [{"extrinsic": {"rotation_matrix": 3x3, "translation_vector": 3}}, ...] one per frame
        (or one object for a fixed camera): camera-to-base, metres
    ROOT/proprio_stats/{task}/{episode}/proprio_stats.h5
        timestamp (T,) int nanoseconds; state/end/position (T, 2, 3) metres in the base frame,
        arm 0 = left, 1 = right; state/end/orientation (T, 2, 4) quaternions x, y, z, w;
        state/effector/position (T, 2) gripper readings; state/joint/position (T, 14) (not used)

Conversion, once: the robot base frame is the world; the extrinsics are ``world_from_cam`` with
the camera axes ``camera_axes`` (OpenCV by default, as AgiBot's own projection code treats
them; ``opengl`` and ``ros_body`` convert through ``mcap_source.CAM_FROM_OURS``);
end-effector poses become ``world_from_ee``; the gripper reading becomes an opening through the
robot's :class:`~egosim.stages.common.gripper.GripperGeometry` (``agibot_g1`` by default). The
left arm takes hand slot 0, the right arm slot 1. The caption is the task name and the action
texts. Timestamps are the h5 file's (seconds from its first row); fps is the video's.

Every failure is :class:`ClipRejected` naming the episode: a missing file or proprio key, a
length mismatch between the video and the states (or the extrinsics), NaN or infinite states.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np

from egosim.pipeline.geometry import make_se3
from egosim.pipeline.media import MediaError, probe_video_file, read_video_file
from egosim.pipeline.records import Clip
from egosim.pipeline.stage import ClipRejected
from egosim.stages.common.gripper import GripperGeometry, gripper_geometry
from egosim.stages.ingest.mcap_source import CAM_FROM_OURS
from egosim.stages.ingest.robot_source import (
    ArmModel,
    RobotEpisode,
    episode_clip,
    pose_from_xyz_quat,
)

PROPRIO_FILE = "proprio_stats.h5"
DEFAULT_CAMERA = "head"  # AgiBot G1's head colour camera
DEFAULT_ROBOT = "agibot_g1"  # gripper geometry preset of AgiBot World episodes
# proprio keys the reader needs: (key, shape after the frame axis)
PROPRIO_KEYS: dict[str, tuple[int, ...]] = {
    "timestamp": (),
    "state/end/position": (2, 3),
    "state/end/orientation": (2, 4),
    "state/effector/position": (2,),
}
JOINT_KEY = "state/joint/position"  # (T, J) joint states (used with a URDF: embodiment_mask)
ARM_HANDS = (0, 1)  # arm 0 (left) -> hand 0, arm 1 (right) -> hand 1


@dataclass(frozen=True)
class AgibotPaths:
    """Where one episode's files live in the AgiBot World layout."""

    root: Path  # dataset root (holds task_info/, observations/, parameters/, proprio_stats/)
    task: str  # task id, e.g. "327"
    episode: str  # episode id, e.g. "648642"
    camera: str  # camera name, e.g. "head"

    @property
    def name(self) -> str:
        """The episode's name in clip ids and rejects: ``agibot_{task}_{episode}``."""
        return f"agibot_{self.task}_{self.episode}"

    @property
    def proprio(self) -> Path:
        """``proprio_stats/{task}/{episode}/proprio_stats.h5``."""
        return self.root / "proprio_stats" / self.task / self.episode / PROPRIO_FILE

    @property
    def video(self) -> Path:
        """``observations/{task}/{episode}/videos/{camera}_color.mp4``."""
        return (
            self.root
            / "observations"
            / self.task
            / self.episode
            / "videos"
            / (f"{self.camera}_color.mp4")
        )

    def camera_file(self, kind: str) -> Path:
        """``{camera}_intrinsic_params.json`` or ``{camera}_extrinsic_params_aligned.json``."""
        base = self.root / "parameters" / self.task / self.episode / "parameters" / "camera"
        if kind == "intrinsic":
            return base / f"{self.camera}_intrinsic_params.json"
        return base / f"{self.camera}_extrinsic_params_aligned.json"

    @property
    def task_info(self) -> Path:
        """``task_info/task_{task}.json``."""
        return self.root / "task_info" / f"task_{self.task}.json"


def in_layout(proprio: Path) -> bool:
    """True when ``proprio`` sits at ``ROOT/proprio_stats/TASK/EPISODE/proprio_stats.h5``."""
    parts = Path(proprio).parts
    return len(parts) >= 5 and parts[-1] == PROPRIO_FILE and parts[-4] == "proprio_stats"


def paths_of(proprio: Path, camera: str = DEFAULT_CAMERA) -> AgibotPaths:
    """The episode paths from its ``proprio_stats.h5`` (``ROOT/proprio_stats/TASK/EP/...``).

    Raises :class:`ClipRejected` for a file outside that layout.
    """
    proprio = Path(proprio)
    if not in_layout(proprio):
        raise ClipRejected(
            f"agibot: {proprio} is not at ROOT/proprio_stats/TASK/EPISODE/{PROPRIO_FILE}"
        )
    return AgibotPaths(proprio.parents[3], proprio.parent.parent.name, proprio.parent.name, camera)


def find_episodes(path: Path) -> list[Path]:
    """The ``proprio_stats.h5`` files of the AgiBot episodes at or under ``path``, sorted."""
    path = Path(path)
    if path.is_file():
        return [path] if in_layout(path) else []
    return sorted(p for p in path.rglob(PROPRIO_FILE) if p.is_file() and in_layout(p))


def owns(path: Path) -> bool:
    """True for files of an AgiBot layout (so the other sources leave them alone)."""
    path = Path(path)
    if path.name == PROPRIO_FILE:
        return True
    parts = path.parts
    return (
        len(parts) >= 5
        and parts[-2] == "videos"
        and parts[-5] == "observations"
        and (Path(*parts[:-5]) / "proprio_stats").is_dir()
    )


def _load_json(path: Path, what: str, name: str) -> object:
    if not path.is_file():
        raise ClipRejected(f"agibot episode {name}: {what} {path} is missing")
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise ClipRejected(f"agibot episode {name}: cannot read {what} {path}: {exc}") from exc


def _read_proprio(paths: AgibotPaths) -> dict[str, np.ndarray]:
    name, path = paths.name, paths.proprio
    try:
        with h5py.File(path, "r") as f:
            missing = [k for k in PROPRIO_KEYS if k not in f]
            if missing:
                raise ClipRejected(
                    f"agibot episode {name}: {path.name} lacks proprio key(s) "
                    f"{', '.join(repr(k) for k in missing)}"
                )
            data = {k: np.asarray(f[k][()]) for k in PROPRIO_KEYS}
            if JOINT_KEY in f:
                data[JOINT_KEY] = np.asarray(f[JOINT_KEY][()], dtype=np.float64)
    except ClipRejected:
        raise
    except (OSError, KeyError, ValueError, TypeError) as exc:
        raise ClipRejected(f"agibot episode {name}: cannot read {path}: {exc}") from exc
    t = len(data["timestamp"])
    problems = [
        f"{k!r} shape {data[k].shape} != {(t, *shape)}"
        for k, shape in PROPRIO_KEYS.items()
        if data[k].shape != (t, *shape)
    ]
    if problems:
        raise ClipRejected(f"agibot episode {name}: " + "; ".join(problems))
    return data


def _intrinsics(paths: AgibotPaths) -> np.ndarray:
    info = _load_json(paths.camera_file("intrinsic"), "intrinsics", paths.name)
    try:
        k = info["intrinsic"]  # type: ignore[index]
        out = np.array([k["fx"], k["fy"], k["ppx"], k["ppy"]], dtype=np.float64)
    except (KeyError, TypeError, ValueError) as exc:
        raise ClipRejected(
            f"agibot episode {paths.name}: intrinsics need intrinsic.fx, fy, ppx, ppy: {exc!r}"
        ) from exc
    return out


def _extrinsics(paths: AgibotPaths, camera_axes: str) -> np.ndarray:
    data = _load_json(paths.camera_file("extrinsic"), "extrinsics", paths.name)
    items = data if isinstance(data, list) else [data]
    try:
        rot = np.array([i["extrinsic"]["rotation_matrix"] for i in items], dtype=np.float64)
        trans = np.array([i["extrinsic"]["translation_vector"] for i in items], dtype=np.float64)
        world_from_rec = make_se3(rot.reshape(-1, 3, 3), trans.reshape(-1, 3))  # (N, 4, 4)
    except (KeyError, TypeError, ValueError) as exc:
        raise ClipRejected(
            f"agibot episode {paths.name}: extrinsics need extrinsic.rotation_matrix and "
            f"translation_vector per entry: {exc!r}"
        ) from exc
    return world_from_rec @ CAM_FROM_OURS[camera_axes]  # (N, 4, 4) world_from_cam, OpenCV


def _seconds(stamps: np.ndarray) -> np.ndarray:
    """Timestamps -> seconds from the first: integers are nanoseconds (AgiBot's), floats are
    taken as seconds unless their steps exceed 1000 (nanoseconds stored as floats)."""
    if not len(stamps):
        return stamps.astype(np.float64)
    rel = stamps - stamps[0]  # integer subtraction first: epoch nanoseconds exceed float64's
    if np.issubdtype(stamps.dtype, np.integer):
        return rel.astype(np.float64) * 1e-9
    steps = np.diff(rel.astype(np.float64))
    scale = 1e-9 if len(steps) and np.nanmedian(np.abs(steps)) > 1e3 else 1.0
    return rel.astype(np.float64) * scale


def task_text(task_info: object, episode: str) -> str | None:
    """``"task_name: action 1; action 2"`` of ``episode`` in a ``task_{task}.json`` list."""
    if not isinstance(task_info, list):
        return None
    for entry in task_info:
        if isinstance(entry, dict) and str(entry.get("episode_id")) == episode:
            name = str(entry.get("task_name") or "").strip()
            actions = (entry.get("label_info") or {}).get("action_config") or []
            steps = [str(a.get("action_text", "")).strip() for a in actions if isinstance(a, dict)]
            steps = [s for s in steps if s]
            text = f"{name}: {'; '.join(steps)}" if name and steps else name or "; ".join(steps)
            return text or None
    return None


def read_agibot_episode(
    proprio: Path,
    camera: str = DEFAULT_CAMERA,
    camera_axes: str = "opencv",
    geometry: GripperGeometry | None = None,
    arm: ArmModel | None = None,
) -> Clip:
    """Read one AgiBot World episode (given by its ``proprio_stats.h5``) into a clip.

    See the module docstring for the layout and conventions; raises :class:`ClipRejected`
    naming the episode for every problem.
    """
    if camera_axes not in CAM_FROM_OURS:
        raise ValueError(f"camera_axes must be one of {sorted(CAM_FROM_OURS)}, got {camera_axes!r}")
    paths = paths_of(proprio, camera)
    geometry = geometry or gripper_geometry(DEFAULT_ROBOT)
    if not paths.proprio.is_file():
        raise ClipRejected(f"agibot episode {paths.name}: {paths.proprio} is missing")
    if not paths.video.is_file():
        raise ClipRejected(f"agibot episode {paths.name}: video {paths.video} is missing")
    data = _read_proprio(paths)
    intrinsics = _intrinsics(paths)
    world_from_cam = _extrinsics(paths, camera_axes)
    try:
        frames, _ = read_video_file(paths.video)
        fps = probe_video_file(paths.video).fps
    except MediaError as exc:
        raise ClipRejected(f"agibot episode {paths.name}: {exc}") from exc
    t = len(frames)
    if len(world_from_cam) == 1:  # a fixed camera
        world_from_cam = np.repeat(world_from_cam, t, axis=0)
    seconds = _seconds(np.asarray(data["timestamp"]))
    info = _load_json(paths.task_info, "task info", paths.name) if paths.task_info.is_file() else []
    episode = RobotEpisode(
        name=paths.name,
        source="agibot",
        uri=str(paths.proprio),
        frames=frames,
        fps=float(fps),
        timestamps=seconds,
        intrinsics=intrinsics,
        world_from_cam=world_from_cam,
        world_from_ee=pose_from_xyz_quat(
            data["state/end/position"], data["state/end/orientation"], "xyzw"
        ),  # (T, 2, 4, 4)
        gripper_state=np.asarray(data["state/effector/position"], dtype=np.float64),
        hands=ARM_HANDS,
        text=task_text(info, paths.episode),
        joint_positions=data.get(JOINT_KEY),
    )
    return episode_clip(episode, geometry, arm)
