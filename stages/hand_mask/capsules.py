"""Hand-and-arm masks drawn from 2D keypoints: bones as capsules, palm as a polygon, forearm.

Keypoints are 21 joints per hand in MANO/OpenPose order (0 wrist; 1-4 thumb; 5-8 index; 9-12
middle; 13-16 ring; 17-20 little), in pixels of the image (pixel centres at integer + 0.5, the
project's convention). Sizes come from the hand's own scale in the image: the projected lengths
of the rigid palm bones (wrist to each knuckle, knuckle span) divided by average adult lengths
give pixels per metre, and every radius is an average adult radius in metres times that scale.
The forearm is a tapered band from the wrist away from the knuckles, extended to the image border.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

NUM_JOINTS = 21
WRIST = 0
KNUCKLES = (5, 9, 13, 17)  # index, middle, ring, little MCP joints
PALM_POLYGON = (0, 1, 5, 9, 13, 17)  # wrist, thumb CMC and the knuckles, in order round the palm
# Rigid palm segments (joint a, joint b, average adult length in metres) for the hand's scale.
PALM_SEGMENTS = (
    (0, 5, 0.091),
    (0, 9, 0.092),
    (0, 13, 0.088),
    (0, 17, 0.085),
    (5, 17, 0.059),
)
# Bones drawn as capsules: (joint a, joint b, radius in metres).
BONES = (
    ((0, 1, 0.014), (1, 2, 0.0125), (2, 3, 0.011), (3, 4, 0.0095))  # noqa: RUF005
    + tuple(
        (a, b, r)
        for base, r in ((5, 0.0105), (9, 0.0105), (13, 0.0100), (17, 0.0090))
        for a, b in ((0, base), (base, base + 1), (base + 1, base + 2), (base + 2, base + 3))
    )
    + ((5, 17, 0.012),)
)
FOREARM_RADIUS_M = (0.027, 0.036)  # forearm half-width at the wrist and one forearm length on
FOREARM_LENGTH_M = 0.26  # wrist to elbow, average adult, metres
SHIFT = 4  # sub-pixel bits for OpenCV drawing
_ONE = 1 << SHIFT


class KeypointError(ValueError):
    """Keypoints have the wrong shape or type; the message quotes what was given."""


@dataclass(frozen=True)
class CapsuleParams:
    """How generous the drawn capsules are."""

    radius_scale: float = 1.0  # multiplies every average radius (1.0 = adult average)
    forearm: bool = True  # draw the forearm from the wrist to the image border
    core_fraction: float = 0.4  # radius of the "certainly hand" skeleton core, times the capsule's
    body_pulls: tuple[float, ...] = (0.0, 1.0, 3.0, 10.0)  # forearms drawn, one per weight of
    # the egocentric prior (arm comes from below, on its own side) against the wrist direction
    # (knuckles to wrist, weight 1); several make a fan that the colour model then trims

    def __post_init__(self) -> None:
        problems = []
        if not 0.1 <= self.radius_scale <= 10.0:
            problems.append(f"radius_scale must be in [0.1, 10], got {self.radius_scale}")
        if not 0.0 < self.core_fraction <= 1.0:
            problems.append(f"core_fraction must be in (0, 1], got {self.core_fraction}")
        if not self.body_pulls or not all(0.0 <= p <= 100.0 for p in self.body_pulls):
            problems.append(f"body_pulls must be 1+ values in [0, 100], got {self.body_pulls}")
        if problems:
            raise ValueError("; ".join(problems))


def hand_scale_px(keypoints: np.ndarray) -> float:
    """Pixels per metre of one hand ``(21, 2)`` from its rigid palm segments; NaN if unknown.

    The largest ratio of projected to average length is used: foreshortening only shortens a
    segment, so the least foreshortened one is the best estimate of the scale.
    """
    ratios = []
    for a, b, length in PALM_SEGMENTS:
        d = keypoints[b] - keypoints[a]  # (2,)
        if np.all(np.isfinite(d)):
            ratios.append(float(np.hypot(d[0], d[1])) / length)
    return max(ratios) if ratios else float("nan")


def fixed_point(points: np.ndarray) -> np.ndarray:
    """Pixel-centre coordinates ``(..., 2)`` to OpenCV fixed-point integer pixel indices."""
    return np.round((np.asarray(points) - 0.5) * _ONE).astype(np.int32)


def _forearm_polygon(
    keypoints: np.ndarray,
    side: int,
    scale: float,
    body_pull: float,
    params: CapsuleParams,
    height: int,
    width: int,
    arm_target: np.ndarray | None = None,
) -> np.ndarray | None:
    """Quadrilateral ``(4, 2)`` of the forearm in pixels, or None when its direction is unknown."""
    wrist = keypoints[WRIST]
    knuckles = keypoints[list(KNUCKLES)]
    knuckles = knuckles[np.all(np.isfinite(knuckles), axis=1)]
    if not np.all(np.isfinite(wrist)) or len(knuckles) == 0:
        return None
    direction = wrist - knuckles.mean(axis=0)  # (2,) from the knuckles back through the wrist
    norm = float(np.hypot(*direction))
    if norm < 1e-6:
        return None
    direction /= norm
    # Egocentric prior: the arm reaches in from the body, below the image on the hand's side
    # (or towards a given point, such as a projected elbow).
    if arm_target is not None and np.all(np.isfinite(arm_target)):
        body = np.asarray(arm_target, dtype=np.float64) - wrist  # (2,)
    else:
        body = np.array([width * (0.5 + 0.3 * side), 1.5 * height]) - wrist  # (2,)
    direction = direction + body_pull * body / max(float(np.hypot(*body)), 1e-6)
    direction /= max(float(np.hypot(*direction)), 1e-6)
    # Length: far enough to leave the image from wherever the wrist is.
    length = float(np.hypot(height, width)) + float(np.hypot(*(wrist - [width / 2, height / 2])))
    r0, r1 = (r * scale * params.radius_scale for r in FOREARM_RADIUS_M)
    growth = (r1 - r0) / max(FOREARM_LENGTH_M * scale, 1e-6)  # half-width per pixel along the arm
    r_end = min(r0 + growth * length, 2.0 * r1)
    normal = np.array([-direction[1], direction[0]])
    end = wrist + direction * length
    return np.stack(
        [wrist + r0 * normal, end + r_end * normal, end - r_end * normal, wrist - r0 * normal]
    )


def draw_hand(
    keypoints: np.ndarray,
    side: int,
    height: int,
    width: int,
    params: CapsuleParams,
    arm_target: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Draw one hand ``(21, 2)`` (NaN = unknown joint). Returns ``(mask, core)`` uint8 ``(H, W)``.

    ``side`` is -1 for a left hand, +1 for a right hand (0: unknown; the arm then comes from
    straight below). ``arm_target (2,)``, when given, is a pixel the forearm heads towards
    (e.g. a projected elbow); otherwise a point below the image on the hand's side.

    ``mask`` is the capsule mask (1 = hand or arm); ``core`` is the skeleton drawn thin, pixels
    that are hand with high confidence (the colour model learns from them).
    """
    keypoints = np.asarray(keypoints, dtype=np.float64)
    if keypoints.shape != (NUM_JOINTS, 2):
        raise KeypointError(f"keypoints must be ({NUM_JOINTS}, 2), got {keypoints.shape}")
    mask = np.zeros((height, width), np.uint8)
    core = np.zeros((height, width), np.uint8)
    scale = hand_scale_px(keypoints)
    if not np.isfinite(scale) or scale <= 0:
        return mask, core
    known = np.all(np.isfinite(keypoints), axis=1)  # (21,)
    fixed = fixed_point(np.where(known[:, None], keypoints, 0.0))  # (21, 2)
    palm = [i for i in PALM_POLYGON if known[i]]
    if len(palm) >= 3:
        cv2.fillPoly(mask, [fixed[palm]], 1, cv2.LINE_8, SHIFT)
        cv2.fillPoly(core, [fixed_point(_shrink(keypoints[palm], 0.5))], 1, cv2.LINE_8, SHIFT)
    for a, b, radius_m in BONES:
        if not (known[a] and known[b]):
            continue
        radius = radius_m * scale * params.radius_scale
        thickness = max(1, round(2.0 * radius))
        core_thickness = max(1, round(2.0 * radius * params.core_fraction))
        pa_, pb = tuple(int(v) for v in fixed[a]), tuple(int(v) for v in fixed[b])
        cv2.line(mask, pa_, pb, 1, thickness, cv2.LINE_8, SHIFT)
        cv2.line(core, pa_, pb, 1, core_thickness, cv2.LINE_8, SHIFT)
    if params.forearm:
        for pull in params.body_pulls:
            polygon = _forearm_polygon(
                keypoints, side, scale, pull, params, height, width, arm_target
            )
            if polygon is not None:
                cv2.fillPoly(mask, [fixed_point(polygon)], 1, cv2.LINE_8, SHIFT)
        if known[WRIST]:  # the wrist itself is certainly arm, whatever the arm's direction
            radius = FOREARM_RADIUS_M[0] * scale * params.radius_scale * params.core_fraction
            centre = tuple(int(v) for v in fixed[WRIST])
            cv2.circle(core, centre, max(1, round(radius)) * _ONE, 1, -1, cv2.LINE_8, SHIFT)
    return mask, core


def _shrink(points: np.ndarray, factor: float) -> np.ndarray:
    """Points ``(N, 2)`` moved towards their centroid by ``factor`` (0.5 = half way)."""
    centre = points.mean(axis=0)
    return centre + (points - centre) * factor


def draw_hands(
    keypoints: np.ndarray,
    valid: np.ndarray,
    height: int,
    width: int,
    params: CapsuleParams,
    arm_targets: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Union of :func:`draw_hand` over hands ``keypoints (K, 21, 2)`` where ``valid (K,)``.

    With two hands, hand 0 is the left and hand 1 the right (the project's convention).
    ``arm_targets (K, 2)`` optionally gives each forearm's target pixel (NaN = none).
    """
    mask = np.zeros((height, width), np.uint8)
    core = np.zeros((height, width), np.uint8)
    sides = (-1, 1) if len(keypoints) == 2 else (0,) * len(keypoints)
    for k, (hand, ok, side) in enumerate(zip(keypoints, valid, sides, strict=True)):
        if ok:
            target = None if arm_targets is None else arm_targets[k]
            m, c = draw_hand(hand, side, height, width, params, target)
            mask |= m
            core |= c
    return mask, core
