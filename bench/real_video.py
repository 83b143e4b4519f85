"""Real development videos through the default dataset workflow: what comes out, and how good.

``python -m bench.real_video [--data ../shared/data] [--out runs/real] [--only NAME]`` (or
``make eval-real``) runs ``workflows/dataset.yaml`` with default settings on every real video in
``../shared/data`` (DWM clips with ``ingest.preset=dwm``), then prints one table and writes
``OUT/real_video.json``. The videos are found by layout (:func:`cases`, :mod:`bench.real_clips`:
every clip file there, not a list of ids), named ``egodex_<stem>``, ``dwm_<id>`` (DWM dynamic
clips), ``<stem>`` (DWM fixed-camera videos) and ``hot3d_rgb``; ``--only TEXT`` runs those whose
name contains TEXT (``--only dwm``: the DWM dynamic clips only). Per video:

- ``clips``: clips ingested and samples packed (the training clips the video gave);
- ``posed``: frames posed by estimation (mapper, PnP tracking or rotation model) / all frames,
  over every window of the video; interpolated frames are not counted;
- ``model``: the camera model each window used (sfm, rotation, static, given);
- ``fov``: horizontal field of view of the estimated focal, beside the nominal one the clip came
  with (the ingest prior: source metadata or the 70 degree guess);
- ``f err``: estimated focal against the true one where it is known (``RealCase.true_focal_px``):
  the DWM Aria clips were undistorted to a linear camera of 1024x1024 px with focal 300 px,
  rotated and centre-cropped to 720x480 without resizing (snuvclab/dwm
  ``data_processing/aria/1_get_images_and_cameras.py``), so f = 300 px, a 100.4 degree
  horizontal FOV, not the 70 degree guess. Nothing in the pipeline reads it;
- ``scale``: metres per reconstruction unit and where it came from;
- ``hand/surf``: hand-to-surface depth ratio at contact: for each hand and frame whose 3D is
  trusted (``hand_lifted``), the median
  over the five fingertips of fingertip depth / depth of the scene cloud under the fingertip
  (cleaned poses, scene cloud rendered into that frame); the contact frames of a hand are the
  quarter of its frames where that ratio is largest (the fingertips closest to the surface behind
  them, i.e. touching it); the figure is the median over contact frames. 1 = hands lie on the
  surfaces they touch. Also against the measured scene points only (point confidence 255: most
  depth under the hands is filled, a guess that moves with the fill). n/a without depth (static
  and rotation-only cameras);
- for DWM clips with a ground-truth static-scene video (``videos_static``): PSNR of the scene
  render against it on the pixels the render marks visible and no hand covers (``videos_hands``
  dilated by 15 px), and the mean distance in px from the render's Canny edges to the truth's,
  each beside the baseline of repeating frame 0 of the real video on the same pixels, averaged
  over t = 0..end. The truth is first registered to the real video: DWM's static render is
  offset from the real frames by a constant 6-8 px (its principal point differs; phase
  correlation of real and truth frame 0 finds (-5.7, -5.1) px on 00013 and (-6.2, -5.7) on
  00017, response 0.8-0.9; the shifted truth matches real frame 0 at 29.7 dB instead of 24.8).
  That shift, measured on frame 0 only (the input, not the render), moves every truth frame;
  pixels it brings in from outside the image are left out. ``videos_hands`` is not offset (its
  best shift onto the real hands is (0, 0) / (0, 2) px) and is used as it is. The JSON keeps the
  unregistered figures too (``*_unregistered``).

The figures are read from the shards the run wrote; nothing here is tuned to these videos.
"""

from __future__ import annotations

import argparse
import itertools
import json
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from bench import real_clips
from egosim.pipeline import media
from egosim.pipeline.geometry import invert_se3, rotation_angle_deg
from egosim.pipeline.shards import open_shard
from egosim.pipeline.workflow import load_workflow

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_DATA = ROOT.parent / "shared" / "data"
WORKFLOW = ROOT / "workflows" / "dataset.yaml"
FINGERTIPS = (4, 8, 12, 16, 20)  # MANO order
HAND_DILATE_PX = 15  # ground-truth hand renders grow by this before leaving pixels out
HAND_RENDER_THRESHOLD = 30  # a videos_hands pixel brighter than this (any channel) is hand
DWM_ARIA_FOCAL_PX = 300.0  # DWM Aria clips (720x480): linear camera focal (module docstring)
DWM_ARIA_WIDTH_PX = 720  # ... at this width; a DWM-layout clip resized from it scales the focal


@dataclass(frozen=True)
class RealCase:
    """One real development video."""

    name: str  # row label
    video: str  # path under the data folder
    preset: str  # ingest preset
    static_truth: str = ""  # ground-truth static-scene video (DWM dynamic clips)
    hands_truth: str = ""  # ground-truth hand renders on black (DWM dynamic clips)
    true_focal_px: float = 0.0  # true focal in pixels of the source video; 0 = unknown
    true_focal_width: int = 0  # the width true_focal_px is stated at: a source of another width
    # (resized, same field of view) scales it; 0 = the source's own width
    crop_x: tuple[float, float] = ()  # keep this span of the width (fractions): one view of a
    # side-by-side recording, written beside the run and ingested instead; () = the whole frame


HOT3D_RGB_X = (427 / 1280, 853 / 1280)  # HOT3D's Aria recording: the RGB view's span of the width


def cases(data: Path) -> tuple[RealCase, ...]:
    """The real videos under ``data``, found by layout (:mod:`bench.real_clips`), sorted in
    each: EgoDex-style clips (``egodex_<stem>``), DWM dynamic clips (``dwm_<id>``, with the
    truth twins that exist: a clip without ``videos_static`` or ``videos_hands`` gets no scene
    figures), DWM fixed-camera videos (``<stem>``), HOT3D recordings (``hot3d_rgb`` for
    ``ego_centric_aria.mp4``, ``hot3d_rgb_<stem>`` for any other)."""
    return (
        *(RealCase(f"egodex_{Path(v).stem}", v, "egosim") for v in real_clips.egodex_videos(data)),
        *(
            RealCase(
                f"dwm_{clip.clip_id}",
                clip.video,
                "dwm",
                clip.static,
                clip.hands,
                DWM_ARIA_FOCAL_PX,
                true_focal_width=DWM_ARIA_WIDTH_PX,
            )
            for clip in real_clips.dwm_dynamic_clips(data)
        ),
        *(RealCase(Path(v).stem, v, "dwm") for v in real_clips.dwm_fixed_videos(data)),
        # HOT3D's Aria recording: the RGB view is the middle third (x 427-853 of 1280), a fisheye
        # image the pipeline treats as a pinhole one; 438 frames at 30 fps, several windows.
        *(
            RealCase(_hot3d_name(Path(v).stem), v, "egosim", crop_x=HOT3D_RGB_X)
            for v in real_clips.hot3d_videos(data)
        ),
    )


def _hot3d_name(stem: str) -> str:
    return "hot3d_rgb" if stem == "ego_centric_aria" else f"hot3d_rgb_{stem}"


def read_step(run: Path, step: str, columns: list[str] | None = None) -> dict[str, dict]:
    """Rows of every shard of ``step`` by clip id ({} when the step wrote nothing)."""
    rows: dict[str, dict] = {}
    for path in sorted((run / step).glob("shard-*.parquet")):
        with open_shard(path) as reader:
            for row in reader.iter_rows(columns=columns):
                rows[row["clip_id"]] = row
    return rows


def source_video(case: RealCase, data: Path, out: Path) -> Path:
    """The video the workflow ingests: the case's file, or its ``crop_x`` view, written once as
    ``OUT/../NAME_source.mp4`` (H.264, the source's mean frame rate)."""
    if not case.crop_x:
        return data / case.video
    path = out.parent / f"{case.name}_source.mp4"
    if not path.is_file():
        frames, times = media.read_video_file(data / case.video)  # (T, H, W, 3), (T,) seconds
        x0, x1 = (round(f * frames.shape[2]) for f in case.crop_x)
        fps = (len(times) - 1) / float(times[-1] - times[0])
        path.parent.mkdir(parents=True, exist_ok=True)
        media.write_video_file(path, np.ascontiguousarray(frames[:, :, x0:x1]), fps)
    return path


def run_case(
    case: RealCase, data: Path, out: Path, workers: int, overrides: Sequence[str] = ()
) -> float:
    """Run the dataset workflow on one video, with ``overrides`` (``step.key=value``, as
    ``egosim run --set``) after the case's preset; returns wall-clock seconds."""
    from egosim.pipeline.runner import run_workflow

    workflow = load_workflow(WORKFLOW, [f"ingest.preset={case.preset}", *overrides])
    source = source_video(case, data, out)
    start = time.perf_counter()
    run_workflow(workflow, out, source=str(source), n_workers=workers)
    return time.perf_counter() - start


def _poses(poses: dict | None, cams: dict) -> np.ndarray:
    """World-from-camera ``(T, 4, 4)``: the cleaned ``poses`` row if present, else the estimate."""
    src = poses if poses is not None else cams
    return np.asarray(src["world_from_cam"], dtype=np.float64).reshape(-1, 4, 4)


def _scene_depth(points: np.ndarray, cam_from_world: np.ndarray, k: np.ndarray, hw: tuple) -> Any:
    """Z-buffer depth ``(H, W)`` of world ``points (N, 3)`` seen from one camera (0 = none)."""
    h, w = hw
    pc = points @ cam_from_world[:3, :3].T + cam_from_world[:3, 3]  # (N, 3)
    pc = pc[pc[:, 2] > 1e-6]
    u = np.floor(k[0] * pc[:, 0] / pc[:, 2] + k[2]).astype(np.int64)
    v = np.floor(k[1] * pc[:, 1] / pc[:, 2] + k[3]).astype(np.int64)
    ok = (u >= 0) & (u < w) & (v >= 0) & (v < h)
    depth = np.full(h * w, np.inf)
    np.minimum.at(depth, v[ok] * w + u[ok], pc[ok, 2])
    depth[~np.isfinite(depth)] = 0.0
    return depth.reshape(h, w)


def _depth_at(depth: np.ndarray, u: float, v: float, radius: int = 4) -> float:
    h, w = depth.shape
    iu, iv = int(u), int(v)
    if not (0 <= iu < w and 0 <= iv < h):
        return float("nan")
    patch = depth[max(0, iv - radius) : iv + radius + 1, max(0, iu - radius) : iu + radius + 1]
    vals = patch[patch > 0]
    return float(np.median(vals)) if len(vals) else float("nan")


def hand_surface_ratio(
    cloud: dict | None,
    hands: dict | None,
    poses: dict | None,
    cams: dict,
    measured_only: bool = False,
) -> float | None:
    """Median fingertip/scene depth ratio over each hand's contact frames (see module doc), from
    one clip's ``scene_cloud``, ``hands``, ``poses`` (None: absent) and ``cameras`` rows;
    ``measured_only``: against the scene points whose depth was measured (point confidence
    255), not the filled ones (under the hands most depth is filled, a guess)."""
    if cloud is None or hands is None or cams.get("depth0") is None:
        return None
    pts = np.frombuffer(cloud["points_xyz"], dtype="<f4").reshape(-1, 3).astype(np.float64)
    if measured_only:
        confidence = np.frombuffer(cloud["point_confidence"], dtype=np.uint8)  # (N,)
        pts = pts[confidence == 255]
    k = np.asarray(cams["intrinsics"], dtype=np.float64)
    hw = (int(cams["height"]), int(cams["width"]))
    cam_from_world = invert_se3(_poses(poses, cams))  # (T, 4, 4)
    joints = np.asarray(hands["hand_joints"], dtype=np.float64).reshape(-1, 2, 21, 3)
    valid = np.asarray(hands["hand_lifted"], dtype=bool)  # (T, 2) a 2D-only hand's depth: a guess
    per_hand: list[list[float]] = [[], []]
    for t in np.flatnonzero(valid.any(axis=1)):
        depth = _scene_depth(pts, cam_from_world[t], k, hw)
        for s in np.flatnonzero(valid[t]):
            tips = joints[t, s, list(FINGERTIPS)]  # (5, 3) world
            tc = tips @ cam_from_world[t, :3, :3].T + cam_from_world[t, :3, 3]  # (5, 3)
            ratios = []
            for x, y, z in tc:
                if z <= 0:
                    continue
                zs = _depth_at(depth, k[0] * x / z + k[2], k[1] * y / z + k[3])
                if np.isfinite(zs):
                    ratios.append(z / zs)
            if ratios:
                per_hand[s].append(float(np.median(ratios)))
    contact: list[float] = []
    for values in per_hand:
        if values:
            top = np.sort(values)[-max(1, len(values) // 4) :]
            contact.extend(top.tolist())
    return float(np.median(contact)) if contact else None


def _video_frames(path: Path) -> np.ndarray:
    frames, _ = media.read_video_file(path)
    return frames


def _fit(
    frames: np.ndarray, indices: np.ndarray, hw: tuple[int, int], source_crop=None
) -> np.ndarray:
    """Source frames at ``indices`` cut as ingest cut the clip: scaled to cover ``hw`` and cropped
    to the clip row's recorded ``source_crop`` (the centre crop when None: rows before clips v5)."""
    from egosim.stages.common.frame_plan import plan_from_crop

    plan = plan_from_crop(frames.shape[2], frames.shape[1], hw[1], hw[0], source_crop)
    return np.stack([plan.apply(frames[min(i, len(frames) - 1)]) for i in indices])


def _psnr(a: np.ndarray, b: np.ndarray, mask: np.ndarray) -> float:
    if mask.sum() == 0:
        return float("nan")
    err = np.mean((a[mask].astype(np.float64) - b[mask].astype(np.float64)) ** 2)
    return float(10 * np.log10(255.0**2 / max(err, 1e-10)))


def _edge_distance(a: np.ndarray, b: np.ndarray, mask: np.ndarray) -> float:
    """Mean distance (px) from ``a``'s Canny edges inside ``mask`` to the nearest edge of ``b``."""
    ea = cv2.Canny(cv2.cvtColor(a, cv2.COLOR_RGB2GRAY), 50, 150) > 0
    eb = cv2.Canny(cv2.cvtColor(b, cv2.COLOR_RGB2GRAY), 50, 150) > 0
    if not eb.any():
        return float("nan")
    dist = cv2.distanceTransform((~eb).astype(np.uint8), cv2.DIST_L2, 5)
    sel = ea & mask
    return float(dist[sel].mean()) if sel.any() else float("nan")


def truth_shift(real0: np.ndarray, truth0: np.ndarray) -> tuple[float, float]:
    """``(dx, dy)`` px that moves ``truth0 (H, W, 3)`` onto ``real0`` (phase correlation).

    The two differ by a constant image translation when their principal points differ; shifting
    the truth by ``(dx, dy)`` (content moves right/down for positive values) registers it.
    """
    h, w = real0.shape[:2]
    grey = [cv2.cvtColor(im, cv2.COLOR_RGB2GRAY).astype(np.float32) for im in (truth0, real0)]
    (dx, dy), _ = cv2.phaseCorrelate(grey[0], grey[1], cv2.createHanningWindow((w, h), cv2.CV_32F))
    return float(dx), float(dy)


def _shift(image: np.ndarray, dx: float, dy: float) -> np.ndarray:
    """``image`` translated by ``(dx, dy)`` px (bilinear; zeros shifted in)."""
    h, w = image.shape[:2]
    m = np.float32([[1, 0, dx], [0, 1, dy]])
    return cv2.warpAffine(image, m, (w, h), flags=cv2.INTER_LINEAR, borderValue=0)


def scene_vs_truth(
    render: dict | None, clip: dict | None, cid: str, case: RealCase, data: Path
) -> dict[str, float] | None:
    """Scene render vs the ground-truth static video, and the repeat-frame-0 baseline, from one
    clip's ``scene_render`` and ``ingest`` rows (None: absent)."""
    if render is None or clip is None or not (case.static_truth and case.hands_truth):
        return None
    h, w = int(render["height"]), int(render["width"])
    scene = media.decode_rgb_video(render["scene_video"], h, w, f"{cid} scene")
    visible = media.decode_lossless_video(render["visible"], f"{cid} visible") > 0
    real = media.decode_rgb_video(clip["video"], h, w, f"{cid} video")
    indices = clip.get("source_frame_indices")
    if indices is None:  # clips v1: the source rate equals the clip rate
        indices = np.arange(len(scene))
    indices = np.asarray(indices, dtype=np.int64)
    crop = clip.get("source_crop")
    truth = _fit(_video_frames(data / case.static_truth), indices, (h, w), crop)
    hands = _fit(_video_frames(data / case.hands_truth), indices, (h, w), crop)
    kernel = cv2.getStructuringElement(
        cv2.MORPH_ELLIPSE, (2 * HAND_DILATE_PX + 1, 2 * HAND_DILATE_PX + 1)
    )
    dx, dy = truth_shift(real[0], truth[0])
    inside = _shift(np.full((h, w), 255, np.uint8), dx, dy) == 255  # (H, W) no border pulled in
    names = ("psnr", "psnr_base", "edge", "edge_base")
    figures: dict[str, list[float]] = {n + sfx: [] for n in names for sfx in ("", "_unregistered")}
    for t in range(len(scene)):
        # videos_hands is not offset (best shift (0, 0) / (0, 2) px at t = 10): never shifted
        hand = cv2.dilate((hands[t].max(axis=2) > HAND_RENDER_THRESHOLD).astype(np.uint8), kernel)
        for sfx, shift in (("", (dx, dy)), ("_unregistered", (0.0, 0.0))):
            truth_t = _shift(truth[t], *shift) if sfx == "" else truth[t]
            mask = visible[t] & (hand == 0) & (inside if sfx == "" else True)
            figures["psnr" + sfx].append(_psnr(scene[t], truth_t, mask))
            figures["psnr_base" + sfx].append(_psnr(real[0], truth_t, mask))
            figures["edge" + sfx].append(_edge_distance(scene[t], truth_t, mask))
            figures["edge_base" + sfx].append(_edge_distance(real[0], truth_t, mask))
    out = {k: float(np.nanmean(v)) for k, v in figures.items()}
    out["visible_fraction"] = float(visible.mean())
    out["truth_shift_x_px"], out["truth_shift_y_px"] = dx, dy
    return out


def _fov_deg(fx: float, width: int) -> float:
    return float(np.degrees(2 * np.arctan(width / (2 * fx))))


def _clip_scale(case: RealCase, data: Path, clip: dict[str, Any]) -> float:
    """Pixels of the clip per pixel of the source video (ingest's cover-and-crop rule)."""
    from egosim.stages.common.frame_plan import plan_resize

    info = media.probe_video_file(data / case.video)
    return plan_resize(info.width, info.height, int(clip["width"]), int(clip["height"])).scale


def true_focal_clip_px(case: RealCase, data: Path, clip: dict[str, Any]) -> float:
    """The true focal in pixels of the ingested ``clip`` (0 when unknown): the source's, scaled
    from ``true_focal_width`` to the source's width (a resized copy keeps its field of view),
    then by ingest's resize (:func:`_clip_scale`)."""
    if case.true_focal_px <= 0:
        return 0.0
    focal = case.true_focal_px
    if case.true_focal_width > 0:
        focal *= media.probe_video_file(data / case.video).width / case.true_focal_width
    return focal * _clip_scale(case, data, clip)


def window_seams(windows: list[tuple[np.ndarray, np.ndarray]]) -> list[dict[str, float]]:
    """Where consecutive windows of one source meet: ``windows`` is ``[(source_frame_indices (T,),
    world_from_cam (T, 4, 4)), ...]`` in source order. Per seam, the camera's jump from the last
    frame of a window to the first of the next (centre distance, rotation in degrees) beside the
    median frame-to-frame step inside the two windows. Windows sharing one world frame jump
    about one step; windows in frames of their own jump by whatever separates those frames."""
    out = []
    for (ia, pa), (ib, pb) in itertools.pairwise(windows):
        steps = np.concatenate(
            [np.linalg.norm(np.diff(p[:, :3, 3], axis=0), axis=1) for p in (pa, pb)]
        )
        turns = [
            rotation_angle_deg(p[i, :3, :3], p[i + 1, :3, :3])
            for p in (pa, pb)
            for i in range(len(p) - 1)
        ]
        jump = float(np.linalg.norm(pb[0, :3, 3] - pa[-1, :3, 3]))
        out.append(
            {
                "source_gap": int(ib[0] - ia[-1]),
                "jump": jump,
                "jump_over_step": jump / max(float(np.median(steps)), 1e-12),
                "jump_deg": float(rotation_angle_deg(pa[-1, :3, :3], pb[0, :3, :3])),
                "step_deg": float(np.median(turns)),
            }
        )
    return out


def summarise(case: RealCase, run: Path, data: Path, seconds: float) -> dict[str, Any]:
    """The table row of one video from the shards its run wrote."""
    clips = read_step(
        run,
        "ingest",
        ["clip_id", "intrinsics", "width", "height", "num_frames", "fps", "source_frame_indices"],
    )
    cams = read_step(run, "cameras")
    packed = read_step(run, "pack", ["clip_id"])
    # Each step's shards read once for all clips (not once per clip and figure).
    clouds = read_step(run, "scene_cloud")
    hands = read_step(run, "hands", ["clip_id", "hand_joints", "hand_lifted"])
    poses = read_step(run, "poses", ["clip_id", "world_from_cam"])
    renders = read_step(run, "scene_render")
    videos = read_step(run, "ingest") if case.static_truth and case.hands_truth else {}
    rejects: list[str] = []
    rej_path = run / "rejects.parquet"
    if rej_path.is_file():
        with open_shard(rej_path) as reader:
            rejects = [f"{r['step']}: {r['reason']}"[:160] for r in reader.iter_rows()]
    posed = total = 0
    models, fovs, nominal, scales, ratios, scene, focal_err = [], [], [], [], [], [], []
    measured_ratios: list[float] = []
    for cid, cam in cams.items():
        t = int(cam["num_frames"])
        total += t
        posed += int(np.sum(np.asarray(cam["registered"], dtype=bool)))
        models.append(cam.get("camera_model") or ("static" if cam["static_camera"] else "sfm"))
        fovs.append(_fov_deg(cam["intrinsics"][0], int(cam["width"])))
        nominal.append(_fov_deg(clips[cid]["intrinsics"][0], int(clips[cid]["width"])))
        true_f = true_focal_clip_px(case, data, clips[cid])
        if true_f > 0:
            focal_err.append(float(cam["intrinsics"][0]) / true_f - 1.0)
        if cam.get("metric_scale") is not None:
            scales.append(f"{cam['metric_scale']:.3g} ({cam.get('scale_source')})")
        rows = (clouds.get(cid), hands.get(cid), poses.get(cid), cam)
        ratio = hand_surface_ratio(*rows)
        if ratio is not None:
            ratios.append(ratio)
        ratio = hand_surface_ratio(*rows, measured_only=True)
        if ratio is not None:
            measured_ratios.append(ratio)
        fig = scene_vs_truth(renders.get(cid), videos.get(cid), cid, case, data)
        if fig is not None:
            scene.append(fig)
    row: dict[str, Any] = {
        "video": case.name,
        "preset": case.preset,
        "clips_ingested": len(clips),
        "clips_packed": len(packed),
        "frames_posed": posed,
        "frames_total": total,
        "camera_models": sorted(set(models)),
        "fov_deg": fovs,
        "nominal_fov_deg": nominal,
        "focal_error": focal_err,
        "scale": scales,
        "hand_surface_ratio": ratios,
        "hand_surface_ratio_measured": measured_ratios,
        "seconds": seconds,
        "rejects": rejects,
    }
    ordered = list(
        (
            np.asarray(clips[cid]["source_frame_indices"]),
            np.reshape(cam["world_from_cam"], (-1, 4, 4)),
        )
        for cid, cam in cams.items()
        if clips[cid].get("source_frame_indices") is not None
    )
    ordered.sort(key=lambda w: int(w[0][0]))
    row["window_seams"] = window_seams(ordered)
    if scene:
        row["scene_vs_truth"] = {k: float(np.mean([f[k] for f in scene])) for k in scene[0]}
    return row


def print_table(rows: list[dict[str, Any]]) -> None:
    """One line per video, then the rejects."""
    head = (
        f"{'video':<14} {'clips':>7} {'posed':>9} {'model':<14} {'fov est/nom':>12} "
        f"{'f err':>6} {'hand/surf':>9} {'scene dB (base)':>16} {'edge px (base)':>15} {'s':>5}"
    )
    print(head)
    print("-" * len(head))
    for r in rows:
        posed = f"{r['frames_posed']}/{r['frames_total']}"
        fov = (
            f"{np.mean(r['fov_deg']):.0f}/{np.mean(r['nominal_fov_deg']):.0f}"
            if r["fov_deg"]
            else "-"
        )
        ratio = f"{np.median(r['hand_surface_ratio']):.2f}" if r["hand_surface_ratio"] else "n/a"
        ferr = f"{np.mean(r['focal_error']):+.1%}" if r.get("focal_error") else "-"
        sv = r.get("scene_vs_truth")
        db = f"{sv['psnr']:.1f} ({sv['psnr_base']:.1f})" if sv else "-"
        edge = f"{sv['edge']:.1f} ({sv['edge_base']:.1f})" if sv else "-"
        clips = f"{r['clips_ingested']}->{r['clips_packed']}"
        print(
            f"{r['video']:<14} {clips:>7} {posed:>9} {','.join(r['camera_models']):<14} "
            f"{fov:>12} {ferr:>6} {ratio:>9} {db:>16} {edge:>15} {r['seconds']:>5.0f}"
        )
    for r in rows:
        if r["scale"]:
            print(f"{r['video']}: scale {', '.join(r['scale'])}")
        if r.get("window_seams"):
            seams = ", ".join(
                f"{m['jump_over_step']:.1f}x step / {m['jump_deg']:.1f} deg "
                f"(step {m['step_deg']:.1f})"
                for m in r["window_seams"]
            )
            print(f"{r['video']}: camera jump where windows meet: {seams}")
        if r.get("hand_surface_ratio_measured"):
            measured = np.median(r["hand_surface_ratio_measured"])
            print(f"{r['video']}: hand/surf against measured scene points only {measured:.2f}")
        sv = r.get("scene_vs_truth")
        if sv:
            print(
                f"{r['video']}: truth registered by ({sv['truth_shift_x_px']:+.1f}, "
                f"{sv['truth_shift_y_px']:+.1f}) px; unregistered scene dB "
                f"{sv['psnr_unregistered']:.1f} ({sv['psnr_base_unregistered']:.1f}), edge px "
                f"{sv['edge_unregistered']:.1f} ({sv['edge_base_unregistered']:.1f})"
            )
        for reason in r["rejects"][:5]:
            print(f"{r['video']}: rejected at {reason}")


def main() -> int:
    """Run every case (or ``--only``), print the table; exit 1 if a video packed nothing."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA, help="the shared data folder")
    parser.add_argument("--out", type=Path, default=ROOT / "runs" / "real", help="run folders")
    parser.add_argument("--only", default="", help="run the cases whose name contains this")
    parser.add_argument("--workers", type=int, default=2, help="local Dask workers")
    parser.add_argument("--no-run", action="store_true", help="only read existing run folders")
    parser.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="STEP.KEY=VALUE",
        help="a workflow parameter, as egosim run --set (repeat)",
    )
    args = parser.parse_args()
    rows = []
    found = cases(args.data)
    if not found:
        print(f"no real videos found under {args.data}")
    for case in found:
        if args.only and args.only not in case.name:
            continue
        dynamic = case.video.startswith(real_clips.DWM_DYNAMIC)
        if dynamic and not (case.static_truth and case.hands_truth):
            print(f"{case.name}: no videos_static or no videos_hands twin: scene figures n/a")
        run = args.out / case.name
        seconds = 0.0 if args.no_run else run_case(case, args.data, run, args.workers, args.set)
        rows.append(summarise(case, run, args.data, seconds))
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "real_video.json").write_text(json.dumps(rows, indent=1))
    print_table(rows)
    return 0 if rows and all(r["clips_packed"] > 0 for r in rows) else 1


if __name__ == "__main__":
    raise SystemExit(main())
