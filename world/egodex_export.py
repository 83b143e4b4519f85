"""Write a :class:`~egosim.pipeline.records.Clip` as an EgoDex episode (``<stem>.hdf5`` + ``.mp4``).

The layout and the joint and camera conventions are :mod:`egosim.pipeline.egodex_format`'s, the
ones the ingest stage's EgoDex reader uses: both directions share its constants. What the export
fills, and how:

- ``camera/intrinsic`` from the clip's intrinsics; ``transforms/camera`` from ``world_from_cam``.
- ``transforms/<side><joint>`` for the 25 ARKit joints of each hand: translation = joint position,
  rotation = identity (we carry no joint orientations). The four finger metacarpals, which we do
  not track, sit :data:`METACARPAL_FRACTION` of the way from the wrist to their knuckle.
- ``confidences/<joint>`` from ``hand_confidence`` (1 where absent); metacarpals get 1 (0 where
  the hand is not valid).
- A hand that is not valid in a frame keeps finite positions, as EgoDex does for untracked hands:
  the nearest valid frame's joints (zeros for a hand never valid), with every confidence 0.
- Attributes: ``llm_description`` (clip text), ``task`` and ``session_name`` (clip id).
  Upper-body joints (``hip``, ``spine*``, ``neck*``, shoulders, arms, forearms) are not written:
  a synthetic clip has no body to report.
- The video is H.264 at the clip's own size and fps (EgoDex itself is 1920x1080 at 30 fps).
"""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np

from egosim.pipeline.egodex_format import (
    EGODEX_HAND_JOINTS,
    EGODEX_METACARPALS,
    EGODEX_SIDES,
    ours_to_egodex_camera,
)
from egosim.pipeline.media import write_video_file
from egosim.pipeline.records import Clip, ClipValueError

METACARPAL_FRACTION = 0.3  # metacarpal joint position on the wrist -> knuckle segment
EGODEX_DTYPE = np.float32  # dtype of transforms, confidences and intrinsics in EgoDex files


def _hold_invalid(joints: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Replace each hand's invalid frames ``(T, 21, 3)`` by its nearest valid frame (or zeros)."""
    out = np.zeros_like(joints)
    for hand in range(joints.shape[1]):
        good = np.flatnonzero(valid[:, hand])
        if good.size == 0:
            continue
        t = np.arange(len(joints))
        nearest = good[np.abs(t[:, None] - good[None, :]).argmin(axis=1)]  # (T,)
        out[:, hand] = joints[nearest, hand]
    return out


def _poses(positions: np.ndarray) -> np.ndarray:
    """``(T, 3)`` positions -> ``(T, 4, 4)`` transforms with identity rotation."""
    out = np.tile(np.eye(4), (len(positions), 1, 1))
    out[:, :3, 3] = positions
    return out.astype(EGODEX_DTYPE)


def write_egodex(
    clip: Clip, out_dir: Path, stem: str | None = None, task: str | None = None
) -> tuple[Path, Path]:
    """Write ``clip`` as ``out_dir/<stem>.hdf5`` and ``out_dir/<stem>.mp4`` in EgoDex's layout.

    The clip needs ``world_from_cam`` and ``hand_joints``; ``hand_valid`` and
    ``hand_confidence`` default to all-valid and 1. ``stem`` defaults to the clip id and ``task``
    (a file attribute; EgoDex names the task folder after it) to ``out_dir``'s name.
    Returns ``(hdf5_path, mp4_path)``. Raises :class:`ClipValueError` for an inconsistent clip.
    """
    clip.check()
    missing = [n for n in ("world_from_cam", "hand_joints") if getattr(clip, n) is None]
    if missing:
        raise ClipValueError(f"clip {clip.clip_id!r}: EgoDex export needs {', '.join(missing)}")
    t = clip.num_frames
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    stem = stem or clip.clip_id
    hdf5_path, mp4_path = out_dir / f"{stem}.hdf5", out_dir / f"{stem}.mp4"

    valid = np.ones((t, 2), bool) if clip.hand_valid is None else np.asarray(clip.hand_valid, bool)
    valid = valid & np.isfinite(clip.hand_joints).all(axis=(2, 3))  # (T, 2)
    joints = _hold_invalid(np.asarray(clip.hand_joints, np.float64), valid)  # (T, 2, 21, 3)
    conf = np.ones(joints.shape[:3]) if clip.hand_confidence is None else clip.hand_confidence
    conf = np.where(valid[:, :, None], np.nan_to_num(np.asarray(conf, np.float64)), 0.0)
    fx, fy, cx, cy = np.asarray(clip.intrinsics, dtype=np.float64)

    with h5py.File(hdf5_path, "w") as f:
        k = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
        f.create_dataset("camera/intrinsic", data=k.astype(EGODEX_DTYPE))
        camera = ours_to_egodex_camera(clip.world_from_cam)  # (T, 4, 4)
        f.create_dataset("transforms/camera", data=camera.astype(EGODEX_DTYPE))
        for name, (hand, joint) in EGODEX_HAND_JOINTS.items():
            f.create_dataset(f"transforms/{name}", data=_poses(joints[:, hand, joint]))
            f.create_dataset(f"confidences/{name}", data=conf[:, hand, joint].astype(EGODEX_DTYPE))
        for hand, side in enumerate(EGODEX_SIDES):
            wrist = joints[:, hand, 0]  # (T, 3)
            for suffix, knuckle in EGODEX_METACARPALS.items():
                between = wrist + METACARPAL_FRACTION * (joints[:, hand, knuckle] - wrist)
                f.create_dataset(f"transforms/{side}{suffix}", data=_poses(between))
                mc_conf = np.where(valid[:, hand], 1.0, 0.0).astype(EGODEX_DTYPE)  # (T,)
                f.create_dataset(f"confidences/{side}{suffix}", data=mc_conf)
        if clip.text:
            f.attrs["llm_description"] = clip.text
        f.attrs["task"] = task or out_dir.name
        f.attrs["session_name"] = clip.clip_id

    write_video_file(mp4_path, clip.frames, clip.fps)
    return hdf5_path, mp4_path
