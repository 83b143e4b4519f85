"""The palm-PnP lift of 2D hand landmarks to metric camera joints, one for every user.

The ``hands`` stage places MediaPipe hands with it, and ``depth_camera``'s metric scale measures
the hands it places against the surfaces they touch, so scene, poses and hands share one metric
scale only if both place a hand the same way (issue 17: with the hands stage on this lift and the
scale on a translation-only fit, real hands sat 50% behind the table they touch). Both import it
from here (a stage never imports another stage).

The lift: the palm (wrist and the four knuckles, nearly coplanar) is placed by a planar PnP
(OpenCV's IPPE) of :data:`PALM_TEMPLATE`, an average adult palm, onto the 2D palm landmarks, both
poses refined on the reprojection error (:func:`palm_candidates`); of the two poses a planar PnP
gives, the one with the knuckles beyond the wrist is taken by default
(egocentric prior: the forearm comes from the camera). MediaPipe's metric world landmarks are
rotated onto that palm (Kabsch) to give every joint a depth, and each joint is put on its own
pixel's ray at that depth, so the result reprojects exactly onto the landmarks. Along each finger
(and the thumb from the wrist) a joint's depth is then blended with the depth at which its ray
meets a sphere of the bone's length about its parent (:func:`refine_by_bone_lengths`; lengths
from the world landmarks, scaled to the template palm, the proximal phalanges lengthened:
:func:`landmark_bone_lengths`), weighted by how well that sphere fixes the depth. The four
fingers' depths are then taken from MediaPipe's fingers bent (and splayed) by the angles that
best fit their 2D landmarks with a pull towards MediaPipe's own bends
(:func:`fit_finger_bends`; hands stage v13), each joint kept on its ray. The
template's size sets the distance. A left palm is the right template mirrored; a mirrored planar
template reaches the same camera points (the plane turned over), so the placed points and their
depth do not depend on the side, only the rotation returned does.
"""

from __future__ import annotations

import itertools

import cv2
import numpy as np

from egosim.pipeline.geometry import intrinsics_matrix, rotation_angle_deg

PALM_JOINTS = (0, 5, 9, 13, 17)  # wrist and the index, middle, ring and pinky knuckles
# Joint chains whose depths follow from bone lengths: the thumb from the wrist, each finger from
# its knuckle (MediaPipe / egosim 21-joint order).
FINGER_CHAINS = ((0, 1, 2, 3, 4), (5, 6, 7, 8), (9, 10, 11, 12), (13, 14, 15, 16), (17, 18, 19, 20))
REFINE_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)  # palm pose LM
MIN_POSE_DEPTH = 0.05  # metres: a palm pose with a joint nearer the camera does not pose others
# MediaPipe's world landmarks put each finger's middle joint (PIP) too near its knuckle: relative
# to the palm their proximal phalanges are 0.70 of the hand's (median over the found hands of the
# default synthetic world, seeds 1-4, 11, 13; per finger 0.62-0.86, and 0.67-0.89 on the held-out
# alt world, 0.62-0.78 on real InterHand hands). The bone-length depths take them that much longer.
PROXIMAL_PHALANGES = (6, 10, 14, 18)  # joints ending the index, middle, ring and pinky's first bone
MEDIAPIPE_PROXIMAL_RATIO = 0.70  # MediaPipe's proximal phalanx length / the hand's
# The four fingers' bend fit (:func:`fit_finger_bends`): its two scales are MediaPipe's errors
# measured on the default synthetic world (seeds 1-4, 11, 13, 333 found hand-frames): finger
# landmarks 0.035 of the landmark box's diagonal off in 2D (median), bends 21.8 degrees off (rms
# per joint, MediaPipe's bones turned onto the true palm).
FINGER_PIXEL_SIGMA = 0.05  # a finger joint's 2D residual scale, of the hand's landmark box diagonal
FINGER_ANGLE_SIGMA_DEG = 20.0  # the pull of each splay and bend change towards MediaPipe's shape
FINGER_ITERATIONS = 20  # damped Gauss-Newton steps of the bend fit
MIN_IN_PLANE = 0.3  # a first finger bone's in-plane length below this: hinge from the palm
# An average adult right palm (metres; x from the wrist towards the fingers, y towards the thumb,
# z = 0: the palm is taken as flat): wrist to middle knuckle 9 cm, index to pinky knuckle 6.4 cm.
# Rows follow PALM_JOINTS; a left hand mirrors y.
PALM_TEMPLATE = np.array(
    [
        [0.0, 0.0, 0.0],
        [0.085, 0.027, 0.0],
        [0.090, 0.005, 0.0],
        [0.084, -0.014, 0.0],
        [0.074, -0.031, 0.0],
    ]
)  # (5, 3)


def best_rotation(source: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Rotation ``(3, 3)`` (det +1) minimising ``|R (source - mean) - (target - mean)|`` (Kabsch);
    ``source``, ``target`` ``(N, 3)``."""
    a = source - source.mean(axis=0)  # (N, 3)
    b = target - target.mean(axis=0)  # (N, 3)
    u, _, vt = np.linalg.svd(b.T @ a)
    d = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))])
    return u @ d @ vt


def palm_candidates(
    uv: np.ndarray, intrinsics: np.ndarray, right: bool, refine: bool = True
) -> list[np.ndarray]:
    """Camera points ``(5, 3)`` of :data:`PALM_TEMPLATE` (mirrored for a left hand) that project
    onto the palm landmarks ``uv[PALM_JOINTS]``: the two poses of a planar PnP (IPPE), best first,
    each (with ``refine``) refined by Levenberg-Marquardt on the reprojection error. Empty when
    the PnP fails (degenerate landmarks).

    Why the refinement: IPPE reads both poses off the homography of the five points, and with
    five points a homography (8 degrees of freedom) also absorbs how the observed palm differs
    from the rigid template, so its poses do not minimise the template's reprojection error
    (mean 1.6-4.4 px on the synthetic world's hands, up to 38 px on InterHand's; 0.6-3.2 px
    refined). The refined pitch is nearer the truth: the chosen pose's wrist-to-middle-knuckle
    depth step, median 74 -> 56 mm on the held-out alt world (seeds 11, 13, 163 found
    hand-frames; true 53; the lifted joints' own step 81 -> 61); the palm's own pose error
    on 5 real InterHand hands 30 -> 18 degrees (mean). When the two refined poses tilt the palm
    the same way (one minimum: seen on alt seed 3, where refining raised the MPJPE 19.7 -> 33.4
    mm), IPPE's poses are returned. On by default (hands stage v8), with the proximal phalanges'
    length corrected (:func:`landmark_bone_lengths`): alone, the better palm turned one real
    InterHand hand's whole hand 18.7 -> 27.3 degrees off (figures in "Hands v8" and "Hands v9",
    docs/design.md)."""
    camera_matrix = intrinsics_matrix(intrinsics)  # (3, 3)
    template = PALM_TEMPLATE * np.array([1.0, 1.0 if right else -1.0, 1.0])  # (5, 3)
    image = np.ascontiguousarray(uv[list(PALM_JOINTS)], dtype=np.float64)  # (5, 2)
    if not np.all(np.isfinite(image)):
        return []
    try:
        count, rvecs, tvecs, _ = cv2.solvePnPGeneric(
            template, image, camera_matrix, None, flags=cv2.SOLVEPNP_IPPE
        )
    except cv2.error:
        return []
    # Refined on the right template whatever the side: the flat mirrored template is the right
    # one turned half a turn about its x axis, so both sides reach the same points.
    flip = np.diag([1.0, 1.0 if right else -1.0, 1.0 if right else -1.0])  # (3, 3)
    ippe, refined = [], []  # (5, 3) camera points of each pose
    for rvec, tvec in zip(rvecs[:count], tvecs[:count], strict=True):
        rot = cv2.Rodrigues(rvec)[0]  # (3, 3) cam_from_template
        ippe.append(template @ rot.T + tvec.ravel())
        if refine:  # IPPE's pose is not the rigid template's least-squares reprojection optimum
            rvec, tvec = cv2.solvePnPRefineLM(
                PALM_TEMPLATE,
                image,
                camera_matrix,
                None,
                cv2.Rodrigues(rot @ flip)[0],
                tvec.copy(),
                REFINE_CRITERIA,
            )
            rot = cv2.Rodrigues(rvec)[0] @ flip  # (3, 3) cam_from_template (this side's)
            refined.append(template @ rot.T + tvec.ravel())
    # A planar pose's two answers tilt the palm opposite ways (knuckles beyond the wrist or
    # before it); refined answers that tilt the same way fell into one minimum, and the choice
    # between them is lost: IPPE's are kept then. (OpenCV's IPPE gives two poses or none.)
    steps = {float(np.sign(p[2, 2] - p[0, 2])) for p in refined}  # PALM_JOINTS[2]: middle
    poses = refined if len(steps) == 2 else ippe
    return [points for points in poses if np.all(points[:, 2] > 0)]


def scale_to_depth(points: np.ndarray, observed_depth: float | None) -> np.ndarray:
    """``points (N, 3)`` camera metres scaled about the camera centre (every projection kept) so
    that their median depth is ``observed_depth``; unchanged when it is None, not finite or not
    positive, or the points' median depth is not positive."""
    if observed_depth is not None and np.isfinite(observed_depth) and observed_depth > 0:
        median_z = float(np.median(points[:, 2]))
        if median_z > 0:
            return points * (observed_depth / median_z)
    return points


def palm_pnp_pose(
    uv: np.ndarray,
    world_landmarks: np.ndarray,
    intrinsics: np.ndarray,
    right: bool = True,
    prefer_fingers_away: bool = True,
    refine: bool = True,
    proximal_ratio: float = MEDIAPIPE_PROXIMAL_RATIO,
    fit_fingers: bool = True,
) -> tuple[np.ndarray, np.ndarray] | None:
    """The palm-PnP lift (see :func:`lift_to_camera`) and its rotation: ``(points (21, 3) camera
    metres, cam_from_landmarks (3, 3))`` taking MediaPipe's world-landmark axes to the camera's;
    None when the PnP fails (a palm seen edge-on: its knuckles on one image line). ``refine``:
    the palm poses refined on the reprojection error (:func:`palm_candidates`).
    ``proximal_ratio``: how short the landmarks' proximal phalanges are
    (:func:`landmark_bone_lengths`; 1.0 for true joints, e.g. a test's oracle landmarks).
    ``fit_fingers``: the four fingers' depths from MediaPipe's fingers bent to fit their 2D
    (:func:`fit_finger_bends`; hands stage v13) instead of the bone-length blend
    (:func:`refine_by_bone_lengths`, which still places the thumb)."""
    candidates = palm_candidates(uv, intrinsics, right, refine)  # each (5, 3)
    if not candidates:
        return None
    palm = list(PALM_JOINTS)
    if prefer_fingers_away:
        # PALM_JOINTS[2] is the middle knuckle, [0] the wrist: larger depth step = pointing away.
        chosen = max(candidates, key=lambda p: p[2, 2] - p[0, 2])
    else:
        own = world_landmarks[palm]  # (5, 3) in MediaPipe's axes
        chosen = min(candidates, key=lambda p: rotation_angle_deg(np.eye(3), best_rotation(own, p)))
    rot = best_rotation(world_landmarks[palm], chosen)  # (3, 3) cam_from_landmarks
    model = (world_landmarks - world_landmarks[palm].mean(axis=0)) @ rot.T + chosen.mean(axis=0)
    z = np.maximum(model[:, 2], 1e-3)  # (21,) depth of each joint from the posed model
    lengths = landmark_bone_lengths(world_landmarks, proximal_ratio)  # (21,) m, template size
    points = refine_by_bone_lengths(
        on_rays(uv, z, intrinsics), model[:, 2], uv, intrinsics, lengths
    )
    if fit_fingers:  # the fit's depths, each joint kept on its own landmark's ray
        fitted = fit_finger_bends(points, uv, world_landmarks, rot, intrinsics, lengths)
        points = on_rays(uv, np.maximum(fitted[:, 2], 1e-3), intrinsics)
    return points, rot


def bone_lengths(world_landmarks: np.ndarray) -> np.ndarray:
    """Length ``(21,)`` (metres) of the bone ending at each joint of ``world_landmarks (21, 3)``
    along :data:`FINGER_CHAINS` (0 at the wrist and the four knuckles, which the palm places),
    scaled so that the landmarks' palm has :data:`PALM_TEMPLATE`'s mean radius (MediaPipe's world
    landmarks carry an average-hand size prior; the lift's palm has the template's size)."""
    palm = world_landmarks[list(PALM_JOINTS)]  # (5, 3)
    radius = np.linalg.norm(palm - palm.mean(axis=0), axis=1).mean()
    template = np.linalg.norm(PALM_TEMPLATE - PALM_TEMPLATE.mean(axis=0), axis=1).mean()
    scale = template / radius if radius > 0 else 1.0
    out = np.zeros(len(world_landmarks))
    for chain in FINGER_CHAINS:
        for parent, child in itertools.pairwise(chain):
            out[child] = scale * np.linalg.norm(world_landmarks[child] - world_landmarks[parent])
    return out


def landmark_bone_lengths(
    world_landmarks: np.ndarray, proximal_ratio: float = MEDIAPIPE_PROXIMAL_RATIO
) -> np.ndarray:
    """The hand's bone lengths ``(21,)`` (metres, at :data:`PALM_TEMPLATE`'s size) read from
    MediaPipe's ``world_landmarks (21, 3)``: :func:`bone_lengths` with the proximal phalanges
    divided by ``proximal_ratio`` (:data:`MEDIAPIPE_PROXIMAL_RATIO`; 1.0 for true joints).

    Why: a bone shorter than its 2D extent allows misses its child's ray (the depth falls back on
    MediaPipe's own finger shape), and a short one fixes the depth with a small weight
    (:func:`refine_by_bone_lengths`), so the fingers kept MediaPipe's flexion. Where that flexion
    is wrong, a better palm carried them further off: one real InterHand hand, fingers straight
    and MediaPipe's curled 30-50 degrees, went 18.7 -> 27.3 degrees off with the refined palm;
    with the longer phalanges 17.2 (with the true lengths of these four bones: 18.8). Measured
    (refined palm, wrist-relative MPJPE / orientation): default world seeds 11, 13 24.2 -> 24.1
    mm, 13.1 -> 12.2 deg; held-out alt 20.6 -> 20.0 mm, 9.5 -> 8.6 deg; 5 InterHand hands 28.9
    -> 26.5 mm, 18.7 -> 14.7 deg."""
    lengths = bone_lengths(world_landmarks)  # (21,)
    lengths[list(PROXIMAL_PHALANGES)] /= proximal_ratio
    return lengths


def refine_by_bone_lengths(
    points: np.ndarray,
    model_z: np.ndarray,
    uv: np.ndarray,
    intrinsics: np.ndarray,
    lengths: np.ndarray,
) -> np.ndarray:
    """Camera points ``(21, 3)``: ``points (21, 3)`` (on their rays, see :func:`on_rays`) with the
    finger joints' depths re-estimated from bone lengths, parent to child along
    :data:`FINGER_CHAINS` (the wrist and knuckles stay).

    A child's ray meets the sphere of radius ``lengths[child]`` about its (already refined) parent
    at up to two depths; the one nearer the posed model's depth step (``model_z (21,)``: the
    parent's depth plus the model's child-minus-parent step) is taken. The two roots are
    ``d.P +- r`` along the unit ray ``d``, with ``r = sqrt(L^2 - |P|^2 + (d.P)^2)`` the bone's
    extent along the ray: a bone seen end-on (``r`` near ``L``) fixes the depth well, one seen
    sideways (``r`` near 0: depth changes barely move the pixel) does not, so the depth is
    ``w * bone + (1 - w) * model`` with ``w = r / L``; a ray that misses the sphere (the 2D bone
    is longer than the bone) takes the model's depth. Every joint stays on its pixel's ray.
    Measured on the synthetic world (seeds 11, 13; wrist-relative MPJPE, default / held-out alt):
    26.6 -> 26.1 mm / 32.3 -> 30.4 mm; the bone depth alone (``w = 1``) gave 29.9 / 25.5 (worse
    on the default world, whose 2D landmarks are off by 11 px)."""
    rays = on_rays(uv, np.ones(len(uv)), intrinsics)  # (21, 3) at depth 1
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)  # (21, 3) unit rays
    out = np.array(points, dtype=np.float64)  # (21, 3)
    for chain in FINGER_CHAINS:
        for parent, child in itertools.pairwise(chain):
            length = float(lengths[child])
            ray, base = rays[child], out[parent]  # (3,), (3,)
            model = base[2] + (model_z[child] - model_z[parent])  # depth the model gives
            along = float(ray @ base)
            disc = along * along - float(base @ base) + length * length
            if length <= 0 or disc < 0 or not np.isfinite(disc):
                depth = model
            else:
                r = np.sqrt(disc)
                bone = min(
                    ((along - r) * ray[2], (along + r) * ray[2]), key=lambda z: abs(z - model)
                )
                w = min(1.0, r / length)
                depth = w * bone + (1.0 - w) * model
            out[child] = ray * (max(depth, 1e-3) / ray[2])
    return out


def palm_axes(points: np.ndarray) -> np.ndarray | None:
    """Rows ``(3, 3)``: the palm's unit axes from ``points (21, 3)`` (any frame): ``x`` from the
    wrist to the middle knuckle, ``t`` from the pinky knuckle towards the index one (made
    orthogonal to ``x``) and ``n = x cross t``, normal to the palm; None when degenerate. The same
    rule on a left and a right hand gives normals out of opposite sides of the palm (out of the
    back of a right hand), so a bend towards ``n`` closes a left hand and opens a right one; the
    fit (:func:`fit_finger_bends`) pulls bends towards MediaPipe's either way, so it does not
    need the side."""
    x = points[9] - points[0]  # (3,) wrist to middle knuckle
    t = points[5] - points[17]  # (3,) pinky knuckle to index knuckle
    x_norm = float(np.linalg.norm(x))
    if not np.isfinite(x_norm) or x_norm <= 0:
        return None
    x = x / x_norm
    t = t - (t @ x) * x
    t_norm = float(np.linalg.norm(t))
    if not np.isfinite(t_norm) or t_norm <= 1e-9:
        return None
    t = t / t_norm
    return np.stack([x, t, np.cross(x, t)])  # (3, 3)


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a x b`` over the last axis (size 3), broadcast (np.cross's overhead dominated the fit)."""
    return np.stack(
        [
            a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1],
            a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2],
            a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0],
        ],
        axis=-1,
    )


def _turn(axis: np.ndarray, angle: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``v (F, B, 3)`` turned about unit ``axis (F, 3)`` by ``angle (F, B)`` radians (Rodrigues)."""
    c, s = np.cos(angle)[..., None], np.sin(angle)[..., None]  # (F, B, 1)
    a = axis[:, None, :]  # (F, 1, 3)
    return v * c + _cross(a, v) * s + a * np.sum(a * v, axis=-1, keepdims=True) * (1.0 - c)


def bend_fingers(
    knuckles: np.ndarray,
    directions: np.ndarray,
    lengths: np.ndarray,
    changes: np.ndarray,
    axes: np.ndarray,
) -> np.ndarray:
    """``(F, 3, 3)`` the three joints after each of ``knuckles (F, 3)`` of fingers whose bones
    point along unit ``directions (F, 3, 3)`` with ``lengths (F, 3)`` metres, changed by
    ``changes (F, 4)`` radians: a splay of the whole finger about the palm's normal ``n``, then a
    bend of each bone and those after it about the finger's hinge axis (the first bone's
    direction in the palm plane crossed with ``n``: a positive bend turns the finger towards
    ``n``; ``-t`` where the first bone is within ``acos(MIN_IN_PLANE)`` of the normal and its
    in-plane direction is noise). ``axes (3, 3)``: rows ``x, t, n`` (:func:`palm_axes`). Zero
    changes give the bones as they are; any changes keep the bone lengths."""
    count = len(knuckles)
    normal = axes[2]  # (3,)
    normals = np.broadcast_to(normal, (count, 3))  # (F, 3)
    along = directions[:, 0] - (directions[:, 0] @ normal)[:, None] * normal  # (F, 3) in plane
    flat = np.linalg.norm(along, axis=1, keepdims=True)  # (F, 1)
    hinge = np.where(  # (F, 3); x cross n = -t
        flat > MIN_IN_PLANE, _cross(along / np.maximum(flat, 1e-12), normal), -axes[1]
    )
    dirs = _turn(normals, np.repeat(changes[:, :1], 3, axis=1), directions)  # (F, 3, 3) splayed
    hinge = _turn(normals, changes[:, :1], hinge[:, None, :])[:, 0]  # (F, 3)
    dirs = _turn(hinge, np.cumsum(changes[:, 1:], axis=1), dirs)  # (F, 3, 3) bent
    return knuckles[:, None, :] + np.cumsum(lengths[..., None] * dirs, axis=1)


def fit_finger_bends(
    points: np.ndarray,
    uv: np.ndarray,
    world_landmarks: np.ndarray,
    cam_from_landmarks: np.ndarray,
    intrinsics: np.ndarray,
    lengths: np.ndarray,
    pixel_sigma: float = FINGER_PIXEL_SIGMA,
    angle_sigma_deg: float = FINGER_ANGLE_SIGMA_DEG,
    iterations: int = FINGER_ITERATIONS,
) -> np.ndarray:
    """Camera points ``(21, 3)``: ``points (21, 3)`` (the lift, palm placed) with the four
    fingers' joints replaced by MediaPipe's fingers bent to fit their landmarks ``uv (21, 2)``.

    Each finger (index..pinky) hangs from its placed knuckle with MediaPipe's bone directions
    (``world_landmarks (21, 3)`` turned by ``cam_from_landmarks (3, 3)``) and the bone
    ``lengths (21,)`` (:func:`landmark_bone_lengths`), changed by four angles
    (:func:`bend_fingers`): a splay about the placed palm's normal (:func:`palm_axes`) and a bend
    at each of its three joints about the finger's hinge axis. The angles minimise the joints'
    reprojection error (scaled by ``pixel_sigma`` of the landmark box's diagonal) plus a pull
    towards zero (MediaPipe's own shape, scaled by ``angle_sigma_deg``), from zero, by damped
    Gauss-Newton (the four fingers at once). Why: each finger's three joints give six 2D
    measures for its four angles, so the 2D (good on the four fingers: 4-10 px on the synthetic
    worlds) decides how far each finger bends towards or away from the camera, where the
    bone-length blend (:func:`refine_by_bone_lengths`) kept MediaPipe's depths wherever a bone
    is seen sideways; the pull keeps the side of the ray MediaPipe's bend is on. MediaPipe's
    shape is kept wherever it already reprojects onto the landmarks (zero changes). The thumb and
    the palm are unchanged. Returns ``points`` unchanged where the palm's axes are degenerate or
    the fit is not finite."""
    axes = palm_axes(points)
    if axes is None or not np.all(np.isfinite(uv)) or not np.all(np.isfinite(world_landmarks)):
        return points
    fx, fy, cx, cy = np.asarray(intrinsics, dtype=np.float64)
    chains = np.array(FINGER_CHAINS[1:])  # (4, 4) knuckle to tip
    knuckles = points[chains[:, 0]]  # (4, 3)
    bones = np.asarray(lengths, dtype=np.float64)[chains[:, 1:]]  # (4, 3)
    directions = np.diff(world_landmarks[chains], axis=1) @ cam_from_landmarks.T  # (4, 3, 3)
    norms = np.linalg.norm(directions, axis=2, keepdims=True)  # (4, 3, 1)
    if np.any(norms <= 0):
        return points
    directions = directions / norms
    target = uv[chains[:, 1:]]  # (4, 3, 2)
    sigma_px = max(pixel_sigma * float(np.linalg.norm(np.ptp(uv, axis=0))), 1.0)
    sigma_angle = np.deg2rad(angle_sigma_deg)

    tiled = {c: (np.tile(knuckles, (c, 1)), np.tile(directions, (c, 1, 1)), np.tile(bones, (c, 1)))
             for c in (1, 4)}  # fmt: skip

    def residuals(changes: np.ndarray) -> np.ndarray:  # (C, 4, 4) -> (C, 4, 10), C = 1 or 4
        c = len(changes)  # sets of changes, all fingers of all sets in one call
        joints = bend_fingers(*tiled[c], changes.reshape(-1, 4), axes).reshape(c, 4, 3, 3)
        z = np.maximum(joints[..., 2], 1e-3)  # (C, 4, 3)
        pix = np.stack([fx * joints[..., 0] / z + cx, fy * joints[..., 1] / z + cy], axis=-1)
        return np.concatenate(
            [((pix - target) / sigma_px).reshape(c, 4, 6), changes / sigma_angle], axis=2
        )

    changes = np.zeros((4, 4))  # radians: MediaPipe's own shape
    damping = np.full(4, 1e-3)  # per finger
    res = residuals(changes[None])[0]  # (4, 10)
    eps = 1e-6  # radians, forward-difference step
    nudges = eps * np.eye(4)[:, None, :]  # (4, 1, 4): each angle of every finger at once
    for _ in range(iterations):
        jac = np.moveaxis((residuals(changes + nudges) - res) / eps, 0, 2)  # (4, 10, 4)
        normal = np.einsum("fri,frj->fij", jac, jac)  # (4, 4, 4)
        grad = np.einsum("fri,fr->fi", jac, res)  # (4, 4)
        lhs = normal + damping[:, None, None] * (np.eye(4) + normal * np.eye(4))
        step = -np.linalg.solve(lhs, grad[..., None])[..., 0]  # (4, 4)
        trial = residuals((changes + step)[None])[0]  # (4, 10)
        better = (trial**2).sum(axis=1) < (res**2).sum(axis=1)  # (4,)
        changes = np.where(better[:, None], changes + step, changes)
        res = np.where(better[:, None], trial, res)
        damping = np.where(better, damping * 0.3, damping * 10.0)
        if np.abs(step).max() < 1e-5:  # radians: converged (or stuck) on every finger
            break
    joints = bend_fingers(knuckles, directions, bones, changes, axes)  # (4, 3, 3)
    if not np.all(np.isfinite(joints)):
        return points
    out = np.array(points, dtype=np.float64)  # (21, 3)
    out[chains[:, 1:].ravel()] = joints.reshape(-1, 3)
    return out


def on_rays(uv: np.ndarray, z: np.ndarray, intrinsics: np.ndarray) -> np.ndarray:
    """Camera points ``(21, 3)``: each pixel of ``uv (21, 2)`` on its ray at depth ``z (21,)``."""
    fx, fy, cx, cy = np.asarray(intrinsics, dtype=np.float64)
    x_n = (uv[:, 0] - cx) / fx  # (21,)
    y_n = (uv[:, 1] - cy) / fy  # (21,)
    return np.stack([x_n * z, y_n * z, z], axis=1)  # (21, 3) on each landmark's ray


def lift_with_rotation(
    uv: np.ndarray,
    world_landmarks: np.ndarray,
    intrinsics: np.ndarray,
    cam_from_landmarks: np.ndarray,
    median_depth: float,
    matched: tuple[int, ...] | None = None,
) -> np.ndarray:
    """Camera joints ``(21, 3)`` of a hand whose palm PnP failed, posed like a neighbouring frame:
    the world landmarks turned by that frame's ``cam_from_landmarks (3, 3)`` give each joint its
    depth offset, the median depth of the ``matched`` joints (None: all 21) is ``median_depth``
    (metres, the neighbour's median over the same joints), and each joint is put on its own
    pixel's ray (so the result reprojects onto ``uv (21, 2)``). The hands stage matches the palm
    (:data:`PALM_JOINTS`, hands v14): the palm is rigid, while the neighbour's finger depths follow
    its own 2D (:func:`fit_finger_bends`), not this frame's."""
    turned = (world_landmarks - world_landmarks.mean(axis=0)) @ cam_from_landmarks.T  # (21, 3)
    pick = list(matched) if matched is not None else slice(None)
    z = np.maximum(turned[:, 2] - np.median(turned[pick, 2]) + median_depth, 1e-3)  # (21,)
    return on_rays(uv, z, intrinsics)
