"""How well the ``hands`` backend ``mediapipe`` finds hands in real and synthetic development video.

``python -m bench.hands_real [--data ../shared/data] [--seeds 11 13] [--variants default alt]
[--skip-synthetic] [--skip-real] [--per-joint] [--misses] [--perturb [NAME ...]]`` prints,
with the default :class:`~egosim.stages.hands.mediapipe_backend.MediaPipeParams`:

- **DWM dynamic clips** (``dwm_realworld/realworld_dynamic/videos/*.mp4``, every clip found there
  by :mod:`bench.real_clips` that has its ``videos_hands`` renders, which paint the true left
  hand green and the right hand red): per side, the frames where the render shows that hand (at
  least ``MIN_RENDER_PIXELS`` pixels of its colour) and the fraction of them with a detection of
  that side (recall; anywhere in the image), with one of that side within ``FAR_PX`` of that
  hand's render (``recall_on_hand``: a hand found and given its own side) and with a trusted 3D
  hand (``coverage_3d``: the backend withholds the 3D of a palm turned off its track, keeping
  its 2D, :attr:`~egosim.stages.hands.mediapipe_backend.MediaPipeResult.lifted`); false positives:
  detections whose keypoint centroid is further than ``FAR_PX`` from every rendered hand pixel of
  either side (the renders leave out a hand on some frames where it is in view: detections there,
  on the frames listed by eye in ``RENDER_GAPS``, count as ``on_unrendered``, not as false
  positives); side-label agreement: of the detections that lie on a rendered hand, the fraction
  whose side is that hand's colour; the mean distance from the keypoint centroid to the rendered
  hand's pixel centroid on frames where both exist. Each clip twice: as the file holds it, and
  "as ingested" (:func:`as_ingested`: the frames the ``hands`` stage of ``bench.real_video`` gets).
- **Fixed-camera and EgoDex videos** (``realworld_fixed/*.mp4``, ``egodex_sample/*.mp4``),
  cut into clips by ingest's own windowing with its egosim preset (16 fps by nearest timestamp,
  scaled to cover 480x832 and centre-cropped; 61-frame windows, then a 1 + 4k tail of at least
  33 frames): per window, frames with 0 / 1 / 2 hands, the fraction
  with any, the share of found hand-frames with a trusted 3D hand (``lifted_share``) and the
  first frame with each hand (no ground truth there); the fixed-camera videos also as
  ``bench.hand_free_real`` takes them (:func:`fixed_sampled`: 8 fps, 49 frames, 640 wide: a
  false hand at frame 0 there is filled into every frame of the static scene; hands v20).
- **Synthetic world** (``render_clip(WorldConfig(seed, mode))``, true joints known): recall, 2D
  error, 3D coverage (true hand-frames found with a trusted 3D hand), and over those the 3D
  orientation error and wrist-relative MPJPE (:mod:`egosim.stages.hands.metrics`),
  for the palm-PnP lift (the default: palm poses refined on the reprojection error), the same
  with IPPE's palm poses as they are (``palm_pnp_ippe``: ``MediaPipeParams.refine_palm`` off,
  the default before hands v8) and the old translation-only lift on the same detections (2D
  error of the landmarks; ``drawn_2d_px``: of the palm-PnP joints' own projection, what masks
  and skeletons draw, which the hands v10 repair moves off the landmarks where it interpolates a
  palm); with
  ``--per-joint``, each joint's mean wrist-relative error (mm) and 2D error (px) for the palm-PnP
  lift (which joints carry the MPJPE: on the drawn hands the wrist and thumb, whose 2D points
  MediaPipe puts 24-40 px from the world's joints where the fingers are 4-9 px off); with
  ``--misses``, for the true hands in view that the backend missed, how often the landmark model
  sees a hand on the true hand's own ROI (:func:`missed_presence`): a search problem when it
  does, the model's when it does not.
- **InterHand fixture** (``interhand_fixture/``: real hands, studio cameras, 3D joints): the
  landmark model run on the ROI of each true hand (the palm detector finds 1 of 6 in these tight
  crops), then the depth each lift gives against the true median joint depth: the palm-PnP lift
  the hands stage and the metric scale share (``prefer_fingers_away=False``: no head-mounted
  prior in a studio), the same with IPPE's palm poses unrefined, and the translation-only fit of
  MediaPipe's world landmarks; and each palm-PnP lift's wrist-relative MPJPE and orientation
  error once placed at the true median depth.
- With ``--tracks``, per real clip (DWM, fixed-camera, EgoDex): each track the side step links
  (:func:`track_rows`) with truth-free cues a filter of false hands could use: its frames and
  side, median hand size and its ratio to the other hand in shared frames, its centre's median
  step per frame (in hand sizes), its median height in the image, the median thinness of its
  landmarks (minor over major spread: a hand seen edge-on, or a fold, is a line), MediaPipe's
  median handedness confidence, the landmark model's median presence on the track's own ROIs
  (:func:`~egosim.stages.common.hand_landmarks.landmark_presence`) and how many of its
  detections were not found by the ROI tracker. None of them separated the false curtain hand of
  the EgoDex portrait clip from every real hand (docs/design.md, "Hands v12").
- With ``--perturb [NAME ...]``, only the DWM dynamic clips, unperturbed and made to look like
  footage we do not have (:data:`PERTURBATIONS`: darker x0.5, gamma 1.8, a 15 px horizontal
  motion blur, 360p scaled back up, 4 fps, JPEG quality 10, mirrored left-right, where a
  correct pipeline gives the unperturbed figures with the sides swapped; :func:`perturb_clip`
  keeps the renders and render gaps aligned with the frames), each as the file holds it and as
  ingested: recall and false-positive frames per side, side agreement and centroid distance
  against the same renders.
- Seconds per clip of the whole backend (detection, tracking, sides, smoothing, lift): wall clock
  and this process's CPU time (``cpu_s``; the wall clock counts other work on a shared machine).
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from bench.real_clips import (
    dwm_dynamic_clips,
    dwm_fixed_videos,
    egodex_videos,
    rehearsal_source,
    table_entry,
)
from egosim.pipeline import media
from egosim.pipeline.geometry import intrinsics_from_fov, project_points
from egosim.pipeline.media import read_video_file
from egosim.pipeline.stage import ClipRejected
from egosim.stages.common.frame_plan import plan_resize
from egosim.stages.common.hand_landmarks import hand_centres, hand_size, landmark_presence
from egosim.stages.hands.mediapipe_backend import (
    MediaPipeParams,
    MediaPipeResult,
    _tracks,
    assign_sides,
    detect_landmarks,
    hands_from_raw,
)
from egosim.stages.hands.metrics import JOINT_NAMES, combine, hand_accuracy, true_hands_in_view
from egosim.stages.ingest.crop_anchor import choose_anchor, sample_video
from egosim.stages.ingest.stage import CLIP_PRESETS, IngestConfig
from egosim.stages.ingest.standardise import Window, WindowPolicy, resample_windows

DEFAULT_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
MIN_RENDER_PIXELS = 150  # a render shows a hand when at least this many pixels have its colour
FAR_PX = 40.0  # a detection this far (px) from every rendered hand pixel is a false positive
EGOSIM = CLIP_PRESETS["egosim"]  # the clip format real videos are cut to (ingest's default)
DWM = CLIP_PRESETS["dwm"]  # the format DWM clips are ingested in (bench.real_video)
SIDES = ("left", "right")
# Frames whose render leaves out a hand that is plainly in view (checked by eye on the real frames;
# 00013 frame 8 renders only the right hand): a detection there away from the rendered hands is
# neither a false positive nor a find ("on_unrendered"); on any other frame, a false positive.
# A clip not listed has none (a printed line says so: bench.real_clips.table_entry).
RENDER_GAPS = {
    "00013": (7, 8, 21, 22, 35),
    "00017": (*range(20, 33), *range(36, 43), 47),
}


def render_gaps(video: Path) -> tuple[int, ...]:
    """The frames of DWM clip ``video`` whose truth render leaves out a visible hand:
    :data:`RENDER_GAPS`' entry, or for a rehearsal copy of a clip it holds
    (:func:`bench.real_clips.rehearsal_source`) the copy's frames made from those; an unknown
    clip has none (said once)."""
    if video.stem not in RENDER_GAPS:
        found = rehearsal_source(video.parent.parent, video.stem)
        if found is not None and found[0] in RENDER_GAPS:
            source, frames = found
            return tuple(i for i, f in enumerate(frames) if f in RENDER_GAPS[source])
    return table_entry(RENDER_GAPS, video.stem, (), "RENDER_GAPS")  # an unknown clip: none


def render_masks(render: np.ndarray) -> np.ndarray:
    """``(T, 2, H, W)`` bool: green (left) and red (right) pixels of renders ``(T, H, W, 3)``."""
    r, g, b = (render[..., c].astype(np.int16) for c in range(3))
    green = (g > 100) & (g > r + 50) & (g > b + 50)  # (T, H, W)
    red = (r > 100) & (r > g + 50) & (r > b + 50)  # (T, H, W)
    return np.stack([green, red], axis=1)


def dwm_figures(
    video: Path,
    render_path: Path,
    ingested: bool = False,
    tracks: list | None = None,
    perturb: str | None = None,
) -> dict[str, float]:
    """Recall, false positives, side agreement and centroid distance on one DWM clip; with
    ``ingested``, on the frames the ``hands`` stage gets (:func:`as_ingested`); given a
    ``tracks`` list, the clip's :func:`track_rows` are added to it; given a ``perturb`` name
    (:data:`PERTURBATIONS`), on the clip so perturbed (:func:`perturb_clip`, before ingest)."""
    frames, _ = read_video_file(video)
    render, _ = read_video_file(render_path)
    t = min(len(frames), len(render))
    frames, render = frames[:t], render[:t]
    gaps = render_gaps(video)
    fps = DWM.fps  # the files' rate and ingest's dwm preset's
    if perturb is not None:
        frames, render, gaps, fps = perturb_clip(frames, render, gaps, perturb)
        t = len(frames)
    if ingested:
        frames = as_ingested(frames)
    w = frames.shape[2]
    start, cpu = time.perf_counter(), time.process_time()
    res = _run(frames, fps)
    seconds, cpu = time.perf_counter() - start, time.process_time() - cpu
    if tracks is not None:
        tracks += track_rows(frames, res)
    masks = render_masks(render)  # (T, 2, H, W)
    shown = masks.sum(axis=(2, 3)) >= MIN_RENDER_PIXELS  # (T, 2)
    any_hand = masks.any(axis=1)  # (T, H, W)
    out: dict[str, float] = {"frames": float(t), "seconds": seconds, "cpu_s": cpu}
    agree = total_on = 0
    dists: list[float] = []
    for s in range(2):
        found = shown[:, s] & res.valid[:, s]
        out[f"{SIDES[s]}_shown"] = float(shown[:, s].sum())
        out[f"{SIDES[s]}_recall"] = float(found.sum() / max(shown[:, s].sum(), 1))
        fp = unrendered = on_hand = 0
        for f in np.flatnonzero(res.valid[:, s]):
            c = np.nanmean(res.landmarks.uv[f, s], axis=0)  # (2,) keypoint centroid
            rows, cols = np.nonzero(any_hand[f])
            if rows.size == 0:
                if f in gaps:
                    unrendered += 1
                else:
                    fp += 1
                continue
            near = np.min(np.hypot(cols + 0.5 - c[0], rows + 0.5 - c[1]))
            if near > FAR_PX:
                if f in gaps:
                    unrendered += 1
                else:
                    fp += 1
                continue
            on = [k for k in range(2) if shown[f, k]]
            if on:
                colour = min(on, key=lambda k: _dist_to_mask(masks[f, k], c))
                total_on += 1
                agree += int(colour == s)
            if shown[f, s]:
                rr, cc = np.nonzero(masks[f, s])
                dists.append(float(np.hypot(cc.mean() + 0.5 - c[0], rr.mean() + 0.5 - c[1])))
                on_hand += int(_dist_to_mask(masks[f, s], c) <= FAR_PX)
        out[f"{SIDES[s]}_recall_on_hand"] = float(on_hand / max(shown[:, s].sum(), 1))
        out[f"{SIDES[s]}_false_pos_frames"] = float(fp)
        out[f"{SIDES[s]}_on_unrendered"] = float(unrendered)
        out[f"{SIDES[s]}_coverage_3d"] = float(
            (found & res.lifted[:, s]).sum() / max(shown[:, s].sum(), 1)
        )
    out["side_agreement"] = agree / total_on if total_on else float("nan")
    out["centroid_px"] = float(np.mean(dists)) if dists else float("nan")
    out["size"] = float(w)
    return out


PERTURBATIONS = {  # name -> what perturb_clip does to a DWM clip (720x480, 8 fps)
    "dark": "every pixel x0.5 (an underexposed clip)",
    "gamma": "gamma 1.8: 255 (x / 255) ** 1.8 (shadows darker, highlights kept)",
    "blur": "horizontal motion blur: a 15 px line kernel (2% of the width)",
    "360p": "down to 540x360 (area), back to 720x480 (bilinear: ingest scales up to the preset)",
    "4fps": "every other frame, at 4 fps (truth and render gaps the same frames)",
    "jpeg": "each frame through JPEG at quality 10",
    "mirror": "frames flipped left-right; the renders flipped with green and red swapped",
}


def perturb_clip(
    frames: np.ndarray, render: np.ndarray, gaps: tuple[int, ...], name: str
) -> tuple[np.ndarray, np.ndarray, tuple[int, ...], float]:
    """``(frames, render, gaps, fps)``: DWM ``frames (T, H, W, 3)`` made to look like footage
    we do not have (:data:`PERTURBATIONS`), with the truth ``render`` and the render-gap frames
    ``gaps`` still aligned with them, and the clip's frame rate."""
    import cv2

    fps = DWM.fps
    if name == "dark":
        frames = np.round(frames * 0.5).astype(np.uint8)
    elif name == "gamma":
        lut = np.round(255.0 * (np.arange(256) / 255.0) ** 1.8).astype(np.uint8)  # (256,)
        frames = lut[frames]
    elif name == "blur":
        kernel = np.full((1, 15), 1.0 / 15.0)  # (1, 15) horizontal line
        frames = np.stack(
            [cv2.filter2D(f, -1, kernel, borderType=cv2.BORDER_REFLECT) for f in frames]
        )
    elif name == "360p":
        h, w = frames.shape[1:3]
        small = (round(w * 360 / h), 360)
        frames = np.stack(
            [cv2.resize(cv2.resize(f, small, interpolation=cv2.INTER_AREA), (w, h)) for f in frames]
        )
    elif name == "4fps":
        frames, render, fps = frames[::2], render[::2], DWM.fps / 2
        gaps = tuple(f // 2 for f in gaps if f % 2 == 0)
    elif name == "jpeg":
        code = [int(cv2.IMWRITE_JPEG_QUALITY), 10]

        def coded(rgb: np.ndarray) -> np.ndarray:  # (H, W, 3) RGB through JPEG and back
            data = cv2.imencode(".jpg", rgb[..., ::-1], code)[1]
            return cv2.imdecode(data, cv2.IMREAD_COLOR)[..., ::-1]

        frames = np.stack([coded(f) for f in frames])
    elif name == "mirror":  # the real left hand is now a right hand: red in the render
        frames, render = (
            frames[:, :, ::-1],
            np.ascontiguousarray(render[:, :, ::-1][..., [1, 0, 2]]),
        )
    else:
        raise ValueError(f"unknown perturbation {name!r}; known: {sorted(PERTURBATIONS)}")
    return np.ascontiguousarray(frames), render, gaps, fps


def as_ingested(frames: np.ndarray) -> np.ndarray:
    """``frames (T, H, W, 3)`` of a DWM clip as ``ingest.preset=dwm`` stores them: same size and
    frame rate (8 fps, 480x720), H.264 at ingest's default quality, decoded again. (The stored
    clip of ``bench.real_video``'s 00013 run is pixel-identical to this.) The second lossy pass
    changes what the palm detector finds: on 00013 MediaPipe alone then finds a hand on 7
    frames, and the tracker has to carry both hands through the rest."""
    data = media.encode_rgb_video(frames, DWM.fps, IngestConfig().crf)
    return np.stack(media.decode_rgb_video(data))


def _dist_to_mask(mask: np.ndarray, point: np.ndarray) -> float:
    rows, cols = np.nonzero(mask)
    return float(np.min(np.hypot(cols + 0.5 - point[0], rows + 0.5 - point[1])))


def _run(frames: np.ndarray, fps: float, params: MediaPipeParams | None = None):
    """The whole backend on ``frames (T, H, W, 3)`` at ``fps`` with a 90-degree camera (2D
    figures, and which hands keep their 3D)."""
    params = params or MediaPipeParams()
    k = intrinsics_from_fov(frames.shape[2], frames.shape[1], 90.0)
    raw = detect_landmarks(frames, params)
    return hands_from_raw(raw, frames.shape[2], k, None, None, params, fps=fps, frames=frames)


def ingest_windows(path: Path) -> list[Window]:
    """The clips ingest's egosim preset cuts from a video (16 fps by nearest timestamp, scaled to
    cover 480x832 and cropped where ingest's default ``crop="hands"`` puts the window, full
    windows then a ``1 + 4k`` tail): ingest's own
    :func:`~egosim.stages.ingest.crop_anchor.choose_anchor` and
    :func:`~egosim.stages.ingest.standardise.resample_windows`; none when it rejects the video."""
    frames, stamps = read_video_file(path)
    cfg = IngestConfig(preset="egosim")
    sample = sample_video(path, media.probe_video_file(path))
    anchor = choose_anchor(cfg, frames.shape[2], frames.shape[1], sample, path.name)
    plan = plan_resize(frames.shape[2], frames.shape[1], EGOSIM.width, EGOSIM.height, anchor)
    policy = WindowPolicy(EGOSIM.fps, EGOSIM.num_frames, EGOSIM.min_frames, preset="egosim")
    pairs = ((float(t), plan.apply(frame)) for t, frame in zip(stamps, frames, strict=True))
    try:
        return list(resample_windows(pairs, policy, what=path.name))
    except ClipRejected:
        return []


def count_figures(path: Path, tracks: list | None = None) -> list[dict[str, float]]:
    """Per ingest window of one video: frames with 0 / 1 / 2 hands, the fraction with any
    (pack's gate wants >= 0.1) and the first frame of each side; given a ``tracks`` list, each
    window's :func:`track_rows` are added to it (the window's start in ``"start"``)."""
    return [
        _counts(window.frames, EGOSIM.fps, float(window.index * EGOSIM.num_frames), tracks)
        for window in ingest_windows(path)
    ]


def fixed_sampled(path: Path, fps: float = 8.0, frames: int = 49, width: int = 640) -> np.ndarray:
    """``(T, H, W, 3)`` the frames of a fixed-camera video as ``bench.hand_free_real``'s
    ``fixed_case`` takes them (``fps`` by nearest timestamp, ``frames`` long, scaled to ``width``):
    on pour_coke so taken the tracker of hands v19 carried the entering hand back onto the jug
    and can (frames 0-4), a false frame-0 hand that ingest's own windows did not show."""
    import cv2

    video, stamps = read_video_file(path)
    pick = [int(np.argmin(np.abs(stamps - k / fps))) for k in range(frames)]
    h = round(video.shape[1] * width / video.shape[2])
    return np.stack([cv2.resize(video[i], (width, h), interpolation=cv2.INTER_AREA) for i in pick])


def _counts(
    frames: np.ndarray, fps: float, first: float, tracks: list | None = None
) -> dict[str, float]:
    """:func:`count_figures`' figures of one clip ``frames (T, H, W, 3)`` at ``fps`` whose first
    frame is the video's frame ``first``."""
    start, cpu = time.perf_counter(), time.process_time()
    res = _run(frames, fps)
    seconds, cpu = time.perf_counter() - start, time.process_time() - cpu
    n = res.valid.sum(axis=1)  # (T,)
    if tracks is not None:
        tracks += [{"start": first, **row} for row in track_rows(frames, res)]
    fig = {"start": first, "frames": float(len(frames)), "seconds": seconds, "cpu_s": cpu}
    for c in range(3):
        fig[f"{c}_hands"] = float((n == c).sum())
    fig["hand_fraction"] = float((n > 0).mean())
    fig["lifted_share"] = float(res.lifted.sum() / max(res.valid.sum(), 1))
    for s in range(2):
        hit = np.flatnonzero(res.valid[:, s])
        fig[f"first_{SIDES[s]}"] = float(hit[0]) if hit.size else float("nan")
    return fig


def landmark_thinness(uv: np.ndarray) -> float:
    """Minor over major spread of landmarks ``uv (21, 2)`` (square root of the ratio of their
    covariance's eigenvalues): about 0.6-0.9 for a hand seen from the palm or back, towards 0
    for landmarks along a line (a hand seen edge-on, a fold the model fits a hand to)."""
    centred = uv - uv.mean(axis=0)  # (21, 2)
    low, high = np.linalg.eigvalsh(centred.T @ centred)
    return float(np.sqrt(max(low, 0.0) / high)) if high > 0 else 0.0


def track_rows(
    frames: np.ndarray, res: MediaPipeResult, params: MediaPipeParams | None = None
) -> list[dict[str, float]]:
    """Per track of ``res.raw`` (the detections the side step links, ``frames (T, H, W, 3)``
    those of the clip) the cues listed in the module docstring (``--tracks``): ``first``,
    ``last``, ``frames``, ``side`` (-1 none, 2 both), ``size_px``, ``size_ratio`` (median of
    its size over the other detection's in frames with one; NaN without), ``step`` (median
    centre move per frame in hand sizes), ``height`` (median centre height over the image's,
    0 top), ``thinness`` (:func:`landmark_thinness`), ``handedness`` (median of
    ``|2 P(right) - 1|``), ``presence`` and ``not_tracked``."""
    params = params or MediaPipeParams()
    raw = res.raw
    presence = landmark_presence(frames, raw, params)  # (T, K)
    side = assign_sides(raw, frames.shape[2], params)  # (T, K)
    centre, size = hand_centres(raw.uv), hand_size(raw.uv)  # (T, K, 2), (T, K)
    tracked = raw.tracked if raw.tracked is not None else np.zeros_like(raw.present)
    rows = []
    for track in _tracks(raw, params):
        f, k = np.array(track).T  # (N,), (N,)
        ratios = [  # this track's size over the other detection's, frame by frame
            size[g, j] / size[g, o]
            for g, j in zip(f, k, strict=True)
            for o in np.flatnonzero(raw.present[g])
            if o != j
        ]
        steps = np.linalg.norm(np.diff(centre[f, k], axis=0), axis=1) / size[f[1:], k[1:]]
        sides = set(side[f, k].tolist())
        rows.append(
            {
                "first": float(f[0]),
                "last": float(f[-1]),
                "frames": float(len(f)),
                "side": float(sides.pop()) if len(sides) == 1 else 2.0,
                "size_px": float(np.median(size[f, k])),
                "size_ratio": float(np.median(ratios)) if ratios else float("nan"),
                "step": float(np.median(steps)) if steps.size else float("nan"),
                "height": float(np.median(centre[f, k, 1])) / frames.shape[1],
                "thinness": float(np.median([landmark_thinness(raw.uv[g, j]) for g, j in track])),
                "handedness": float(np.median(np.abs(2.0 * raw.label_right[f, k] - 1.0))),
                "presence": float(np.nanmedian(presence[f, k])),
                "not_tracked": float((~tracked[f, k]).sum()),
            }
        )
    return rows


def missed_presence(clip, valid: np.ndarray, model) -> list[float]:
    """The landmark model's hand-presence score on the ROI of each true hand the backend missed
    (``valid (T, 2)`` False where the world's hand is in view: at least 11 joints inside the
    image, as :func:`~egosim.stages.hands.metrics.hand_accuracy` counts it). A high score means a
    search could find the hand there; a low one that the model does not see it even there."""
    from egosim.stages.common.roi_landmarks import TrackParams, roi_from_landmarks

    _, truth_uv, in_view = true_hands_in_view(
        clip.hand_joints.astype(np.float64),
        clip.hand_valid,
        clip.world_from_cam,
        clip.intrinsics,
        (clip.width, clip.height),
    )  # the hands hand_accuracy counts as in view
    out = []
    for f, s in zip(*np.nonzero(in_view & ~valid), strict=True):
        roi = roi_from_landmarks(truth_uv[f, s])
        out.append(model.run(clip.frames[f], roi, TrackParams().max_gain).presence)
    return out


def synthetic_figures(
    seeds: list[int],
    variant: str = "default",
    per_joint: dict | None = None,
    misses: list | None = None,
) -> dict[str, dict[str, float]]:
    """Accuracy against the synthetic world's true joints, palm-PnP (the default, and with IPPE's
    palm poses unrefined) vs translation-only lift, on the world ``variant`` ("default": the one the
    backend was tuned on; "alt": held out). Given a ``per_joint`` dict, each lift's ``(21, 2)``
    per-joint table (mm, px) is put in it
    (:meth:`~egosim.stages.hands.metrics.HandAccuracy.per_joint`); given a ``misses`` list, the
    landmark model's presence on each missed true hand (:func:`missed_presence`) is added to it."""
    from egosim.world.clip import render_clip
    from egosim.world.config import WorldConfig

    lifts = {
        "palm_pnp": {"lift": "palm_pnp"},
        "palm_pnp_ippe": {"lift": "palm_pnp", "refine_palm": False},
        "translation": {"lift": "translation"},
    }  # bench row -> MediaPipeParams fields
    parts: dict[str, list] = {name: [] for name in lifts}
    drawn_parts: list = []  # palm_pnp, 2D of the joints themselves (what masks and skeletons draw)
    seconds = []
    for seed in seeds:
        mode = "tabletop" if seed % 2 else "wild"
        clip = render_clip(WorldConfig(seed=seed, mode=mode, variant=variant))
        params = MediaPipeParams()
        start = time.perf_counter()
        raw = detect_landmarks(clip.frames, params)
        seconds.append(time.perf_counter() - start)
        truth_valid = (
            clip.hand_valid if clip.hand_valid is not None else np.ones((clip.num_frames, 2), bool)
        )
        for lift in parts:
            p = replace(params, **lifts[lift])
            res = hands_from_raw(
                raw, clip.width, clip.intrinsics, None, None, p, fps=clip.fps, frames=clip.frames
            )
            if misses is not None and lift == "palm_pnp":
                from egosim.stages.common.roi_landmarks import LandmarkModel

                misses += missed_presence(clip, res.valid, LandmarkModel(params.model_complexity))
            # 2D of the landmarks, and (palm_pnp) of the joints' own projection, which the
            # repair moves off the landmarks where it interpolates a palm
            drawn = project_points(res.joints, clip.intrinsics)[0]  # (T, 2, 21, 2)
            pairs = [(parts[lift], res.landmarks.uv)]
            pairs += [(drawn_parts, drawn)] if lift == "palm_pnp" else []
            for into, uv in pairs:
                into.append(
                    hand_accuracy(
                        res.joints,
                        uv,
                        res.valid,
                        clip.hand_joints,
                        truth_valid,
                        clip.world_from_cam,
                        clip.intrinsics,
                        (clip.width, clip.height),
                        lifted=res.lifted,
                    )
                )
    out = {lift: combine(p).summary() for lift, p in parts.items()}
    out["palm_pnp"]["drawn_2d_px"] = combine(drawn_parts).summary()["error_2d_px"]
    if per_joint is not None:
        per_joint.update({lift: combine(p).per_joint() for lift, p in parts.items()})
    for figures in out.values():
        figures["detect_seconds_per_clip"] = float(np.mean(seconds))
    return out


# InterHand joint order per hand: thumb tip..base, index, middle, ring, pinky (tip first), wrist.
INTERHAND_TO_MANO = [20, 3, 2, 1, 0, 7, 6, 5, 4, 11, 10, 9, 8, 15, 14, 13, 12, 19, 18, 17, 16]
MIN_INSIDE_JOINTS = 15  # a true hand with fewer joints inside the image is not measured
MIN_PRESENCE = 0.5  # the landmark model's answer on a hand's ROI counts from this presence on


def interhand_depth_figures(folder: Path) -> list[dict[str, float]]:
    """Per real InterHand hand: true median joint depth, each lift's depth / truth, and the
    palm-PnP lift's wrist-relative MPJPE (mm) and orientation error (degrees) once placed at the
    true median depth (``scale_to_depth``), with the palm poses refined (``palm_pnp``, the
    default) and IPPE's as they are (``palm_pnp_ippe``, ``MediaPipeParams.refine_palm`` off); NaN
    where the palm PnP fails. ``proximal_ratio``: the median over the four proximal phalanges of
    MediaPipe's bone length (:func:`~egosim.stages.common.hand_lift.bone_lengths`, at the template
    palm's size) over the true one (the lift divides them by
    :data:`~egosim.stages.common.hand_lift.MEDIAPIPE_PROXIMAL_RATIO`)."""
    import json

    import cv2

    from egosim.stages.common.hand_landmarks import place_in_camera
    from egosim.stages.common.hand_lift import (
        PROXIMAL_PHALANGES,
        bone_lengths,
        palm_pnp_pose,
        scale_to_depth,
    )
    from egosim.stages.common.roi_landmarks import LandmarkModel, roi_from_landmarks
    from egosim.stages.hands.metrics import orientation_error_deg, wrist_relative_mpjpe_mm

    cams = json.loads((folder / "test_interhand2.6m_camera.json").read_text())
    joints3d = json.loads((folder / "test_interhand2.6m_joint_3d.json").read_text())
    data = json.loads((folder / "test_interhand2.6m_data.json").read_text())
    model = LandmarkModel(1)
    out = []
    for image in data["images"]:
        cam, cid = cams[str(image["capture"])], image["camera"]
        rot, pos = np.array(cam["camrot"][cid]), np.array(cam["campos"][cid])
        k = np.array([*cam["focal"][cid], *cam["princpt"][cid]])
        world = joints3d[str(image["capture"])][str(image["frame_idx"])]["world_coord"]
        cam_pts = (np.array(world) - pos) @ rot.T / 1000.0  # (42, 3) camera metres
        rgb = np.ascontiguousarray(cv2.imread(str(folder / image["file_name"]))[:, :, ::-1])
        h, w = rgb.shape[:2]
        for which, hand in enumerate((cam_pts[:21], cam_pts[21:])):
            hand = hand[INTERHAND_TO_MANO]  # (21, 3) right hand first
            uv = project_points(hand, k)[0]  # (21, 2)
            inside = (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
            if inside.sum() < MIN_INSIDE_JOINTS:
                continue
            found = model.run(rgb, roi_from_landmarks(uv))
            if found.presence < MIN_PRESENCE:
                continue
            truth = float(np.median(hand[:, 2]))
            moved = float(np.median(place_in_camera(found.uv, found.world, k)[:, 2])) / truth
            fig = {"true_depth_m": truth, "translation": moved}
            prox = list(PROXIMAL_PHALANGES)  # both hands' bones at the template palm's size:
            # MediaPipe's proximal phalanges relative to its palm, against the true hand's
            ratio = bone_lengths(found.world)[prox] / bone_lengths(hand)[prox]  # (4,)
            fig["proximal_ratio"] = float(np.median(ratio))
            fig["proximal_ratios"] = [round(float(r), 3) for r in ratio]  # index..pinky
            for name, refine in (("palm_pnp", True), ("palm_pnp_ippe", False)):
                pose = palm_pnp_pose(found.uv, found.world, k, which == 0, False, refine)
                depth = mpjpe = turn = float("nan")
                if pose is not None:
                    depth = float(np.median(pose[0][:, 2])) / truth
                    placed = scale_to_depth(pose[0], truth)  # (21, 3) at the true median depth
                    mpjpe = wrist_relative_mpjpe_mm(placed, hand)
                    turn = orientation_error_deg(placed, hand)
                fig[name] = depth
                fig[f"{name}_mpjpe_mm"], fig[f"{name}_orientation_deg"] = mpjpe, turn
            out.append(fig)
    return out


def _line(name: str, figures: dict) -> str:
    def value(v) -> str:
        return str(v) if isinstance(v, list) else f"{v:.3g}"  # InterHand's per-finger ratios

    return f"{name:28s} " + "  ".join(f"{k}={value(v)}" for k, v in figures.items())


def main(argv: list[str] | None = None) -> None:
    """Print the figures described in the module docstring."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA, help="the shared data folder")
    ap.add_argument("--seeds", type=int, nargs="*", default=[11, 13], help="synthetic seeds")
    ap.add_argument(
        "--variants", nargs="*", default=["default", "alt"], help="synthetic world variants"
    )
    ap.add_argument("--skip-synthetic", action="store_true", help="real videos only")
    ap.add_argument("--skip-real", action="store_true", help="synthetic world only")
    ap.add_argument(
        "--per-joint", action="store_true", help="synthetic: per-joint error table (palm PnP)"
    )
    ap.add_argument(
        "--tracks", action="store_true", help="real: each track's cues for false-hand filters"
    )
    ap.add_argument(
        "--misses",
        action="store_true",
        help="synthetic: the landmark model's presence on the true ROI of each missed hand",
    )
    ap.add_argument(
        "--perturb",
        nargs="*",
        choices=sorted(PERTURBATIONS),
        help="only the DWM clips, each perturbed (all perturbations when none is named)",
    )
    args = ap.parse_args(argv)
    if args.perturb is not None:
        perturbed(args.data, args.perturb or list(PERTURBATIONS))
        return
    if not args.skip_real:
        real(args.data, args.tracks)
        interhand = args.data / "interhand_fixture"
        if not (interhand / "test_interhand2.6m_camera.json").is_file():
            print(f"InterHand: no fixture in {interhand}, skipped")  # e.g. a kept-aside folder
            figures = []
        else:
            print("InterHand real hands, lifted depth / true depth (landmarks on the true ROI)")
            figures = interhand_depth_figures(interhand)
        for i, fig in enumerate(figures):
            print(_line(f"hand {i}", fig))
        for lift in ("palm_pnp", "palm_pnp_ippe", "translation") if figures else ():
            print(f"median {lift}: {np.nanmedian([f[lift] for f in figures]):.3f}")
        for name in ("palm_pnp", "palm_pnp_ippe") if figures else ():
            for key in (f"{name}_mpjpe_mm", f"{name}_orientation_deg"):
                print(f"mean {key}: {np.nanmean([f[key] for f in figures]):.1f}")
    if not args.skip_synthetic:
        for variant in args.variants:
            held = " (held out)" if variant != "default" else ""
            print(f"Synthetic world {variant}{held}, seeds {args.seeds} (odd tabletop, even wild)")
            tables: dict[str, np.ndarray] = {}
            missed: list[float] | None = [] if args.misses else None
            for lift, figures in synthetic_figures(args.seeds, variant, tables, missed).items():
                print(_line(lift, figures))
            if missed is not None:
                score = np.array(missed)
                print(
                    f"  missed hand-frames {score.size}: the landmark model on the true hand's "
                    f"ROI has presence >= 0.5 on {np.mean(score >= 0.5):.2f}, >= 0.2 on "
                    f"{np.mean(score >= 0.2):.2f}, median {np.median(score):.3f}"
                    if score.size
                    else "  missed hand-frames 0"
                )
            if args.per_joint:
                print("  joint     wrist-relative mm   2D px  (palm_pnp, found hand-frames in 3D)")
                for name, (mm, px) in zip(JOINT_NAMES, tables["palm_pnp"], strict=True):
                    print(f"  {name:8s} {mm:12.1f} {px:13.1f}")


PERTURB_KEYS = (
    "left_shown",
    "right_shown",
    "left_recall",
    "right_recall",
    "left_recall_on_hand",
    "right_recall_on_hand",
    "left_false_pos_frames",
    "right_false_pos_frames",
    "left_coverage_3d",
    "right_coverage_3d",
    "side_agreement",
    "centroid_px",
)  # the figures of dwm_figures the perturbation table shows (coverage_3d: what withheld 3D costs)


def truth_clips(data: Path) -> list[tuple[Path, Path]]:
    """``(video, hand render)`` of every DWM dynamic clip under ``data`` that has its hand
    renders (:func:`~bench.real_clips.dwm_dynamic_clips`, sorted by id); a clip without them
    is named in a printed line and left out (it has no hand truth)."""
    out = []
    for clip in dwm_dynamic_clips(data):
        if clip.hands:
            out.append((data / clip.video, data / clip.hands))
        else:
            print(f"DWM clip {clip.clip_id} has no hand renders (videos_hands): not measured")
    return out


def perturbed(data: Path, names: list[str]) -> None:
    """Print the DWM dynamic clips' figures (:func:`dwm_figures`) unperturbed and under each
    perturbation of ``names`` (:data:`PERTURBATIONS`), as the file holds them and as ingested."""
    print("DWM dynamic clips perturbed (against the same hand renders):")
    for name in names:
        print(f"  {name}: {PERTURBATIONS[name]}")
    for video, render in truth_clips(data):
        for name in (None, *names):
            for ingested in (False, True):
                fig = dwm_figures(video, render, ingested, perturb=name)
                label = f"{video.stem} {name or 'none'}{' ingested' if ingested else ''}"
                print(_line(label, {k: fig[k] for k in PERTURB_KEYS}), flush=True)


def real(data: Path, tracks: bool = False) -> None:
    """Print the real-video tables (DWM dynamic clips, fixed-camera and EgoDex windows); with
    ``tracks``, each clip's :func:`track_rows` after its line."""
    print("DWM dynamic clips (ground-truth hand renders; 'false_pos' = far from any render)")
    for video, render in truth_clips(data):
        for ingested in (False, True):
            rows: list | None = [] if tracks else None
            name = f"{video.stem} (as ingested)" if ingested else video.stem
            print(_line(name, dwm_figures(video, render, ingested, rows)))
            for row in rows or []:
                print(_line("  track", row))
    print("Fixed-camera and EgoDex videos (16 fps, 480x832, ingest's windows: NAME@START)")
    for video in [data / v for v in (*dwm_fixed_videos(data), *egodex_videos(data))]:
        rows = [] if tracks else None
        for fig in count_figures(video, rows):
            print(_line(f"{video.stem}@{fig['start']:.0f}", fig))
        for row in rows or []:
            print(_line("  track", row))
    print("Fixed-camera videos as bench.hand_free_real takes them (8 fps, 49 frames, 640 wide)")
    for video in [data / v for v in dwm_fixed_videos(data)]:
        rows = [] if tracks else None
        print(_line(f"{video.stem}@8fps", _counts(fixed_sampled(video), 8.0, 0.0, rows)))
        for row in rows or []:
            print(_line("  track", row))


if __name__ == "__main__":
    main()
