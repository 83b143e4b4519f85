"""MediaPipe Hands landmarks and their metric placement in the camera (shared, not a stage).

Two pieces that more than one stage needs:

- :func:`detect_hand_landmarks`: ``mediapipe.solutions.hands.Hands`` over a clip's frames in
  order (video/tracking mode by default, which finds far more hands on egocentric video than
  per-image mode), plus zoomed tiles of the lower image where head-mounted footage shows small,
  partial hands; per frame up to two hands: 21 image landmarks (pixels), 21 world landmarks
  (metres about the hand's centre, MediaPipe's average-hand size prior) and the handedness
  score; while one side has no palm detection in the whole clip, the palm detector runs again on
  the dim frames contrast-stretched (:func:`stretched_frame`; issue 10, hands16: DWM 00013
  darkened x0.5 lost its left hand for the whole clip for want of a single palm detection);
  then every found hand is followed through the frames where the palm detector missed it,
  forwards and backwards (:func:`egosim.stages.common.roi_landmarks.track_through_misses`).
  The ``hands`` stage and ``depth_camera``'s metric scale call it with the same
  :class:`HandLandmarkParams`, so the scale measures the hands the hands stage places (issue 17:
  with a simpler detector of its own the scale saw 6 usable detections on DWM 00013 where the
  hands stage found 22, and none at all on a HOT3D window with hands).
- :func:`place_in_camera`: the translation that puts the metric world landmarks where their
  projection fits the 2D landmarks (linear least squares, a translation-only PnP).

MediaPipe is imported lazily: install it as ``make setup`` does (``--no-deps mediapipe==0.10.21``).
"""

from __future__ import annotations

import itertools
import warnings
from dataclasses import dataclass, replace

import cv2
import numpy as np

from egosim.stages.common.roi_landmarks import (
    MIN_STRETCH_GAIN,
    LandmarkModel,
    TrackParams,
    roi_from_landmarks,
    track_through_misses,
)

NUM_JOINTS = 21  # MediaPipe / MANO joint count per hand
MAX_HANDS = 2  # hands detected per frame


class MediaPipeUnavailableError(ImportError):
    """``mediapipe`` is not installed (install it as ``make setup`` does)."""


@dataclass(frozen=True)
class HandLandmarkParams:
    """Knobs of the MediaPipe hand detector (the ``hands`` stage's and the metric scale's)."""

    video_mode: bool = True  # tracking mode (False: every frame detected on its own)
    min_detection_confidence: float = 0.3  # palm detector threshold (0.5 misses drawn hands)
    min_tracking_confidence: float = 0.5  # below it the tracker re-runs the palm detector
    model_complexity: int = 1  # landmark model: 0 lite, 1 full
    swap_labels: bool = True  # egocentric video: MediaPipe's "Left" is the real right hand
    tiles: tuple[tuple[float, float, float, float], ...] = (
        (0.0, 0.3, 0.55, 1.0),
        (0.45, 0.3, 1.0, 1.0),
    )  # extra search regions (x0, y0, x1, y1) as fractions of the frame; () = full frame only
    tile_zoom: float = 2.0  # tiles are enlarged by this factor before detection
    duplicate_distance: float = 0.5  # a tile hand this near a kept hand (in hand sizes) is the same
    # dim clips: while one side has no palm detection in the whole clip, the palm detector runs
    # again on the dim frames contrast-stretched (stretched_frame, gain up to this; 1 = never),
    # and hands of the missing side are added where the first pass left a slot free
    stretch_gain: float = 4.0
    # the stretched pass runs only if a probe finds a hand of the missing side first, searching
    # every this-many-th of the frames the pass would search, in per-image mode (_stretch_probe:
    # a one-hand clip always has a "missing" side, and the pass searched it for nothing; 4 lost
    # DWM 00013 darkened x0.5 as ingested its left hand); 0 = no probe
    stretch_probe: int = 2
    track_misses: bool = True  # follow found hands through detector misses, forwards and
    # backwards (the landmark model on flow-carried ROIs, :mod:`.roi_landmarks`; ai-edge-litert)
    track: TrackParams = TrackParams()  # noqa: RUF009 (frozen) how hands are followed

    def __post_init__(self) -> None:
        problems = []
        for name in ("min_detection_confidence", "min_tracking_confidence"):
            value = getattr(self, name)
            if not 0.0 <= value <= 1.0:
                problems.append(f"{name} must be in [0, 1], got {value!r}")
        if self.stretch_gain < 1.0:
            problems.append(f"stretch_gain must be >= 1, got {self.stretch_gain!r}")
        if self.stretch_probe < 0:
            problems.append(f"stretch_probe must be >= 0, got {self.stretch_probe!r}")
        if self.model_complexity not in (0, 1):
            problems.append(f"model_complexity must be 0 or 1, got {self.model_complexity!r}")
        if problems:
            raise ValueError("invalid HandLandmarkParams: " + "; ".join(problems))


@dataclass
class RawLandmarks:
    """MediaPipe's output for a clip, up to ``K = 2`` detections per frame, unordered."""

    uv: np.ndarray  # (T, K, 21, 2) float64 pixels (u right, v down)
    world: np.ndarray  # (T, K, 21, 3) float64 metres about the hand's centre
    label_right: np.ndarray  # (T, K) float64 score that this is the real right hand, in [0, 1]
    present: np.ndarray  # (T, K) bool
    tracked: np.ndarray | None = None  # (T, K) bool found by following a hand (None: none were)
    # rows of the frames searched (the sides' forearm-entry vote needs the bottom border); None:
    # landmarks made up without frames (a test), which get no forearm vote
    frame_height: int | None = None


def import_mediapipe():
    """The ``mediapipe`` module; :class:`MediaPipeUnavailableError` naming the install if absent."""
    try:
        import mediapipe as mp
    except ImportError as exc:
        raise MediaPipeUnavailableError(
            "hand landmarks need mediapipe==0.10.21 (pip install --no-deps "
            "mediapipe==0.10.21 absl-py flatbuffers attrs matplotlib 'protobuf>=5.29.6,<6')"
        ) from exc
    return mp


def detect_hand_landmarks(
    frames: np.ndarray, params: HandLandmarkParams | None = None
) -> RawLandmarks:
    """Run MediaPipe Hands on ``frames (T, H, W, 3)`` uint8 RGB, in order (full frame + tiles)."""
    params = params or HandLandmarkParams()
    mp = import_mediapipe()
    t = frames.shape[0]
    out = RawLandmarks(
        uv=np.full((t, MAX_HANDS, NUM_JOINTS, 2), np.nan),
        world=np.full((t, MAX_HANDS, NUM_JOINTS, 3), np.nan),
        label_right=np.full((t, MAX_HANDS), 0.5),
        present=np.zeros((t, MAX_HANDS), dtype=bool),
        frame_height=int(frames.shape[1]),
    )

    def make(video: bool):
        return mp.solutions.hands.Hands(
            static_image_mode=not video,
            max_num_hands=MAX_HANDS,
            model_complexity=params.model_complexity,
            min_detection_confidence=params.min_detection_confidence,
            min_tracking_confidence=params.min_tracking_confidence,
        )

    full = make(params.video_mode)
    tiled = [make(False) for _ in params.tiles]
    per_frame: list[list[Detection]] = []  # the palm detector's hands per frame
    try:
        for i in range(t):
            frame = np.ascontiguousarray(frames[i])
            per_frame.append(_search(full, tiled, frame, None, params))
    finally:
        for hands in (full, *tiled):
            hands.close()
    missing = {False, True} - _sides(per_frame)
    if (
        params.stretch_gain > 1.0
        and missing
        and _stretch_probe(frames, per_frame, missing, params, make)
    ):
        per_frame = _stretched_pass(frames, per_frame, missing, params, make)
    for i, found in enumerate(per_frame):
        for k, (uv, world, right) in enumerate(found[:MAX_HANDS]):
            out.uv[i, k], out.world[i, k], out.label_right[i, k] = uv, world, right
            out.present[i, k] = True
    if params.track_misses and out.present.any():  # nothing found: nothing to follow
        model = LandmarkModel(params.model_complexity)
        out.tracked = track_through_misses(
            frames, out.uv, out.world, out.label_right, out.present, model, params.track
        )
    return out


def _search(
    full,
    tiled: list,
    image: np.ndarray,
    found: list[Detection] | None,
    params: HandLandmarkParams,
    sides: set[bool] | None = None,
) -> list[Detection]:
    """The hands the palm detector finds in ``image (H, W, 3)``: the whole frame with ``full``,
    then, while fewer than two hands are kept, each of ``params.tiles`` zoomed with its detector
    in ``tiled`` (a tile hand must lie inside its tile; the earlier source wins a duplicate).
    ``found``: hands already kept (merged first), or None to start from the whole frame's hands
    as they are; ``sides`` (True: right, by the label): only hands of these sides are added."""
    h, w = image.shape[:2]

    def wanted(dets: list[Detection]) -> list[Detection]:
        return dets if sides is None else [d for d in dets if (d[2] > 0.5) in sides]

    whole = wanted(_hands_in(full, image, (0, 0, w, h), params.swap_labels))
    found = (
        whole if found is None else merge_tile_detections(found, whole, params.duplicate_distance)
    )
    for hands, box in zip(tiled, params.tiles, strict=True):
        if len(found) >= MAX_HANDS:  # both hands found: tiles cannot add one
            break
        x0, y0 = round(box[0] * w), round(box[1] * h)
        x1, y1 = round(box[2] * w), round(box[3] * h)
        crop = image[y0:y1, x0:x1]
        if params.tile_zoom != 1.0:
            crop = cv2.resize(crop, None, fx=params.tile_zoom, fy=params.tile_zoom)
        tile = _hands_in(hands, crop, (x0, y0, x1 - x0, y1 - y0), params.swap_labels)
        tile = wanted([d for d in tile if inside_tile(d[0], (x0, y0, x1, y1), (w, h))])
        found = merge_tile_detections(found, tile, params.duplicate_distance)
    return found


def _sides(per_frame: list[list[Detection]]) -> set[bool]:
    """The sides (True: right, by the label) of the clip's detections ``per_frame``."""
    return {det[2] > 0.5 for found in per_frame for det in found}


def _stretch_probe(
    frames: np.ndarray,
    per_frame: list[list[Detection]],
    missing: set[bool],
    params: HandLandmarkParams,
    make,
) -> bool:
    """Whether :func:`_stretched_pass` is worth running: True when the palm detector, in
    per-image mode, finds a hand of a ``missing`` side on every ``params.stretch_probe``-th of
    the frames that pass would search (dim ones holding fewer than two hands; the whole frame,
    then the tiles), or when there is no probe (``stretch_probe`` 0). On ordinary one-hand
    footage the pass searched up to every frame for a second hand that is not there (DWM
    00017: 20 of 49 frames, +47% detection CPU); the probe searches half of them, and where it
    finds a hand the pass then searches them all as before (docs/design.md, "Hands v16: sides
    from the forearm, the mirror, a probe before the stretched pass")."""
    if params.stretch_probe == 0:
        return True
    hands = make(False)
    tiled = [make(False) for _ in params.tiles]
    dim = 0  # dim frames with a free slot seen so far: the frames the pass would search
    try:
        for frame, found in zip(frames, per_frame, strict=True):
            if len(found) >= MAX_HANDS:
                continue
            image = stretched_frame(frame, params.stretch_gain)
            if image is None:
                continue
            dim += 1
            if (dim - 1) % params.stretch_probe:  # probed: the 1st, the (1 + probe)th, ...
                continue
            if len(_search(hands, tiled, image, found, params, missing)) > len(found):
                return True
    finally:
        for one in (hands, *tiled):
            one.close()
    return False


def _stretched_pass(
    frames: np.ndarray,
    per_frame: list[list[Detection]],
    missing: set[bool],
    params: HandLandmarkParams,
    make,
) -> list[list[Detection]]:
    """``per_frame`` plus the hands of a ``missing`` side (True: right, by the label) that the
    palm detector finds on the contrast-stretched frames.

    Only frames that :func:`stretched_frame` stretches (dim ones) and that hold fewer than two
    hands are searched, as the first pass searches: the whole frame with a detector of the same
    mode, then the zoomed ``tiles`` (on DWM 00013 darkened x0.5 the whole frame alone gave one
    left seed in 49 frames, left recall 0.917 file; with the tiles 4 and 1.0). The first pass's
    hands come first: a
    stretched-pass hand near one of them (``duplicate_distance``) is the same hand, and one
    labelled with a side the first pass found is not added (on DWM 00013 darkened and
    ingested, adding those too took the right hand's track onto the left hand: right recall
    0.958 -> 0.542)."""
    hands = make(params.video_mode)
    tiled = [make(False) for _ in params.tiles]
    merged = []
    try:
        for frame, found in zip(frames, per_frame, strict=True):
            if len(found) < MAX_HANDS:
                image = stretched_frame(frame, params.stretch_gain)
                if image is not None:
                    found = _search(hands, tiled, image, found, params, missing)
            merged.append(found)
    finally:
        for one in (hands, *tiled):
            one.close()
    return merged


def stretched_frame(frame: np.ndarray, max_gain: float) -> np.ndarray | None:
    """``frame (H, W, 3)`` uint8 with :func:`~egosim.stages.common.roi_landmarks.stretch_contrast`'s
    mapping (1st-99th percentile range onto [0, 255], gain capped at ``max_gain``), or None when
    the frame needs a gain under ``MIN_STRETCH_GAIN`` (well exposed).

    The percentiles are read on every 4th row and column and the map is applied as a lookup
    table: the full-frame percentiles cost about 0.1 s per 480x832 frame, 6 s per clip."""
    lo, hi = np.percentile(frame[::4, ::4], (1.0, 99.0)) / 255.0
    gain = min(max_gain, 1.0 / max(float(hi - lo), 1e-6))
    if gain < MIN_STRETCH_GAIN:
        return None
    lut = stretch_lut(float(lo), float(hi), gain)  # (256,) uint8
    return lut[frame]


def stretch_lut(lo: float, hi: float, gain: float) -> np.ndarray:
    """``(256,)`` uint8: :func:`~egosim.stages.common.roi_landmarks.stretch_contrast`'s map of the
    range ``lo..hi`` (in [0, 1]) by ``gain``, for uint8 values."""
    x = np.arange(256, dtype=np.float32) / 255.0
    mid = 0.5 * (lo + hi)  # the stretch keeps the range's middle unless that clips it
    low = float(np.clip(mid - 0.5 / gain, 0.0, 1.0 - 1.0 / gain))
    return np.round(np.clip((x - low) * gain, 0.0, 1.0) * 255.0).astype(np.uint8)


def landmark_presence(
    frames: np.ndarray, raw: RawLandmarks, params: HandLandmarkParams | None = None
) -> np.ndarray:
    """``(T, K)`` the landmark model's hand-presence score on the ROI that each detection's own
    landmarks give (:func:`~egosim.stages.common.roi_landmarks.roi_from_landmarks`, the crop
    contrast-stretched as the tracker does), NaN where a slot holds no detection.

    One score for every detection, whoever found it (the palm detector, MediaPipe's own tracking
    or :func:`~egosim.stages.common.roi_landmarks.track_through_misses`), asked the same way: is
    there a hand where these landmarks say one is? ``frames (T, H, W, 3)`` uint8 RGB, those
    ``raw`` was found in. A diagnostic (``bench.hands_real --tracks``), not a filter: as a track
    filter it did not separate a false hand on a curtain fold from real dim or edge-on hands
    (docs/design.md, "Hands v12")."""
    params = params or HandLandmarkParams()
    out = np.full(raw.present.shape, np.nan)  # (T, K)
    if not raw.present.any():
        return out
    model = LandmarkModel(params.model_complexity)
    for f, k in zip(*np.nonzero(raw.present), strict=True):
        roi = roi_from_landmarks(raw.uv[f, k])
        out[f, k] = model.run(np.ascontiguousarray(frames[f]), roi, params.track.max_gain).presence
    return out


Detection = tuple[np.ndarray, np.ndarray, float]  # uv (21, 2) px, world (21, 3) m, P(right)


def _hands_in(hands, image: np.ndarray, box: tuple[int, int, int, int], swap: bool) -> list:
    """Detections in ``image``, landmarks mapped into the frame through ``box`` (x, y, w, h)."""
    result = hands.process(np.ascontiguousarray(image))
    if not result.multi_hand_landmarks:
        return []
    found: list[Detection] = []
    x0, y0, bw, bh = box
    triples = zip(
        result.multi_hand_landmarks,
        result.multi_hand_world_landmarks,
        result.multi_handedness,
        strict=True,
    )
    for image_lm, world_lm, handedness in triples:
        uv = np.array([(x0 + p.x * bw, y0 + p.y * bh) for p in image_lm.landmark])
        world = np.array([(p.x, p.y, p.z) for p in world_lm.landmark])
        cls = handedness.classification[0]
        is_right = (cls.label == "Right") != swap
        found.append((uv, world, cls.score if is_right else 1.0 - cls.score))
    return found


def inside_tile(
    uv: np.ndarray, box: tuple[int, int, int, int], size: tuple[int, int], margin: float = 0.02
) -> bool:
    """False when landmarks ``uv (21, 2)`` cross an edge of ``box`` (x0, y0, x1, y1) that lies
    inside the frame of ``size`` (w, h): that hand is cut by the tile, so its landmarks are
    guessed; the full frame or another tile sees it whole. ``margin`` is a fraction of the frame."""
    x0, y0, x1, y1 = box
    w, h = size
    mx, my = margin * w, margin * h
    if (x0 > 0 and uv[:, 0].min() < x0 - mx) or (y0 > 0 and uv[:, 1].min() < y0 - my):
        return False
    return not ((x1 < w and uv[:, 0].max() > x1 + mx) or (y1 < h and uv[:, 1].max() > y1 + my))


def merge_tile_detections(kept: list, extra: list, duplicate_distance: float) -> list:
    """``kept`` plus each ``extra`` detection whose centre is not within ``duplicate_distance``
    hand sizes of one already kept (the earlier source wins: full frame before tiles)."""
    merged = list(kept)
    for det in extra:
        centre = det[0].mean(axis=0)
        size = float(hand_size(det[0]))
        if all(
            np.linalg.norm(centre - k[0].mean(axis=0))
            > duplicate_distance * max(size, float(hand_size(k[0])))
            for k in merged
        ):
            merged.append(det)
    return merged


def drop_overlapping(raw: RawLandmarks, duplicate_distance: float) -> RawLandmarks:
    """``raw`` without a second detection of one hand in a frame.

    MediaPipe's tracker sometimes returns two hands at one place (on the synthetic world: the
    left hand twice, once labelled right with score 0.91), which would then take both sides. Of
    two detections whose centres are within ``duplicate_distance`` hand sizes, the one nearer
    the detections of the neighbouring frames is kept (the earlier slot when neither has any).
    """
    present = raw.present.copy()  # (T, K)
    centre = hand_centres(raw.uv)  # (T, K, 2)
    size = hand_size(raw.uv)  # (T, K)
    t = present.shape[0]
    for f in range(t):
        slots = np.flatnonzero(present[f])
        for a, b in itertools.combinations(slots, 2):
            if not (present[f, a] and present[f, b]):
                continue
            limit = duplicate_distance * max(size[f, a], size[f, b])
            if np.linalg.norm(centre[f, a] - centre[f, b]) > limit:
                continue
            near = [  # centres of the neighbouring frames' detections
                centre[g, k]
                for g in (f - 1, f + 1)
                if 0 <= g < t
                for k in np.flatnonzero(raw.present[g])
            ]

            cost = [_nearest(centre[f, k], near) for k in (a, b)]
            present[f, b if cost[0] <= cost[1] else a] = False
    return replace(raw, present=present)  # keeps ``tracked``


def _nearest(point: np.ndarray, others: list[np.ndarray]) -> float:
    """Distance from ``point (2,)`` to the nearest of ``others`` (each ``(2,)``); 0 if none."""
    return min((float(np.linalg.norm(point - c)) for c in others), default=0.0)


def hand_size(uv: np.ndarray) -> np.ndarray:
    """Hand size ``(...,)`` in pixels: the diagonal of the landmarks' box, ``uv (..., 21, 2)``."""
    return np.linalg.norm(uv.max(axis=-2) - uv.min(axis=-2), axis=-1)


def hand_centres(uv: np.ndarray) -> np.ndarray:
    """Mean over joints of ``uv (T, K, 21, 2)`` -> ``(T, K, 2)``, NaN for absent slots."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN slots
        return np.nanmean(uv, axis=2)


def place_in_camera(
    uv: np.ndarray,
    world_landmarks: np.ndarray,
    intrinsics: np.ndarray,
    weights: np.ndarray | None = None,
) -> np.ndarray:
    """Metric camera joints ``(N, 3)`` from 2D ``uv (N, 2)`` and metric ``world_landmarks (N, 3)``.

    Finds the translation ``t`` minimising the (weighted) algebraic reprojection error of
    ``world_landmarks + t`` in closed form: for each joint ``x_n (W_z + t_z) = W_x + t_x`` and
    likewise for y, with ``x_n = (u - cx) / fx``. The landmarks' own size fixes the distance.
    """
    fx, fy, cx, cy = np.asarray(intrinsics, dtype=np.float64)
    x_n = (uv[:, 0] - cx) / fx  # (N,)
    y_n = (uv[:, 1] - cy) / fy  # (N,)
    n = len(uv)
    a = np.zeros((2 * n, 3))  # (2N, 3)
    b = np.zeros(2 * n)  # (2N,)
    a[:n, 0], a[:n, 2], b[:n] = 1.0, -x_n, x_n * world_landmarks[:, 2] - world_landmarks[:, 0]
    a[n:, 1], a[n:, 2], b[n:] = 1.0, -y_n, y_n * world_landmarks[:, 2] - world_landmarks[:, 1]
    if weights is not None:
        wts = np.sqrt(np.concatenate([weights, weights]))  # (2N,)
        a, b = a * wts[:, None], b * wts
    t, *_ = np.linalg.lstsq(a, b, rcond=None)  # (3,)
    return world_landmarks + t  # (N, 3)
