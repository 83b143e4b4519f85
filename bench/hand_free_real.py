"""Hand-free first frames (issue 9): arm masks and first-frame inpainting, measured.

``python -m bench.hand_free_real [--data ../shared/data] [--out runs/hand_free]
[--world tabletop:2,wild:5,alt:tabletop:0,...] [--size 240x416] [--frames 25]
[--skip-real] [--fixed-only] [--selfie] [--runs runs/real] [--shift 1]`` prints one line per
case, writes ``OUT/hand_free_real.json`` and contact sheets ``OUT/*.png`` (real | mask |
inpainted | truth [| Telea]). About 5 minutes on 2 shared cores; each line gives the seconds
of masks + fill.

Synthetic world (``egosim.world``; ``[variant:]mode:seed``). Tuned on: the default
variant (tabletop seeds 0-3 and tabletop 2 / wild 5 were looked at while the arm search was
built). ``alt`` (another hand/arm model with sleeves and upper arms, cameras and scenes) came
after the method was built; of it, tabletop 0, wild 1, tabletop 3, wild 4 and wild 6 have since
been looked at (``inpaint.occluder_ratio`` was set after seeing tabletop 3's ghost sleeve,
``arm_region.region_probable`` after wild 6's missed sleeves) and tabletop 5's figures were seen
before the last change; alt tabletop 7 and wild 8 are held out.

- ``iou_true``: mean per-frame hand+arm mask IoU against the world's mask, masks from the true
  joints (the ``hand_mask`` stage on the clip); ``iou_mp``: from MediaPipe's 2D landmarks (as
  the ``hands`` stage's ``mediapipe`` backend tracks them, before lifting); ``iou_mp_presence``:
  from the true keypoints kept only where MediaPipe has that side (what its detection alone
  leaves: tuned default world, 7 clips, 0.296 against 0.824 with every true hand and 0.277 with
  MediaPipe's keypoints; the same 0.277 at the world's own 480x832), with ``mp_found`` /
  ``visible`` the hand-frames per side MediaPipe has / the world shows. The pipeline runs the
  world at 480x832 (``--size 480x832``), where MediaPipe finds other hands on some clips:
  held-out alt tabletop 7 / wild 8 MediaPipe IoU 0.709 / 0.325 there against 0.697 / 0.499
  here (design.md, "hand_mask with MediaPipe joints, diagnosed");
- ``breakdown_true``: where the true-joint masks lose, frame 0 and later frames apart (missed
  hand / missed arm pixels, false pixels near the truth / far from it; :func:`mask_breakdown`);
- ``psnr``: frame-0 inpainting (the ``inpaint`` stage's default fill given the predicted masks
  from true joints, the clip's depth and poses) in the true hand+arm region of frame 0, against
  ``first_frame_clean``; ``telea``: OpenCV Telea given the true mask (dilated 2 px).

Real DWM clips (``dwm_realworld/realworld_dynamic``, every clip there:
:func:`bench.real_clips.dwm_dynamic_ids`; no cameras or depth: masks from MediaPipe 2D
landmarks, fill by the image-aligned path). Hand truth: ``videos_hands`` pixels brighter than 30
(rendered hands, no arms; the render misses the hands in some frames). A clip without its
``videos_hands`` twin gets its mask figures as ``n/a``, one without ``videos_static`` its fill
figures.

- ``recall``: the fraction of hand-truth pixels (all frames) inside the mask; ``recall_3px``:
  within 3 px of it. The render is a hand mesh drawn without the scene: it covers fingers hidden
  under a held object (00013 t=17-20, under the cushion) and sits a few px off the real hand in
  places, so part of what ``recall`` misses is not visible hand (00013, hand_mask v11: recall
  0.836, within 3 / 6 / 10 px 0.911 / 0.950 / 0.976; v15, whose hands grow into the pixels of
  their own colour round them: 0.870, within 3 / 6 px 0.938 / 0.967); ``missed_bg_like``: the
  fraction of the missed truth pixels whose colour is more like the background's round it than
  the visible hand's (:func:`background_like_misses`; v16: 00013 78% of 19,435 px, 00017 98%
  of 3,905 px); ``recall_filled``: the fraction inside the region the hand-free frame actually
  replaces, each frame's mask grown as the ``inpaint`` stage grows it before filling
  (:func:`filled_region`: ``InpaintConfig.dilate_px`` plus ``dilate_fraction`` of the image
  diagonal), with what that costs: ``mask_px_mean`` / ``filled_px_mean``, pixels per frame of
  the mask and of the grown region. A per-frame proxy: the stage fills frame 0's region only,
  so each frame is scored as if a clip started there (as the inpainting figures below are);
- ``far_px``: mask pixels per frame farther than 50 px from the allowed region: hand truth plus,
  for each hand blob, the cone from it down to the bottom border within 45 degrees of vertical
  (where an egocentric arm comes from; see :func:`allowed_region`), dilated by 50 px; taken on
  the frames whose hand truth shows a hand. Both of 00013's far patches with hand_mask v11 are
  real arm or hand: t=8's (3,785 px) is the left hand and forearm, which the render leaves out
  of that frame, and t=19's (395 px) the right sleeve at the bottom-right corner, flatter than
  the 45-degree cone;
- ``shift_iou_mean`` / ``shift_iou_min``: per-frame mask IoU between the masks from the
  keypoints as found and from the same keypoints moved by ``--shift`` px (default 1) in x and
  y (:func:`shift_stability`): how much the masks flicker with a change no real hand makes
  (hand_mask v23 on 00013: mean 0.853, min 0.285 at t=31, its dark sleeve on and off; v24:
  0.877 / 0.716, over t=8-35 with the keypoints of 37f660e's day);
- frame 0 of both clips shows no hand, so the inpainting is measured on the sub-clip that starts
  at the first frame with a visible hand (``start``; what a clip cut there would get as its
  frame 0): ``psnr_hand`` in the hand truth dilated by 15 px and ``psnr_frame`` over the frame,
  against ``videos_static`` at that frame, beside ``telea_*``: OpenCV Telea with the same mask.
  ``videos_static`` is itself a re-rendering (blurred), offset from the real frames by its
  principal point: it is first registered by the shift that moves static frame 0 onto real
  frame 0 (``bench.real_video.truth_shift``, as the scene figures
  do; before this the fill was judged against a truth 6-8 px off, which favours a blurry fill),
  and pixels the shift brings in from outside the image are left out.

Real runs of the dataset workflow (``--runs RUNS``: the folders ``bench.real_video --out RUNS``
wrote; the figures come from its ``hand_mask`` and ``inpaint`` shards, masks from the ``hands``
stage's joints), see :func:`run_case`: per clip the hand-mask pixels in frames 0-4 and on average,
and how much of frame 0 the fill changed (pixels off by more than ``CHANGED_LEVELS`` and PSNR of
the hand-free frame 0 against frame 0 itself; where frame 0 shows no hand, as on pour_coke, any
change is a false mask's ghost, which the static-camera scene video repeats in every frame).

Real fixed-camera videos (every ``dwm_realworld/realworld_fixed/*.mp4``, no truth): the
static-camera path of the default ``inpaint`` backend (temporal median), see
:func:`fixed_case`. ``--selfie`` scores MediaPipe's selfie-segmentation model alone as a
hand+arm cue (see :func:`selfie_cases`).
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import time
from pathlib import Path
from typing import Any, NamedTuple

import cv2
import numpy as np

from bench import real_clips
from bench.real_video import (
    DEFAULT_DATA,
    HAND_DILATE_PX,
    HAND_RENDER_THRESHOLD,
    ROOT,
    _psnr,
    _shift,
    truth_shift,
)
from egosim.pipeline import media
from egosim.stages.hand_mask.capsules import CapsuleParams, draw_hands
from egosim.stages.hand_mask.stage import (
    HandMaskConfig,
    HandMaskStage,
    masks_from_keypoints,
    project_keypoints,
)
from egosim.stages.inpaint.reproject_fill import dilate, opencv_fill
from egosim.stages.inpaint.stage import InpaintConfig, InpaintStage
from egosim.world import WorldConfig, render_clip

DWM = real_clips.DWM_DYNAMIC  # the DWM dynamic clips' folder (found by bench.real_clips)
FAR_PX = 50  # mask farther than this from a hand or its arm corridor is a false positive
MIN_HAND_FRACTION = 0.003  # a frame "shows a hand" when this fraction of it is hand truth
CHANGED_LEVELS = 20  # a frame-0 pixel the fill moved by more than this (any channel) is changed


def iou(a: np.ndarray, b: np.ndarray) -> float:
    """Intersection over union of boolean masks (1.0 when both are empty)."""
    union = np.logical_or(a, b).sum()
    return 1.0 if union == 0 else float(np.logical_and(a, b).sum() / union)


def mediapipe_keypoints(frames: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """MediaPipe 2D landmarks ``(T, 2, 21, 2)`` pixels and presence ``(T, 2)`` of ``frames``.

    As the ``hands`` stage's ``mediapipe`` backend makes them before lifting: full frame and
    zoomed tiles, duplicates dropped, sides assigned, short gaps bridged, jitter smoothed.
    """
    from egosim.stages.hands.mediapipe_backend import (
        MediaPipeParams,
        detect_landmarks,
        drop_overlapping,
        side_landmarks,
    )

    # Tracking through misses needs a TFLite runtime that may not be installed: off without it.
    params = MediaPipeParams(track_misses=importlib.util.find_spec("ai_edge_litert") is not None)
    raw = drop_overlapping(detect_landmarks(frames, params), params.duplicate_distance)
    sides = side_landmarks(raw, frames.shape[2], params)
    return sides.uv, sides.present


def contact_sheet(path: Path, panels: list[np.ndarray], height: int = 240) -> None:
    """One row of RGB or mask ``panels`` scaled to ``height``, written as PNG."""
    row = []
    for p in panels:
        img = np.repeat(p[..., None] * 255, 3, axis=2).astype(np.uint8) if p.ndim == 2 else p
        scale = height / img.shape[0]
        row.append(cv2.resize(img, (round(img.shape[1] * scale), height)))
    cv2.imwrite(str(path), cv2.cvtColor(np.concatenate(row, axis=1), cv2.COLOR_RGB2BGR))


def world_case(
    variant: str, mode: str, seed: int, size: tuple[int, int], frames: int, out: Path
) -> dict:
    """Figures of one synthetic clip (see the module docstring)."""
    extra = {} if variant == "default" else {"variant": variant}
    clip = render_clip(WorldConfig(seed=seed, mode=mode, height=size[0], width=size[1],
                                   num_frames=frames, **extra))  # fmt: skip
    truth = clip.hand_mask > 0  # (T, H, W)
    start = time.perf_counter()
    masks = HandMaskStage().masks_for_clip(clip)  # (T, H, W)
    mask_s = time.perf_counter() - start
    uv, present = mediapipe_keypoints(clip.frames)
    mp_masks = masks_from_keypoints(clip.frames, uv, present, HandMaskConfig())
    kp = project_keypoints(clip)  # (T, 2, 21, 2)
    valid = np.ones(kp.shape[:2], bool) if clip.hand_valid is None else clip.hand_valid
    # True keypoints only where MediaPipe has that side: what detection alone leaves.
    det_masks = masks_from_keypoints(clip.frames, kp, valid & present, HandMaskConfig())
    start = time.perf_counter()
    result = InpaintStage().fill(
        clip.frames, masks, clip.world_from_cam, clip.intrinsics, clip.depth[0]
    )
    fill_s = time.perf_counter() - start
    telea = opencv_fill(clip.frames[0], dilate(clip.hand_mask[0], 2))
    region = truth[0]
    contact_sheet(
        out / f"world_{variant}_{mode}_{seed}.png",
        [clip.frames[0], masks[0], result.image, clip.first_frame_clean, telea],
    )
    return {
        "case": f"{variant}:{mode}:{seed}",
        "iou_true": float(np.mean([iou(m > 0, g) for m, g in zip(masks, truth, strict=True)])),
        "iou_mp": float(np.mean([iou(m > 0, g) for m, g in zip(mp_masks, truth, strict=True)])),
        "iou_mp_presence": float(
            np.mean([iou(m > 0, g) for m, g in zip(det_masks, truth, strict=True)])
        ),
        "mp_found": present.sum(axis=0).tolist(),
        "visible": valid.sum(axis=0).tolist(),
        "iou_true_f0": iou(masks[0] > 0, truth[0]),
        "breakdown_true": mask_breakdown(masks, truth, clip),
        "psnr": _psnr(result.image, clip.first_frame_clean, region),
        "telea": _psnr(telea, clip.first_frame_clean, region),
        "mask_s": mask_s,
        "fill_s": fill_s,
    }


def mask_breakdown(masks: np.ndarray, truth: np.ndarray, clip: Any) -> dict[str, dict[str, int]]:
    """Where ``masks (T, H, W)`` lose against ``truth (T, H, W)``, frame 0 and later frames apart.

    Pixels: ``fn_hand`` (missed, within 3 px of the hand drawn round the clip's true keypoints
    without a forearm), ``fn_arm`` (missed elsewhere: arm and sleeve), ``fp_near`` (false,
    within 10 px of the truth: fat edges, a held object), ``fp_far`` (false, farther: bands).
    """
    kp = project_keypoints(clip)  # (T, 2, 21, 2)
    valid = np.ones(kp.shape[:2], bool) if clip.hand_valid is None else clip.hand_valid
    h, w = truth.shape[1:]
    out = {}
    for name, frames in (("frame0", [0]), ("later", range(1, len(truth)))):
        sums = dict.fromkeys(("truth", "fn_hand", "fn_arm", "fp_near", "fp_far"), 0)
        for t in frames:
            hand = dilate(draw_hands(kp[t], valid[t], h, w, CapsuleParams(forearm=False))[0], 3)
            m, g = masks[t] > 0, truth[t]
            near = dilate(g.astype(np.uint8), 10) > 0
            sums["truth"] += int(g.sum())
            sums["fn_hand"] += int((~m & g & (hand > 0)).sum())
            sums["fn_arm"] += int((~m & g & (hand == 0)).sum())
            sums["fp_near"] += int((m & ~g & near).sum())
            sums["fp_far"] += int((m & ~g & ~near).sum())
        out[name] = sums
    return out


def allowed_region(hands: np.ndarray) -> np.ndarray:
    """Pixels ``(H, W)`` where a mask may be: hand truth and the arm's cone to the bottom.

    ``videos_hands`` renders hands, not arms, so the arm is allowed where an egocentric arm can
    run: from each hand blob down to the bottom border, within 45 degrees of straight down (the
    convex hull of the blob and the bottom-border segment it sees in that cone); then grown by
    ``FAR_PX``. A band sideways or upwards from a hand (what the old world-z elbow guess drew on
    real clips) falls outside.
    """
    h = hands.shape[0]
    allowed = hands.astype(np.uint8).copy()
    count, comp = cv2.connectedComponents(allowed)
    for k in range(1, count):
        ys, xs = np.nonzero(comp == k)
        if len(ys) < 20:
            continue
        drop = h - 1 - ys.min()  # (the cone widens by one pixel per pixel down)
        base = np.array([[xs.min() - drop, h - 1], [xs.max() + drop, h - 1]])
        hull = cv2.convexHull(np.concatenate([np.stack([xs, ys], 1), base]).astype(np.int32))
        cv2.fillConvexPoly(allowed, hull, 1)
    return dilate(allowed, FAR_PX) > 0


def background_like_misses(
    video: np.ndarray, masks: np.ndarray, hands: np.ndarray, bins: int = 16
) -> int:
    """Hand-truth pixels the ``masks (T, H, W)`` miss whose colour looks like background.

    Per frame of ``video (T, H, W, 3)`` with ``hands (T, H, W)`` truth: a Lab histogram
    (``bins`` per channel) of the truth pixels the mask holds (eroded 1 px: the visible hand)
    against one of the unmasked pixels 5-40 px round the truth (the background there); a missed
    pixel counts when its colour is more likely background than hand (a colour in neither
    histogram does not count). Such misses are mostly
    not visible hand: fingers the render draws under a held object, or a render a few px off the
    real hand (design.md, "hand_mask with MediaPipe joints, diagnosed").
    """
    count = 0
    for frame, mask, truth in zip(video, masks, hands, strict=True):
        miss = truth & ~mask
        if not miss.any():
            continue
        lab = cv2.cvtColor(frame, cv2.COLOR_RGB2LAB).astype(np.int32) * bins // 256  # (H, W, 3)
        codes = (lab[..., 0] * bins + lab[..., 1]) * bins + lab[..., 2]  # (H, W)
        hand = cv2.erode((truth & mask).astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
        ring = (dilate(truth, 40) > 0) & ~(dilate(truth, 5) > 0) & ~mask
        fg = np.bincount(codes[hand], minlength=bins**3) / max(int(hand.sum()), 1)
        bg = np.bincount(codes[ring], minlength=bins**3) / max(int(ring.sum()), 1)
        c = codes[miss]
        count += int((fg[c] < bg[c]).sum())
    return count


def filled_region(masks: np.ndarray, config: InpaintConfig | None = None) -> np.ndarray:
    """The pixels the hand-free frame replaces given ``masks (T, H, W)``: each frame's mask grown
    as the ``inpaint`` stage grows it before filling (:meth:`InpaintConfig.grow_px` of ``config``,
    default :class:`InpaintConfig`'s); ``(T, H, W)`` bool."""
    grow = (InpaintConfig() if config is None else config).grow_px(*masks.shape[1:3])
    return dilate(masks > 0, grow) > 0


class DwmTruth(NamedTuple):
    """One real DWM clip and its truth (a twin the data folder lacks is None)."""

    video: np.ndarray  # (T, H, W, 3) uint8: the real video
    static: np.ndarray | None  # (T, H, W, 3) uint8: videos_static registered onto the real frames
    inside: np.ndarray  # (H, W) bool: pixels the registered static video covers
    hands: np.ndarray | None  # (T, H, W) bool: the videos_hands render's hand pixels
    shift: tuple[float, float]  # (dx, dy) px that registered videos_static


def dwm_truth(cid: str, data: Path) -> DwmTruth:
    """Read DWM clip ``cid`` with its static-scene video (registered) and hand renders.

    A twin missing from the data folder (:func:`bench.real_clips.dwm_dynamic_clips`) comes back
    as None, and the figures that need it are n/a. Twins of another length than the video are
    cut, with the video, to the shortest (said once).
    """
    found = [c for c in real_clips.dwm_dynamic_clips(data) if c.clip_id == cid]
    if not found:
        raise FileNotFoundError(f"no DWM dynamic clip {cid!r} under {data / DWM}")
    clip = found[0]
    video, _ = media.read_video_file(data / clip.video)
    static = media.read_video_file(data / clip.static)[0] if clip.static else None
    hands_video = media.read_video_file(data / clip.hands)[0] if clip.hands else None
    lengths = [len(v) for v in (video, static, hands_video) if v is not None]
    if len(set(lengths)) > 1:
        print(f"dwm {cid}: video and truth twins of {lengths} frames: cut to {min(lengths)}")
        video = video[: min(lengths)]
        static = None if static is None else static[: min(lengths)]
        hands_video = None if hands_video is None else hands_video[: min(lengths)]
    dx, dy = 0.0, 0.0
    inside = np.ones(video.shape[1:3], bool)  # (H, W)
    if static is not None:
        # videos_static is offset from the real frames by its principal point: register it by
        # the shift that moves static frame 0 onto real frame 0 (no hand in either).
        # videos_hands is not offset (at t=10 of both clips its hands sit where the real frame
        # differs from the registered static one with no shift), so it is used as it is.
        dx, dy = truth_shift(video[0], static[0])
        static = np.stack([_shift(f, dx, dy) for f in static])
        inside = _shift(np.full(video.shape[1:3], 255, np.uint8), dx, dy) == 255  # (H, W)
    hands = None if hands_video is None else hands_video.max(axis=3) > HAND_RENDER_THRESHOLD
    return DwmTruth(video, static, inside, hands, (dx, dy))  # hands: (T, H, W)


def _num(value: float | None, spec: str) -> str:
    """``value`` formatted by ``spec``, or ``n/a`` for a figure with no truth (None or NaN)."""
    return "n/a" if value is None or not np.isfinite(value) else format(value, spec)


def shift_stability(
    video: np.ndarray, uv: np.ndarray, present: np.ndarray, masks: np.ndarray, shift_px: float
) -> tuple[float, float, int]:
    """``(mean, min, frame of the min)`` per-frame IoU between ``masks (T, H, W)`` (from the
    keypoints ``uv (T, K, 21, 2)`` as found) and the masks from the same keypoints moved by
    ``shift_px`` in x and y, over the frames where either mask covers at least
    :data:`MIN_HAND_FRACTION` of the image (NaN, NaN, -1 when none does, or ``shift_px`` is 0;
    a few stray pixels in a frame without a hand would score 0). A mask that holds on the image
    does not move much with a 1 px change of its keypoints; DWM 00013's dark sleeve (hand_mask
    v23) switched on and off with one (t=31 10,306 -> 26,671 px)."""
    if shift_px <= 0:
        return float("nan"), float("nan"), -1
    moved = masks_from_keypoints(video, uv + shift_px, present, HandMaskConfig()) > 0
    least = MIN_HAND_FRACTION * masks[0].size  # pixels
    pairs = [(t, iou(a, b)) for t, (a, b) in enumerate(zip(masks, moved, strict=True))
             if max(a.sum(), b.sum()) >= least]  # fmt: skip
    if not pairs:
        return float("nan"), float("nan"), -1
    worst = min(pairs, key=lambda p: p[1])
    return float(np.mean([p[1] for p in pairs])), float(worst[1]), int(worst[0])


def dwm_case(cid: str, data: Path, out: Path, shift_px: float = 1.0) -> dict:
    """Figures of one real DWM clip (see the module docstring). Without ``videos_hands`` the
    mask figures are NaN (no truth) and the fill is measured from frame 0; without
    ``videos_static`` the fill figures are NaN. ``shift_px``: see :func:`shift_stability`
    (0: not measured)."""
    video, static, inside, hands, (dx, dy) = dwm_truth(cid, data)
    start = time.perf_counter()
    uv, present = mediapipe_keypoints(video)
    masks = masks_from_keypoints(video, uv, present, HandMaskConfig()) > 0  # (T, H, W)
    mask_s = time.perf_counter() - start
    shift_mean, shift_min, shift_frame = shift_stability(video, uv, present, masks, shift_px)
    truth = hands is not None
    if hands is None:
        print(f"dwm {cid}: no videos_hands twin: mask figures n/a", flush=True)
        hands = np.zeros_like(masks)  # no truth: recall NaN, no frame judged
    if static is None:
        print(f"dwm {cid}: no videos_static twin: fill figures n/a", flush=True)
    recall = float(masks[hands].mean()) if hands.any() else float("nan")
    near = dilate(masks.astype(np.uint8), 3) > 0  # (T, H, W)
    recall_3px = float(near[hands].mean()) if hands.any() else float("nan")
    filled = filled_region(masks)  # (T, H, W): what the fill replaces
    recall_filled = float(filled[hands].mean()) if hands.any() else float("nan")
    missed = int((hands & ~masks).sum())
    nan = float("nan")
    miss_bg = background_like_misses(video, masks, hands) / max(missed, 1) if truth else nan
    shown = np.nonzero(hands.reshape(len(hands), -1).mean(axis=1) >= MIN_HAND_FRACTION)[0]
    # videos_hands misses the hands in some frames (its own tracking): those frames have no
    # truth to judge a mask by, so the false-positive figure is taken on the others only.
    far = np.zeros(len(masks))  # (T,)
    for t in shown:
        far[t] = float((masks[t] & ~allowed_region(hands[t])).sum())
    s = int(shown[0]) if len(shown) else 0
    start = time.perf_counter()
    result = InpaintStage().fill(video[s:], masks[s:].astype(np.uint8), None, np.zeros(4), None)
    fill_s = time.perf_counter() - start
    telea = opencv_fill(video[s], result.filled.astype(np.uint8))
    region = (dilate(hands[s], HAND_DILATE_PX) > 0) & inside
    whole = inside
    truth_s = np.zeros_like(video[s]) if static is None else static[s]  # (H, W, 3)
    contact_sheet(
        out / f"dwm_{cid}.png", [video[s], masks[s].astype(np.uint8), result.image, truth_s]
    )
    worst = int(np.argmax(far))
    contact_sheet(
        out / f"dwm_{cid}_worst_far.png",
        [
            video[worst],
            masks[worst].astype(np.uint8),
            allowed_region(hands[worst]).astype(np.uint8),
        ],
    )
    return {
        "case": cid,
        "recall": recall,
        "recall_3px": recall_3px,
        "recall_filled": recall_filled,
        "mask_px_mean": float(masks.sum() / len(masks)),
        "filled_px_mean": float(filled.sum() / len(filled)),
        "missed_px": missed,
        "missed_bg_like": miss_bg,
        "far_px_mean": float(np.mean(far[shown])) if len(shown) else 0.0 if truth else nan,
        "far_px_max": float(np.max(far)) if truth else nan,
        "far_px_frame": worst,
        "frames_judged": len(shown),
        "start": s,
        "psnr_hand": nan if static is None else _psnr(result.image, static[s], region),
        "telea_hand": nan if static is None else _psnr(telea, static[s], region),
        "psnr_frame": nan if static is None else _psnr(result.image, static[s], whole),
        "telea_frame": nan if static is None else _psnr(telea, static[s], whole),
        "truth_shift_px": [dx, dy],
        "shift_iou_mean": shift_mean,
        "shift_iou_min": shift_min,
        "shift_iou_frame": shift_frame,
        "mask_s": mask_s,
        "fill_s": fill_s,
    }


def fixed_case(path: Path, out: Path, fps: float = 8.0, frames: int = 49, width: int = 640) -> dict:
    """Figures of one real fixed-camera video (no truth: what the default fill does with it).

    The video is taken at ``fps`` (nearest frames), ``frames`` long, scaled to ``width``; masks
    from MediaPipe landmarks; frame 0 filled by the ``inpaint`` stage's default backend with no
    depth and no poses, told the camera is static (as ``depth_camera`` would say). Reported:
    frame-0 mask area, the fraction of it filled from other frames (the temporal median) and
    the largest mask area in any frame; the contact sheet shows frame 0, its mask, the fill and
    the frame where the mask is largest.
    """
    video, stamps = media.read_video_file(path)
    pick = [int(np.argmin(np.abs(stamps - k / fps))) for k in range(frames)]
    pick = [i for i in pick if stamps[i] <= stamps[-1]][:frames]
    h = round(video.shape[1] * width / video.shape[2])
    clip = np.stack([cv2.resize(video[i], (width, h), interpolation=cv2.INTER_AREA) for i in pick])
    start = time.perf_counter()
    uv, present = mediapipe_keypoints(clip)
    masks = masks_from_keypoints(clip, uv, present, HandMaskConfig())  # (T, H, W)
    mask_s = time.perf_counter() - start
    start = time.perf_counter()
    result = InpaintStage().fill(clip, masks, None, np.zeros(4), None, static_camera=True)
    fill_s = time.perf_counter() - start
    areas = masks.reshape(len(masks), -1).sum(axis=1)  # (T,)
    big = int(np.argmax(areas))
    contact_sheet(
        out / f"fixed_{path.stem}.png", [clip[0], masks[0], result.image, clip[big], masks[big]]
    )
    filled = max(int(result.filled.sum()), 1)
    return {
        "case": path.stem,
        "mask0_px": int(areas[0]),
        "from_frames": float((result.fill_source == 1).sum() / filled),
        "max_mask_px": int(areas[big]),
        "max_mask_frame": big,
        "mask_s": mask_s,
        "fill_s": fill_s,
    }


def run_case(run: Path, name: str) -> list[dict]:
    """Figures of the clips of one ``bench.real_video`` run folder (see the module docstring)."""
    from bench.real_video import read_step
    from egosim.pipeline.clip_io import clip_from_row

    clips = read_step(run, "ingest")
    masks = read_step(run, "hand_mask", ["clip_id", "hand_mask"])
    fills = read_step(run, "inpaint", ["clip_id", "first_frame"])
    rows = []
    for cid in sorted(set(clips) & set(masks) & set(fills)):
        first = clip_from_row(clips[cid]).frames[0]  # (H, W, 3)
        mask = media.decode_lossless_video(masks[cid]["hand_mask"]) > 0  # (T, H, W)
        filled = media.decode_png(fills[cid]["first_frame"], f"inpaint first_frame of {cid}")
        moved = np.abs(filled.astype(np.int16) - first.astype(np.int16)).max(axis=2)
        areas = mask.reshape(len(mask), -1).sum(axis=1)  # (T,)
        rows.append({
            "case": f"{name}/{cid}",
            "mask_px_0_4": areas[:5].tolist(),
            "mask_px_mean": float(areas.mean()),
            "changed_px": int((moved > CHANGED_LEVELS).sum()),
            "psnr_vs_frame0": _psnr(filled, first, np.ones(first.shape[:2], bool)),
        })  # fmt: skip
    return rows


def selfie_masks(frames: np.ndarray, threshold: float = 0.5) -> np.ndarray:
    """MediaPipe selfie segmentation of ``frames (T, H, W, 3)``: person masks ``(T, H, W)`` bool."""
    import mediapipe as mp

    out = []
    with mp.solutions.selfie_segmentation.SelfieSegmentation(model_selection=0) as seg:
        for frame in frames:
            out.append(seg.process(np.ascontiguousarray(frame)).segmentation_mask > threshold)
    return np.stack(out)


def selfie_cases(worlds: list[tuple[str, str, int]], size: tuple[int, int], frames: int,
                 data: Path) -> list[dict]:  # fmt: skip
    """The selfie-segmentation model (same wheel as MediaPipe Hands) as a hand+arm cue alone:
    IoU on the synthetic clips, recall and far pixels on the DWM clips (as for the masks)."""
    rows = []
    for variant, mode, seed in worlds:
        extra = {} if variant == "default" else {"variant": variant}
        clip = render_clip(WorldConfig(seed=seed, mode=mode, height=size[0], width=size[1],
                                       num_frames=frames, **extra))  # fmt: skip
        masks, truth = selfie_masks(clip.frames), clip.hand_mask > 0
        score = float(np.mean([iou(m, g) for m, g in zip(masks, truth, strict=True)]))
        rows.append({"case": f"{variant}:{mode}:{seed}", "iou": score})
    for dwm in real_clips.dwm_dynamic_clips(data):
        cid = dwm.clip_id
        if not dwm.hands:
            print(f"selfie {cid}: no videos_hands twin, not scored", flush=True)
            continue
        video, _ = media.read_video_file(data / dwm.video)
        hands_video, _ = media.read_video_file(data / dwm.hands)
        hands = hands_video.max(axis=3) > HAND_RENDER_THRESHOLD  # (T, H, W)
        masks = selfie_masks(video)
        shown = np.nonzero(hands.reshape(len(hands), -1).mean(axis=1) >= MIN_HAND_FRACTION)[0]
        far = [float((masks[t] & ~allowed_region(hands[t])).sum()) for t in shown]
        rows.append({"case": cid, "recall": float(masks[hands].mean()),
                     "far_px_mean": float(np.mean(far))})  # fmt: skip
    return rows


def main() -> int:
    """Run the synthetic and (when present) the real cases; print and write the figures."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA, help="the shared data folder")
    parser.add_argument("--out", type=Path, default=ROOT / "runs" / "hand_free", help="output")
    parser.add_argument(
        "--world",
        default="tabletop:2,wild:5,alt:tabletop:0,alt:wild:1,alt:tabletop:3,alt:wild:4,"
        "alt:tabletop:5,alt:wild:6,alt:tabletop:7,alt:wild:8",
        help="[variant:]mode:seed,... (default variant: tuned on; alt: see the module docstring)",
    )
    parser.add_argument("--size", default="240x416", help="synthetic HxW")
    parser.add_argument("--frames", type=int, default=25, help="synthetic frames")
    parser.add_argument("--skip-real", action="store_true", help="synthetic cases only")
    parser.add_argument("--fixed-only", action="store_true", help="the fixed-camera videos only")
    parser.add_argument(
        "--selfie", action="store_true", help="also score MediaPipe selfie segmentation alone"
    )
    parser.add_argument(
        "--runs", type=Path, default=None, help="only read bench.real_video's run folders here"
    )
    parser.add_argument(
        "--shift", type=float, default=1.0,
        help="DWM: also mask with the keypoints moved this many px (stability; 0: off)",
    )  # fmt: skip
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    size = tuple(int(v) for v in args.size.split("x"))
    rows: dict[str, list[dict[str, Any]]] = {"world": [], "dwm": []}
    if args.runs is not None:
        rows = {"runs": []}
        for run in sorted(p for p in args.runs.iterdir() if (p / "hand_mask").is_dir()):
            for r in run_case(run, run.name):
                rows["runs"].append(r)
                print(
                    f"run {r['case']:<32} mask px frames 0-4 {r['mask_px_0_4']} "
                    f"(mean {r['mask_px_mean']:.0f}) | frame 0 changed by the fill: "
                    f"{r['changed_px']} px, PSNR {r['psnr_vs_frame0']:.2f} dB",
                    flush=True,
                )
        (args.out / "hand_free_runs.json").write_text(json.dumps(rows, indent=1))
        return 0
    if args.fixed_only:
        args.world = ""
    for item in filter(None, args.world.split(",")):
        parts = item.split(":")
        variant, mode, seed = parts if len(parts) == 3 else ["default", *parts]
        rows["world"].append(world_case(variant, mode, int(seed), size, args.frames, args.out))  # type: ignore[arg-type]
        r = rows["world"][-1]
        print(
            f"world {r['case']:<20} IoU true {r['iou_true']:.3f} (f0 {r['iou_true_f0']:.3f}) "
            f"MediaPipe {r['iou_mp']:.3f} (true at its presence {r['iou_mp_presence']:.3f}; "
            f"found L/R {r['mp_found'][0]}/{r['visible'][0]} {r['mp_found'][1]}/{r['visible'][1]}) "
            f"| f0 PSNR {r['psnr']:.2f} dB vs Telea(true mask) "
            f"{r['telea']:.2f} | {r['mask_s']:.1f}+{r['fill_s']:.1f} s",
            flush=True,
        )
        for part, b in r["breakdown_true"].items():
            print(
                f"  {part:<6} truth {b['truth']} px: missed hand {b['fn_hand']} arm "
                f"{b['fn_arm']} | false near {b['fp_near']} far {b['fp_far']}",
                flush=True,
            )
    if not args.skip_real and not args.fixed_only and (args.data / DWM).is_dir():
        for cid in real_clips.dwm_dynamic_ids(args.data):
            r = dwm_case(cid, args.data, args.out, args.shift)
            rows["dwm"].append(r)
            print(
                f"dwm {cid} recall {_num(r['recall'], '.3f')} (3 px {_num(r['recall_3px'], '.3f')}"
                f"; filled {_num(r['recall_filled'], '.3f')} at {r['filled_px_mean']:.0f} "
                f"px/frame against the mask's {r['mask_px_mean']:.0f}; missed "
                f"{r['missed_px']} px, {_num(100 * r['missed_bg_like'], '.0f')}% "
                f"background-coloured) far px/frame {_num(r['far_px_mean'], '.0f')} "
                f"({r['frames_judged']} frames judged) "
                f"(max {_num(r['far_px_max'], '.0f')} at t={r['far_px_frame']}) | start "
                f"{r['start']}: hand {_num(r['psnr_hand'], '.2f')} vs Telea "
                f"{_num(r['telea_hand'], '.2f')} dB, frame {_num(r['psnr_frame'], '.2f')} vs "
                f"{_num(r['telea_frame'], '.2f')} | {args.shift:g} px shift: mask IoU mean "
                f"{_num(r['shift_iou_mean'], '.3f')} min {_num(r['shift_iou_min'], '.3f')} at "
                f"t={r['shift_iou_frame']} | {r['mask_s']:.1f}+{r['fill_s']:.1f} s",
                flush=True,
            )
    fixed = args.data / "dwm_realworld" / "realworld_fixed"
    rows["fixed"] = []
    if not args.skip_real and fixed.is_dir():
        for path in (args.data / v for v in real_clips.dwm_fixed_videos(args.data)):
            r = fixed_case(path, args.out)
            rows["fixed"].append(r)
            print(
                f"fixed {r['case']:<14} frame-0 mask {r['mask0_px']} px, "
                f"{100 * r['from_frames']:.1f}% filled from other frames | largest mask "
                f"{r['max_mask_px']} px at t={r['max_mask_frame']} | "
                f"{r['mask_s']:.1f}+{r['fill_s']:.1f} s",
                flush=True,
            )
    if args.selfie:
        worlds = []
        for item in filter(None, args.world.split(",")):
            parts = item.split(":")
            variant, mode, seed = parts if len(parts) == 3 else ["default", *parts]
            worlds.append((variant, mode, int(seed)))
        rows["selfie"] = selfie_cases(worlds, size, args.frames, args.data)
        for r in rows["selfie"]:
            print(f"selfie {r['case']:<22} " + " ".join(
                f"{k} {v:.3f}" for k, v in r.items() if k != "case"), flush=True)  # fmt: skip
    (args.out / "hand_free_real.json").write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
