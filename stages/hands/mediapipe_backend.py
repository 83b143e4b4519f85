"""Backend ``mediapipe``: MediaPipe Hands 2D landmarks lifted to 3D world joints.

Steps, for one clip:

1. **Detect** (:func:`detect_landmarks`): ``mediapipe.solutions.hands.Hands`` in video (tracking)
   mode (``static_image_mode=False``), which finds far more hands on egocentric video than
   per-image mode. Per frame up to two hands: 21 image landmarks (pixels), 21 world landmarks
   (metres, about the hand's centre, camera-aligned axes, an average-hand size prior) and a
   handedness label with its score. Head-mounted footage shows hands low and at the image edges,
   small, partial and in sleeves, where the full-frame palm detector misses most of them; so the
   frame is also searched in zoomed tiles (``tiles``, per-image mode, ``tile_zoom`` times larger)
   and a tile's detection is kept where the full frame found no hand near it
   (:func:`merge_tile_detections`). On the real DWM Aria clips this raised the frames with a
   detection from 1 to 12 of 49 (00013) and found the second hand in 00017.
   Then every hand found is followed forwards and backwards in time into the frames that miss
   it (``track_misses``): MediaPipe's landmark model is run directly, with a TFLite runtime, on
   the ROI its previous landmarks predict, moved by optical flow
   (:mod:`egosim.stages.common.roi_landmarks`), so a hand found at frame 3 is also found at
   frames 0-2. On DWM clip 00013 this raised left-hand recall from 0.17 to 1.0, right 0.42 to
   0.96; on HOT3D both hands went from 61% to 76% of frames. A hand the landmark model loses
   (a blurred frame while the head turns, a hand half out of the frame) is carried on by the
   optical flow alone for up to ``track.max_coast`` frames and looked for again there, and dark
   crops are contrast-stretched (``track.max_gain``) before the model sees them.
2. **Scene check** (:func:`drop_scene_tracks`, hands v13): a track whose hull colour is off the
   clip's confident hands' skin and that stays still against the background is part of the
   scene and dropped (:mod:`egosim.stages.hands.scene_check`: the EgoDex portrait variant's
   curtain fold, found and followed on 20 of 33 frames). A confident track (median presence at
   least ``seed_presence``) and one of under three frames are never dropped.
3. **Sides** (:func:`assign_sides`): MediaPipe's labels assume a mirrored (selfie) image, so on
   egocentric video its "Left" is the real right hand, and the labels flip now and then. Detections
   are linked into tracks (nearest centroid frame to frame); each track takes one side from its
   swapped labels' summed scores plus an image-position vote (left half = left hand) and a
   forearm vote (:func:`forearm_entry`: where the line through the middle knuckle and the wrist
   meets the bottom of the image; egocentric, the left forearm comes in from the bottom left),
   which does not use MediaPipe's handedness head; two tracks at the same time never share a
   side (the one further right becomes the right hand). A track shorter than
   ``min_track_frames`` whose vote wants a side a longer track holds at that time is dropped
   rather than given the other side (an isolated false hand would otherwise take it); one of
   the same length does not drop it (two hands entering in one frame, each too fast to link to
   its later track: both keep a side, by position; hands v18).
4. **Bridge and smooth** (:func:`bridge_and_smooth`): gaps of up to ``max_gap`` frames inside a
   track (ends no further apart than ``_tracks`` links) are filled by linear interpolation (lower
   confidence), then image and world landmarks
   are smoothed over time with a Gaussian of ``smooth_sigma`` frames (landmarks jitter by a few
   percent of the hand's size frame to frame), within runs of frames whose centres are as near
   as ``_tracks`` links one frame apart: two tracks given one side in adjacent frames are not
   blended (HOT3D window 0: the right hand was pulled 20-110 px onto the forearm at frames
   24-28 by a false sleeve detection that took its side at frame 26).
5. **Lift** (:func:`lift_to_camera`): MediaPipe's world landmarks give a hand *shape* but their
   axes are not the camera's (on the synthetic world they were 74-82 degrees off), so the palm is
   placed by a planar PnP of an average palm template onto the 2D palm landmarks, refined on the
   reprojection error (of its two poses, the one with the fingers pointing away from a
   head-mounted camera), the world landmarks are rotated onto that palm to give each joint a
   depth, and each joint is put on its pixel's ray; finger joints' depths are then pulled
   towards the bone lengths (:func:`~egosim.stages.common.hand_lift.refine_by_bone_lengths`;
   MediaPipe's proximal phalanges lengthened,
   :func:`~egosim.stages.common.hand_lift.landmark_bone_lengths`), and the four fingers are
   MediaPipe's fingers bent to fit their 2D (hands v13,
   :func:`~egosim.stages.common.hand_lift.fit_finger_bends`). The points are then scaled
   about the camera centre (which keeps the projection) so that their median depth equals the
   median depth observed under the 2D landmarks; without depth the template's average-hand size
   sets the distance. A palm seen edge-on has no PnP pose in front of the camera: it takes the
   rotation and depth of the same hand's nearest frame with one (within ``max_gap`` frames;
   :func:`lift_with_rotation`) rather than MediaPipe's own axes, whose 74-82 degree turn the
   spike filter would drop.
6. **Repair** (:func:`repair_unsure`, hands v10): a palm turning off its own track faster than
   ``max_turn_rate`` (:func:`~egosim.stages.hands.filters.turn_outliers`, over ``turn_window``
   frames either side, in the camera frame) is interpolated between trusted frames of its track
   within ``max_gap`` (turn slerped, wrist lerped); where there are none its 3D is withheld: the
   hand stays valid with its joints on its landmarks' rays (its 2D), confidence times 0.1, and
   ``MediaPipeResult.lifted`` False, which the stage writes as ``hand_lifted`` (hands schema v3).
   A small hand (wrist to middle knuckle under ``spread_max_size`` of the frame height: 40 px at
   480 rows) whose landmarks the model reads differently when its ROI is turned, scaled or
   mirrored (:func:`spread_outliers`, over ``max_spread`` of its size; hands v15) is treated the
   same way: on the synthetic world these are small and half-hidden hands whose lifted palm is
   60-180 degrees off.
   The fingers' wrist-relative depths are smoothed over time within runs of trusted frames
   (``finger_depth_sigma``, :func:`~egosim.stages.hands.filters.smooth_finger_depths`, hands
   v14; each joint kept on its ray), and so is each trusted palm's turn, in the world frame
   when the clip has poses (``palm_turn_sigma``,
   :func:`~egosim.stages.hands.filters.smooth_palm_turns`, hands v21: the shape turned about
   its wrist, each joint kept on its ray). Then to world with ``world_from_cam``.

:func:`mediapipe_hands` runs all of it; :func:`mediapipe_detections` wraps it for the stage.
MediaPipe is imported lazily: install it as ``make setup`` does (``--no-deps mediapipe==0.10.21``).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, replace

import numpy as np

from egosim.pipeline.geometry import slerp_rotations, transform_points
from egosim.pipeline.records import LEFT, NUM_HAND_JOINTS, RIGHT, Clip
from egosim.stages.common.hand_landmarks import (  # one detector for hands and metric scale
    HandLandmarkParams,
    MediaPipeUnavailableError,  # noqa: F401 (raised by detect_landmarks, importable here)
    RawLandmarks,
    drop_overlapping,
    hand_centres,
    hand_size,
    landmark_presence,
    place_in_camera,
)
from egosim.stages.common.hand_landmarks import detect_hand_landmarks as detect_landmarks
from egosim.stages.common.hand_lift import (  # one lift for the hands and the metric scale
    MIN_POSE_DEPTH,
    PALM_JOINTS,
    lift_with_rotation,
    palm_pnp_pose,
    scale_to_depth,
)
from egosim.stages.common.roi_landmarks import MIDDLE_MCP, LandmarkModel, landmark_spread
from egosim.stages.hands.filters import (
    Detections,
    gaussian_smooth_runs,
    palm_rotations,
    smooth_finger_depths,
    smooth_palm_turns,
    turn_outliers,
)
from egosim.stages.hands.scene_check import SceneCheckParams, scene_tracks, seed_candidates

BRIDGED_CONFIDENCE_FACTOR = 0.5  # confidence of interpolated frames relative to detected ones
WITHHELD_CONFIDENCE_FACTOR = 0.1  # confidence of a hand whose 3D is withheld (2D kept)


@dataclass(frozen=True)
class MediaPipeParams(HandLandmarkParams):
    """Knobs of the MediaPipe backend: the detector's (:class:`HandLandmarkParams`, shared with the
    metric scale, so both see the same hands) plus sides, bridging, smoothing and the lift."""

    max_gap: int = 4  # frames of a track's gap filled by interpolation
    smooth_sigma: float = 1.0  # Gaussian smoothing of landmarks over time, in frames; 0 = none
    # Gaussian smoothing over time of the four fingers' depths (wrist-relative, on their rays:
    # the 2D kept) within runs of trusted frames, in frames (filters.smooth_finger_depths: the
    # bend fit is per frame; hands v14); 0 = none
    finger_depth_sigma: float = 1.0
    # Gaussian smoothing over time of each trusted hand's palm turn (in the world frame when the
    # clip has poses), the shape turned about the wrist and kept on its rays (the 2D kept), in
    # frames (filters.smooth_palm_turns: the palm PnP is per frame; hands v21); 0 = none
    palm_turn_sigma: float = 1.0
    link_distance: float = 0.6  # max centroid jump between linked detections, in hand sizes
    # per frame of gap up to two (link_limit: tracks, and which gaps are bridged)
    position_weight: float = 0.5  # weight of the image-position side vote vs the labels
    # weight of the forearm side vote (forearm_entry: where the forearm comes into the image)
    # vs the labels; 0 = labels and position only (hands v15)
    forearm_weight: float = 1.0
    lift: str = "palm_pnp"  # 3D lift: "palm_pnp" (template palm PnP) or "translation" (old)
    prefer_fingers_away: bool = True  # palm PnP: of its two poses take knuckles beyond the wrist
    min_track_frames: int = 3  # a shorter track wanting a side a longer one holds then is dropped
    refine_palm: bool = True  # palm PnP: refine IPPE's poses on the reprojection error (hand_lift
    # palm_candidates; see "Hands v8" and "Hands v9" in docs/design.md)
    max_turn_rate: float = 320.0  # deg/s: a palm turning faster than this from its track's
    # neighbours (filters.turn_outliers) is interpolated between them or withheld; inf = no test
    turn_window: int = 3  # frames either side the turn test compares with
    # a small hand (spread_max_size) whose landmarks move by more than max_spread of its size
    # when the landmark model is run again on its ROI turned, scaled and mirrored
    # (roi_landmarks.landmark_spread) has its 3D withheld (hands v15); the test needs the frames
    # (hands_from_raw's frames=None skips it); inf = no test. 0.05 with the four answers of
    # roi_landmarks.SPREAD_TRANSFORMS flags the tuned hand-frames 0.06 flagged with six (hands17)
    max_spread: float = 0.05
    # wrist to middle knuckle as a share of the frame height (40 px at 480 rows, so an ingest at
    # another size tests the same hands); only smaller hands are tested (0 = none)
    spread_max_size: float = 40.0 / 480.0
    scene_check: SceneCheckParams | None = SceneCheckParams()  # noqa: RUF009 (frozen) a track
    # off the clip's skin and still against the scene is dropped (scene_check); None = keep all

    def __post_init__(self) -> None:
        super().__post_init__()
        problems = []
        if not 0 <= self.palm_turn_sigma < np.inf:
            problems.append(
                f"palm_turn_sigma must be >= 0 and finite, got {self.palm_turn_sigma!r}"
            )
        if not self.max_turn_rate > 0:
            problems.append(f"max_turn_rate must be > 0 deg/s, got {self.max_turn_rate!r}")
        if self.turn_window < 1:
            problems.append(f"turn_window must be >= 1, got {self.turn_window!r}")
        if not self.max_spread > 0:
            problems.append(f"max_spread must be > 0, got {self.max_spread!r}")
        if not self.spread_max_size >= 0:
            problems.append(
                f"spread_max_size must be >= 0 (of the frame height), got {self.spread_max_size!r}"
            )
        if problems:
            raise ValueError("invalid MediaPipeParams: " + "; ".join(problems))


@dataclass
class SideLandmarks:
    """Landmarks per side (slot 0 = left, 1 = right)."""

    uv: np.ndarray  # (T, 2, 21, 2) float64 pixels, NaN where absent
    world: np.ndarray  # (T, 2, 21, 3) float64 metres, NaN where absent
    confidence: np.ndarray  # (T, 2) float64 in [0, 1], 0 where absent
    present: np.ndarray  # (T, 2) bool detected or bridged
    detected: np.ndarray  # (T, 2) bool detected (not bridged)
    # (T, 2) bool: a present frame that begins a new run after a present frame (two tracks given
    # one side in adjacent frames: two hands, smoothed apart); None: runs are the present frames
    starts: np.ndarray | None = None


def link_limit(size_a: float, size_b: float, gap: int, params: MediaPipeParams) -> float:
    """The largest centroid jump (pixels) between two detections ``gap`` frames apart, of
    hand sizes ``size_a`` and ``size_b`` pixels, that can be one hand: the tracks' links and the
    bridged gaps both use it. It grows with the gap but stops at two frames' worth: a hand
    reappearing far away after a gap is another hand (the synthetic world's right hand at frame
    0 was linked to the left hand's track 5 frames and 250 px later)."""
    return params.link_distance * max(size_a, size_b) * min(gap, 2)


def _tracks(raw: RawLandmarks, params: MediaPipeParams) -> list[list[tuple[int, int]]]:
    """Link detections ``(frame, slot)`` into tracks by nearest centroid, across short gaps."""
    centre = hand_centres(raw.uv)  # (T, K, 2)
    size = hand_size(raw.uv)  # (T, K)
    tracks: list[list[tuple[int, int]]] = []
    open_tracks: list[int] = []  # indices into tracks still extendable
    for f in range(raw.present.shape[0]):
        dets = [k for k in np.flatnonzero(raw.present[f])]
        candidates = []
        for ti in open_tracks:
            lf, lk = tracks[ti][-1]
            if f - lf > params.max_gap + 1:
                continue
            for k in dets:
                dist = np.linalg.norm(centre[f, k] - centre[lf, lk])
                if dist <= link_limit(size[lf, lk], size[f, k], f - lf, params):
                    candidates.append((dist, ti, k))
        used_t: set[int] = set()
        used_k: set[int] = set()
        for _, ti, k in sorted(candidates):
            if ti in used_t or k in used_k:
                continue
            tracks[ti].append((f, k))
            used_t.add(ti)
            used_k.add(k)
        for k in dets:
            if k not in used_k:
                tracks.append([(f, k)])
        open_tracks = [ti for ti, tr in enumerate(tracks) if f - tr[-1][0] <= params.max_gap + 1]
    return tracks


def forearm_entry(uv: np.ndarray, width: int, height: int) -> np.ndarray:
    """``(...)`` in [-1, 1]: where the forearm of landmarks ``uv (..., 21, 2)`` (pixels in a
    ``width`` x ``height`` frame) comes into the image, -1 at the left border, +1 at the right:
    the line from the middle knuckle through the wrist, followed on from the wrist, meets the
    bottom row's level at this horizontal place (clipped: a line that leaves through a side
    border first gives that side). A forearm pointing up from the wrist (an arm from above)
    gives 0, as do absent landmarks. Head-mounted cameras see the left forearm come in from
    the bottom left and the right one from the bottom right, wherever the hand is; unlike
    MediaPipe's handedness it does not flip under heavy compression (docs/design.md, "Hands
    v16: sides from the forearm, the mirror, a probe before the stretched pass")."""
    wrist = uv[..., 0, :]  # (..., 2)
    ray = wrist - uv[..., MIDDLE_MCP, :]  # (..., 2) from the knuckle, on past the wrist
    with np.errstate(invalid="ignore", divide="ignore"):
        reach = (height - wrist[..., 1]) / ray[..., 1]  # (...) steps to the bottom row's level
        at_bottom = wrist[..., 0] + reach * ray[..., 0]  # (...) pixels, +-inf when level
        vote = np.clip(2.0 * at_bottom / width - 1.0, -1.0, 1.0)  # (...)
        down = ray[..., 1] > 0  # (...) a forearm going down from the wrist
    level = (ray[..., 1] == 0) & (ray[..., 0] != 0)  # (...) a level forearm: its side
    vote = np.where(level, np.sign(ray[..., 0]), np.where(down, vote, 0.0))
    return np.nan_to_num(vote, nan=0.0)


def assign_sides(
    raw: RawLandmarks, width: int, params: MediaPipeParams | None = None
) -> np.ndarray:
    """Side per detection ``(T, K)`` int (0 left, 1 right, -1 none); see the module docstring."""
    params = params or MediaPipeParams()
    centre_u = hand_centres(raw.uv)[..., 0]  # (T, K)
    forearm = np.zeros(raw.present.shape)  # (T, K) > 0: a forearm from the bottom right
    if raw.frame_height is not None:
        forearm = forearm_entry(raw.uv, width, raw.frame_height)
    side = np.full(raw.present.shape, -1, dtype=int)
    tracks = _tracks(raw, params)
    votes = []
    for tr in tracks:
        f, k = np.array(tr).T
        label_vote = float(np.sum(2.0 * raw.label_right[f, k] - 1.0))  # > 0: right
        position_vote = float(np.sum(np.clip(2.0 * centre_u[f, k] / width - 1.0, -1, 1)))
        forearm_vote = float(np.sum(forearm[f, k]))
        votes.append(
            label_vote
            + params.position_weight * position_vote
            + params.forearm_weight * forearm_vote
        )
    # Longest tracks choose first; a side already taken in any shared frame goes to the other.
    held = np.zeros((raw.present.shape[0], 2), dtype=int)  # (T, 2) holding track's length; 0: free
    for ti in sorted(range(len(tracks)), key=lambda i: -len(tracks[i])):
        f, k = np.array(tracks[ti]).T
        n = len(tracks[ti])
        want = RIGHT if votes[ti] > 0 else LEFT
        other = 1 - want
        if n < params.min_track_frames and (held[f, want] > n).any():
            continue  # an isolated detection contradicting a longer track of its side: dropped
        # (a track of the same length is no more established: the two then share the frames'
        # sides, and the position rule below orders them; hands v18)
        for s in (want, other):
            if not held[f, s].any():
                side[f, k] = s
                held[f, s] = n
                break
        else:  # both sides taken somewhere: per frame, the free side nearest its preference
            for fi, ki in zip(f, k, strict=True):
                for s in (want, other):
                    if not held[fi, s]:
                        side[fi, ki] = s
                        held[fi, s] = n
                        break
    # Two hands in a frame: the one further right in the image is the right hand.
    both = (side == LEFT).any(axis=1) & (side == RIGHT).any(axis=1)
    for f in np.flatnonzero(both):
        kl, kr = int(np.flatnonzero(side[f] == LEFT)[0]), int(np.flatnonzero(side[f] == RIGHT)[0])
        if centre_u[f, kl] > centre_u[f, kr]:
            side[f, kl], side[f, kr] = RIGHT, LEFT
    return side


def bridge_and_smooth(
    raw: RawLandmarks, side: np.ndarray, params: MediaPipeParams | None = None
) -> SideLandmarks:
    """Per-side landmarks with gaps of ``max_gap`` frames bridged and jitter smoothed."""
    params = params or MediaPipeParams()
    t = raw.present.shape[0]
    uv = np.full((t, 2, NUM_HAND_JOINTS, 2), np.nan)
    world = np.full((t, 2, NUM_HAND_JOINTS, 3), np.nan)
    conf = np.zeros((t, 2))
    detected = np.zeros((t, 2), dtype=bool)
    for f, k in zip(*np.nonzero(side >= 0), strict=True):
        s = side[f, k]
        uv[f, s], world[f, s], detected[f, s] = raw.uv[f, k], raw.world[f, k], True
        # Detection confidence: how clearly the labels agree with the assigned side.
        conf[f, s] = 0.5 + abs(raw.label_right[f, k] - 0.5)
    present = detected.copy()
    centre = hand_centres(uv)  # (T, 2, 2)
    size = hand_size(uv)  # (T, 2)
    starts = np.zeros((t, 2), dtype=bool)  # (T, 2)
    for s in range(2):
        idx = np.flatnonzero(detected[:, s])
        for a, b in itertools.pairwise(idx):
            # Only a gap inside one hand's track: two tracks given the same side (one hand
            # before a gap, the other after) are two hands, and frames between them
            # interpolated would lie on neither.
            jump = np.linalg.norm(centre[b, s] - centre[a, s])
            linked = jump <= link_limit(size[a, s], size[b, s], b - a, params)
            if 1 < b - a <= params.max_gap + 1 and linked:
                for f in range(a + 1, b):
                    w = (f - a) / (b - a)
                    uv[f, s] = (1 - w) * uv[a, s] + w * uv[b, s]
                    world[f, s] = (1 - w) * world[a, s] + w * world[b, s]
                    conf[f, s] = BRIDGED_CONFIDENCE_FACTOR * min(conf[a, s], conf[b, s])
                    present[f, s] = True
        # Two tracks given this side in adjacent frames are two hands: not smoothed together
        centre_s = hand_centres(uv[:, s : s + 1])[:, 0]  # (T, 2) after bridging
        size_s = hand_size(uv[:, s])  # (T,)
        for f in range(1, t):
            if present[f - 1, s] and present[f, s]:
                jump = np.linalg.norm(centre_s[f] - centre_s[f - 1])
                starts[f, s] = not jump <= link_limit(size_s[f - 1], size_s[f], 1, params)
        uv[:, s] = gaussian_smooth_runs(uv[:, s], present[:, s], params.smooth_sigma, starts[:, s])
        world[:, s] = gaussian_smooth_runs(
            world[:, s], present[:, s], params.smooth_sigma, starts[:, s]
        )
    return SideLandmarks(uv, world, conf, present, detected, starts)


def depth_under(depth: np.ndarray, uv: np.ndarray) -> float:
    """Median positive depth ``depth (H, W)`` at the pixels of ``uv (N, 2)``; NaN if none."""
    h, w = depth.shape
    cols = np.clip(np.floor(uv[:, 0]).astype(int), 0, w - 1)
    rows = np.clip(np.floor(uv[:, 1]).astype(int), 0, h - 1)
    values = depth[rows, cols]  # (N,)
    values = values[np.isfinite(values) & (values > 0)]
    return float(np.median(values)) if values.size else float("nan")


place_by_translation = place_in_camera  # the translation-only fit, shared with the metric scale


def lift_to_camera(
    uv: np.ndarray,
    world_landmarks: np.ndarray,
    intrinsics: np.ndarray,
    observed_depth: float | None = None,
    weights: np.ndarray | None = None,
    right: bool = True,
    method: str = "palm_pnp",
    prefer_fingers_away: bool = True,
    refine: bool = True,
) -> np.ndarray:
    """Camera joints ``(21, 3)`` from 2D ``uv (21, 2)`` and metric ``world_landmarks (21, 3)``.

    MediaPipe's world landmarks are *not* in camera-aligned axes: on the synthetic world their
    rotation to the true camera-frame hand averages 74-82 degrees (mostly about the camera's x
    axis: a hand pointing away from a head-mounted camera comes out pointing up or towards it).
    So only their shape is used, never their orientation. ``method``:

    - ``"palm_pnp"`` (default): the palm (wrist and the four knuckles, nearly coplanar) is placed by
      a planar PnP of :data:`PALM_TEMPLATE`, an average adult palm (mirrored for a left hand,
      ``right``), onto the palm landmarks. A planar PnP has two poses (the palm tilted towards or
      away from the camera); with ``prefer_fingers_away`` the one whose knuckles are further from
      the camera than the wrist is taken (egocentric prior: the forearm comes from the camera),
      otherwise the one nearer MediaPipe's own orientation. The world landmarks are rotated onto
      that palm (Kabsch on the palm joints) to give every joint a depth, and each joint is then
      put on its own pixel's ray at that depth, so the result reprojects exactly onto ``uv``.
    - ``"translation"``: the landmarks translated only (:func:`place_by_translation`), the old
      method, kept for comparison.

    When ``observed_depth`` (metres) is given, the points are then scaled about the camera centre
    so that their median depth equals it; the scaling keeps every projection. ``refine``: the
    palm poses refined on the reprojection error (``MediaPipeParams.refine_palm``).
    """
    points = None
    if method == "palm_pnp":
        points = _palm_pnp_lift(uv, world_landmarks, intrinsics, right, prefer_fingers_away, refine)
    elif method != "translation":
        raise ValueError(f"lift method must be 'palm_pnp' or 'translation', got {method!r}")
    if points is None:  # translation asked for, or the PnP failed
        points = place_by_translation(uv, world_landmarks, intrinsics, weights)
    return scale_to_depth(points, observed_depth)


def _palm_pnp_lift(
    uv: np.ndarray,
    world_landmarks: np.ndarray,
    intrinsics: np.ndarray,
    right: bool,
    prefer_fingers_away: bool,
    refine: bool = True,
) -> np.ndarray | None:
    """The ``"palm_pnp"`` lift of :func:`lift_to_camera` (no depth scaling); None on failure."""
    pose = palm_pnp_pose(uv, world_landmarks, intrinsics, right, prefer_fingers_away, refine)
    return None if pose is None else pose[0]


@dataclass
class MediaPipeResult:
    """World joints per side, and what MediaPipe saw (for diagnostics and tests)."""

    joints: np.ndarray  # (T, 2, 21, 3) float64 world metres, NaN where invalid
    valid: np.ndarray  # (T, 2) bool
    confidence: np.ndarray  # (T, 2, 21) float64 in [0, 1]
    landmarks: SideLandmarks  # smoothed per-side 2D/3D landmarks
    raw: RawLandmarks  # unordered detections as MediaPipe gave them
    # (T, 2) bool: valid and its 3D trusted (lifted, or interpolated from lifted neighbours); a
    # valid hand-frame that is not keeps joints on its landmarks' rays (its 2D) at low confidence
    lifted: np.ndarray


def mediapipe_hands(
    frames: np.ndarray,
    intrinsics: np.ndarray,
    world_from_cam: np.ndarray | None = None,
    depth: np.ndarray | None = None,
    params: MediaPipeParams | None = None,
    *,
    fps: float,
) -> MediaPipeResult:
    """Detect, assign sides, bridge, smooth and lift hands in one clip.

    ``frames (T, H, W, 3)`` uint8 RGB, ``intrinsics (4,)``, ``world_from_cam (T, 4, 4)`` (None:
    joints stay in camera coordinates), ``depth (T, H, W)`` metres with 0 = unknown (None: the
    world landmarks' size prior sets the distance), ``fps`` the clip's frame rate (the turn
    test's limit is per second; no default, so a clip's rate is never assumed).
    """
    params = params or MediaPipeParams()
    raw = detect_landmarks(frames, params)
    return hands_from_raw(
        raw, frames.shape[2], intrinsics, world_from_cam, depth, params, fps=fps, frames=frames
    )


def side_landmarks(
    raw: RawLandmarks, width: int, params: MediaPipeParams | None = None
) -> SideLandmarks:
    """Sides, bridging and smoothing of ``raw`` landmarks (already without overlaps) found in
    frames ``width`` pixels wide: the 2D part of :func:`hands_from_raw`, without any lift."""
    params = params or MediaPipeParams()
    return bridge_and_smooth(raw, assign_sides(raw, width, params), params)


def checked_side_landmarks(
    raw: RawLandmarks, width: int, params: MediaPipeParams, frames: np.ndarray | None
) -> tuple[RawLandmarks, SideLandmarks]:
    """The 2D chain of :func:`hands_from_raw`, shared with the regressor backend's boxes: overlaps
    dropped (:func:`drop_overlapping`), then, with the ``frames (T, H, W, 3)`` and unless
    ``params.scene_check`` is None, the tracks that are part of the scene
    (:func:`drop_scene_tracks`), then sides, bridging and smoothing (:func:`side_landmarks`) of
    frames ``width`` pixels wide. Returns the detections kept and their landmarks per side."""
    raw = drop_overlapping(raw, params.duplicate_distance)
    if frames is not None and params.scene_check is not None:
        raw = drop_scene_tracks(raw, frames, params)
    return raw, side_landmarks(raw, width, params)


def hands_from_raw(
    raw: RawLandmarks,
    width: int,
    intrinsics: np.ndarray,
    world_from_cam: np.ndarray | None = None,
    depth: np.ndarray | None = None,
    params: MediaPipeParams | None = None,
    *,
    fps: float,
    frames: np.ndarray | None,
) -> MediaPipeResult:
    """Everything after detection: sides, bridging, smoothing, lifting and the repair of palms
    turned off their track (:func:`~egosim.stages.hands.filters.turn_outliers`,
    :func:`repair_unsure`) of ``raw`` landmarks found in frames ``width`` pixels wide (arguments
    otherwise as :func:`mediapipe_hands`). With the ``frames (T, H, W, 3)`` they were found in,
    tracks that are part of the scene are dropped first (:func:`drop_scene_tracks`) and the small
    hands' spread test (:func:`spread_outliers`) runs; both are skipped without them. ``frames``
    has no default, so a caller without them (landmarks made up in a test) says None on purpose
    and a bench cannot skip the checks unnoticed."""
    params = params or MediaPipeParams()
    raw, lm = checked_side_landmarks(raw, width, params, frames)
    t = raw.present.shape[0]
    joints = np.full((t, 2, NUM_HAND_JOINTS, 3), np.nan)  # camera metres, world below
    poses = _palm_poses(lm, intrinsics, params) if params.lift == "palm_pnp" else {}
    for f, s in zip(*np.nonzero(lm.present), strict=True):
        observed = depth_under(depth[f], lm.uv[f, s]) if depth is not None else None
        if (f, s) in poses:  # the palm-PnP lift, already computed by _palm_poses
            points_cam = scale_to_depth(poses[(f, s)][0], observed)
        elif (near := _nearest_pose(poses, f, s, params.max_gap)) is not None:
            # palm PnP failed here: pose it like the neighbour, its palm at the neighbour's
            # palm depth (the neighbour's fingers follow its own 2D since hands v13: hands v14)
            palm_depth = float(np.median(near[0][list(PALM_JOINTS), 2]))
            points_cam = lift_with_rotation(
                lm.uv[f, s], lm.world[f, s], intrinsics, near[1], palm_depth, PALM_JOINTS
            )
            points_cam = scale_to_depth(points_cam, observed)
        else:
            points_cam = lift_to_camera(
                lm.uv[f, s],
                lm.world[f, s],
                intrinsics,
                observed,
                right=bool(s == RIGHT),
                method=params.lift,
                prefer_fingers_away=params.prefer_fingers_away,
                refine=params.refine_palm,
            )
        joints[f, s] = points_cam
    valid = lm.present & np.all(np.isfinite(joints), axis=(2, 3))
    shaky = np.zeros_like(valid)  # (T, 2) hands whose landmarks the model reads unsteadily
    if frames is not None:
        shaky = spread_outliers(frames, lm, params, valid)
    unsure = turn_outliers(joints, valid & ~shaky, fps, params.turn_window, params.max_turn_rate)
    unsure |= shaky
    joints = smooth_finger_depths(joints, valid & ~unsure, params.finger_depth_sigma, lm.starts)
    joints = smooth_palm_turns(
        joints, valid & ~unsure, params.palm_turn_sigma, lm.starts, world_from_cam
    )
    joints, lifted = repair_unsure(joints, valid, unsure, params.max_gap)
    if world_from_cam is not None:
        for f in range(t):
            joints[f] = transform_points(world_from_cam[f], joints[f])  # now world
    factor = np.where(lifted, 1.0, WITHHELD_CONFIDENCE_FACTOR)  # (T, 2)
    conf = np.repeat(np.where(valid, lm.confidence * factor, 0.0)[..., None], NUM_HAND_JOINTS, 2)
    return MediaPipeResult(joints, valid, conf, lm, raw, lifted)


def spread_outliers(
    frames: np.ndarray, lm: SideLandmarks, params: MediaPipeParams, valid: np.ndarray
) -> np.ndarray:
    """``(T, 2)`` bool: ``valid (T, 2)`` hand-frames (:func:`hands_from_raw`'s: present, with
    finite joints; the model runs four times on each one tested, so on no other) smaller than
    ``spread_max_size`` of the frame height (wrist to middle knuckle) whose landmarks the model
    does not read steadily: their :func:`~egosim.stages.common.roi_landmarks.landmark_spread`
    on ``frames (T, H, W, 3)`` is over ``max_spread``. Their 2D is kept, their 3D withheld (or
    interpolated between trusted neighbours by :func:`repair_unsure`). On the synthetic world
    these are small hands and hands half behind an object, whose palm the lift turns 60-180
    degrees off (docs/design.md, "Hands v15: small hands")."""
    out = np.zeros(lm.present.shape, dtype=bool)  # (T, 2)
    if not np.isfinite(params.max_spread):
        return out
    size = np.linalg.norm(lm.uv[:, :, MIDDLE_MCP] - lm.uv[:, :, 0], axis=-1)  # (T, 2) NaN: absent
    max_size = params.spread_max_size * frames.shape[1]  # pixels: 40 at 480 rows
    small = valid & (np.nan_to_num(size, nan=np.inf) < max_size)
    if not small.any():
        return out
    model = LandmarkModel(params.model_complexity)
    for f, s in zip(*np.nonzero(small), strict=True):
        spread = landmark_spread(
            model, np.ascontiguousarray(frames[f]), lm.uv[f, s], max_gain=params.track.max_gain
        )
        out[f, s] = spread > params.max_spread
    return out


def drop_scene_tracks(
    raw: RawLandmarks, frames: np.ndarray, params: MediaPipeParams
) -> RawLandmarks:
    """``raw`` without the tracks (:func:`_tracks`) that are part of the scene: off the clip's
    skin colour and still against its background (:func:`~egosim.stages.hands.scene_check.
    scene_tracks`; the EgoDex portrait variant's curtain fold). ``raw`` must already be without
    overlaps (:func:`drop_overlapping`)."""
    tracks = _tracks(raw, params)
    if len(tracks) < 2 or params.scene_check is None:
        return raw  # one track has no other hand to seed the skin from
    asked = seed_candidates(tracks, raw.present.shape, params.scene_check.seed_samples)  # (T, K)
    presence = landmark_presence(
        frames, replace(raw, present=asked), params
    )  # (T, K) NaN: not asked
    dropped = scene_tracks(frames, raw, tracks, presence, params.scene_check)
    if not dropped:
        return raw
    present = raw.present.copy()  # (T, K)
    for ti in dropped:
        f, k = np.array(tracks[ti]).T
        present[f, k] = False
    return replace(raw, present=present)


def repair_unsure(
    joints_cam: np.ndarray, valid: np.ndarray, unsure: np.ndarray, reach: int
) -> tuple[np.ndarray, np.ndarray]:
    """``(joints (T, 2, 21, 3), lifted (T, 2))``: each ``unsure`` hand-frame with a trusted frame
    of its side at most ``reach`` frames before and after it (and at most ``reach + 1`` apart)
    is interpolated between them: the palm's rotation slerped, the wrist moved linearly, the
    wrist-relative shape (in the palm's frame) the nearer frame's. The other unsure frames keep
    their joints (on their landmarks' rays: their 2D) and are not ``lifted``.
    ``joints_cam`` camera metres (NaN where not valid)."""
    out = joints_cam.copy()
    lifted = valid & ~unsure  # (T, 2)
    rot = palm_rotations(joints_cam)  # (T, 2, 3, 3) cam_from_palm
    for s in range(2):
        trusted = np.flatnonzero(lifted[:, s])
        for f in np.flatnonzero(unsure[:, s]):
            before, after = trusted[trusted < f], trusted[trusted > f]
            if not (before.size and after.size):
                continue
            a, b = int(before[-1]), int(after[0])
            if f - a > reach or b - f > reach or b - a > reach + 1:
                continue
            if not np.all(np.isfinite(rot[[a, b], s])):  # a degenerate palm (knuckles on the
                continue  # wrist) has no frame to turn from
            w = (f - a) / (b - a)
            turn = slerp_rotations(
                np.array([a, b], dtype=np.float64), rot[[a, b], s], np.array([float(f)])
            )[0]  # (3, 3) cam_from_palm
            src = a if w <= 0.5 else b
            shape = (joints_cam[src, s] - joints_cam[src, s, 0]) @ rot[src, s]  # (21, 3) palm
            wrist = (1.0 - w) * joints_cam[a, s, 0] + w * joints_cam[b, s, 0]  # (3,)
            out[f, s] = wrist + shape @ turn.T
            lifted[f, s] = True
    return out, lifted


def _palm_poses(
    lm: SideLandmarks, intrinsics: np.ndarray, params: MediaPipeParams
) -> dict[tuple[int, int], tuple[np.ndarray, np.ndarray]]:
    """``(frame, side) -> (points (21, 3), cam_from_landmarks (3, 3))`` where the palm PnP works
    and puts every joint at least :data:`MIN_POSE_DEPTH` in front of the camera (a pose with
    joints at the camera's centre is a degenerate one: it must not pose its neighbours)."""
    out = {}
    for f, s in zip(*np.nonzero(lm.present), strict=True):
        pose = palm_pnp_pose(
            lm.uv[f, s],
            lm.world[f, s],
            intrinsics,
            bool(s == RIGHT),
            params.prefer_fingers_away,
            params.refine_palm,
        )
        if pose is not None and float(pose[0][:, 2].min()) >= MIN_POSE_DEPTH:
            out[(int(f), int(s))] = pose
    return out


def _nearest_pose(
    poses: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]], f: int, s: int, reach: int
) -> tuple[np.ndarray, np.ndarray] | None:
    """The palm pose of side ``s`` nearest in time to frame ``f`` within ``reach`` frames (the
    earlier on a tie); None when there is none. (A palm seen edge-on for a frame otherwise fell
    back to the translation lift in MediaPipe's own axes, 74-82 degrees off, and the spike filter
    then dropped the frame: DWM 00013's right hand at frame 24.)"""
    for d in range(1, reach + 1):
        for g in (f - d, f + d):
            if (g, s) in poses:
                return poses[(g, s)]
    return None


def mediapipe_detections(clip: Clip, params: MediaPipeParams | None = None) -> Detections:
    """The stage's detections (``K = 2``, slot = side) from a decoded clip with poses."""
    res = mediapipe_hands(
        clip.frames, clip.intrinsics, clip.world_from_cam, clip.depth, params, fps=clip.fps
    )
    side = np.tile(np.array([LEFT, RIGHT]), (clip.num_frames, 1))  # (T, 2)
    joints = np.where(res.valid[..., None, None], res.joints, 0.0)
    return Detections(
        joints=joints, side=side, confidence=res.confidence, present=res.valid, lifted=res.lifted
    )
