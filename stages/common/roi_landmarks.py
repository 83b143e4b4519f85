"""MediaPipe's hand landmark model run directly on regions we choose (tracking through misses).

MediaPipe Hands finds a hand with its palm detector and then follows it with the landmark model on a
region of interest (ROI) predicted from the previous frame's landmarks; when the landmark model's
hand-presence score drops below ``min_tracking_confidence`` the hand is dropped and only the palm
detector can find it again. On head-mounted footage the palm detector misses most small, partial
and sleeved hands, so a hand that MediaPipe found once is lost for good a frame later. Here the same
landmark model (``hand_landmark_full.tflite``, shipped inside the ``mediapipe`` 0.10.21 wheel) is
run with a TFLite runtime (``ai-edge-litert``) on ROIs built the way MediaPipe builds them
(:func:`roi_from_landmarks`), carried from frame to frame by optical flow
(:func:`flow_shift`), forwards and backwards in time from every detection
(:func:`track_through_misses`), so a hand found at frame 3 is also followed back to frame 0. A
hand the model loses for a frame or two (motion blur while the head turns, a hand half out of
the frame) is carried on by the flow and taken up again when the model finds it clearly; dark
crops (dim rooms, sleeves) are contrast-stretched first (:func:`stretch_contrast`).

Crops are rotated so that the wrist-to-knuckles direction points up, as MediaPipe's are; the
landmarks come back in crop pixels and are mapped to the frame through the same affine map.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from egosim.pipeline.records import NUM_HAND_JOINTS

INPUT_SIZE = 224  # the landmark model's square input, pixels
MIDDLE_MCP = 9  # joint index of the middle finger's knuckle (hand size: wrist to it)
# Landmarks MediaPipe builds its tracking ROI from: wrist, thumb CMC/MCP/IP, index, middle, ring and
# pinky MCP and PIP (hand_landmark_landmarks_to_roi.pbtxt).
ROI_JOINTS = (0, 1, 2, 3, 5, 6, 9, 10, 13, 14, 17, 18)
ROI_SCALE = 2.0  # the ROI's side over the rotated box of ROI_JOINTS (MediaPipe's value)
ROI_SHIFT = -0.1  # ROI centre moved along the hand's axis by this fraction of the box (MediaPipe)
MIN_STRETCH_GAIN = 2.0  # crops spanning half the intensity range or more are not stretched


class LandmarkRuntimeUnavailableError(ImportError):
    """No TFLite runtime (``ai-edge-litert``) or no landmark model in the ``mediapipe`` wheel."""


@dataclass(frozen=True)
class Roi:
    """A square, rotated region of a frame: its centre, side and the hand's up direction."""

    centre: np.ndarray  # (2,) pixels (u right, v down)
    side: float  # pixels
    up: np.ndarray  # (2,) unit vector in the frame that the crop's up (-v) maps to

    def crop_from_frame(self) -> np.ndarray:
        """Affine ``(2, 3)`` taking frame pixels to crop pixels (``INPUT_SIZE`` square)."""
        return cv2.invertAffineTransform(self.frame_from_crop())

    def crop_axes(self) -> np.ndarray:
        """Rotation ``(2, 2)`` whose columns are the crop's x (right) and y (down) axes in the
        frame: crop directions to frame directions."""
        ex = np.array([-self.up[1], self.up[0]])  # (2,) crop x axis in the frame
        ey = -self.up  # (2,) crop y axis (down) in the frame
        return np.stack([ex, ey], axis=1)  # (2, 2)

    def frame_from_crop(self) -> np.ndarray:
        """Affine ``(2, 3)`` taking crop pixels to frame pixels."""
        s = self.side / INPUT_SIZE
        lin = s * self.crop_axes()  # (2, 2) columns: crop axes in the frame
        offset = self.centre - lin @ np.array([INPUT_SIZE / 2, INPUT_SIZE / 2])  # (2,)
        return np.concatenate([lin, offset[:, None]], axis=1)

    def turned(self, degrees: float, scale: float = 1.0) -> Roi:
        """The same ROI turned by ``degrees`` about its centre (clockwise as seen in the image,
        whose v axis points down) and its side times ``scale``."""
        a = np.radians(degrees)
        c, s = np.cos(a), np.sin(a)
        up = np.array([c * self.up[0] - s * self.up[1], s * self.up[0] + c * self.up[1]])
        return Roi(centre=self.centre, side=self.side * scale, up=up)


def roi_from_landmarks(uv: np.ndarray) -> Roi:
    """MediaPipe's tracking ROI for the next frame from landmarks ``uv (21, 2)`` pixels.

    The hand's up direction runs from the wrist to the mean of the middle knuckle and of the
    index/ring knuckles' mean; the box of :data:`ROI_JOINTS` in that rotated frame, shifted by
    :data:`ROI_SHIFT` along the hand and scaled by :data:`ROI_SCALE` (long side), is the ROI.
    """
    wrist = uv[0]
    knuckles = 0.5 * (0.5 * (uv[5] + uv[13]) + uv[9])  # (2,)
    up = knuckles - wrist
    norm = float(np.linalg.norm(up))
    up = up / norm if norm > 1e-6 else np.array([0.0, -1.0])
    ex = np.array([-up[1], up[0]])  # (2,) crop x in the frame
    pts = uv[list(ROI_JOINTS)]  # (12, 2)
    local = np.stack([pts @ ex, pts @ -up], axis=1)  # (12, 2) rotated coordinates
    lo, hi = local.min(axis=0), local.max(axis=0)
    mid = 0.5 * (lo + hi)  # (2,) rotated
    size = hi - lo  # (2,) box width, height in rotated axes
    mid = mid + np.array([0.0, ROI_SHIFT * size[1]])
    centre = mid[0] * ex + mid[1] * -up  # (2,) back to the frame
    return Roi(centre=centre, side=float(ROI_SCALE * max(size.max(), 1.0)), up=up)


def world_in_frame_axes(world: np.ndarray, roi: Roi) -> np.ndarray:
    """``world (21, 3)`` landmarks as the model gives them on ``roi``'s crop (x right, y down in
    the rotated crop) turned about the depth axis into the frame's axes, as MediaPipe's own graph
    does (``WorldLandmarkProjectionCalculator``: rotation only). Without it a tracked hand's
    world landmarks were turned by its crop's roll, unlike the palm detector's, so smoothing and
    bridging over time mixed differently turned shapes; on the InterHand hands the world
    landmarks' orientation error was 14-85 degrees (mean 54) as the crop gave them and 4-34
    (mean 16) in the frame's axes."""
    out = np.array(world, dtype=np.float64)  # (21, 3)
    out[:, :2] = out[:, :2] @ roi.crop_axes().T  # (21, 2) frame axes
    return out


@dataclass
class RoiLandmarks:
    """The landmark model's answer on one ROI."""

    uv: np.ndarray  # (21, 2) frame pixels
    world: np.ndarray  # (21, 3) metres about the hand's centre (MediaPipe's world landmarks)
    presence: float  # hand-presence score in [0, 1]
    right: float  # score that this is a right hand as seen in the (unmirrored) frame, [0, 1]


def _model_path(complexity: int) -> Path:
    """The landmark ``.tflite`` inside the installed ``mediapipe`` wheel."""
    import importlib.util

    spec = importlib.util.find_spec("mediapipe")
    if spec is None or not spec.submodule_search_locations:
        raise LandmarkRuntimeUnavailableError("mediapipe is not installed (make setup)")
    name = "hand_landmark_full.tflite" if complexity else "hand_landmark_lite.tflite"
    path = Path(spec.submodule_search_locations[0]) / "modules" / "hand_landmark" / name
    if not path.is_file():
        raise LandmarkRuntimeUnavailableError(f"{path}: no landmark model (mediapipe 0.10.21)")
    return path


def stretch_contrast(x: np.ndarray, max_gain: float) -> np.ndarray:
    """``x (..., H, W, 3)`` in [0, 1] with its 1st-99th percentile range stretched onto [0, 1],
    the gain capped at ``max_gain``; a crop whose range needs a gain below
    :data:`MIN_STRETCH_GAIN` (well exposed) is returned as it is.

    Head-mounted video of dim rooms shows hands dark, in dark sleeves: on DWM clip 00013 the
    landmark model's presence score on the right hand's crops stays below 0.2 at frames 20-21 as
    recorded and rises above it once the crop is stretched.
    """
    lo, hi = np.percentile(x, (1.0, 99.0))
    gain = min(max_gain, 1.0 / max(float(hi - lo), 1e-6))
    if gain < MIN_STRETCH_GAIN:
        return x
    mid = 0.5 * (lo + hi)  # the stretch keeps the range's middle unless that clips it
    low = float(np.clip(mid - 0.5 / gain, 0.0, 1.0 - 1.0 / gain))
    return np.clip((x - low) * gain, 0.0, 1.0).astype(np.float32)


class LandmarkModel:
    """``hand_landmark_{full,lite}.tflite`` on ROIs, one thread (see the module docstring)."""

    def __init__(self, complexity: int = 1, num_threads: int = 1) -> None:
        try:
            from ai_edge_litert.interpreter import Interpreter
        except ImportError as exc:
            raise LandmarkRuntimeUnavailableError(
                "ROI tracking needs a TFLite runtime: pip install ai-edge-litert"
            ) from exc
        self._interp = Interpreter(model_path=str(_model_path(complexity)), num_threads=num_threads)
        self._interp.allocate_tensors()
        self._input = self._interp.get_input_details()[0]["index"]
        # Outputs by name: Identity landmarks (63), _1 presence, _2 handedness, _3 world (63).
        self._out = {d["name"]: d["index"] for d in self._interp.get_output_details()}

    def run(
        self, frame: np.ndarray, roi: Roi, max_gain: float = 1.0, mirror: bool = False
    ) -> RoiLandmarks:
        """Landmarks of the hand in ``roi`` of ``frame (H, W, 3)`` uint8 RGB; the crop's contrast
        is stretched by up to ``max_gain`` first (:func:`stretch_contrast`; 1 = as it is). With
        ``mirror`` the model sees the crop mirrored left to right, and its answer is mirrored
        back (landmarks, world landmarks and the handedness score)."""
        crop = cv2.warpAffine(
            frame,
            roi.crop_from_frame(),
            (INPUT_SIZE, INPUT_SIZE),
            flags=cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_CONSTANT,
        )  # (224, 224, 3)
        if mirror:
            crop = np.ascontiguousarray(crop[:, ::-1])
        x = (crop.astype(np.float32) / 255.0)[None]  # (1, 224, 224, 3) in [0, 1]
        if max_gain > 1.0:
            x = stretch_contrast(x, max_gain)
        self._interp.set_tensor(self._input, x)
        self._interp.invoke()
        lm = self._interp.get_tensor(self._out["Identity"]).reshape(NUM_HAND_JOINTS, 3)
        presence = float(self._interp.get_tensor(self._out["Identity_1"]).ravel()[0])
        right = float(self._interp.get_tensor(self._out["Identity_2"]).ravel()[0])
        world = self._interp.get_tensor(self._out["Identity_3"]).reshape(NUM_HAND_JOINTS, 3)
        lm, world = lm.astype(np.float64), world.astype(np.float64)
        if mirror:  # back from the mirrored crop: x (pixels, metres) and the side flip
            lm[:, 0] = INPUT_SIZE - lm[:, 0]
            world[:, 0] = -world[:, 0]
            right = 1.0 - right
        m = roi.frame_from_crop()  # (2, 3)
        uv = lm[:, :2] @ m[:, :2].T + m[:, 2]  # (21, 2) frame pixels
        return RoiLandmarks(uv, world_in_frame_axes(world, roi), presence, right)


# The ROI changes :func:`landmark_spread` runs the model on: (turn in degrees, scale, mirrored).
# Four of hands14's six (-20 degrees and 0.8 dropped; hands17): a third less CPU per small hand,
# and at MediaPipeParams.max_spread 0.05 the same hand-frames flagged on the tuned world.
SPREAD_TRANSFORMS: tuple[tuple[float, float, bool], ...] = (
    (0.0, 1.0, False),
    (20.0, 1.0, False),
    (0.0, 1.25, False),
    (0.0, 1.0, True),
)


# The reads that check a reading found only in a mirrored crop (TrackParams.mirror_max_spread):
# as it is, turned +20 degrees and scaled 1.25, all mirrored.
MIRROR_SPREAD_TRANSFORMS: tuple[tuple[float, float, bool], ...] = (
    (0.0, 1.0, True),
    (20.0, 1.0, True),
    (0.0, 1.25, True),
)


def landmark_spread(
    model: LandmarkModel,
    frame: np.ndarray,
    uv: np.ndarray,
    transforms: tuple[tuple[float, float, bool], ...] = SPREAD_TRANSFORMS,
    max_gain: float = 1.0,
) -> float:
    """How much the landmark model's answer on the ROI of landmarks ``uv (21, 2)`` in ``frame
    (H, W, 3)`` moves when the ROI is turned, scaled or mirrored (``transforms``, see
    :data:`SPREAD_TRANSFORMS`): the median, over all answers and joints, of the distance from the
    per-joint median answer, over the hand's size (wrist to middle knuckle in ``uv``).

    A truth-free cue of a hand-frame whose 2D cannot be trusted: a small or half-hidden hand the
    model reads differently at every turn of its crop. On the synthetic tuned world the hand-frames
    whose palm is more than 45 degrees off have a median spread of 0.088 against 0.042 for the
    others (AUC 0.95; held-out alt 0.111 against 0.022, AUC 0.99; measured with hands14's six
    answers, of which the default keeps four; docs/design.md "Hands v15: small hands")."""
    roi = roi_from_landmarks(uv)
    answers = np.stack(
        [
            model.run(frame, roi.turned(deg, scale), max_gain, mirror).uv
            for deg, scale, mirror in transforms
        ]
    )  # (N, 21, 2) frame pixels
    median = np.median(answers, axis=0)  # (21, 2)
    size = max(float(np.linalg.norm(uv[MIDDLE_MCP] - uv[0])), 1.0)
    return float(np.median(np.linalg.norm(answers - median, axis=2))) / size


@dataclass(frozen=True)
class TrackParams:
    """Knobs of :func:`track_through_misses`."""

    min_presence: float = 0.2  # landmark model's hand-presence score needed to keep a tracked hand
    good_presence: float = 0.5  # a hand this present ends the search over ROIs early (speed)
    refine: bool = True  # re-run the model on the ROI of its own best first answer (hand moved)
    scales: tuple[float, ...] = (1.0, 1.3)  # ROI sides tried, relative to the predicted one
    shifts: tuple[float, ...] = (0.0, 0.15)  # ROI moves tried, down the image, in ROI sides
    unmoved: bool = True  # also try the predicted ROI without the optical flow's shift
    # tried when none of the above finds the hand: (scale, right, down) ROI changes, shifts in sides
    wider: tuple[tuple[float, float, float], ...] = (
        (1.6, 0.0, 0.0),
        (1.6, 0.3, 0.0),
        (1.6, -0.3, 0.0),
        (1.0, 0.3, 0.0),
        (1.0, -0.3, 0.0),
        (1.0, 0.0, -0.15),
    )
    max_size_change: float = 1.6  # a tracked hand's size may change at most this factor per frame
    # ... and at most max_drift from its last trusted reading (a palm detection, or a tracked
    # one of presence >= trust_presence), so that steps under that presence cannot add up (a
    # hand's readings spreading over its dark sleeve); a reading refused for it is searched for
    # again from the trusted landmarks, carried by the flow. None: no such test.
    max_drift: float | None = 1.6
    trust_presence: float = 0.5  # a tracked reading this present (or more) is trusted
    max_jump: float = 1.0  # ... and its centre move at most this many hand sizes per frame
    duplicate_distance: float = 0.5  # a hand this near (in hand sizes) one already there is it
    flow: bool = True  # carry the ROI by the optical flow of the landmarks between frames
    max_steps: int = 1000  # frames a hand is followed from its last palm-detector detection
    max_coast: int = 3  # frames a lost hand's landmarks are carried by the flow alone
    reacquire_presence: float = 0.5  # presence needed to take a hand up again after carrying it
    max_gain: float = 4.0  # dark, flat crops get their contrast stretched by up to this gain
    carry_to_edge: bool = True  # a hand lost at the clip's first/last frame, found next to it,
    # is carried there by the optical flow (no later frame could take it up again)
    mirror_retry: bool = True  # when no ROI holds the hand at the presence the step needs,
    # read the predicted ROIs once more mirrored (the model is not mirror-symmetric; _search)
    # a reading found only in the ``wider`` ROIs (away from where the hand was predicted) is kept
    # only when it is confirmed: the model, searching back from it on the frame it was followed
    # from, finds there the hand it was followed from (:func:`_confirmed`); False: no such test
    confirm_wider: bool = True
    # a reading found only in a mirrored crop is kept only when mirrored crops turned and scaled
    # (MIRROR_SPREAD_TRANSFORMS) read it alike: its landmark_spread at most this (the hands
    # stage's max_spread, not tuned here); None: no such test
    mirror_max_spread: float | None = 0.05

    def __post_init__(self) -> None:
        if self.mirror_max_spread is not None and not 0.0 < self.mirror_max_spread < np.inf:
            raise ValueError(
                f"mirror_max_spread must be > 0 and finite or None, got {self.mirror_max_spread!r}"
            )


def flow_shift(prev_gray: np.ndarray, next_gray: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Median displacement ``(2,)`` pixels of ``points (N, 2)`` from one grey frame to the next
    (pyramidal Lucas-Kanade); zero when no point is followed."""
    p0 = np.ascontiguousarray(points, dtype=np.float32).reshape(-1, 1, 2)
    p1, status, _ = cv2.calcOpticalFlowPyrLK(
        prev_gray, next_gray, p0, None, winSize=(21, 21), maxLevel=3
    )
    ok = status.ravel() == 1
    if not ok.any():
        return np.zeros(2)
    return np.median((p1 - p0).reshape(-1, 2)[ok], axis=0).astype(np.float64)


def _size(uv: np.ndarray) -> float:
    return float(np.linalg.norm(uv.max(axis=0) - uv.min(axis=0)))


def track_through_misses(
    frames: np.ndarray,
    uv: np.ndarray,
    world: np.ndarray,
    label_right: np.ndarray,
    present: np.ndarray,
    model: LandmarkModel,
    params: TrackParams | None = None,
) -> np.ndarray:
    """Follow every detected hand forwards and backwards in time into frames that lack it.

    ``frames (T, H, W, 3)`` uint8 RGB; ``uv (T, K, 21, 2)``, ``world (T, K, 21, 3)``,
    ``label_right (T, K)`` and ``present (T, K)`` are the detections, filled in place where a
    followed hand lands in a free slot. A hand at frame ``f`` is looked for at ``f +- 1`` in the
    ROI its landmarks predict (:func:`roi_from_landmarks`, moved by :func:`flow_shift`) unless a
    hand is already there; it is kept when the model's presence score is at least
    ``min_presence`` and its size and position stay plausible, and then followed on. Where the
    model does not find it (motion blur, a hand half out of the frame for a moment), its
    landmarks are carried on by the optical flow alone (the camera's motion moves the hand in the
    image) for up to ``max_coast`` frames, and the search goes on from there; a hand taken up
    again that way needs ``reacquire_presence`` (nothing vouches for it but the flow: on the
    synthetic world, accepting it at ``min_presence`` raised recall 0.60 -> 0.68 but the mean
    orientation error 13.5 -> 22.5 degrees), and the frames crossed stay empty (the sides step
    bridges them). A hand lost at the clip's first or last frame, found on the frame next to it,
    is carried onto it by the flow (``carry_to_edge``: no frame beyond could take it up again,
    and no bridge reaches an end). Each step may change the size by ``max_size_change``, but
    the reading must also stay within ``max_drift`` of the size of the track's last trusted
    reading (a detection, or one of presence ``trust_presence`` or more), so that steps of low
    presence cannot add up: on DWM 00013 from frame 8 as ingested (window 70013) the right
    hand's readings, 0.12-0.51 present, spread over its dark sleeve 95 -> 122 -> 181 -> 220 px
    in four frames and the hand was lost. A reading refused for that is searched for again, as
    a lost hand, from the trusted landmarks carried on by the flow (there the real hand came
    back in view two frames later and was found). A reading found only in the ``wider`` ROIs
    (away from where the hand was predicted) while following a reading must lead back to it
    (``confirm_wider``, :func:`_confirmed`): searched for from it on the frame it was followed
    from, the model must find that reading's hand there; if it does not, the model read
    another thing as a hand, and the hand is not followed further in that direction. On
    pour_coke at 8 fps the right hand, entering at the border at frame 5, was followed back to
    frame 4, where only its fingertips show: the widest ROI shifted away from the border read
    the jug and the can as a hand 1.58x its size (presence 0.45), which, searched for back on
    frame 5, is the jug and can again; the flow then carried the hand onto them to frame 0, a
    false hand that the hand-free fill of a static camera repeats in every frame (issue 9). A
    hand already in a frame that is a fit to the followed hand's fingers alone
    (:func:`_partial_fits`) does not stop it: the whole hand replaces it.
    Returns ``tracked (T, K)`` bool: the slots filled here.
    """
    params = params or TrackParams()
    t = present.shape[0]
    tracked = np.zeros_like(present)
    steps = np.where(present, 0, -1)  # (T, K) frames since a detection, -1 = empty
    anchor = np.array(uv, dtype=np.float64)  # (T, K, 21, 2) last trusted landmarks, carried
    grey = [cv2.cvtColor(f, cv2.COLOR_RGB2GRAY) if params.flow else None for f in frames]
    for direction in (1, -1):
        order = range(t) if direction > 0 else range(t - 1, -1, -1)
        # frame -> (uv, coast, steps, slot, trusted landmarks)
        coasting: dict[int, list[tuple[np.ndarray, int, int, int, np.ndarray]]] = {}
        for f in order:
            g = f + direction
            if not 0 <= g < t:
                continue
            sources = [
                (uv[f, k], 0, int(steps[f, k]), k, anchor[f, k]) for k in np.flatnonzero(present[f])
            ]
            for src, coast, step, k, trusted in sources + coasting.pop(f, []):
                if step >= params.max_steps:
                    continue
                size = _size(src)
                whole = present[g] & ~_partial_fits(src, uv[g], present[g], params)  # (K,)
                if _near_any(src.mean(axis=0), size, uv[g], whole, params.duplicate_distance):
                    continue
                if not (~whole).any():
                    continue
                move = flow_shift(grey[f], grey[g], src) if params.flow else np.zeros(2)  # (2,)
                need = params.min_presence if coast == 0 else params.reacquire_presence
                res, wide = _search(model, frames[g], src, move, params, need)
                partial = present[g] & _partial_fits(res.uv, uv[g], present[g], params)  # (K,)
                whole = present[g] & ~partial
                plausible = _plausible(res, src, need, params)
                drifted = plausible and _drifted(res, trusted, params)
                # found only away from the prediction, from a reading (not a coasting guess):
                # it must lead back to the hand it was followed from
                if (
                    params.confirm_wider
                    and wide
                    and coast == 0
                    and plausible
                    and not drifted
                    and not _confirmed(model, frames[f], grey[f], grey[g], res, src, params)
                ):
                    continue  # another thing read as a hand where this one was looked for:
                    # the hand is not followed further this way (coasting on, the search only
                    # took that thing up again: pour_coke's jug and can)
                if (
                    not plausible
                    or drifted
                    or _near_any(
                        res.uv.mean(axis=0), _size(res.uv), uv[g], whole, params.duplicate_distance
                    )
                ):  # lost here (or it slid onto a hand already there)
                    if coast < params.max_coast and 0 <= g + direction < t:
                        # a reading that drifted off the trusted one: search again from that
                        last = trusted if drifted else src
                        coasting.setdefault(g, []).append(
                            (last + move, coast + 1, step + 1, -1, trusted + move)
                        )
                    elif params.carry_to_edge and coast == 0 and g in (0, t - 1):
                        # g is the clip's first or last frame: no later frame can take the hand
                        # up again, so the flow carries the hand found next to it onto it
                        carried = src + move  # (21, 2)
                        if not (~present[g]).any() or _near_any(
                            carried.mean(axis=0), size, uv[g], present[g], params.duplicate_distance
                        ):
                            continue
                        s = int(np.flatnonzero(~present[g])[0])
                        uv[g, s], world[g, s] = carried, world[f, k]
                        label_right[g, s] = label_right[f, k]
                        present[g, s], tracked[g, s], steps[g, s] = True, True, step + 1
                        anchor[g, s] = trusted + move
                    continue
                free = np.flatnonzero(partial | ~present[g])  # a partial fit of it is replaced
                if not free.size:
                    continue
                s = int(free[np.argmax(partial[free])])
                uv[g, s], world[g, s], label_right[g, s] = res.uv, res.world, res.right
                present[g, s], tracked[g, s] = True, True
                steps[g, s] = step + 1
                trust = res.presence >= params.trust_presence
                anchor[g, s] = res.uv if trust else trusted + move
    return tracked


def _plausible(res: RoiLandmarks, src: np.ndarray, presence: float, params: TrackParams) -> bool:
    """Whether the model's answer ``res`` is the hand of landmarks ``src (21, 2)``: at least
    ``presence``, of a similar size and not too far (see :class:`TrackParams`)."""
    if res.presence < presence:
        return False
    size, new_size = _size(src), _size(res.uv)
    ratio = new_size / max(size, 1e-6)
    if not 1 / params.max_size_change <= ratio <= params.max_size_change:
        return False
    jump = float(np.linalg.norm(res.uv.mean(axis=0) - src.mean(axis=0)))
    return jump <= params.max_jump * max(size, new_size)


def _drifted(res: RoiLandmarks, trusted: np.ndarray, params: TrackParams) -> bool:
    """Whether the answer ``res`` has a size more than ``params.max_drift`` off the track's
    last trusted landmarks ``trusted (21, 2)``."""
    if params.max_drift is None:
        return False
    ratio = _size(res.uv) / max(_size(trusted), 1e-6)
    return not 1 / params.max_drift <= ratio <= params.max_drift


def _confirmed(
    model: LandmarkModel,
    frame: np.ndarray,
    grey: np.ndarray | None,
    grey_found: np.ndarray | None,
    res: RoiLandmarks,
    src: np.ndarray,
    params: TrackParams,
) -> bool:
    """Whether the reading ``res``, found in the frame after (or before) ``frame`` by following
    landmarks ``src (21, 2)`` of ``frame``, leads back to them: searched for from ``res`` in
    ``frame`` (moved by the flow from ``grey_found``, the found frame's grey image, to ``grey``),
    the hand the model finds there is present (``min_presence``), within ``duplicate_distance``
    of ``src``'s size of it and of a size within ``max_size_change`` of it."""
    move = flow_shift(grey_found, grey, res.uv) if params.flow else np.zeros(2)  # (2,)
    back, _ = _search(model, frame, res.uv, move, params, params.min_presence)
    if back.presence < params.min_presence:
        return False
    size = _size(src)
    ratio = _size(back.uv) / max(size, 1e-6)
    if not 1 / params.max_size_change <= ratio <= params.max_size_change:
        return False
    jump = float(np.linalg.norm(back.uv.mean(axis=0) - src.mean(axis=0)))
    return jump <= params.duplicate_distance * size


def _search(
    model: LandmarkModel,
    frame: np.ndarray,
    src: np.ndarray,
    move: np.ndarray,
    params: TrackParams,
    need: float,
) -> tuple[RoiLandmarks, bool]:
    """The most present hand among ROIs around the one ``src (21, 2)`` predicts in ``frame``,
    and whether it was found only in the ``wider`` ROIs.

    Tried: the predicted ROI moved by ``move (2,)`` pixels (the optical flow) at every scale and
    downward shift of ``params`` (head-mounted cameras tilt up and down, so hands move mostly
    vertically in the image), and unmoved (when ``params.unmoved`` and there is a move); when
    none holds a hand, the ``wider`` set (larger and sideways-shifted ROIs: fast hands; the
    second value returned says the answer came from there). The search stops at the first
    answer with ``good_presence``. When no ROI holds a hand at ``need`` (the presence the
    tracker needs on this step: ``min_presence`` following a reading, ``reacquire_presence``
    after a coast) and ``params.mirror_retry``, each predicted ROI (not the wider ones) is read
    once more with the crop mirrored (answer mirrored back), and the most present answer of
    all is kept. The landmark model is not mirror-symmetric: on DWM 00013 mirrored left to
    right the real left hand (then a right one) was lost at frames 12-20 that the unmirrored
    clip follows throughout (hands v17 read the first predicted ROI mirrored when none held a
    hand at ``min_presence``: recall 0.625 -> 1; design.md, "Hands v17"). On the rehearsal copy
    90013 (00013 mirrored, re-encoded) the same sleeved hand, at the bottom border at frame 22,
    was read at 0.12 at best (the first predicted ROI mirrored no better), then, coasting, at
    0.48 and 0.43 on frames 23-24 (under ``reacquire_presence``) and never found again (recall
    0.542): another predicted ROI read mirrored holds it at 0.23 on frame 22, and it is
    followed to frame 32 (recall 1.0). On 00013 re-encoded as ingested (60013) the right hand,
    coasting at frames 28-30 from an oversized palm detection, is read 0.45 on 28, and on 30
    at 0.89 mirrored (recall 0.708 -> 0.958). design.md, "Tracker: every predicted ROI read
    mirrored". The best answer is refined once on its own ROI (mirrored again if it came from
    a mirrored read). An answer from a mirrored read is then kept only if mirrored crops turned
    and scaled read it alike (``params.mirror_max_spread``, :data:`MIRROR_SPREAD_TRANSFORMS`):
    on the synthetic tuned world every predicted ROI read mirrored added a hidden hand read as
    a clump 33-48 px off its joints (default seed 1), which that test removes; it also removes
    90013's gain, so that copy stays at 0.542 (60013 as ingested 0.708 -> 0.917 and 40013 as
    ingested left 0.875 -> 1 stay).
    """
    base = roi_from_landmarks(src)
    moves = [move] + ([np.zeros(2)] if params.unmoved and np.any(move != 0) else [])
    rois = [
        Roi(base.centre + m + np.array([0.0, shift * base.side]), base.side * scale, base.up)
        for i, m in enumerate(moves)
        for scale in (params.scales if i == 0 else (1.0,))
        for shift in (params.shifts if i == 0 else (0.0,))
    ]
    start = base.centre + moves[0]  # (2,)
    wider = [
        Roi(start + base.side * np.array([right, down]), base.side * scale, base.up)
        for scale, right, down in params.wider
    ]
    best = None
    wide = False  # the best answer came from the wider set
    for i, roi in enumerate(rois + wider):
        if i == len(rois) and best is not None and best.presence >= params.min_presence:
            break  # the wider set only when the others found nothing
        res = model.run(frame, roi, params.max_gain)
        if best is None or res.presence > best.presence:
            best, wide = res, i >= len(rois)
        if best.presence >= params.good_presence:
            break  # clearly found: the remaining ROIs cannot matter much
    mirrored, plain, plain_wide = False, best, wide
    if params.mirror_retry and best.presence < max(need, params.min_presence):
        for roi in rois:  # the predicted ROIs only: a mirrored read is no wider search
            res = model.run(frame, roi, params.max_gain, mirror=True)
            if res.presence > best.presence:
                best, mirrored, wide = res, True, False
    if params.refine and best.presence >= params.min_presence:
        again = model.run(frame, roi_from_landmarks(best.uv), params.max_gain, mirror=mirrored)
        if again.presence >= best.presence:
            best = again
    if mirrored and params.mirror_max_spread is not None and best.presence >= params.min_presence:
        spread = landmark_spread(model, frame, best.uv, MIRROR_SPREAD_TRANSFORMS, params.max_gain)
        if spread > params.mirror_max_spread:  # read differently at every turn: not kept
            best, wide = plain, plain_wide  # the plain reads' answer (under ``need``: not taken)
    return best, wide


def _partial_fits(
    hand: np.ndarray, uv: np.ndarray, present: np.ndarray, params: TrackParams
) -> np.ndarray:
    """``(K,)`` bool: present hands of ``uv (K, 21, 2)`` that look like a part of ``hand (21, 2)``
    (its fingers alone): smaller by more than ``max_size_change`` and with centres nearer than
    ``duplicate_distance`` of its size (the rule that makes two answers one hand).

    The landmark model sometimes fits a whole hand to a grasping hand's fingers (HOT3D window 0:
    a 40-50 px "hand" on the fingertips of a 150-190 px hand reaching for a toy house, found by
    the palm detector at frames 12-13 and followed back to frame 3); such a fit must not stop
    the whole hand, followed from where it is found whole, from taking those frames.
    """
    out = np.zeros(len(uv), dtype=bool)
    size = _size(hand)
    centre = hand.mean(axis=0)  # (2,)
    for k in np.flatnonzero(present):
        near = np.linalg.norm(uv[k].mean(axis=0) - centre) <= params.duplicate_distance * size
        out[k] = bool(near) and _size(uv[k]) * params.max_size_change < size
    return out


def _near_any(
    centre: np.ndarray, size: float, uv: np.ndarray, present: np.ndarray, distance: float
) -> bool:
    """Whether a present hand of ``uv (K, 21, 2)`` has its centre within ``distance`` sizes."""
    for k in np.flatnonzero(present):
        other = uv[k]
        limit = distance * max(size, _size(other))
        if np.linalg.norm(other.mean(axis=0) - centre) <= limit:
            return True
    return False
