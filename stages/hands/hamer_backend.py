"""Backend ``hamer``: import HaMeR's per-frame outputs (3D keypoints and camera translation).

HaMeR (Pavlakos et al. 2024) is not run here; users who have it run its demo on the clip's frames
(as stored in the clips shard, e.g. exported with ``egosim`` or decoded from the row) and save one
``<clip_id>.npz`` per clip with, for ``N`` hand detections:

- ``frame_index (N,)`` int: the clip frame of each detection;
- ``is_right (N,)``: HaMeR's ``right`` flag (1 = right hand);
- ``keypoints_3d (N, 21, 3)``: ``pred_keypoints_3d`` in metres, OpenPose/MANO joint order, as
  HaMeR outputs it for its (right-hand, possibly flipped) model: the x coordinate of left hands
  is mirrored here, as HaMeR's demo does (``x * (2 * is_right - 1)``);
- ``cam_t (N, 3)``: ``pred_cam_t_full``, the translation in the full image's camera (OpenCV axes)
  under HaMeR's assumed pinhole;
- ``focal_length`` (scalar): HaMeR's ``scaled_focal_length`` in pixels of that image;
- optional ``image_size (2,)`` ``(width, height)`` of the images HaMeR saw (default: the clip's
  size), and ``score (N,)`` in [0, 1] (default 1).

HaMeR's camera is a guess (a fixed focal, centred principal point), so its absolute depth is not
trusted: the keypoints are projected with HaMeR's camera to pixels, then lifted again with the
clip's intrinsics by the same fit as the ``mediapipe`` backend
(:func:`~egosim.stages.hands.mediapipe_backend.lift_to_camera`), at the depth observed under
the hand when the clip has depth.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from egosim.pipeline.geometry import project_points, transform_points
from egosim.pipeline.records import LEFT, NUM_HAND_JOINTS, RIGHT, Clip
from egosim.stages.hands.filters import Detections
from egosim.stages.hands.mediapipe_backend import depth_under, lift_to_camera

HAMER_KEYS = ("frame_index", "is_right", "keypoints_3d", "cam_t", "focal_length")


class HamerFileError(ValueError):
    """A HaMeR output file is missing, unreadable or inconsistent; the message names it."""


def read_hamer_file(path: Path, num_frames: int) -> dict[str, np.ndarray]:
    """Load and check one HaMeR ``.npz`` (layout in the module docstring)."""
    path = Path(path)
    if not path.is_file():
        raise HamerFileError(f"{path}: HaMeR output file does not exist")
    try:
        with np.load(path, allow_pickle=False) as f:
            data = {k: np.asarray(f[k]) for k in f.files}
    except (OSError, ValueError) as exc:
        raise HamerFileError(f"{path}: cannot read HaMeR output: {exc}") from exc
    problems = [f"missing array {k!r}" for k in HAMER_KEYS if k not in data]
    if problems:
        raise HamerFileError(f"{path}: " + "; ".join(problems))
    n = len(data["frame_index"])
    shapes = {
        "is_right": (n,),
        "keypoints_3d": (n, NUM_HAND_JOINTS, 3),
        "cam_t": (n, 3),
        "score": (n,),
        "image_size": (2,),
    }
    for key, shape in shapes.items():
        if key in data and data[key].shape != shape:
            problems.append(f"{key} shape {data[key].shape} != {shape}")
    idx = data["frame_index"]
    if n and (idx.min() < 0 or idx.max() >= num_frames):
        problems.append(f"frame_index outside [0, {num_frames}): {idx.min()}..{idx.max()}")
    if data["focal_length"].size != 1 or not float(data["focal_length"]) > 0:
        problems.append(f"focal_length must be one positive value, got {data['focal_length']}")
    if problems:
        raise HamerFileError(f"{path}: " + "; ".join(problems))
    return data


def hamer_detections(clip: Clip, path: Path) -> Detections:
    """Detections (``K`` = most hands HaMeR found in one frame) of ``clip`` from its HaMeR file.

    Joints are in world metres through the clip's ``world_from_cam`` (camera metres if None).
    """
    data = read_hamer_file(path, clip.num_frames)
    t = clip.num_frames
    idx = data["frame_index"].astype(int)  # (N,)
    counts = np.bincount(idx, minlength=t) if len(idx) else np.zeros(t, int)
    k_max = max(1, int(counts.max()))
    joints = np.zeros((t, k_max, NUM_HAND_JOINTS, 3))
    side = np.zeros((t, k_max), dtype=int)
    conf = np.zeros((t, k_max, NUM_HAND_JOINTS))
    present = np.zeros((t, k_max), dtype=bool)
    w_h, h_h = data.get("image_size", (clip.width, clip.height))
    focal = float(data["focal_length"])
    hamer_k = np.array([focal, focal, w_h / 2.0, h_h / 2.0])
    to_clip = np.array([clip.width / w_h, clip.height / h_h])  # pixel scale HaMeR -> clip
    scores = data.get("score", np.ones(len(idx)))
    slot = np.zeros(t, dtype=int)
    for n, f in enumerate(idx):
        right = bool(data["is_right"][n])
        shape = data["keypoints_3d"][n].astype(np.float64).copy()  # (21, 3)
        shape[:, 0] *= 1.0 if right else -1.0
        uv, z = project_points(shape + data["cam_t"][n], hamer_k)  # (21, 2)
        if not np.all(z > 0):
            continue  # HaMeR put the hand behind its camera: unusable
        uv = uv * to_clip
        observed = depth_under(clip.depth[f], uv) if clip.depth is not None else None
        # HaMeR's keypoints are already in the camera's axes: place them by translation only.
        points_cam = lift_to_camera(
            uv, shape - shape.mean(axis=0), clip.intrinsics, observed, method="translation"
        )
        k = slot[f]
        slot[f] += 1
        joints[f, k] = (
            points_cam
            if clip.world_from_cam is None
            else transform_points(clip.world_from_cam[f], points_cam)
        )
        side[f, k] = RIGHT if right else LEFT
        conf[f, k] = float(np.clip(scores[n], 0.0, 1.0))
        present[f, k] = True
    return Detections(joints=joints, side=side, confidence=conf, present=present)
