"""Typed, decoded clip records: what tests, benchmarks and notebooks work with.

A :class:`Clip` holds one clip with every array decoded (frames as ``uint8`` RGB, depth in metres,
poses as 4x4 matrices). :mod:`egosim.pipeline.clip_io` turns clips into rows of the ``clips``
shard schema and back. Shapes use ``T`` frames, ``H`` x ``W`` pixels and ``N`` objects.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np

NUM_HAND_JOINTS = 21
LEFT, RIGHT = 0, 1


class ClipValueError(ValueError):
    """A clip's arrays disagree with each other (shape, dtype or values); names the clip."""


@dataclass
class Clip:
    """One clip, decoded. Optional fields are ground truth or outputs of later stages."""

    clip_id: str  # unique id of the clip within a dataset
    source: str  # ingest source that produced it: "video", "frames", "synthetic", "egodex", ...
    source_uri: str  # file or recording the clip came from ("" for generated clips)
    fps: float  # frames per second of the stored frames
    timestamps: np.ndarray  # (T,) float64 seconds from the source's start
    intrinsics: np.ndarray  # (4,) float64 fx, fy, cx, cy in pixels of the stored frames
    frames: np.ndarray  # (T, H, W, 3) uint8 RGB
    world_from_cam: np.ndarray | None = None  # (T, 4, 4) float64 camera-to-world, OpenCV axes
    depth: np.ndarray | None = None  # (T, H, W) float32 z-depth in metres, 0 = unknown
    static_frames: np.ndarray | None = None  # (T, H, W, 3) uint8 same camera path, no hands
    static_depth: np.ndarray | None = None  # (T, H, W) float32 depth of the static scene
    first_frame_clean: np.ndarray | None = None  # (H, W, 3) uint8 hand-free first frame
    hand_joints: np.ndarray | None = None  # (T, 2, 21, 3) float32 world metres, 0=left 1=right
    hand_valid: np.ndarray | None = None  # (T, 2) bool hand present in the frame
    hand_confidence: np.ndarray | None = None  # (T, 2, 21) float32 per-joint confidence 0..1
    hand_mask: np.ndarray | None = None  # (T, H, W) uint8 1 = hand or arm pixel
    object_mask: np.ndarray | None = None  # (T, H, W) uint8 object instance id, 0 = none
    object_poses: np.ndarray | None = None  # (T, N, 4, 4) float64 world_from_object
    text: str | None = None  # description of the interaction
    source_fps: float | None = None  # frame rate of the source the clip was cut from
    source_num_frames: int | None = None  # frames in that source (None when unknown)
    source_frame_indices: np.ndarray | None = None  # (T,) int index of each frame in the source
    clip_policy: str | None = None  # what ingest's clip policy did: "full|short|tail[:preset]"
    gripper_opening: np.ndarray | None = None  # (T, 2) float32 metres per hand slot, NaN = none
    embodiment_mask: np.ndarray | None = None  # (T, H, W) uint8 1 = robot arm (URDF + joints)

    @property
    def num_frames(self) -> int:
        """Number of frames ``T``."""
        return int(self.frames.shape[0])

    @property
    def height(self) -> int:
        """Frame height ``H`` in pixels."""
        return int(self.frames.shape[1])

    @property
    def width(self) -> int:
        """Frame width ``W`` in pixels."""
        return int(self.frames.shape[2])

    def problems(self) -> list[str]:
        """Every inconsistency between the clip's arrays, as readable sentences."""
        out: list[str] = []
        f = self.frames
        if f.ndim != 4 or f.shape[-1] != 3 or f.dtype != np.uint8:
            return [f"frames must be (T, H, W, 3) uint8, got {f.shape} {f.dtype}"]
        t, h, w = f.shape[:3]
        if t == 0:
            out.append("clip has no frames")
        if not (np.isfinite(self.fps) and self.fps > 0):
            out.append(f"fps must be positive, got {self.fps}")
        ts = np.asarray(self.timestamps)
        if ts.shape != (t,):
            out.append(f"timestamps shape {ts.shape} != ({t},)")
        elif t > 1 and not np.all(np.diff(ts) > 0):
            out.append("timestamps are not strictly increasing")
        k = np.asarray(self.intrinsics, dtype=np.float64)
        if k.shape != (4,) or not np.all(np.isfinite(k)) or k[0] <= 0 or k[1] <= 0:
            out.append(f"intrinsics must be 4 finite values with fx, fy > 0, got {k.tolist()}")
        expected = {
            "world_from_cam": (t, 4, 4),
            "depth": (t, h, w),
            "static_frames": (t, h, w, 3),
            "static_depth": (t, h, w),
            "first_frame_clean": (h, w, 3),
            "hand_joints": (t, 2, NUM_HAND_JOINTS, 3),
            "hand_valid": (t, 2),
            "hand_confidence": (t, 2, NUM_HAND_JOINTS),
            "gripper_opening": (t, 2),
            "hand_mask": (t, h, w),
            "embodiment_mask": (t, h, w),
            "object_mask": (t, h, w),
        }
        for name, shape in expected.items():
            value = getattr(self, name)
            if value is not None and tuple(value.shape) != shape:
                out.append(f"{name} shape {tuple(value.shape)} != {shape}")
        if self.source_frame_indices is not None:
            idx = np.asarray(self.source_frame_indices)
            if idx.shape != (t,) or not np.issubdtype(idx.dtype, np.integer):
                out.append(
                    f"source_frame_indices must be ({t},) integers, got {idx.shape} {idx.dtype}"
                )
            elif t and (idx.min() < 0 or np.any(np.diff(idx) < 0)):
                out.append("source_frame_indices must be >= 0 and non-decreasing")
        if self.source_fps is not None and not (
            np.isfinite(self.source_fps) and self.source_fps > 0
        ):
            out.append(f"source_fps must be positive, got {self.source_fps}")
        if self.object_poses is not None:
            shape = self.object_poses.shape
            if len(shape) != 4 or shape[0] != t or shape[2:] != (4, 4):
                out.append(f"object_poses shape {shape} != ({t}, N, 4, 4)")
        return out

    def check(self) -> Clip:
        """Raise :class:`ClipValueError` naming the clip and every problem; return self if none."""
        problems = self.problems()
        if problems:
            raise ClipValueError(f"clip {self.clip_id!r}: " + "; ".join(problems))
        return self


CLIP_FIELDS = tuple(f.name for f in fields(Clip))
