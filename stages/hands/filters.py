"""Hand detection filters of the paper (Sec. 3.3.3): frame-wise de-duplication, temporal outliers.

De-duplication: in each frame, every detection's 21 joints are projected with the clip's camera
to a 2D box; detections whose boxes overlap with IoU above a threshold are linked, linked
detections are grouped by breadth-first search, each group keeps its most confident detection,
and then each side keeps its most confident survivor.

Temporal outliers: a hand's position is the mean of its joints in *camera* coordinates and its
orientation the palm's frame (wrist, middle, index and pinky knuckles) there; a frame whose
incoming and outgoing speeds (``|p_t - p_{t-1}| * fps`` and ``|p_{t+1} - p_t| * fps``) both
exceed ``max_speed``, or whose incoming and outgoing turns (angle of ``R_{t-1}^T R_t`` times
``fps``) both exceed ``max_angular_speed``, is dropped. (Position alone caught 1 of 10 rotation
spikes on the peer harness: a hand flipped about its centre barely moves its centre.) Frames
without a valid neighbour on both sides are kept (they cannot be tested); a spike lasting two or
more frames is not caught by this test.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, replace

import numpy as np

from egosim.pipeline.geometry import (
    invert_se3,
    project_world_points,
    rotation_angle_deg,
    transform_points,
)


class HandFilterError(ValueError):
    """Filter inputs disagree (shapes, frame counts) or are unusable (NaN poses)."""


@dataclass
class Detections:
    """Up to ``K`` hand detections per frame (padded; ``present`` says which slots hold one)."""

    joints: np.ndarray  # (T, K, 21, 3) float64 world metres
    side: np.ndarray  # (T, K) int 0 = left, 1 = right
    confidence: np.ndarray  # (T, K, 21) float per-joint confidence in [0, 1]
    present: np.ndarray  # (T, K) bool slot holds a detection
    # (T, K, 51 + B) world MANO fit per slot: global_orient (3) and hand_pose (45) rotation
    # vectors, transl (3), betas (B) (:func:`egosim.stages.hands.mano.hand_joints_from_params`);
    # NaN where a slot has none; None: the backend fits no MANO
    mano: np.ndarray | None = None
    # (T, K) bool: the slot's 3D is trusted (the backend lifted it, or interpolated it from lifted
    # neighbours); False: only its 2D is (joints on the landmarks' rays at a guessed depth).
    # None: every detection's 3D is trusted (backends that regress or are given 3D)
    lifted: np.ndarray | None = None

    def check(self, num_frames: int) -> None:
        """Raise :class:`HandFilterError` when the arrays disagree with each other."""
        t, k = self.present.shape
        problems = []
        if t != num_frames:
            problems.append(f"detections cover {t} frames, the clip has {num_frames}")
        if self.joints.shape != (t, k, 21, 3):
            problems.append(f"joints shape {self.joints.shape} != ({t}, {k}, 21, 3)")
        if self.side.shape != (t, k) or self.confidence.shape != (t, k, 21):
            problems.append(f"side {self.side.shape} / confidence {self.confidence.shape} bad")
        if self.mano is not None and (self.mano.ndim != 3 or self.mano.shape[:2] != (t, k)):
            problems.append(f"mano shape {self.mano.shape} != ({t}, {k}, 51 + B)")
        if self.lifted is not None and self.lifted.shape != (t, k):
            problems.append(f"lifted shape {self.lifted.shape} != ({t}, {k})")
        if problems:
            raise HandFilterError("; ".join(problems))


def box_iou(a: np.ndarray, b: np.ndarray) -> float:
    """IoU of two boxes ``(u0, v0, u1, v1)`` in pixels; 0 when either is empty."""
    iw = min(a[2], b[2]) - max(a[0], b[0])
    ih = min(a[3], b[3]) - max(a[1], b[1])
    if iw <= 0 or ih <= 0:
        return 0.0
    inter = iw * ih
    union = (a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter
    return float(inter / union) if union > 0 else 0.0


def joint_boxes(
    joints: np.ndarray, world_from_cam: np.ndarray, intrinsics: np.ndarray
) -> np.ndarray:
    """2D boxes ``(K, 4)`` of ``joints (K, 21, 3)`` world metres seen by one camera.

    A box spans the joints in front of the camera; NaN when fewer than two joints are.
    """
    uv, _ = project_world_points(joints, world_from_cam, intrinsics)  # (K, 21, 2)
    boxes = np.full((len(joints), 4), np.nan)
    for i, pts in enumerate(uv):
        ok = np.all(np.isfinite(pts), axis=1)
        if ok.sum() >= 2:
            boxes[i] = [*pts[ok].min(axis=0), *pts[ok].max(axis=0)]
    return boxes


def deduplicate(
    det: Detections,
    world_from_cam: np.ndarray,
    intrinsics: np.ndarray,
    iou_threshold: float = 0.5,
) -> tuple[Detections, int]:
    """Drop duplicate detections frame by frame; returns ``(kept detections, number dropped)``.

    Groups are the connected components (breadth-first search) of the graph linking detections
    whose projected boxes have IoU > ``iou_threshold``; each group keeps its most confident
    member (mean joint confidence), then each side keeps its most confident survivor.
    """
    present = det.present.copy()
    mean_conf = det.confidence.mean(axis=2)  # (T, K)
    for t in range(present.shape[0]):
        idx = np.flatnonzero(present[t])
        if len(idx) < 2:
            continue
        boxes = joint_boxes(det.joints[t, idx], world_from_cam[t], intrinsics)  # (M, 4)
        seen = np.zeros(len(idx), dtype=bool)
        survivors = []
        for start in range(len(idx)):
            if seen[start]:
                continue
            group, queue = [], deque([start])
            seen[start] = True
            while queue:
                i = queue.popleft()
                group.append(i)
                for j in range(len(idx)):
                    if not seen[j] and _linked(boxes[i], boxes[j], iou_threshold):
                        seen[j] = True
                        queue.append(j)
            survivors.append(max(group, key=lambda g: mean_conf[t, idx[g]]))
        best_per_side: dict[int, int] = {}
        for g in survivors:
            side = int(det.side[t, idx[g]])
            if (
                side not in best_per_side
                or mean_conf[t, idx[g]] > mean_conf[t, best_per_side[side]]
            ):
                best_per_side[side] = idx[g]
        keep = set(best_per_side.values())
        for i in idx:
            present[t, i] = i in keep
    removed = int(det.present.sum() - present.sum())
    return replace(det, present=present), removed


def _linked(a: np.ndarray, b: np.ndarray, threshold: float) -> bool:
    if np.isnan(a).any() or np.isnan(b).any():
        return False
    return box_iou(a, b) > threshold


def to_hands(det: Detections) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One detection per side per frame: ``(joints (T, 2, 21, 3), valid (T, 2), conf (T, 2, 21))``.

    Raises :class:`HandFilterError` if a frame still has two detections of one side (run
    :func:`deduplicate` first). Joints of invalid hands are NaN, confidences 0.
    """
    t = det.present.shape[0]
    joints = np.full((t, 2, 21, 3), np.nan)
    valid = np.zeros((t, 2), dtype=bool)
    conf = np.zeros((t, 2, 21), dtype=np.float32)
    for f, k in zip(*np.nonzero(det.present), strict=True):
        side = int(det.side[f, k])
        if valid[f, side]:
            raise HandFilterError(f"frame {f} has two {('left', 'right')[side]} hands")
        joints[f, side], valid[f, side], conf[f, side] = (
            det.joints[f, k],
            True,
            det.confidence[f, k],
        )
    return joints, valid, conf


def mano_to_sides(det: Detections) -> np.ndarray | None:
    """The MANO fits of :func:`to_hands`'s hands: ``(T, 2, 51 + B)`` by side, NaN where a side
    has no detection or its detection no fit; None when the backend fits no MANO."""
    if det.mano is None:
        return None
    t = det.present.shape[0]
    out = np.full((t, 2, det.mano.shape[2]), np.nan)
    for f, k in zip(*np.nonzero(det.present), strict=True):
        out[f, int(det.side[f, k])] = det.mano[f, k]
    return out


def lifted_to_sides(det: Detections) -> np.ndarray:
    """``(T, 2)`` bool: :func:`to_hands`'s hand is there and its 3D trusted (every present one
    where the backend does not say, :attr:`Detections.lifted` None)."""
    t = det.present.shape[0]
    out = np.zeros((t, 2), dtype=bool)
    lifted = det.present if det.lifted is None else det.present & det.lifted
    for f, k in zip(*np.nonzero(det.present), strict=True):
        out[f, int(det.side[f, k])] = lifted[f, k]
    return out


def palm_rotations(joints: np.ndarray) -> np.ndarray:
    """Palm frames ``(..., 3, 3)`` (columns x, y, z) of ``joints (..., 21, 3)``: x from the wrist to
    the middle knuckle, y from the pinky knuckle towards the index knuckle (orthogonalised),
    z = x cross y. NaN where the joints are NaN or degenerate."""
    x = joints[..., 9, :] - joints[..., 0, :]  # (..., 3)
    y = joints[..., 5, :] - joints[..., 17, :]  # (..., 3)
    with np.errstate(invalid="ignore", divide="ignore"):
        x = x / np.linalg.norm(x, axis=-1, keepdims=True)
        y = y - x * np.sum(x * y, axis=-1, keepdims=True)
        y = y / np.linalg.norm(y, axis=-1, keepdims=True)
    return np.stack([x, y, np.cross(x, y)], axis=-1)


def temporal_outliers(
    joints: np.ndarray,
    valid: np.ndarray,
    world_from_cam: np.ndarray,
    fps: float,
    max_speed: float = 2.5,
    max_angular_speed: float = 720.0,
) -> np.ndarray:
    """``(T, 2)`` True where a hand-frame is a bidirectional spike (see the module docstring).

    ``joints (T, 2, 21, 3)`` world metres, ``valid (T, 2)``, ``world_from_cam (T, 4, 4)``,
    ``max_speed`` metres per second of the hand centre in camera space, ``max_angular_speed``
    degrees per second of the palm's orientation in camera space (``inf`` = position only). A
    frame is a spike when its incoming and outgoing motion both exceed one of the two limits.
    """
    t = joints.shape[0]
    if world_from_cam.shape != (t, 4, 4) or valid.shape != (t, 2):
        raise HandFilterError(
            f"{t} frames of joints, poses {world_from_cam.shape}, valid {valid.shape}"
        )
    cam_from_world = invert_se3(world_from_cam)  # (T, 4, 4)
    joints_cam = np.stack([transform_points(cam_from_world[f], joints[f]) for f in range(t)])
    centre = joints_cam.mean(axis=2)  # (T, 2, 3) hand centres in camera metres
    out = np.zeros((t, 2), dtype=bool)
    if t < 3:
        return out
    speed = np.linalg.norm(np.diff(centre, axis=0), axis=-1) * fps  # (T-1, 2) m/s
    rot = palm_rotations(joints_cam)  # (T, 2, 3, 3) cam_from_palm
    relative = np.einsum("tsji,tsjk->tsik", rot[:-1], rot[1:])  # (T-1, 2, 3, 3) R_t^T R_t+1
    cos = (np.trace(relative, axis1=-2, axis2=-1) - 1.0) / 2.0  # (T-1, 2)
    angular = np.degrees(np.arccos(np.clip(np.nan_to_num(cos, nan=1.0), -1.0, 1.0))) * fps
    both_valid = valid[:-1] & valid[1:]  # (T-1, 2) speed defined
    fast_move = both_valid & (speed > max_speed)  # (T-1, 2)
    fast_turn = both_valid & (angular > max_angular_speed)  # (T-1, 2)
    spike_move = fast_move[:-1] & fast_move[1:]  # (T-2, 2)
    spike_turn = fast_turn[:-1] & fast_turn[1:]  # (T-2, 2)
    out[1:-1] = (spike_move | spike_turn) & valid[1:-1]
    return out


def turn_outliers(
    joints_cam: np.ndarray,
    valid: np.ndarray,
    fps: float,
    window: int = 3,
    max_turn_rate: float = 320.0,
) -> np.ndarray:
    """``(T, 2)`` True where a valid hand's palm (:func:`palm_rotations`) turns away from its own
    valid frames within ``window`` frames either side faster than ``max_turn_rate`` degrees per
    second: the median over those frames of the angle to each, divided by the time between
    them. A hand-frame with no such neighbour is kept; a good frame with as many wrong
    neighbours as good ones in the window can be flagged too (the median is then half-way).

    ``joints_cam (T, 2, 21, 3)`` camera metres (NaN where absent), ``valid (T, 2)``, ``fps``
    the clip's frame rate. Unlike :func:`temporal_outliers`' bidirectional test, a frame with
    neighbours on one side only is tested too: the palm a lifting backend places wrongly is
    mostly at a track's end, where the hand closes on an object or leaves the view, for one to
    four frames. Tuned synthetic world (MediaPipe backend, default seeds 1-4, 11, 13, 16 fps,
    found hand-frames): of 24 more than 40 degrees off, the bidirectional test at 20-45 degrees
    per frame flags none; this one at 320 degrees per second flags 7 (and 1 of the 315 others);
    figures in docs/design.md, "Hands v10"."""
    t = joints_cam.shape[0]
    if valid.shape != (t, 2) or joints_cam.shape[1:] != (2, 21, 3):
        raise HandFilterError(f"joints {joints_cam.shape} and valid {valid.shape} disagree")
    rot = palm_rotations(joints_cam)  # (T, 2, 3, 3) cam_from_palm
    out = np.zeros((t, 2), dtype=bool)
    for f, s in zip(*np.nonzero(valid), strict=True):
        near = [g for g in range(max(0, f - window), min(t, f + window + 1)) if g != f]
        near = np.array([g for g in near if valid[g, s]], dtype=int)  # (G,)
        if not near.size:
            continue
        turn = np.nan_to_num(rotation_angle_deg(rot[f, s], rot[near, s]), nan=0.0)  # (G,)
        out[f, s] = float(np.median(turn / np.abs(near - f))) * fps > max_turn_rate
    return out


FINGER_JOINTS = (6, 7, 8, 10, 11, 12, 14, 15, 16, 18, 19, 20)  # index..pinky, past the knuckles


def smooth_finger_depths(
    joints_cam: np.ndarray,
    ok: np.ndarray,
    sigma: float = 1.0,
    starts: np.ndarray | None = None,
    joints: tuple[int, ...] = FINGER_JOINTS,
) -> np.ndarray:
    """``joints_cam (T, 2, 21, 3)`` (camera metres, each joint on its landmark's ray) with the
    depths of ``joints`` relative to the wrist smoothed over time by a Gaussian of ``sigma``
    frames within runs of consecutive ``ok (T, 2)`` frames (edges renormalised; a frame where
    ``starts (T, 2)`` is True begins a new run: another hand given the same side), each joint
    kept on its own ray (its 2D unchanged). Other joints and frames are unchanged; ``sigma <= 0``
    changes nothing. Why: the finger bend fit (hands v13, :func:`~egosim.stages.common.
    hand_lift.fit_finger_bends`) is per frame, and a finger's depth is its least sure
    coordinate (figures in docs/design.md, "Hands v14")."""
    if sigma <= 0:
        return joints_cam
    t = joints_cam.shape[0]
    if ok.shape != (t, 2) or joints_cam.shape[1:] != (2, 21, 3):
        raise HandFilterError(f"joints {joints_cam.shape} and ok {ok.shape} disagree")
    picked = list(joints)
    out = joints_cam.copy()
    for s in range(2):
        good = ok[:, s] & np.all(np.isfinite(joints_cam[:, s]), axis=(1, 2))  # (T,)
        rel = joints_cam[:, s, picked, 2] - joints_cam[:, s, :1, 2]  # (T, J) depth from wrist
        smooth = gaussian_smooth_runs(rel, good, sigma, None if starts is None else starts[:, s])
        for f in np.flatnonzero(good):
            depth = joints_cam[f, s, 0, 2] + smooth[f]  # (J,)
            old = joints_cam[f, s, picked]  # (J, 3)
            out[f, s, picked] = old * (np.maximum(depth, 1e-3) / old[:, 2])[:, None]
    return out


def smooth_palm_turns(
    joints_cam: np.ndarray,
    ok: np.ndarray,
    sigma: float = 1.0,
    starts: np.ndarray | None = None,
    world_from_cam: np.ndarray | None = None,
) -> np.ndarray:
    """``joints_cam (T, 2, 21, 3)`` (camera metres, each joint on its landmark's ray) with each
    ``ok (T, 2)`` hand's palm turn (:func:`palm_rotations`) smoothed over time by a Gaussian of
    ``sigma`` frames within runs of consecutive ``ok`` frames (edges renormalised; a frame where
    ``starts (T, 2)`` is True begins a new run: another hand given the same side). The smoothed
    turn is the chordal mean of the weighted rotations, taken in the world frame when
    ``world_from_cam (T, 4, 4)`` is given (a turning head does not turn the hand; None: in the
    camera frame). Each hand's wrist-relative shape is turned about its wrist from its own palm
    to the smoothed one, then each joint is put back on its own ray at its new depth, so the 2D
    does not change. Other frames are unchanged; ``sigma <= 0`` changes nothing. Why: the palm
    PnP is per frame, and its pitch is its least sure angle (figures in docs/design.md, "Hands
    v21")."""
    if sigma <= 0:
        return joints_cam
    t = joints_cam.shape[0]
    if ok.shape != (t, 2) or joints_cam.shape[1:] != (2, 21, 3):
        raise HandFilterError(f"joints {joints_cam.shape} and ok {ok.shape} disagree")
    if world_from_cam is not None and world_from_cam.shape != (t, 4, 4):
        raise HandFilterError(f"world_from_cam {world_from_cam.shape} != ({t}, 4, 4)")
    cam_from_palm = palm_rotations(joints_cam)  # (T, 2, 3, 3)
    turn = np.broadcast_to(np.eye(3), (t, 3, 3))  # (T, 3, 3) world_from_cam's rotation
    if world_from_cam is not None:
        turn = world_from_cam[:, :3, :3]
    world_from_palm = np.einsum("tij,tsjk->tsik", turn, cam_from_palm)  # (T, 2, 3, 3)
    out = joints_cam.copy()
    for s in range(2):
        good = ok[:, s] & np.all(np.isfinite(world_from_palm[:, s]), axis=(1, 2))  # (T,)
        summed = gaussian_smooth_runs(
            world_from_palm[:, s].reshape(t, 9),
            good,
            sigma,
            None if starts is None else starts[:, s],
        ).reshape(t, 3, 3)  # (T, 3, 3) weighted means of rotations (not rotations)
        for f in np.flatnonzero(good):
            u, _, vt = np.linalg.svd(summed[f])
            mean = u @ np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))]) @ vt  # (3, 3) world
            smooth = turn[f].T @ mean  # (3, 3) cam_from_palm, smoothed
            wrist = joints_cam[f, s, 0]  # (3,)
            moved = wrist + (joints_cam[f, s] - wrist) @ cam_from_palm[f, s] @ smooth.T  # (21, 3)
            old = joints_cam[f, s]  # (21, 3) on their rays
            out[f, s] = old * (np.maximum(moved[:, 2], 1e-3) / old[:, 2])[:, None]
    return out


def gaussian_smooth_runs(
    values: np.ndarray, ok: np.ndarray, sigma: float, starts: np.ndarray | None = None
) -> np.ndarray:
    """Smooth ``values (T, ...)`` over time by a Gaussian of ``sigma`` frames within runs of
    ``ok (T,)`` frames, edges renormalised; a frame where ``starts (T,)`` is True begins a new
    run even after an ``ok`` frame. Frames not ``ok`` are unchanged; ``sigma <= 0`` changes
    nothing."""
    if sigma <= 0:
        return values
    radius = int(np.ceil(3 * sigma))
    kernel = np.exp(-0.5 * (np.arange(-radius, radius + 1) / sigma) ** 2)  # (2r+1,)
    out = values.copy()
    t = len(values)
    begins = ok & ~np.concatenate([[False], ok[:-1]])  # (T,) first frame of each ok run
    if starts is not None:
        begins |= ok & starts
    label = np.cumsum(begins)  # (T,) run number of each ok frame
    for f in np.flatnonzero(ok):
        window = np.arange(max(0, f - radius), min(t, f + radius + 1))
        run = ok[window] & (label[window] == label[f])  # the same run as f only
        wts = kernel[window[run] - f + radius]  # (n,)
        picked = np.nan_to_num(values[window[run]])
        out[f] = np.tensordot(wts / wts.sum(), picked, axes=1)
    return out
