"""EgoDex episodes (``N.hdf5`` + ``N.mp4``) read into a :class:`~egosim.pipeline.records.Clip`.

The file layout, the ARKit joint map and the camera axes are described once in
:mod:`egosim.pipeline.egodex_format` (the synthetic world's EgoDex writer shares them).
:func:`read_egodex_clips` (what ingest runs: the episode cut into standard clips while its video
streams) and :func:`read_egodex_clip` (the whole episode as one clip, its reference) read the
same checked labels, and check the camera convention on every file (hands must lie in front of
the camera).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np

from egosim.pipeline.egodex_format import EGODEX_HAND_JOINTS, egodex_camera_to_ours
from egosim.pipeline.geometry import invert_se3, transform_points
from egosim.pipeline.media import MediaError, iter_video_file, probe_video_file, read_video_file
from egosim.pipeline.records import NUM_HAND_JOINTS, Clip
from egosim.pipeline.stage import ClipRejected
from egosim.stages.common.frame_plan import plan_resize
from egosim.stages.ingest.crop_anchor import choose_anchor, sample_video
from egosim.stages.ingest.standardise import resample_windows
from egosim.stages.ingest.video_source import ClipFormat, window_policy

MIN_IN_FRONT_FRACTION = 0.5  # below this share of valid joints at z > 0 the convention is wrong


def _attr_text(value: object) -> str | None:
    """A string file attribute as ``str`` (h5py may give bytes or a numpy scalar)."""
    if isinstance(value, bytes):
        value = value.decode("utf-8", errors="replace")
    text = str(value).strip() if value is not None else ""
    return text if text and text != "None" else None


def _read_hdf5(path: Path) -> tuple[dict[str, np.ndarray], int, str | None]:
    """Every array the clip needs from one EgoDex hdf5 file, checked for presence and shape.

    Returns ``(arrays by dataset key as float64, frame count T, llm_description or None)``.
    """
    names = list(EGODEX_HAND_JOINTS)
    keys = ["camera/intrinsic", "transforms/camera"]
    keys += [f"transforms/{n}" for n in names] + [f"confidences/{n}" for n in names]
    try:
        with h5py.File(path, "r") as f:
            missing = [k for k in keys if k not in f]
            if missing:
                shown = ", ".join(repr(k) for k in missing[:8])
                more = f" and {len(missing) - 8} more" if len(missing) > 8 else ""
                raise ClipRejected(f"{path}: missing dataset(s) {shown}{more}")
            data = {k: np.asarray(f[k][()], dtype=np.float64) for k in keys}
            text = _attr_text(f.attrs.get("llm_description"))
    except ClipRejected:
        raise
    except (OSError, KeyError, ValueError, TypeError) as exc:
        raise ClipRejected(f"{path}: cannot read EgoDex hdf5 file: {exc}") from exc
    t = data["transforms/camera"].shape[0]
    problems = []
    if data["camera/intrinsic"].shape != (3, 3):
        problems.append(f"'camera/intrinsic' shape {data['camera/intrinsic'].shape} != (3, 3)")
    for key in keys[1:]:
        shape = (t, 4, 4) if key.startswith("transforms/") else (t,)
        if data[key].shape != shape:
            problems.append(f"{key!r} shape {data[key].shape} != {shape}")
    if t == 0:
        problems.append("'transforms/camera' holds no frames")
    if problems:
        raise ClipRejected(f"{path}: " + "; ".join(problems))
    return data, t, text


def _sibling_video(hdf5_path: Path) -> Path:
    """The episode's ``.mp4`` next to ``hdf5_path``; rejects either file missing."""
    if not hdf5_path.is_file():
        raise ClipRejected(f"{hdf5_path}: EgoDex hdf5 file does not exist")
    mp4_path = hdf5_path.with_suffix(".mp4")
    if not mp4_path.is_file():
        raise ClipRejected(f"{hdf5_path}: sibling video {mp4_path.name} is missing")
    return mp4_path


def _camera_poses(hdf5_path: Path, cam: np.ndarray) -> np.ndarray:
    """``world_from_cam (T, 4, 4)`` in our axes from EgoDex's ``cam`` (world_from_egodex_cam).

    Rejects the clip when a frame's camera transform is not finite.
    """
    bad = np.flatnonzero(~np.isfinite(cam).all(axis=(1, 2)))
    if bad.size:
        raise ClipRejected(
            f"{hdf5_path}: 'transforms/camera' is not finite in {bad.size} of {len(cam)} frames "
            f"(first {bad[:5].tolist()})"
        )
    return egodex_camera_to_ours(cam)


def _hands(
    data: dict[str, np.ndarray], t: int, min_wrist_confidence: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Joints ``(T, 2, 21, 3)``, confidences ``(T, 2, 21)`` and validity ``(T, 2)`` of both hands.

    Non-finite positions and confidences become 0 (after validity is decided).
    """
    joints = np.zeros((t, 2, NUM_HAND_JOINTS, 3))
    confidence = np.zeros((t, 2, NUM_HAND_JOINTS))
    for name, (hand, joint) in EGODEX_HAND_JOINTS.items():
        joints[:, hand, joint] = data[f"transforms/{name}"][:, :3, 3]  # (T, 3)
        confidence[:, hand, joint] = data[f"confidences/{name}"]
    finite = np.isfinite(joints).all(axis=(2, 3))  # (T, 2)
    wrist_conf = confidence[:, :, 0]  # (T, 2)
    valid = finite & np.isfinite(wrist_conf) & (wrist_conf > min_wrist_confidence)
    joints = np.where(np.isfinite(joints), joints, 0.0)
    confidence = np.where(np.isfinite(confidence), confidence, 0.0)
    return joints, confidence, valid


def _check_hands_in_front(
    hdf5_path: Path, world_from_cam: np.ndarray, joints: np.ndarray, valid: np.ndarray
) -> None:
    """Reject a clip whose valid hand joints lie mostly behind the camera (wrong convention)."""
    if not valid.any():
        return
    cam_from_world = invert_se3(world_from_cam)  # (T, 4, 4)
    z = np.concatenate(
        [
            transform_points(cam_from_world[i], joints[i][valid[i]])[..., 2]
            for i in range(len(joints))
        ]
    )  # (N * 21,) depth of every valid joint
    in_front = float(np.mean(z > 0))
    if in_front < MIN_IN_FRONT_FRACTION:
        raise ClipRejected(
            f"{hdf5_path}: only {in_front:.0%} of valid hand joints are in front of the "
            "camera; the camera convention looks wrong (expected camera-to-world with "
            "x right, y down, z forward)"
        )


def _read_frames(hdf5_path: Path, mp4_path: Path, t: int) -> tuple[np.ndarray, float]:
    """The video's frames ``(T, H, W, 3)`` and fps; rejects a frame count other than ``t``."""
    try:
        frames, _ = read_video_file(mp4_path)
        fps = probe_video_file(mp4_path).fps
    except MediaError as exc:
        raise ClipRejected(f"{hdf5_path}: {exc}") from exc
    if len(frames) != t:
        raise _count_mismatch(hdf5_path, mp4_path, t, len(frames))
    return frames, fps


def read_egodex_clip(
    hdf5_path: Path, clip_id: str | None = None, min_wrist_confidence: float = 0.0
) -> Clip:
    """Read one EgoDex episode (``hdf5_path`` and the sibling ``.mp4``) into a :class:`Clip`.

    Hands: 21 joints each via :data:`EGODEX_HAND_JOINTS` (finger metacarpals dropped), positions
    from the transforms' translations. A hand is valid in a frame where its wrist confidence is
    finite and above ``min_wrist_confidence`` and all its 21 positions are finite; non-finite
    positions and confidences become 0. Real EgoDex marks untracked joints with a floor near 0.003,
    so pass ~0.1 to drop them. ``clip_id`` defaults to ``<task folder>_<stem>``.

    Raises :class:`ClipRejected` naming the file for a missing or unreadable file, a missing
    dataset, a non-finite camera pose, an hdf5/mp4 frame-count mismatch, or hands that lie mostly
    behind the camera (a camera-convention error).
    """
    episode = _read_episode(Path(hdf5_path), clip_id, min_wrist_confidence)
    frames, fps = _read_frames(episode.hdf5_path, episode.mp4_path, episode.num_frames)
    return episode.clip(frames, fps)


@dataclass(frozen=True)
class _Episode:
    """An EgoDex episode's labels, checked, without its frames."""

    hdf5_path: Path  # the labels
    mp4_path: Path  # the sibling video
    clip_id: str  # the clip id the episode's clips start with
    num_frames: int  # frames of the episode (T)
    intrinsics: np.ndarray  # (4,) fx, fy, cx, cy of the video's frames
    world_from_cam: np.ndarray  # (T, 4, 4) in our camera axes
    joints: np.ndarray  # (T, 2, 21, 3) float32
    valid: np.ndarray  # (T, 2) bool
    confidence: np.ndarray  # (T, 2, 21) float32
    text: str | None  # llm_description

    def clip(self, frames: np.ndarray, fps: float) -> Clip:
        """The whole episode as one clip with ``frames (T, H, W, 3)`` at ``fps``."""
        return Clip(
            clip_id=self.clip_id,
            source="egodex",
            source_uri=str(self.hdf5_path),
            fps=float(fps),
            timestamps=np.arange(self.num_frames, dtype=np.float64) / fps,
            intrinsics=self.intrinsics,
            frames=frames,
            world_from_cam=self.world_from_cam,
            hand_joints=self.joints,
            hand_valid=self.valid,
            hand_confidence=self.confidence,
            text=self.text,
        )


def _read_episode(hdf5_path: Path, clip_id: str | None, min_wrist_confidence: float) -> _Episode:
    """Read and check an episode's labels (see :func:`read_egodex_clip` for the rejections)."""
    mp4_path = _sibling_video(hdf5_path)
    data, t, text = _read_hdf5(hdf5_path)
    world_from_cam = _camera_poses(hdf5_path, data["transforms/camera"])  # (T, 4, 4)
    joints, confidence, valid = _hands(data, t, min_wrist_confidence)
    _check_hands_in_front(hdf5_path, world_from_cam, joints, valid)
    k = data["camera/intrinsic"]
    return _Episode(
        hdf5_path=hdf5_path,
        mp4_path=mp4_path,
        clip_id=clip_id or f"{hdf5_path.parent.name}_{hdf5_path.stem}",
        num_frames=t,
        intrinsics=np.array([k[0, 0], k[1, 1], k[0, 2], k[1, 2]], dtype=np.float64),
        world_from_cam=world_from_cam,
        joints=joints.astype(np.float32),
        valid=valid,
        confidence=confidence.astype(np.float32),
        text=text,
    )


def read_egodex_clips(
    hdf5_path: Path, cfg: ClipFormat, min_wrist_confidence: float = 0.0
) -> Iterator[Clip]:
    """An EgoDex episode cut into standard clips by the clip policy, streaming its video.

    The same clips as ``standardise_clip(read_egodex_clip(hdf5_path), cfg)``, but the video is
    decoded frame by frame and resized as it goes, so memory holds one window of clip-size
    frames, not the whole episode at 1080p (an average 8.8 s EgoDex episode is 1.6 GB of RGB;
    a minute is 11 GB). The video's declared frame count is checked against the labels before
    any clip is made; the decoded count again at the end, when every clip is kept
    (``max_clips_per_source`` 0: a capped run stops decoding early, so its count is not checked).
    """
    episode = _read_episode(Path(hdf5_path), None, min_wrist_confidence)
    t, mp4_path = episode.num_frames, episode.mp4_path
    try:
        info = probe_video_file(mp4_path)
    except MediaError as exc:
        raise ClipRejected(f"{hdf5_path}: {exc}") from exc
    if info.num_frames and info.num_frames != t:
        raise _count_mismatch(hdf5_path, mp4_path, t, info.num_frames)
    sample = sample_video(mp4_path, info)
    anchor = choose_anchor(cfg, info.width, info.height, sample, f"EgoDex episode {hdf5_path}")
    plan = plan_resize(info.width, info.height, cfg.width, cfg.height, anchor)
    policy = window_policy(cfg)
    decoded = 0

    def frames() -> Iterator[tuple[float, np.ndarray]]:
        nonlocal decoded
        for _, image in iter_video_file(mp4_path):
            if decoded >= t:  # more frames than labels: checked after the stream ends
                decoded += 1
                continue
            yield decoded / info.fps, plan.apply(image)
            decoded += 1

    try:
        windows = resample_windows(frames(), policy, info.fps, f"EgoDex episode {hdf5_path}")
        for window in windows:
            idx = window.source_indices  # (T,) indices into the episode
            yield Clip(
                clip_id=f"{episode.clip_id}-w{window.index:03d}",
                source="egodex",
                source_uri=str(hdf5_path),
                fps=window.fps,
                timestamps=window.timestamps,
                intrinsics=plan.intrinsics(episode.intrinsics),
                frames=window.frames,
                world_from_cam=episode.world_from_cam[idx],
                hand_joints=episode.joints[idx],
                hand_valid=episode.valid[idx],
                hand_confidence=episode.confidence[idx],
                text=episode.text,
                source_fps=float(info.fps),
                source_num_frames=t,
                source_frame_indices=idx,
                clip_policy=policy.label(window.kind),
                source_crop=np.array(plan.source_crop),
            ).check()
    except MediaError as exc:
        raise ClipRejected(f"{hdf5_path}: {exc}") from exc
    if decoded != t and not policy.max_windows:
        raise _count_mismatch(hdf5_path, mp4_path, t, decoded)


def _count_mismatch(hdf5_path: Path, mp4_path: Path, t: int, frames: int) -> ClipRejected:
    return ClipRejected(
        f"{hdf5_path}: frame count mismatch: hdf5 has {t} frames, {mp4_path.name} has {frames}"
    )
