"""Interaction-aware state fusion (EgoSim section 3.3, supplementary section 2) on arrays.

:func:`fuse_state` turns one observed clip (frames, per-frame depth, hand masks, hand boxes,
cameras) and an optional previous :class:`State` into the next state:

1. register the clip's cameras to the previous state's world frame by a Sim3 from overlapping
   camera poses (:func:`sim3_from_poses`: rotation from the orientations, scale and translation
   from the centres, Umeyama's closed form given the rotation);
2. find object instances without weights: the support plane by seeded RANSAC
   (:func:`ransac_plane`) on the clip's points, DBSCAN clusters of what rests on it in every frame,
   tracked across frames by 3D voxel overlap (:func:`track_objects`);
3. the paper's interaction test per object and frame: box overlap with a hand box above
   ``hand_box_iou`` and median depth gap below ``depth_gap_m``, with the retrospective update
   of each object's last observed frame (:func:`interaction_test`). The paper's overlap is IoU;
   the default ``box_overlap`` is intersection over the object's box, because geometric
   segmentation sees only the part of a held object the hand leaves visible, whose box barely
   overlaps the hand's (IoU missed the moved object in 3 of 4 clips of the held-out world);
4. fuse the background by TSDF (open3d tensor ``VoxelBlockGrid``) with hands/arms and
   interacted objects removed by their dilated masks; each interacted object takes its points
   from its last observed frame (of the frames that see it at its last place, the one that
   sees most of it: :func:`geometry_frame`);
5. merge with the previous state: an old point is dropped where the clip's latest observation
   of it disagrees in depth (free space in front of the observed surface, or behind it by more
   than ``overlap_depth_m``) or colour, or where it belongs to an instance the hands moved; a
   new point is added where no kept old point lies within a voxel; then statistical outlier
   removal and small-cluster removal.

Bad input raises :class:`FusionError` with the numbers that failed; nothing returns the
previous state unchanged.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Iterable

import cv2
import numpy as np
import open3d as o3d
import open3d.core as o3c
from scipy import ndimage
from scipy.spatial import cKDTree

from egosim.pipeline.geometry import (
    intrinsics_matrix,
    invert_se3,
    project_points,
    rotation_angle_deg,
    transform_points,
    unproject_depth,
)
from egosim.stages.state_fusion.carry import Carry, carried_objects
from egosim.stages.state_fusion.config import StateFusionConfig
from egosim.stages.state_fusion.segmenters import Segmenter

SOURCE_BACKGROUND, SOURCE_OBJECT, SOURCE_LAST_OBSERVED, SOURCE_PREVIOUS = 0, 1, 2, 3
TRACK_MEMORY = 5  # a track matches clusters against the voxels of its last 5 observations


class FusionError(ValueError):
    """The observation or the previous state cannot give a correct state; says which numbers."""


@dataclasses.dataclass
class Instance:
    """One object instance of a state."""

    id: int  # >= 1, stable across states
    label: str  # "object" for geometric segmentation
    interactive: bool  # the hands interacted with it in the fused clip
    last_observed_frame: int  # last frame of the clip that saw it; -1 = carried over unseen
    geometry_frame: int  # frame its points came from (interacted objects); -1 = TSDF/previous
    interaction: np.ndarray  # (T,) bool status per frame
    depth_gap: np.ndarray  # (T,) float32 metres, NaN where not measured
    centroid: np.ndarray  # (3,) float64 world metres


@dataclasses.dataclass
class State:
    """A world state: points with instances and sources, the instance table, the cameras."""

    clip_id: str  # clip the state was fused from
    previous_clip_id: str | None  # clip of the previous state, None for a first state
    world_frame: str  # first clip of the chain: names the world frame
    num_frames: int  # frames T of the fused clip
    points: np.ndarray  # (N, 3) float32 world metres
    colours: np.ndarray  # (N, 3) uint8 RGB
    point_size: np.ndarray  # (N,) float32 metres
    instance: np.ndarray  # (N,) int32, 0 = background
    source: np.ndarray  # (N,) uint8 SOURCE_* code
    instances: list[Instance]  # instance table
    intrinsics: np.ndarray  # (4,) fx, fy, cx, cy
    width: int  # image width of the cameras
    height: int  # image height of the cameras
    world_from_cam: np.ndarray  # (K, 4, 4) cameras the state was built from
    camera_frames: list[str]  # (K,) "<clip_id>:<frame>"
    previous_from_clip: np.ndarray  # (4, 4) Sim3 clip frame -> state frame
    sim3_scale: float  # scale of previous_from_clip
    registration_rms: float | None  # camera-centre residual of the Sim3, None if not registered

    def instance_points(self, instance_id: int) -> np.ndarray:
        """``(n, 3)`` points of one instance."""
        return self.points[self.instance == instance_id]


@dataclasses.dataclass(frozen=True)
class Observation:
    """One clip as state fusion sees it, in the clip's own camera frame."""

    clip_id: str  # id of the clip
    frames: np.ndarray  # (T, H, W, 3) uint8 RGB
    depth: np.ndarray  # (T, H, W) float32 z-depth in the poses' units, 0 = unknown
    hand_mask: np.ndarray  # (T, H, W) bool, True = hand or arm
    hand_boxes: np.ndarray  # (T, 2, 4) float64 x0, y0, x1, y1 keypoint boxes; NaN where no hand
    intrinsics: np.ndarray  # (4,) fx, fy, cx, cy
    world_from_cam: np.ndarray  # (T, 4, 4) the clip's cameras (estimated or given)
    # (T, 4, 4) the same cameras in the previous state's world frame (the action's trajectory in
    # simulation); None when the clip's cameras are already in that frame.
    reference_world_from_cam: np.ndarray | None = None
    # True when depth was estimated (plane sweep: every stride-th frame, consistency-checked)
    depth_estimated: bool = False
    # (T, 2, 21, 3) hand joints in the frame of world_from_cam (0 = left, 1 = right) and
    # (T, 2) bool valid with its 3D trusted (hands' hand_lifted): carried objects follow them
    # (carry.py); None = not carried
    hand_joints: np.ndarray | None = None
    hand_valid: np.ndarray | None = None


# ---------------------------------------------------------------- registration


def sim3_from_poses(
    src: np.ndarray, dst: np.ndarray, min_centre_spread: float
) -> tuple[float, np.ndarray, np.ndarray, float]:
    """Sim3 ``dst ~ s R src + t`` from paired camera poses ``src, dst (K, 4, 4)``.

    The rotation is the chordal mean of ``R_dst R_src^T`` over the pairs (so orientations fix it
    even when the centres are collinear or one point); scale and translation are Umeyama's
    closed form for the centres given that rotation. When the ``src`` centres spread less than
    ``min_centre_spread`` (RMS about their mean) the scale is not observable and is fixed to 1.
    Returns ``(s, R (3, 3), t (3,), rms)`` with ``rms`` the RMS centre residual in ``dst`` units.
    """
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    if src.shape != dst.shape or src.ndim != 3 or src.shape[1:] != (4, 4) or len(src) < 1:
        raise FusionError(f"need two (K>=1, 4, 4) pose arrays, got {src.shape} and {dst.shape}")
    m = np.einsum("kij,klj->il", dst[:, :3, :3], src[:, :3, :3])  # (3, 3) sum R_dst R_src^T
    u, _, vt = np.linalg.svd(m)
    fix = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))])
    rot = u @ fix @ vt  # (3, 3)
    c_src, c_dst = src[:, :3, 3], dst[:, :3, 3]  # (K, 3)
    a = c_src - c_src.mean(0)
    b = c_dst - c_dst.mean(0)
    spread = float(np.sqrt((a**2).sum(1).mean()))
    scale = float(np.sum(b * (a @ rot.T)) / np.sum(a**2)) if spread >= min_centre_spread else 1.0
    trans = c_dst.mean(0) - scale * rot @ c_src.mean(0)
    resid = c_dst - (scale * c_src @ rot.T + trans)
    return scale, rot, trans, float(np.sqrt((resid**2).sum(1).mean()))


def sim3_matrix(scale: float, rot: np.ndarray, trans: np.ndarray) -> np.ndarray:
    """``(4, 4)`` matrix of the Sim3 ``x -> s R x + t``."""
    out = np.eye(4)
    out[:3, :3] = scale * rot
    out[:3, 3] = trans
    return out


def apply_sim3_to_poses(sim3: np.ndarray, scale: float, poses: np.ndarray) -> np.ndarray:
    """``poses (K, 4, 4)`` moved by the Sim3 (their rotations stay rotations; depth scales)."""
    out = np.array(poses, dtype=np.float64)
    rot = sim3[:3, :3] / scale
    out[:, :3, :3] = rot @ out[:, :3, :3]
    out[:, :3, 3] = out[:, :3, 3] @ sim3[:3, :3].T + sim3[:3, 3]
    return out


def overlapping_cameras(
    new: np.ndarray, old: np.ndarray, max_distance: float, max_angle_deg: float
) -> np.ndarray:
    """``(K_new,)`` bool: each new camera lies near some old camera in centre and orientation."""
    dist = np.linalg.norm(new[:, None, :3, 3] - old[None, :, :3, 3], axis=-1)  # (Kn, Ko)
    ang = rotation_angle_deg(new[:, None, :3, :3], old[None, :, :3, :3])  # (Kn, Ko)
    return np.any((dist <= max_distance) & (ang <= max_angle_deg), axis=1)


# ---------------------------------------------------------------- objects


def _dilate(mask: np.ndarray, pixels: int) -> np.ndarray:
    """``mask (H, W)`` bool grown by ``pixels`` (square structuring element)."""
    if pixels <= 0 or not mask.any():
        return mask
    kernel = np.ones((2 * pixels + 1, 2 * pixels + 1), np.uint8)
    return cv2.dilate(mask.astype(np.uint8), kernel) > 0


@dataclasses.dataclass
class SupportPlane:
    """The plane objects rest on: ``normal . x + offset = 0``, normal towards the cameras."""

    normal: np.ndarray  # (3,) unit
    offset: float  # metres
    basis: np.ndarray  # (2, 3) in-plane axes
    lo: np.ndarray  # (2,) footprint of the inliers in plane coordinates
    hi: np.ndarray  # (2,)

    def height(self, points: np.ndarray) -> np.ndarray:
        """Signed height ``(N,)`` of ``points (N, 3)`` above the plane."""
        return points @ self.normal + self.offset

    def inside(self, points: np.ndarray) -> np.ndarray:
        """``(N,)`` bool: the point's foot lies within the inliers' footprint."""
        uv = points @ self.basis.T  # (N, 2)
        return np.all((uv >= self.lo) & (uv <= self.hi), axis=1)


RANSAC_CHUNK = 64  # plane hypotheses scored at once (memory: chunk x points floats)


def ransac_plane(
    points: np.ndarray, threshold: float, iterations: int, seed: int = 0
) -> tuple[np.ndarray, float, np.ndarray]:
    """The plane of most inliers among ``points (N, 3)``: ``(unit normal (3,), offset, inliers)``.

    Seeded RANSAC on three-point samples; the best hypothesis (most inliers, distance <=
    ``threshold``; the first of equals) is refitted once by least squares on its inliers, and the
    refit is kept when it holds at least as many inliers, else the sampled plane. Inliers as
    sorted indices. Deterministic for the same input: open3d's ``segment_plane`` is not, even
    seeded (its parallel loop stops early in whichever thread gets there first; open3d issues
    #5647 and #7270), and the state fusion built on it changed between runs of the same command.
    Raises :class:`FusionError` for fewer than three points or when every sample is degenerate.
    """
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) < 3:
        raise FusionError(f"a plane needs (N >= 3, 3) points, got shape {pts.shape}")
    rng = np.random.default_rng(seed)
    picks = rng.integers(0, len(pts), size=(iterations, 3))
    a, b, c = pts[picks[:, 0]], pts[picks[:, 1]], pts[picks[:, 2]]
    normals = np.cross(b - a, c - a)  # (I, 3)
    norms = np.linalg.norm(normals, axis=1)
    ok = norms > 1e-12  # three collinear or repeated points give no plane
    normals = normals[ok] / norms[ok, None]
    offsets = -np.einsum("ij,ij->i", normals, a[ok])
    if len(normals) == 0:
        raise FusionError(f"no plane through {len(pts)} points: every sample is degenerate")
    counts = np.concatenate(
        [
            (
                np.abs(pts @ normals[i : i + RANSAC_CHUNK].T + offsets[i : i + RANSAC_CHUNK])
                <= threshold
            ).sum(0)
            for i in range(0, len(normals), RANSAC_CHUNK)
        ]
    )
    best = int(np.argmax(counts))  # the first of equals
    normal, offset = normals[best], float(offsets[best])
    inliers = np.flatnonzero(np.abs(pts @ normal + offset) <= threshold)
    centre = pts[inliers].mean(axis=0)
    refit = np.linalg.svd(pts[inliers] - centre, full_matrices=False)[2][2]  # least-squares normal
    refit_inliers = np.flatnonzero(np.abs((pts - centre) @ refit) <= threshold)
    if len(refit_inliers) >= len(inliers):
        normal, offset, inliers = refit, float(-refit @ centre), refit_inliers
    return normal, offset, inliers


def support_plane(
    points: np.ndarray, cam_up: np.ndarray, cam_centre: np.ndarray, config: StateFusionConfig
) -> SupportPlane:
    """The support plane among ``points (N, 3)``: RANSAC planes, nearly horizontal, nearest.

    Up to three planes are peeled off by :func:`ransac_plane`; a candidate holds at least
    ``plane_min_fraction`` of the points and its normal is within ``plane_max_tilt_deg`` of
    ``cam_up (3,)``; of those the one nearest ``cam_centre`` wins (a table over the floor).
    """
    if len(points) < 100:
        raise FusionError(f"too few points ({len(points)}) to find a support plane")
    rest = points
    best: SupportPlane | None = None
    best_dist = np.inf
    cos_tilt = np.cos(np.deg2rad(config.plane_max_tilt_deg))
    for _ in range(3):
        if len(rest) < 0.5 * config.plane_min_fraction * len(points) or len(rest) < 50:
            break
        normal, offset, inliers = ransac_plane(
            rest, config.plane_distance_m, config.plane_iterations
        )
        if normal @ cam_centre + offset < 0:
            normal, offset = -normal, -offset
        dist = float(normal @ cam_centre + offset)
        upright = float(normal @ cam_up) >= cos_tilt  # normal faces the camera already
        if upright and len(inliers) >= config.plane_min_fraction * len(points) and dist < best_dist:
            helper = np.array([1.0, 0.0, 0.0]) if abs(normal[0]) < 0.9 else np.array([0, 1.0, 0])
            e1 = np.cross(normal, helper)
            e1 /= np.linalg.norm(e1)
            basis = np.stack([e1, np.cross(normal, e1)])  # (2, 3)
            uv = rest[inliers] @ basis.T
            lo, hi = np.percentile(uv, 0.5, axis=0), np.percentile(uv, 99.5, axis=0)
            best, best_dist = SupportPlane(normal, offset, basis, lo, hi), dist
        rest = np.delete(rest, inliers, axis=0)
    if best is None:
        raise FusionError(
            f"no support plane: no RANSAC plane within {config.plane_max_tilt_deg} deg of the "
            f"camera's up holds {config.plane_min_fraction:.0%} of {len(points)} points"
        )
    return best


@dataclasses.dataclass
class Track:
    """One object tracked through the clip: per-frame pixels and world points."""

    pixels: dict[int, np.ndarray]  # frame -> (n,) flat pixel indices
    points: dict[int, np.ndarray]  # frame -> (n, 3) world points
    voxels: set  # voxel keys of the latest TRACK_MEMORY observations (union)
    centroid: np.ndarray  # (3,) of the latest observation
    recent: list = dataclasses.field(default_factory=list)  # voxel sets of those observations


def _voxel_keys(points: np.ndarray, size: float) -> set:
    return set(map(tuple, np.unique(np.floor(points / size).astype(np.int64), axis=0).tolist()))


def cluster_points(points: np.ndarray, eps: float) -> np.ndarray:
    """DBSCAN labels ``(N,)`` (-1 = noise) of ``points (N, 3)``, on ``eps / 2`` voxel cells.

    Clustering the occupied cells' centres instead of every point makes the cost independent of
    the image size (a 480x832 frame has 16 times the points of a 120x208 one, same objects).
    """
    cells = np.floor(points / (0.5 * eps)).astype(np.int64)
    uniq, inverse = np.unique(cells, axis=0, return_inverse=True)
    centres = (uniq + 0.5) * (0.5 * eps)  # (U, 3)
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(centres))
    labels = np.asarray(cloud.cluster_dbscan(eps, 2))  # (U,)
    return labels[inverse.reshape(-1)]


def track_objects(
    frames: Iterable[tuple[np.ndarray, np.ndarray]],
    plane: SupportPlane,
    config: StateFusionConfig,
    frame_masks: Callable[[int], list[np.ndarray]] | None = None,
) -> list[Track]:
    """Object tracks from per-frame ``(world points (n_k, 3), flat pixel indices (n_k,))``.

    In each frame, points between ``object_min_height_m`` and ``object_max_height_m`` above the
    plane and inside its footprint are clustered by DBSCAN (``cluster_eps_m``, on voxel cells:
    :func:`cluster_points`); clusters of at
    least ``min_object_points`` continue the track they overlap most (shared ``track_voxel_m``
    voxels over the smaller set at least ``track_min_overlap``, against the union of the track's
    last ``TRACK_MEMORY`` observations, so a part left visible by a hand still matches), else
    the nearest centroid within ``track_max_jump_m``) or start a new one. Several clusters may
    join one track in a frame (an object split by an occluding hand).

    ``frame_masks(k)`` (a learned segmenter's flat ``(H*W,)`` bool masks of frame ``k``)
    replaces DBSCAN: each mask's points above the plane are one cluster.
    """
    tracks: list[Track] = []
    for k, (pts, pix) in enumerate(frames):
        if len(pts) == 0:
            continue
        h = plane.height(pts)
        keep = (h > config.object_min_height_m) & (h < config.object_max_height_m)
        pts, pix = pts[keep], pix[keep]
        keep = plane.inside(pts)
        pts, pix = pts[keep], pix[keep]
        if len(pts) < config.min_object_points:
            continue
        if frame_masks is None:
            labels = cluster_points(pts, config.cluster_eps_m)
            clusters = [
                np.flatnonzero(labels == lab)
                for lab in range(labels.max() + 1)
                if (labels == lab).sum() >= config.min_object_points
            ]
        else:
            clusters = [np.flatnonzero(m[pix]) for m in frame_masks(k)]
            clusters = [c for c in clusters if len(c) >= config.min_object_points]
        assigned: dict[int, list[np.ndarray]] = {}
        for idx in clusters:
            cpts = pts[idx]
            keys = _voxel_keys(cpts, config.track_voxel_m)
            centroid = cpts.mean(0)
            best, best_score = -1, 0.0
            for j, tr in enumerate(tracks):
                shared = len(keys & tr.voxels) / max(1, min(len(keys), len(tr.voxels)))
                if shared >= config.track_min_overlap and shared > best_score:
                    best, best_score = j, shared
            if best < 0:
                dists = [float(np.linalg.norm(centroid - tr.centroid)) for tr in tracks]
                if dists and min(dists) <= config.track_max_jump_m:
                    best = int(np.argmin(dists))
            if best < 0:
                tracks.append(Track({}, {}, set(), centroid))
                best = len(tracks) - 1
            assigned.setdefault(best, []).append(idx)
        for j, parts in assigned.items():
            idx = np.concatenate(parts)
            tr = tracks[j]
            tr.pixels[k], tr.points[k] = pix[idx], pts[idx]
            tr.recent = [
                *tr.recent[-(TRACK_MEMORY - 1) :],
                _voxel_keys(pts[idx], config.track_voxel_m),
            ]
            tr.voxels = set().union(*tr.recent)
            tr.centroid = pts[idx].mean(0)
    return link_tracks(tracks, config.track_max_jump_m)


def _centroid(track: Track, frame: int) -> np.ndarray:
    return track.points[frame].mean(0)


def link_tracks(tracks: list[Track], max_jump: float) -> list[Track]:
    """Merge tracks that are one object seen in turns (a track lost behind a hand, then found).

    Track B joins track A when their frames are disjoint and B fits in time against A: where
    A was seen in the frame before B's first (or B starts after A's last), B's first centroid
    lies within ``max_jump`` per elapsed frame of A's, and where A is seen again after B's last
    frame, B's last centroid lies as close to A's next one. The nearest candidate wins; merges
    repeat until none applies.
    """
    tracks = list(tracks)
    merged = True
    while merged:
        merged = False
        best: tuple[float, int, int] | None = None
        for a, ta in enumerate(tracks):
            fa = sorted(ta.pixels)
            for b, tb in enumerate(tracks):
                fb = sorted(tb.pixels)
                if a == b or not fa or not fb or set(fa) & set(fb):
                    continue
                before = [f for f in fa if f < fb[0]]
                after = [f for f in fa if f > fb[-1]]
                if not before or any(fb[0] < f < fb[-1] for f in fa):
                    continue  # B must start after A was seen and not interleave with it
                d0 = np.linalg.norm(_centroid(tb, fb[0]) - _centroid(ta, before[-1]))
                ok = d0 <= max_jump * (fb[0] - before[-1])
                if after:
                    d1 = np.linalg.norm(_centroid(ta, after[0]) - _centroid(tb, fb[-1]))
                    ok &= d1 <= max_jump * (after[0] - fb[-1])
                if ok and (best is None or d0 < best[0]):
                    best = (float(d0), a, b)
        if best is not None:
            _, a, b = best
            tracks[a].pixels.update(tracks[b].pixels)
            tracks[a].points.update(tracks[b].points)
            last = max(tracks[a].pixels)
            tracks[a].centroid = _centroid(tracks[a], last)
            del tracks[b]
            merged = True
    return tracks


def geometry_frame(track: Track, settled_distance: float) -> int:
    """The frame an interacted object takes its geometry from: its last observed place.

    Of the frames whose points lie where the last observation's do (median distance to them
    within ``settled_distance``: the object already at rest there), the one that saw most of
    the object, so a hand still near it in the very last frame does not cut the object.
    """
    last = max(track.pixels)
    tree = cKDTree(track.points[last])
    best, best_count = last, len(track.pixels[last])
    for k in sorted(track.pixels, reverse=True):
        dist, _ = tree.query(track.points[k])
        if np.median(dist) <= settled_distance and len(track.pixels[k]) > best_count:
            best, best_count = k, len(track.pixels[k])
    return best


def box_overlap(a: np.ndarray, b: np.ndarray, measure: str = "iou") -> float:
    """Overlap of boxes ``(x0, y0, x1, y1)``: IoU, or ``"ioa"`` intersection over ``a``'s area."""
    ix = max(0.0, min(a[2], b[2]) - max(a[0], b[0]))
    iy = max(0.0, min(a[3], b[3]) - max(a[1], b[1]))
    inter = ix * iy
    area_a = (a[2] - a[0]) * (a[3] - a[1])
    if measure == "ioa":
        return inter / area_a if area_a > 0 else 0.0
    union = area_a + (b[2] - b[0]) * (b[3] - b[1]) - inter
    return inter / union if union > 0 else 0.0


def interaction_test(
    tracks: list[Track], obs: Observation, config: StateFusionConfig
) -> tuple[np.ndarray, np.ndarray]:
    """Per track and frame: ``(status (M, T) bool, depth_gap (M, T) float32)`` (paper, supp. 2.2).

    A track interacts with a hand in a frame when its pixel box has IoU above ``hand_box_iou``
    with the hand's keypoint box widened by ``hand_box_pad`` of its size on every side, and the
    median depth of its pixels differs from the median depth of that hand's mask pixels inside
    the keypoint box by less than ``depth_gap_m``. The depth gap
    recorded is the smallest over the hands whose box passes the IoU test (NaN if none). The
    retrospective update: each track's status at its last observed frame becomes True when any
    earlier frame was (so its last geometry is known to be post-interaction).
    """
    t, h, w = obs.depth.shape
    status = np.zeros((len(tracks), t), bool)
    gap = np.full((len(tracks), t), np.nan, np.float32)
    for m, tr in enumerate(tracks):
        for k, pix in tr.pixels.items():
            v, u = np.divmod(pix, w)
            box = np.array([u.min(), v.min(), u.max() + 1.0, v.max() + 1.0])
            z_obj = float(np.median(obs.depth[k].reshape(-1)[pix]))
            for hand in range(obs.hand_boxes.shape[1]):
                hb = obs.hand_boxes[k, hand]  # keypoints' box: its mask pixels give the depth
                size = hb[2:] - hb[:2]
                padded = np.concatenate(
                    [hb[:2] - config.hand_box_pad * size, hb[2:] + config.hand_box_pad * size]
                )
                overlap = box_overlap(box, padded, config.box_overlap)
                if not np.all(np.isfinite(hb)) or overlap <= config.hand_box_iou:
                    continue
                x0, y0 = max(0, int(hb[0])), max(0, int(hb[1]))
                x1, y1 = min(w, int(np.ceil(hb[2]))), min(h, int(np.ceil(hb[3])))
                sub = obs.depth[k, y0:y1, x0:x1][obs.hand_mask[k, y0:y1, x0:x1]]
                sub = sub[sub > 0]
                if sub.size == 0:
                    continue
                g = abs(float(np.median(sub)) - z_obj)
                gap[m, k] = g if np.isnan(gap[m, k]) else min(gap[m, k], g)
                status[m, k] |= g < config.depth_gap_m
        if tr.pixels:
            last = max(tr.pixels)
            status[m, last] |= status[m, :last].any()
    return status, gap


# ---------------------------------------------------------------- fusion


def _integrate_tsdf(
    depth: np.ndarray,
    frames: np.ndarray,
    world_from_cam: np.ndarray,
    intrinsics: np.ndarray,
    config: StateFusionConfig,
    min_weight: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Fuse ``depth (T, H, W)`` (0 = skip) by TSDF; returns points ``(N, 3)`` and RGB ``(N, 3)``.

    Surface points come from voxels observed in at least ``min_weight`` frames
    (``config.tsdf_min_weight`` or ``tsdf_min_weight_estimated``)."""
    k_mat = o3c.Tensor(intrinsics_matrix(intrinsics), o3c.float64)  # (3, 3)
    grid = o3d.t.geometry.VoxelBlockGrid(
        attr_names=("tsdf", "weight", "color"),
        attr_dtypes=(o3c.float32, o3c.float32, o3c.float32),
        attr_channels=((1), (1), (3)),
        voxel_size=config.voxel_size_m,
        block_resolution=8,
        block_count=config.block_count,
        device=o3c.Device("CPU:0"),
    )
    for k in range(len(depth)):
        if not np.any(depth[k] > 0):
            continue
        d_img = o3d.t.geometry.Image(o3c.Tensor(np.ascontiguousarray(depth[k], np.float32)))
        c_img = o3d.t.geometry.Image(
            o3c.Tensor(np.ascontiguousarray(frames[k], np.float32) / 255.0)
        )
        extrinsic = o3c.Tensor(invert_se3(world_from_cam[k]), o3c.float64)
        trunc = config.sdf_trunc_voxels
        blocks = grid.compute_unique_block_coordinates(
            d_img, k_mat, extrinsic, 1.0, config.depth_max_m, trunc
        )
        grid.integrate(
            blocks, d_img, c_img, k_mat, k_mat, extrinsic, 1.0, config.depth_max_m, trunc
        )
    cloud = grid.extract_point_cloud(weight_threshold=min_weight)
    if "positions" not in cloud.point or len(cloud.point.positions) == 0:
        return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint8)
    pts = cloud.point.positions.numpy().astype(np.float32)
    rgb = np.clip(cloud.point.colors.numpy() * 255.0 + 0.5, 0, 255).astype(np.uint8)
    # open3d lists the points in its voxel hash map's order, which changes from run to run;
    # sorted (by z, then y, then x) the same clip fuses to the same state every time
    order = np.lexsort(pts.T)  # (N,)
    return pts[order], rgb[order]


def _project(
    points: np.ndarray, cam_from_world: np.ndarray, intrinsics: np.ndarray, h: int, w: int
):
    """Pixel ``(row, col)`` and z of ``points (N, 3)``; ``ok (N,)`` where in the image, z > 0."""
    uv, z = project_points(transform_points(cam_from_world, points), intrinsics)  # (N, 2), (N,)
    u, v = np.floor(uv[:, 0]), np.floor(uv[:, 1])  # NaN behind the camera
    ok = (z > 1e-6) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
    u, v = np.where(ok, u, 0), np.where(ok, v, 0)  # no NaN into the integer cast
    return v.astype(np.int64), u.astype(np.int64), z, ok


def compare_with_observation(
    points: np.ndarray,
    colours: np.ndarray,
    depth: np.ndarray,
    frames: np.ndarray,
    valid: np.ndarray,
    world_from_cam: np.ndarray,
    intrinsics: np.ndarray,
    config: StateFusionConfig,
    use_colour: bool = True,
) -> tuple[np.ndarray, np.ndarray]:
    """Old ``points (N, 3)`` against the clip's observations: ``(seen (N,), contradicted (N,))``.

    A point is seen in a frame when it projects inside the image onto a ``valid`` pixel with
    known depth and is not hidden behind the observed surface by more than ``overlap_depth_m``.
    The latest frame that sees it decides: contradicted when it lies in front of the observed
    surface by more than ``overlap_depth_m`` (free space) or its colour differs by more than
    ``overlap_colour`` (mean absolute RGB difference in [0, 1]; only with ``use_colour``).
    """
    n = len(points)
    seen = np.zeros(n, bool)
    contradicted = np.zeros(n, bool)
    t, h, w = depth.shape
    col = colours.astype(np.float32) / 255.0
    for k in range(t - 1, -1, -1):  # latest first: later frames decide
        todo = ~seen
        if not todo.any():
            break
        idx = np.flatnonzero(todo)
        v, u, z, ok = _project(points[idx], invert_se3(world_from_cam[k]), intrinsics, h, w)
        idx, v, u, z = idx[ok], v[ok], u[ok], z[ok]
        d = depth[k, v, u]
        good = valid[k, v, u] & (d > 0) & (z <= d + config.overlap_depth_m)
        idx, v, u, z, d = idx[good], v[good], u[good], z[good], d[good]
        seen[idx] = True
        colour_diff = np.abs(frames[k, v, u].astype(np.float32) / 255.0 - col[idx]).mean(1)
        contradicted[idx] = (z < d - config.overlap_depth_m) | (
            use_colour & (colour_diff > config.overlap_colour)
        )
    return seen, contradicted


def remove_outliers(points: np.ndarray, config: StateFusionConfig) -> np.ndarray:
    """``(N,)`` bool keep-mask: statistical outlier removal, then small connected components.

    Statistical: ``outlier_neighbours`` neighbours, ``outlier_std_ratio`` (paper: 20 and 2.0).
    Components: points in voxels of twice ``voxel_size_m``, 26-connected; components with fewer
    than ``min_cluster_points`` points go.
    """
    keep = np.ones(len(points), bool)
    if len(points) > config.outlier_neighbours:
        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points.astype(np.float64)))
        _, kept = cloud.remove_statistical_outlier(
            config.outlier_neighbours, config.outlier_std_ratio
        )
        keep[:] = False
        keep[np.asarray(kept, dtype=np.int64)] = True
    if config.min_cluster_points > 1 and keep.any():
        size = 2.0 * config.voxel_size_m
        cells = np.floor(points[keep] / size).astype(np.int64)
        cells -= cells.min(0)
        uniq, inverse, counts = np.unique(cells, axis=0, return_inverse=True, return_counts=True)
        inverse = inverse.reshape(-1)
        shape = tuple(uniq.max(0) + 1)
        if np.prod(shape, dtype=np.float64) <= 5e7:
            occ = np.zeros(shape, np.int32)
            occ[tuple(uniq.T)] = counts
            labels, _ = ndimage.label(occ > 0, structure=np.ones((3, 3, 3)))
            comp = labels[tuple(uniq.T)]  # (U,)
            comp_size = np.bincount(comp, weights=counts)
            small = comp_size[comp] < config.min_cluster_points  # (U,)
            idx = np.flatnonzero(keep)
            keep[idx[small[inverse]]] = False
    return keep


def _check_observation(obs: Observation) -> None:
    problems: list[str] = []
    if obs.frames.ndim != 4 or obs.frames.shape[-1] != 3:
        raise FusionError(f"frames must be (T, H, W, 3), got {obs.frames.shape}")
    t, h, w = obs.frames.shape[:3]
    for name in ("depth", "hand_mask"):
        shape = getattr(obs, name).shape
        if shape != (t, h, w):
            problems.append(f"{name} shape {shape} != frames {(t, h, w)}")
    if obs.hand_boxes.shape[:1] != (t,) or obs.hand_boxes.shape[2:] != (4,):
        problems.append(f"hand_boxes shape {obs.hand_boxes.shape}, expected ({t}, hands, 4)")
    if obs.world_from_cam.shape != (t, 4, 4):
        problems.append(f"world_from_cam shape {obs.world_from_cam.shape} != ({t}, 4, 4)")
    ref = obs.reference_world_from_cam
    if ref is not None and ref.shape != (t, 4, 4):
        problems.append(f"reference_world_from_cam shape {ref.shape} != ({t}, 4, 4)")
    if not np.all(np.isfinite(obs.depth)) or np.any(obs.depth < 0):
        problems.append("depth has NaN, infinite or negative values")
    if problems:
        raise FusionError("; ".join(problems))


@dataclasses.dataclass
class _Points:
    """Columns of a point set being built: positions, colours, sizes, labels, sources."""

    pts: np.ndarray  # (N, 3) world
    rgb: np.ndarray  # (N, 3) uint8
    size: np.ndarray  # (N,) float32 metres
    label: np.ndarray  # (N,) int32: track index + 1 (new points) or instance id
    source: np.ndarray  # (N,) uint8 SOURCE_* code

    @staticmethod
    def concat(parts: list[_Points]) -> _Points:
        """One point set of ``parts`` in order."""
        return _Points(*(np.concatenate([getattr(p, f) for p in parts]) for f in _POINT_FIELDS))

    def select(self, keep: np.ndarray) -> _Points:
        """The points where ``keep`` (bool or indices)."""
        return _Points(*(getattr(self, f)[keep] for f in _POINT_FIELDS))


_POINT_FIELDS = ("pts", "rgb", "size", "label", "source")


def _register(
    obs: Observation, config: StateFusionConfig
) -> tuple[float, np.ndarray, float | None]:
    """``(scale, sim3 (4, 4), residual)`` taking the clip's cameras to the state's world frame
    (identity when the observation has no reference trajectory)."""
    if obs.reference_world_from_cam is None:
        return 1.0, np.eye(4), None
    scale, rot, trans, rms = sim3_from_poses(
        obs.world_from_cam, obs.reference_world_from_cam, config.min_centre_spread_m
    )
    lo, hi = config.sim3_scale_range
    if not lo <= scale <= hi:
        raise FusionError(f"Sim3 scale {scale:.4g} outside sim3_scale_range {(lo, hi)}")
    if rms > config.max_registration_rms_m:
        raise FusionError(
            f"camera poses do not register by a Sim3: residual {rms:.4g} > "
            f"max_registration_rms_m {config.max_registration_rms_m}"
        )
    return scale, sim3_matrix(scale, rot, trans), rms


def _check_overlap(poses: np.ndarray, previous: State, config: StateFusionConfig) -> None:
    """Raise :class:`FusionError` unless enough clip cameras overlap the previous state's."""
    overlap = overlapping_cameras(
        poses, previous.world_from_cam, config.overlap_max_distance_m, config.overlap_max_angle_deg
    )
    if overlap.sum() < config.min_overlap_cameras:
        dist = np.linalg.norm(
            poses[:, None, :3, 3] - previous.world_from_cam[None, :, :3, 3], axis=-1
        ).min()
        raise FusionError(
            f"no overlap in camera poses with the previous state of {previous.clip_id!r}: "
            f"{int(overlap.sum())} of {len(poses)} cameras within "
            f"{config.overlap_max_distance_m} m and {config.overlap_max_angle_deg} deg (nearest "
            f"centre {dist:.3g} m), need {config.min_overlap_cameras}"
        )


def _objects_and_background(
    obs: Observation,
    depth: np.ndarray,
    valid: np.ndarray,
    poses: np.ndarray,
    config: StateFusionConfig,
    segmenter: Segmenter | None,
    previous: State | None = None,
    joints: np.ndarray | None = None,
) -> tuple[list[Track], np.ndarray, np.ndarray, _Points, np.ndarray, np.ndarray]:
    """Steps 2-3: object tracks, the interaction test, carried objects, the clip's own points.

    ``joints`` (``(T, 2, 21, 3)`` in the state's frame, with ``obs.hand_valid``) carry the
    ``previous`` state's objects a hand held (:func:`_carried_tracks`).
    Returns ``(tracks, status (M, T), gap (M, T), points, geometry frame (M,), dropped (N,))``;
    the points' labels are track index + 1 (0 = background); ``dropped`` marks the previous
    state's points a hand carried away (empty without a previous state).
    """
    t, h, w = depth.shape
    intrinsics = np.asarray(obs.intrinsics, dtype=np.float64)
    rays = unproject_depth(np.ones((h, w), np.float32), intrinsics).reshape(-1, 3)  # (H*W, 3)

    def frame_points(k: int, step: int = 1) -> tuple[np.ndarray, np.ndarray]:
        pix = np.flatnonzero(valid[k])[::step]
        pc = rays[pix] * depth[k].reshape(-1)[pix, None]  # (n, 3) camera
        return transform_points(poses[k], pc), pix  # (n, 3) world, (n,)

    step = max(1, int(valid[0].size // 2000))
    sample = np.concatenate([frame_points(k, step)[0] for k in range(t)])
    plane = support_plane(sample, -poses[0, :3, 1], poses[0, :3, 3], config)
    masks_of = None
    if segmenter is not None:

        def masks_of(k: int) -> list[np.ndarray]:
            return [np.asarray(m, bool).reshape(-1) for m in segmenter.masks(obs.frames[k])]

    tracks = track_objects((frame_points(k) for k in range(t)), plane, config, masks_of)
    status, gap = interaction_test(tracks, obs, config)
    dropped = np.zeros(len(previous.points) if previous is not None else 0, bool)
    carried: list[Carry] = []
    if config.carry_held and previous is not None and joints is not None:
        carried = _carried(joints, obs, previous, plane, tracks, status, config)
    for c in carried:  # each carry is one more track, interacting from grasp to release
        source = previous.points[c.source]  # (n, 3)
        placed = transform_points(c.moved, source)  # (n, 3) at the release
        tracks.append(
            Track(
                {c.grasp: np.zeros(0, np.int64), c.release: np.zeros(0, np.int64)},
                {c.grasp: source, c.release: placed},
                set(),
                placed.mean(0),
            )
        )
        row = np.zeros((1, t), bool)
        row[0, c.grasp : c.release + 1] = True
        status = np.concatenate([status, row])
        gap = np.concatenate([gap, np.full((1, t), np.nan, np.float32)])
        dropped[c.source] = True
    interactive = status.any(axis=1)  # (M,)

    # Background (and untouched objects) by TSDF, without hands and interacted objects.
    tsdf_depth = np.where(valid, depth, 0.0).astype(np.float32)
    for m in np.flatnonzero(interactive):
        for k, pix in tracks[m].pixels.items():
            obj = np.zeros(h * w, bool)
            obj[pix] = True
            grown = _dilate(obj.reshape(h, w), config.hand_dilation_px)
            tsdf_depth[k][grown] = 0.0
    min_weight = config.tsdf_min_weight_estimated if obs.depth_estimated else config.tsdf_min_weight
    bg_pts, bg_rgb = _integrate_tsdf(tsdf_depth, obs.frames, poses, intrinsics, config, min_weight)
    bg_inst = np.zeros(len(bg_pts), np.int32)  # track index + 1 for untouched objects
    for m in np.flatnonzero(~interactive):
        seen = np.concatenate(list(tracks[m].points.values()))
        if len(bg_pts) and len(seen):
            near, _ = cKDTree(seen).query(bg_pts, distance_upper_bound=1.5 * config.voxel_size_m)
            bg_inst[np.isfinite(near) & (bg_inst == 0)] = m + 1
    parts = [
        _Points(
            bg_pts,
            bg_rgb,
            np.full(len(bg_pts), config.voxel_size_m, np.float32),
            bg_inst,
            np.where(bg_inst > 0, SOURCE_OBJECT, SOURCE_BACKGROUND).astype(np.uint8),
        )
    ]
    geo_frame = np.full(len(tracks), -1, np.int64)
    first_carried = len(tracks) - len(carried)
    for i, c in enumerate(carried):  # the carried object: its points before the grasp, moved
        geo_frame[first_carried + i] = c.release
        parts.append(
            _Points(
                tracks[first_carried + i].points[c.release].astype(np.float32),
                previous.colours[c.source],
                previous.point_size[c.source],
                np.full(len(c.source), first_carried + i + 1, np.int32),
                np.full(len(c.source), SOURCE_LAST_OBSERVED, np.uint8),
            )
        )
    for m in np.flatnonzero(interactive[:first_carried]):
        k = geo_frame[m] = geometry_frame(tracks[m], config.settled_distance_m)
        pix = tracks[m].pixels[k]
        obj_pts = tracks[m].points[k].astype(np.float32)
        # A later frame that sees through the object's last place (free space in front of the
        # observed surface) means it left (a lid opened, a track lost): those points go.
        if k + 1 < t:
            _, gone = compare_with_observation(
                obj_pts,
                obs.frames[k].reshape(-1, 3)[pix],
                depth[k + 1 :],
                obs.frames[k + 1 :],
                valid[k + 1 :],
                poses[k + 1 :],
                intrinsics,
                config,
                use_colour=False,
            )
            pix, obj_pts = pix[~gone], obj_pts[~gone]
        parts.append(
            _Points(
                obj_pts,
                obs.frames[k].reshape(-1, 3)[pix],
                (depth[k].reshape(-1)[pix] / intrinsics[0]).astype(np.float32),
                np.full(len(pix), m + 1, np.int32),
                np.full(len(pix), SOURCE_LAST_OBSERVED, np.uint8),
            )
        )
    return tracks, status, gap, _Points.concat(parts), geo_frame, dropped


def _carried(
    joints: np.ndarray,
    obs: Observation,
    previous: State,
    plane: SupportPlane,
    tracks: list[Track],
    status: np.ndarray,
    config: StateFusionConfig,
) -> list[Carry]:
    """The previous state's objects the hands carried (:func:`carry.carried_objects`), less
    those an interacting track already saw: where a track the interaction test flagged starts
    on the carried object (``instance_match_fraction`` of its first points within
    ``instance_match_m`` of it), the observed geometry wins over the carried one."""
    valid = obs.hand_valid if obs.hand_valid is not None else np.ones(joints.shape[:2], bool)
    carries = carried_objects(
        joints, np.asarray(valid, bool), previous.points, previous.instance, plane, config
    )
    kept = []
    for c in carries:
        tree = cKDTree(previous.points[c.source])
        seen = False
        for m in np.flatnonzero(status.any(axis=1)):
            first = tracks[m].points[min(tracks[m].pixels)]
            dist, _ = tree.query(first, distance_upper_bound=config.instance_match_m)
            seen |= float(np.isfinite(dist).mean()) >= config.instance_match_fraction
        if not seen:
            kept.append(c)
    return kept


def _instance_ids(
    tracks: list[Track], previous: State | None, config: StateFusionConfig
) -> np.ndarray:
    """Step 4: ``(M + 1,)`` instance id per track index + 1 (index 0: background = 0); tracks
    that match a previous instance keep its id, others get new ones."""
    ids = np.zeros(len(tracks) + 1, np.int32)
    prev_ids = [inst.id for inst in previous.instances] if previous else []
    next_id = max(prev_ids, default=0) + 1
    for m, tr in enumerate(tracks):
        match = 0
        if previous is not None and tr.pixels:
            first = tr.points[min(tr.pixels)]
            best_frac = config.instance_match_fraction
            for iid in prev_ids:
                ipts = previous.instance_points(iid)
                if len(ipts) == 0:
                    continue
                dist, _ = cKDTree(ipts).query(first, distance_upper_bound=config.instance_match_m)
                frac = float(np.isfinite(dist).mean())
                if frac >= best_frac and iid not in ids:
                    match, best_frac = iid, frac
        if match == 0:
            match, next_id = next_id, next_id + 1
        ids[m + 1] = match
    return ids


def _merge_previous(
    new: _Points,
    previous: State,
    moved_ids: np.ndarray,
    obs: Observation,
    depth: np.ndarray,
    valid: np.ndarray,
    poses: np.ndarray,
    config: StateFusionConfig,
    carried: np.ndarray | None = None,
) -> _Points:
    """Step 5: the previous state's points the clip does not contradict (and not of a moved
    instance, nor ``carried (N,)`` away by a hand), then the new points that add something
    (labels: instance ids)."""
    intrinsics = np.asarray(obs.intrinsics, dtype=np.float64)
    seen, contradicted = compare_with_observation(
        previous.points, previous.colours, depth, obs.frames, valid, poses, intrinsics, config
    )
    n_seen = int(seen.sum())
    if n_seen < config.min_seen_points:
        raise FusionError(
            f"no overlap with the previous state of {previous.clip_id!r}: the clip sees "
            f"{n_seen} of its {len(previous.points)} points, need {config.min_seen_points}"
        )
    in_moved = np.isin(previous.instance, moved_ids) & (previous.instance > 0)
    if carried is not None and len(carried):
        in_moved |= carried
    background_seen = seen & ~in_moved
    agree = 1.0 - contradicted[background_seen].mean() if background_seen.any() else 0.0
    if agree < config.min_agreement:
        raise FusionError(
            f"the previous state of {previous.clip_id!r} disagrees with the clip's depth: "
            f"{agree:.0%} of the {int(background_seen.sum())} points the clip sees agree "
            f"(need {config.min_agreement:.0%}); a state from another world frame?"
        )
    keep_old = ~contradicted & ~in_moved
    old_pts = previous.points[keep_old]
    if len(old_pts):
        near, _ = cKDTree(old_pts).query(new.pts, distance_upper_bound=config.voxel_size_m)
        add = ~np.isfinite(near) | (new.source == SOURCE_LAST_OBSERVED)
    else:
        add = np.ones(len(new.pts), bool)
    old = _Points(
        previous.points[keep_old],
        previous.colours[keep_old],
        previous.point_size[keep_old],
        previous.instance[keep_old],
        np.full(int(keep_old.sum()), SOURCE_PREVIOUS, np.uint8),
    )
    return _Points.concat([old, new.select(add)])


def _instance_table(
    cloud: _Points,
    tracks: list[Track],
    ids: np.ndarray,
    status: np.ndarray,
    gap: np.ndarray,
    geo_frame: np.ndarray,
    previous: State | None,
    t: int,
) -> tuple[list[Instance], np.ndarray]:
    """The instance table of the cleaned cloud (tracks first, then previous instances still
    holding points) and the cloud's instance column with ids outside the table set to 0."""
    interactive = status.any(axis=1)
    last_frame = np.array([max(tr.pixels) if tr.pixels else -1 for tr in tracks], np.int64)
    table: list[Instance] = []
    for m in range(len(tracks)):
        iid = int(ids[m + 1])
        ipts = cloud.pts[cloud.label == iid]
        if len(ipts) == 0:
            continue
        table.append(
            Instance(
                iid,
                "object",
                bool(interactive[m]),
                int(last_frame[m]),
                int(geo_frame[m]),
                status[m],
                gap[m],
                ipts.mean(0).astype(np.float64),
            )
        )
    present = {inst.id for inst in table}
    for inst in previous.instances if previous else []:
        ipts = cloud.pts[cloud.label == inst.id]
        if inst.id in present or len(ipts) == 0:
            continue
        table.append(
            Instance(
                inst.id,
                inst.label,
                False,
                -1,
                -1,
                np.zeros(t, bool),
                np.full(t, np.nan, np.float32),
                ipts.mean(0).astype(np.float64),
            )
        )
    known = {inst.id for inst in table}
    instance = np.where(np.isin(cloud.label, list(known)), cloud.label, 0).astype(np.int32)
    table.sort(key=lambda inst: inst.id)
    return table, instance


def fuse_state(
    obs: Observation,
    previous: State | None,
    config: StateFusionConfig | None = None,
    segmenter: Segmenter | None = None,
) -> State:
    """The state after ``obs`` fused onto ``previous`` (None: the first state of a world).

    ``segmenter`` (the ``grounded_sam`` backend, or any object with ``masks(image)``) gives
    the object clusters instead of DBSCAN (:func:`track_objects`).

    See the module docstring for the steps. Raises :class:`FusionError` for an empty
    observation, a Sim3 outside ``sim3_scale_range`` or with a residual above
    ``max_registration_rms_m``, no camera overlap with the previous state, or a previous state
    that the clip's depth contradicts (another world frame).
    """
    config = config or StateFusionConfig()
    _check_observation(obs)
    t, h, w = obs.depth.shape

    # 1. Registration into the state's world frame.
    scale, sim3, rms = _register(obs, config)
    poses = apply_sim3_to_poses(sim3, scale, obs.world_from_cam)  # (T, 4, 4) state frame
    depth = obs.depth * np.float32(scale)  # (T, H, W) state units
    hands = np.stack([_dilate(obs.hand_mask[k], config.hand_dilation_px) for k in range(t)])
    valid = (depth > 0) & (depth <= config.depth_max_m) & ~hands  # (T, H, W)
    if valid.sum() < 100:
        raise FusionError(
            f"empty observation: {int(valid.sum())} pixels with known depth outside the hands "
            f"in {t} frames"
        )
    if previous is not None:
        _check_overlap(poses, previous, config)

    # 2-3. Object tracks, the interaction test, background by TSDF, interacted objects.
    joints = None
    if obs.hand_joints is not None:  # into the state's frame, as the cameras
        joints = np.asarray(obs.hand_joints, np.float64) @ sim3[:3, :3].T + sim3[:3, 3]
    tracks, status, gap, cloud, geo_frame, dropped = _objects_and_background(
        obs, depth, valid, poses, config, segmenter, previous, joints
    )

    # 4. Instance ids: tracks that match a previous instance keep its id.
    ids = _instance_ids(tracks, previous, config)
    cloud.label = ids[cloud.label]

    # 5. Merge with the previous state.
    if previous is not None:
        moved_ids = ids[1:][status.any(axis=1)]
        cloud = _merge_previous(
            cloud, previous, moved_ids, obs, depth, valid, poses, config, dropped
        )

    # 6. Cleaning, then the instance table.
    cloud = cloud.select(remove_outliers(cloud.pts, config))
    if len(cloud.pts) == 0:
        raise FusionError("empty state: no point survived fusion and outlier removal")
    table, instance = _instance_table(cloud, tracks, ids, status, gap, geo_frame, previous, t)

    frames_names = [f"{obs.clip_id}:{k}" for k in range(t)]
    cams, names = poses, frames_names
    if previous is not None:
        cams = np.concatenate([previous.world_from_cam, poses])
        names = [*previous.camera_frames, *frames_names]
    return State(
        clip_id=obs.clip_id,
        previous_clip_id=previous.clip_id if previous else None,
        world_frame=previous.world_frame if previous else obs.clip_id,
        num_frames=t,
        points=cloud.pts.astype(np.float32),
        colours=cloud.rgb.astype(np.uint8),
        point_size=cloud.size.astype(np.float32),
        instance=instance,
        source=cloud.source.astype(np.uint8),
        instances=table,
        intrinsics=np.asarray(obs.intrinsics, dtype=np.float64),
        width=w,
        height=h,
        world_from_cam=cams,
        camera_frames=names,
        previous_from_clip=sim3,
        sim3_scale=float(scale),
        registration_rms=rms,
    )
