"""Objects the hands carry, placed by the hand's rigid motion (no object depth needed).

Fusion from an estimated depth (a plane sweep) sees almost nothing of a flat-coloured object:
no texture, no match, no depth, so no object track and no interaction test. The hands row has
what the sweep lacks: 3D joints in the world for every frame. An object a hand holds moves
rigidly with it, so :func:`carried_objects` predicts where it went, per hand:

1. closed frames: the hand's finger spread (:func:`closure`) is at least ``carry_close_drop``
   below its most open over the clip (:func:`closed_frames`);
2. the grasp frame ``g``: of the closed frames whose grip point (between the thumb tip and the
   index and middle tips) lies within ``carry_contact_m`` of a previous-state point resting on
   the support plane (between ``object_min_height_m`` and ``object_max_height_m`` above it,
   inside its footprint), the one where the palm moves least (:func:`grasp_frame`);
3. the object: the DBSCAN clusters (``cluster_eps_m``) of those resting points that the grip
   touches at ``g`` (an object seen in parts is several clusters), their lowest centimetre,
   and the whole of any previous instance they mostly hold;
4. the palm's rigid motion from ``g`` to each later closed frame ``k`` (Kabsch on the wrist
   and the four knuckles, joints 0, 5, 9, 13 and 17, which finger closure does not move)
   carries the object; it must leave the support (its lowest points more than
   ``carry_lift_m`` above their height at ``g``) and come back to rest (within
   ``carry_rest_m``): the release frame ``r`` is the frame of that first rest where it sits
   lowest (:func:`release_frame`). After the release the hand lifts off or opens, so a hand
   that only touches or pushes an object never moves it, nor does one that never puts it
   down;
5. the object's points at ``r`` are its points before the grasp (the previous state's: its
   last observed geometry) moved by the palm's motion ``g -> r``: the retrospective update of
   the paper, with the geometry carried instead of observed.

A carry is kept when the object moved by more than ``settled_distance_m``.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial import cKDTree

from egosim.pipeline.geometry import make_se3, transform_points, umeyama
from egosim.stages.common.hand_lift import PALM_JOINTS  # wrist and knuckles: rigid in the hand
from egosim.stages.state_fusion.config import StateFusionConfig

if TYPE_CHECKING:  # fusion imports this module
    from egosim.stages.state_fusion.fusion import SupportPlane

GRIP_JOINTS = (4, 8, 12)  # thumb, index and middle tips: the grip point lies between them


@dataclasses.dataclass
class Carry:
    """One object a hand carried from its place at ``grasp`` to where it rests at ``release``."""

    hand: int  # 0 = left, 1 = right
    grasp: int  # frame the hand takes hold
    release: int  # frame the object rests at its new place
    moved: np.ndarray  # (4, 4) world transform of the object from grasp to release
    source: np.ndarray  # (n,) indices of the object's points in the previous state
    instance: int  # previous instance id of the object, 0 = none


def grip_points(joints: np.ndarray) -> np.ndarray:
    """Grip point ``(..., 3)`` of hands ``(..., 21, 3)``: half the thumb tip, a quarter each
    of the index and middle tips."""
    thumb, index, middle = GRIP_JOINTS
    return 0.5 * joints[..., thumb, :] + 0.25 * (joints[..., index, :] + joints[..., middle, :])


def palm_motion(palm_from: np.ndarray, palm_to: np.ndarray) -> np.ndarray:
    """``(4, 4)`` rigid transform taking palm joints ``palm_from (5, 3)`` onto ``palm_to``."""
    _, rot, trans = umeyama(palm_from, palm_to, with_scale=False)
    return make_se3(rot, trans)


def closure(joints: np.ndarray) -> np.ndarray:
    """Finger spread ``(...)`` of hands ``(..., 21, 3)``: the mean distance of the five
    fingertips to the palm centre over the palm's size (knuckles to wrist); it drops when the
    hand closes (the synthetic hand: 1.16 open, 0.97 gripping)."""
    palm = joints[..., PALM_JOINTS, :].mean(-2)  # (..., 3)
    size = np.linalg.norm(joints[..., (5, 9, 13, 17), :] - joints[..., :1, :], axis=-1).mean(-1)
    tips = np.linalg.norm(joints[..., (4, 8, 12, 16, 20), :] - palm[..., None, :], axis=-1)
    return tips.mean(-1) / np.maximum(size, 1e-9)


def _speed(centres: np.ndarray, frames: np.ndarray) -> np.ndarray:
    """Palm speed ``(len(frames),)`` per frame by central differences over ``centres (T, 3)``
    (NaN rows: hand not seen; the nearest seen neighbours are used)."""
    seen = np.flatnonzero(np.all(np.isfinite(centres), axis=1))
    out = np.full(len(frames), np.inf)
    for i, k in enumerate(frames):
        before = seen[seen < k]
        after = seen[seen > k]
        a = before[-1] if len(before) else k
        b = after[0] if len(after) else k
        if b > a:
            out[i] = float(np.linalg.norm(centres[b] - centres[a])) / (b - a)
    return out


def grasp_frame(
    joints: np.ndarray, closed: np.ndarray, points: np.ndarray, contact_m: float
) -> int | None:
    """The frame a hand ``joints (T, 21, 3)`` takes hold of something among ``points (n, 3)``:
    of the frames where it is ``closed (T,)`` and its grip point lies within ``contact_m`` of
    a point, the one where the palm moves least (latest on ties); None without contact."""
    if len(points) == 0 or not closed.any():
        return None
    dist = np.full(len(joints), np.inf)
    dist[closed], _ = cKDTree(points).query(grip_points(joints[closed]))
    contact = np.flatnonzero(dist <= contact_m)
    if len(contact) == 0:
        return None
    centres = np.where(closed[:, None], joints[:, PALM_JOINTS].mean(1), np.nan)  # (T, 3)
    speed = _speed(centres, contact)
    return int(contact[np.flatnonzero(speed == speed.min())[-1]])


def release_frame(
    joints: np.ndarray,
    closed: np.ndarray,
    grasp: int,
    points: np.ndarray,
    height: Callable[[np.ndarray], np.ndarray],
    lift_m: float,
    rest_m: float,
) -> tuple[int, np.ndarray] | None:
    """``(release, moved (4, 4))`` of an object of ``points (n, 3)`` held from ``grasp`` by a
    hand ``joints (T, 21, 3)`` while ``closed (T,)``; ``height(points) -> (n,)`` is the height
    above the support. The object, carried by the palm's motion, must rise more than
    ``lift_m`` (its 5th-percentile height against its own at ``grasp``) and come back within
    ``rest_m``; the release is the frame of that first rest where it sits lowest (latest on
    ties). None if it never does before the hand opens or the clip ends."""
    palm = joints[:, PALM_JOINTS]  # (T, 5, 3)
    low = np.percentile(height(points), 5)  # the object's bottom at rest
    rest: list[tuple[float, int, np.ndarray]] = []  # (lowness, frame, moved) of the first rest
    lifted = False
    for k in range(grasp + 1, len(joints)):
        if not closed[k]:
            break  # the hand opened (or was lost): it let go
        moved = palm_motion(palm[grasp], palm[k])
        bottom = float(np.percentile(height(transform_points(moved, points)), 5)) - low
        if not lifted:
            lifted = bottom > lift_m
            continue
        if abs(bottom) <= rest_m:
            rest.append((abs(bottom), k, moved))
        elif rest:
            break  # the first rest after the lift is over
    if not rest:
        return None
    _, release, moved = min(rest, key=lambda item: (item[0], -item[1]))
    return release, moved


def closed_frames(joints: np.ndarray, valid: np.ndarray, close_drop: float) -> np.ndarray:
    """``(T,)`` bool: the hand ``joints (T, 21, 3)`` is valid and closed, its :func:`closure`
    at least ``close_drop`` below its most open over the clip."""
    t = len(joints)
    ok = valid & np.all(np.isfinite(joints.reshape(t, -1)), axis=1)
    if not ok.any():
        return ok
    spread = closure(np.where(ok[:, None, None], joints, 0.0))  # (T,)
    return ok & (spread <= spread[ok].max() - close_drop)


def carried_objects(
    joints: np.ndarray,
    valid: np.ndarray,
    points: np.ndarray,
    instance: np.ndarray,
    plane: SupportPlane,
    config: StateFusionConfig,
) -> list[Carry]:
    """Every object of a previous state (``points (N, 3)``, ``instance (N,)``) that a hand of
    ``joints (T, 2, 21, 3)`` (``valid (T, 2)``) carried, on the support ``plane`` (a
    ``fusion.SupportPlane``), by the module docstring's steps; at most one per hand.

    The object is every DBSCAN cluster of the points above the plane with a point within
    ``carry_contact_m`` of the grip point at the grasp (an object seen in parts is several
    clusters), with the points below ``object_min_height_m`` (but above the plane's inlier
    band, ``plane_distance_m``) within ``cluster_eps_m`` of them, grown to the whole of each
    previous instance holding most of it."""
    from egosim.stages.state_fusion.fusion import cluster_points  # fusion imports this module

    joints = np.asarray(joints, np.float64)
    h = plane.height(points)
    idx = np.flatnonzero(
        (h > config.object_min_height_m) & (h < config.object_max_height_m) & plane.inside(points)
    )
    if len(idx) == 0:
        return []
    labels = cluster_points(points[idx], config.cluster_eps_m)
    idx, labels = idx[labels >= 0], labels[labels >= 0]
    # the objects' lowest centimetres (below object_min_height_m, above the plane's inlier band)
    low = np.flatnonzero((h > config.plane_distance_m) & (h <= config.object_min_height_m))
    carries: list[Carry] = []
    taken = np.zeros(len(points), bool)
    for hand in range(joints.shape[1]):
        closed = closed_frames(joints[:, hand], valid[:, hand], config.carry_close_drop)
        free = idx[~taken[idx]]
        grasp = grasp_frame(joints[:, hand], closed, points[free], config.carry_contact_m)
        if grasp is None:
            continue
        grip = grip_points(joints[grasp, hand])
        near = np.linalg.norm(points[idx] - grip, axis=1) <= config.carry_contact_m
        members = idx[np.isin(labels, labels[near])]
        if len(low) and len(members):
            dist, _ = cKDTree(points[members]).query(points[low])
            members = np.union1d(members, low[dist <= config.cluster_eps_m])
        ids, counts = np.unique(instance[members], return_counts=True)
        for iid, count in zip(ids, counts, strict=True):
            if iid > 0 and count >= 0.5 * (instance == iid).sum():
                members = np.union1d(members, np.flatnonzero(instance == iid))
        members = members[~taken[members]]
        if len(members) == 0:
            continue
        got = release_frame(
            joints[:, hand],
            closed,
            grasp,
            points[members],
            plane.height,
            config.carry_lift_m,
            config.carry_rest_m,
        )
        if got is None:
            continue
        release, moved = got
        pts = points[members]
        shift = float(np.linalg.norm(transform_points(moved, pts).mean(0) - pts.mean(0)))
        if shift <= config.settled_distance_m:
            continue
        ids, counts = np.unique(instance[members], return_counts=True)
        iid = int(ids[np.argmax(counts)])
        carries.append(Carry(hand, grasp, release, moved, members, iid))
        taken[members] = True
    return carries
