"""Accuracy of detected hands against ground-truth joints (synthetic world, labelled data sets).

All comparisons are per side (slot 0 = left, 1 = right) in the *camera* frame:

- **recall**: hand-frames with a true hand in view (at least ``min_visible_joints`` joints project
  inside the image) that the method reports for the same side;
- **3D coverage**: of the same true hand-frames, those reported with a 3D hand the method
  trusts (a backend may keep a hand's 2D but withhold its 3D: ``lifted``); the 3D figures below
  are over these, so withholding hands lowers them only with this share printed beside them;
- **2D error**: mean pixel distance between the method's 2D landmarks and the projected true
  joints (``2d_offset_u``/``v``: its signed mean, a systematic shift shows there);
- **orientation error**: angle of the rotation that best aligns the method's wrist-relative joints
  with the true ones (Kabsch over all 21 joints), degrees;
- **wrist-relative MPJPE**: mean joint distance after subtracting each hand's wrist, millimetres
  (no rotation alignment: a wrong orientation counts in full);
- **depth ratio**: the method's median joint depth over the true one (1 = the hand sits at the
  right distance; what places a hand on the surface it touches);
- **aligned MPJPE**: mean joint distance after the rotation and translation that best align the
  method's joints with the true ones (Procrustes without scale), millimetres: the error of the
  hand's shape alone, which orientation adds to in the wrist-relative MPJPE.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from egosim.pipeline.geometry import invert_se3, project_points, transform_points
from egosim.stages.common.hand_lift import best_rotation

WRIST = 0  # joint index of the wrist
JOINTS = 21  # joints per hand (MediaPipe / MANO order: wrist, then thumb, index, ... 4 each)
JOINT_NAMES = (
    "wrist",
    *(
        f"{finger}{k}"
        for finger in ("thumb", "index", "middle", "ring", "pinky")
        for k in (1, 2, 3, 4)
    ),
)  # 1 = the finger's base joint (CMC / MCP), 4 = its tip


def orientation_error_deg(pred: np.ndarray, truth: np.ndarray) -> float:
    """Angle (degrees) of the best rotation from ``pred (21, 3)`` onto ``truth (21, 3)``."""
    rot = best_rotation(pred, truth)
    return float(np.degrees(np.arccos(np.clip((np.trace(rot) - 1.0) / 2.0, -1.0, 1.0))))


def aligned_mpjpe_mm(pred: np.ndarray, truth: np.ndarray) -> float:
    """Mean joint distance (mm) of ``pred (21, 3)`` and ``truth (21, 3)`` metres after the best
    rotation and translation of ``pred`` onto ``truth`` (Kabsch about the centroids)."""
    rot = best_rotation(pred, truth)  # (3, 3)
    moved = (pred - pred.mean(axis=0)) @ rot.T + truth.mean(axis=0)  # (21, 3)
    return float(1000.0 * np.linalg.norm(moved - truth, axis=1).mean())


def wrist_relative_errors_mm(pred: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """``(21,)`` each joint's distance (mm) of ``pred (21, 3)`` and ``truth (21, 3)`` metres,
    wrists aligned."""
    return 1000.0 * np.linalg.norm((pred - pred[WRIST]) - (truth - truth[WRIST]), axis=1)


def wrist_relative_mpjpe_mm(pred: np.ndarray, truth: np.ndarray) -> float:
    """Mean joint distance (mm) of ``pred (21, 3)`` and ``truth (21, 3)`` metres, wrists aligned."""
    return float(wrist_relative_errors_mm(pred, truth).mean())


@dataclass
class HandAccuracy:
    """Figures of one clip (or several, see :func:`combine`); NaN where nothing was compared."""

    visible: int  # true hand-frames in view
    found: int  # of those, reported for the same side
    wrong_side: int  # true hand-frames reported only on the other side
    false_positive: int  # reported hand-frames with no true hand of that side near them
    error_2d_px: list[float]  # per found hand-frame: mean joint pixel error
    offset_2d_px: list[np.ndarray]  # per found hand-frame: signed mean (du, dv) pixel offset
    orientation_deg: list[float]  # per found hand-frame
    mpjpe_mm: list[float]  # per found hand-frame, wrist-relative
    depth_ratio: list[float] = field(default_factory=list)  # per found hand-frame: median
    # joint depth / true median joint depth
    aligned_mpjpe_mm: list[float] = field(default_factory=list)  # per found hand-frame,
    # after the best rotation and translation
    joint_error_mm: list[np.ndarray] = field(default_factory=list)  # per found hand-frame:
    # (21,) each joint's wrist-relative distance (the terms of ``mpjpe_mm``)
    joint_error_2d_px: list[np.ndarray] = field(default_factory=list)  # per found hand-frame
    # with 3D: (21,) each joint's pixel distance (beside ``joint_error_mm``)
    found_3d: int = 0  # of ``found``, those with a trusted 3D hand (the 3D lists' length)

    def per_joint(self) -> np.ndarray:
        """``(21, 2)``: each joint's mean wrist-relative error (mm) and mean 2D error (px) over
        the found hand-frames with 3D (NaN when none): which joints carry the MPJPE."""
        if not self.joint_error_mm:
            return np.full((JOINTS, 2), np.nan)
        return np.stack(
            [np.mean(self.joint_error_mm, axis=0), np.mean(self.joint_error_2d_px, axis=0)], axis=1
        )

    def summary(self) -> dict[str, float]:
        """Scalar figures: recall, mean 2D error and offset, orientation error, MPJPE."""

        def mean(values: list) -> float:
            return float(np.mean(values)) if values else float("nan")

        offset = np.mean(self.offset_2d_px, axis=0) if self.offset_2d_px else np.full(2, np.nan)
        return {
            "visible": float(self.visible),
            "recall": self.found / self.visible if self.visible else float("nan"),
            "coverage_3d": self.found_3d / self.visible if self.visible else float("nan"),
            "wrong_side": float(self.wrong_side),
            "false_positive": float(self.false_positive),
            "error_2d_px": mean(self.error_2d_px),
            "offset_2d_u_px": float(offset[0]),
            "offset_2d_v_px": float(offset[1]),
            "orientation_deg": mean(self.orientation_deg),
            "orientation_median_deg": float(np.median(self.orientation_deg))
            if self.orientation_deg
            else float("nan"),
            "mpjpe_mm": mean(self.mpjpe_mm),
            "aligned_mpjpe_mm": mean(self.aligned_mpjpe_mm),
            "depth_ratio_median": float(np.median(self.depth_ratio))
            if self.depth_ratio
            else float("nan"),
        }


def combine(parts: list[HandAccuracy]) -> HandAccuracy:
    """Pool the hand-frames of several clips."""
    out = HandAccuracy(0, 0, 0, 0, [], [], [], [])
    for p in parts:
        out.visible += p.visible
        out.found += p.found
        out.wrong_side += p.wrong_side
        out.false_positive += p.false_positive
        out.error_2d_px += p.error_2d_px
        out.offset_2d_px += p.offset_2d_px
        out.orientation_deg += p.orientation_deg
        out.mpjpe_mm += p.mpjpe_mm
        out.depth_ratio += p.depth_ratio
        out.aligned_mpjpe_mm += p.aligned_mpjpe_mm
        out.joint_error_mm += p.joint_error_mm
        out.joint_error_2d_px += p.joint_error_2d_px
        out.found_3d += p.found_3d
    return out


def true_hands_in_view(
    truth_world: np.ndarray,
    truth_valid: np.ndarray,
    world_from_cam: np.ndarray,
    intrinsics: np.ndarray,
    size: tuple[int, int],
    min_visible_joints: int = 11,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The true hands in the camera: ``(joints (T, 2, 21, 3) camera frame, uv (T, 2, 21, 2),
    in_view (T, 2))``. A hand of ``truth_valid (T, 2)`` is in view when ``min_visible_joints`` of
    its ``truth_world (T, 2, 21, 3)`` joints project inside the ``(width, height)`` image in front
    of the camera (``world_from_cam (T, 4, 4)``, ``intrinsics (4,)``)."""
    t = truth_world.shape[0]
    w, h = size
    cam_from_world = invert_se3(world_from_cam)  # (T, 4, 4)
    truth_cam = np.stack([transform_points(cam_from_world[f], truth_world[f]) for f in range(t)])
    truth_uv, depth = project_points(truth_cam, intrinsics)  # (T, 2, 21, 2), (T, 2, 21)
    inside = (
        (depth > 0)
        & (truth_uv[..., 0] >= 0)
        & (truth_uv[..., 0] < w)
        & (truth_uv[..., 1] >= 0)
        & (truth_uv[..., 1] < h)
    )  # (T, 2, 21)
    in_view = truth_valid & (inside.sum(axis=2) >= min_visible_joints)  # (T, 2)
    return truth_cam, truth_uv, in_view


def hand_accuracy(
    joints_cam: np.ndarray,
    uv: np.ndarray,
    valid: np.ndarray,
    truth_world: np.ndarray,
    truth_valid: np.ndarray,
    world_from_cam: np.ndarray,
    intrinsics: np.ndarray,
    size: tuple[int, int],
    min_visible_joints: int = 11,
    max_centroid_fraction: float = 0.5,
    lifted: np.ndarray | None = None,
) -> HandAccuracy:
    """Compare a method's hands with the truth, per side and frame.

    ``joints_cam (T, 2, 21, 3)`` the method's camera-frame joints, ``uv (T, 2, 21, 2)`` its 2D
    landmarks, ``valid (T, 2)``; ``truth_world (T, 2, 21, 3)`` true world joints,
    ``truth_valid (T, 2)``, ``world_from_cam (T, 4, 4)``, ``intrinsics (4,)``, image ``size``
    ``(width, height)``. A true hand is in view when ``min_visible_joints`` of its joints project
    inside the image in front of the camera. A reported hand whose 2D centroid is further than
    ``max_centroid_fraction`` of the true hand's 2D size from the true centroid is a false
    positive, not a find. ``lifted (T, 2)``: the valid hands whose 3D the method trusts (None:
    all); a found hand without it counts in the recall and the 2D error, not in the 3D figures
    (orientation, MPJPE, depth ratio, per-joint errors) and not in ``found_3d``.
    """
    truth_cam, truth_uv, in_view = true_hands_in_view(
        truth_world, truth_valid, world_from_cam, intrinsics, size, min_visible_joints
    )
    acc = HandAccuracy(int(in_view.sum()), 0, 0, 0, [], [], [], [])
    acc.false_positive = int((valid & ~in_view).sum())
    for f, s in zip(*np.nonzero(in_view), strict=True):
        if not valid[f, s]:
            acc.wrong_side += int(valid[f, 1 - s] and not in_view[f, 1 - s])
            continue
        diff = uv[f, s] - truth_uv[f, s]  # (21, 2)
        true_size = float(np.linalg.norm(np.ptp(truth_uv[f, s], axis=0)))
        if np.linalg.norm(diff.mean(axis=0)) > max_centroid_fraction * true_size:
            acc.false_positive += 1
            continue
        acc.found += 1
        error_2d = np.linalg.norm(diff, axis=1)  # (21,) px
        acc.error_2d_px.append(float(error_2d.mean()))
        acc.offset_2d_px.append(diff.mean(axis=0))
        if lifted is not None and not lifted[f, s]:
            continue
        acc.found_3d += 1
        acc.joint_error_2d_px.append(error_2d)
        error_3d = wrist_relative_errors_mm(joints_cam[f, s], truth_cam[f, s])  # (21,)
        acc.joint_error_mm.append(error_3d)
        acc.orientation_deg.append(orientation_error_deg(joints_cam[f, s], truth_cam[f, s]))
        acc.mpjpe_mm.append(float(error_3d.mean()))
        acc.aligned_mpjpe_mm.append(aligned_mpjpe_mm(joints_cam[f, s], truth_cam[f, s]))
        acc.depth_ratio.append(
            float(np.median(joints_cam[f, s, :, 2]) / np.median(truth_cam[f, s, :, 2]))
        )
    return acc
