"""MediaPipe Hands landmarks and their metric placement in the camera (shared, not a stage).

Two pieces that more than one stage needs:

- :func:`detect_hand_landmarks`: ``mediapipe.solutions.hands.Hands`` over a clip's frames in
  order (video/tracking mode by default, which finds far more hands on egocentric video than
  per-image mode). Per frame up to two hands: 21 image landmarks (pixels), 21 world landmarks
  (metres about the hand's centre, camera-aligned axes, scaled by MediaPipe's average-hand size
  prior: wrist to middle knuckle 8-10 cm whatever the hand) and the handedness score; then
  every found hand is followed through the frames where the palm detector missed it, forwards
  and backwards (:func:`egosim.stages.common.roi_landmarks.track_through_misses`, the same
  tracker the ``hands`` stage uses).
- :func:`place_in_camera`: the translation that puts the metric world landmarks where their
  projection fits the 2D landmarks (linear least squares, a translation-only PnP). The result is
  metric camera-frame joints whose distance comes from the hand-size prior.

The ``hands`` stage adds tiled search and side assignment (``stages/hands/mediapipe_backend.py``:
``detect_landmarks``) and its palm-PnP lift (``lift_to_camera``); the metric scale needs neither.
MediaPipe is imported lazily: install it as ``make setup`` does (``--no-deps mediapipe==0.10.21``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from egosim.stages.common.roi_landmarks import LandmarkModel, TrackParams, track_through_misses

NUM_JOINTS = 21  # MediaPipe / MANO joint count per hand
MAX_HANDS = 2  # hands detected per frame


class MediaPipeUnavailableError(ImportError):
    """``mediapipe`` is not installed (install it as ``make setup`` does)."""


@dataclass(frozen=True)
class HandLandmarkParams:
    """Knobs of the MediaPipe hand detector."""

    video_mode: bool = True  # tracking mode (False: every frame detected on its own)
    min_detection_confidence: float = 0.3  # palm detector threshold (0.5 misses drawn hands)
    min_tracking_confidence: float = 0.5  # below it the tracker re-runs the palm detector
    model_complexity: int = 1  # landmark model: 0 lite, 1 full
    track_misses: bool = True  # follow found hands through detector misses, forwards and
    # backwards (the landmark model on flow-carried ROIs, :mod:`.roi_landmarks`; ai-edge-litert)
    # How hands are followed: the hands v3 tracker (no flow-carrying through misses, crops as they
    # are). The hands stage's v4 tracker also finds dark, blurred and edge-cut hands, but moved DWM
    # 00013's metric scale 0.094 -> 0.084 and its hand/surface ratio 1.53 -> 1.71 (further from 1);
    # with no true scale to check it against, the scale keeps the detections it was measured with.
    track: TrackParams = TrackParams(max_coast=0, max_gain=1.0)  # noqa: RUF009 (frozen)

    def __post_init__(self) -> None:
        problems = []
        for name in ("min_detection_confidence", "min_tracking_confidence"):
            value = getattr(self, name)
            if not 0.0 <= value <= 1.0:
                problems.append(f"{name} must be in [0, 1], got {value!r}")
        if self.model_complexity not in (0, 1):
            problems.append(f"model_complexity must be 0 or 1, got {self.model_complexity!r}")
        if problems:
            raise ValueError("invalid HandLandmarkParams: " + "; ".join(problems))


@dataclass
class HandLandmarks:
    """MediaPipe's output for a clip, up to ``K = 2`` detections per frame, unordered."""

    uv: np.ndarray  # (T, K, 21, 2) float64 pixels (u right, v down), NaN where absent
    world: np.ndarray  # (T, K, 21, 3) float64 metres about the hand's centre, NaN where absent
    score: np.ndarray  # (T, K) float64 handedness score in [0, 1], 0 where absent
    present: np.ndarray  # (T, K) bool


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
) -> HandLandmarks:
    """Run MediaPipe Hands on ``frames (T, H, W, 3)`` uint8 RGB, in order."""
    params = params or HandLandmarkParams()
    mp = import_mediapipe()
    t, h, w = frames.shape[:3]
    out = HandLandmarks(
        uv=np.full((t, MAX_HANDS, NUM_JOINTS, 2), np.nan),
        world=np.full((t, MAX_HANDS, NUM_JOINTS, 3), np.nan),
        score=np.zeros((t, MAX_HANDS)),
        present=np.zeros((t, MAX_HANDS), dtype=bool),
    )
    with mp.solutions.hands.Hands(
        static_image_mode=not params.video_mode,
        max_num_hands=MAX_HANDS,
        model_complexity=params.model_complexity,
        min_detection_confidence=params.min_detection_confidence,
        min_tracking_confidence=params.min_tracking_confidence,
    ) as hands:
        for i in range(t):
            result = hands.process(np.ascontiguousarray(frames[i]))
            if not result.multi_hand_landmarks:
                continue
            triples = zip(
                result.multi_hand_landmarks,
                result.multi_hand_world_landmarks,
                result.multi_handedness,
                strict=True,
            )
            for k, (image_lm, world_lm, handedness) in enumerate(list(triples)[:MAX_HANDS]):
                out.uv[i, k] = [(p.x * w, p.y * h) for p in image_lm.landmark]
                out.world[i, k] = [(p.x, p.y, p.z) for p in world_lm.landmark]
                out.score[i, k] = handedness.classification[0].score
                out.present[i, k] = True
    if params.track_misses and out.present.any():
        model = LandmarkModel(params.model_complexity)
        tracked = track_through_misses(
            frames, out.uv, out.world, out.score, out.present, model, params.track
        )  # fills uv, world, score and present in place
        out.score[tracked] = 0.5  # the side of a followed hand is not scored here
    return out


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
