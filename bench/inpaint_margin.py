"""Frame-0 inpainting against OpenCV Telea, the fill alone (issue 9), several configs at once.

``python -m bench.inpaint_margin [--set default] [--config 'name:key=value,key=value' ...]
[--skip-real] [--runs runs/real_s24b] [--out runs/inpaint_margin]`` prints, per case and config,
the fill's PSNR in the true hand(+arm) region of frame 0 and the margin over Telea;
``OUT/inpaint_margin.json`` holds the figures and ``OUT/<config>_<case>.png`` the sheets
(synthetic: frame 0 | fill | fill given the true mask | truth | Telea; DWM: frame 0 | mask |
fill | truth | Telea).

Masks are computed once and cached in ``OUT/cache`` (the ``hand_mask`` stage's masks from the
true joints on the synthetic world, MediaPipe-landmark masks on the DWM clips, as
``bench.hand_free_real`` makes them), so configs are compared on the same masks. The cache file
names carry the ``hand_mask`` stage's version (``_hm<version>``), and the DWM ones the ``hands``
stage's too (``_hands<version>``: their keypoints come from its MediaPipe backend): a new mask
or keypoint version is computed afresh rather than read from another version's cache (figures
of earlier sessions came from stale masks this way); a change of the mask code without a
version bump does not move the fill figures (delete the cache to refresh it).

Synthetic world (``[variant:]mode:seed``): ``tuned`` = default-variant cases (the fill is tuned
on these); ``held`` = ``alt`` tabletop 7 / wild 8 (held out by ``bench.hand_free_real``), alt
tabletop 3 (the issue's worst case) and alt seeds 9-12 nobody had looked at. Per case:

- ``pred``: the ``inpaint`` stage's fill given the predicted masks; ``true``: given the true mask
  (the world's hand mask, as the stage's own dilation grows it); ``telea``: OpenCV Telea given
  the true mask dilated 2 px. All in the true hand+arm region of frame 0 against
  ``first_frame_clean``.

Real DWM clips (``dwm_realworld/realworld_dynamic``, every clip with both truth twins found
there by :func:`bench.real_clips.dwm_dynamic_clips`): as ``bench.hand_free_real``'s ``dwm_case``:
the sub-clip from the first frame with a visible hand, image-aligned fill, ``videos_static``
registered to the real frames, PSNR in the hand truth dilated 15 px, Telea with the same mask.
``--aligned`` runs the synthetic cases without depth and poses too (the fill DWM gets: later
frames aligned by homographies), so that path has cases to tune on that are not the real ones.
``--sweep`` gives the synthetic depth fill the depth the workflow would make instead of the
world's (:func:`sweep_depth`: the ``depth_camera`` plane sweep and its confidence, true poses,
no hand exclusion), and ``--pose-noise D`` poses whose rotation error random-walks ``D``
degrees a frame (:func:`drifted_poses`): cases with estimated-looking cameras to tune on.

The real dataset workflow (``bench.real_video``: ``workflows/dataset.yaml``, preset ``dwm``) gives
the DWM clips cameras from SfM and a plane-sweep depth, so what it ships on them is the **depth**
fill, not the image-aligned one. ``--runs RUNS`` (default ``runs/real_s24b``, a finished
``bench.real_video --out RUNS``) adds those rows, read from each clip's run ``RUNS/dwm_<id>``:

- ``dwm-depth:<id>``: the same sub-clip, masks and Telea as the aligned row, filled by the depth
  path with the run's cameras: intrinsics from its ``cameras`` step, poses from its ``poses``
  step (pose_clean, as the workflow's ``inpaint`` reads them), and the sub-clip's frame-0 depth
  made by the run's ``depth_camera`` code and parameters (:func:`window_depth` on the sub-clip,
  with the cameras step's poses; no hand exclusion, as that step had no masks; depth range and
  sources from the run's frame-0 depth lifted to the world). The run's own depth is frame 0's, where
  neither clip shows a hand, so the sub-clip's first frame needs its own;
- ``dwm-run:<id>``: the same, with the masks of the run's ``hand_mask`` step (from its
  ``hands`` stage's joints: the masks the workflow ships) instead of the bench's.

``--starts N`` also scores up to ``N - 1`` later sub-clips of each DWM clip (rows
``<case>@<start>``, printed as the groups ``dwm@``, ``dwm-depth@``, ``dwm-run@``): each starts
at a later frame with a visible hand that leaves 12 frames to fill from (:func:`start_frames`),
against ``videos_static`` at that frame. The two clips hold few cases; later starts give other
holes and other frames after them. A start where the hands have moved the scene round the hole
(:func:`scene_level`: ``videos_static`` is the scene before they touched it) is not scored, and
the depth rows of a start are left out when the plane sweep finds too little parallax after it.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
import zlib
from pathlib import Path

import cv2
import numpy as np
import yaml

from bench import real_clips
from bench.hand_free_real import (
    DWM,
    MIN_HAND_FRACTION,
    contact_sheet,
    dwm_truth,
    mediapipe_keypoints,
)
from bench.real_video import (
    DEFAULT_DATA,
    HAND_DILATE_PX,
    ROOT,
    _psnr,
    read_step,
)
from egosim.pipeline.geometry import invert_se3, transform_points, unproject_depth
from egosim.pipeline.records import DepthCameraRecord, HandMaskRecord, PosesRecord
from egosim.stages.depth_camera.stage import DepthCameraConfig, DepthCameraStage, window_depth
from egosim.stages.hand_mask.stage import HandMaskConfig, HandMaskStage, masks_from_keypoints
from egosim.stages.hands.stage import HandsStage
from egosim.stages.inpaint.reproject_fill import dilate, opencv_fill
from egosim.stages.inpaint.stage import InpaintConfig, InpaintStage
from egosim.world import WorldConfig, render_clip

SETS = {
    "tuned": "tabletop:0,tabletop:1,tabletop:2,tabletop:3,wild:4,wild:5",
    "held": "alt:tabletop:7,alt:wild:8,alt:tabletop:3,alt:tabletop:9,alt:wild:10,"
    "alt:tabletop:11,alt:wild:12",
}


def parse_config(text: str) -> tuple[str, InpaintConfig]:
    """``name:key=value,...`` -> (name, InpaintConfig with those fields); ``name``: default."""
    name, _, body = text.partition(":")
    fields = {f.name for f in dataclasses.fields(InpaintConfig)}
    kwargs: dict = {}
    for item in filter(None, body.split(",")):
        key, _, value = item.partition("=")
        if key not in fields:
            raise SystemExit(f"unknown InpaintConfig field {key!r}")
        default = getattr(InpaintConfig(), key)
        kwargs[key] = type(default)(value) if not isinstance(default, bool) else value == "true"
    return name, InpaintConfig(**kwargs)


def world_masks(case: str, size: tuple[int, int], frames: int, cache: Path):
    """The clip of ``case`` and its predicted masks (cached)."""
    parts = case.split(":")
    variant, mode, seed = ("default", *parts) if len(parts) == 2 else parts
    extra = {} if variant == "default" else {"variant": variant}
    clip = render_clip(WorldConfig(seed=int(seed), mode=mode, height=size[0], width=size[1],
                                   num_frames=frames, **extra))  # fmt: skip
    name = f"world_{variant}_{mode}_{seed}_{size[0]}x{size[1]}x{frames}_hm{HandMaskStage.version}"
    path = cache / f"{name}.npz"
    if path.exists():
        masks = np.load(path)["masks"]
    else:
        masks = HandMaskStage().masks_for_clip(clip)
        np.savez_compressed(path, masks=masks)
    return clip, masks


def world_rows(
    case: str,
    configs,
    size,
    frames,
    out: Path,
    aligned: bool = False,
    pose_noise: float = 0.0,
    sweep: bool = False,
) -> list[dict]:
    """Figures of one synthetic clip under every config (``aligned``: no depth, no poses;
    ``pose_noise``: the depth fill gets poses that drift, :func:`drifted_poses`; ``sweep``:
    frame 0's depth and confidence from :func:`sweep_depth` instead of the world's depth)."""
    clip, masks = world_masks(case, size, frames, out / "cache")
    region = clip.hand_mask[0] > 0
    telea = opencv_fill(clip.frames[0], dilate(clip.hand_mask[0], 2))
    world_from_cam = clip.world_from_cam
    if pose_noise > 0:
        world_from_cam = drifted_poses(world_from_cam, pose_noise, zlib.crc32(case.encode()))
    depth0, conf0 = clip.depth[0], None
    if sweep:  # the workflow's own depth: a plane sweep (true poses), hands not left out
        points = transform_points(
            clip.world_from_cam[0], unproject_depth(depth0, clip.intrinsics)[depth0 > 0]
        )
        depth0, conf0 = sweep_depth(clip.frames, clip.intrinsics, clip.world_from_cam, points)
    rows = []
    for name, cfg in configs:
        stage = InpaintStage(cfg)
        start = time.perf_counter()
        poses, d0 = (None, None) if aligned else (world_from_cam, depth0)
        pred = stage.fill(clip.frames, masks, poses, clip.intrinsics, d0, depth0_confidence=conf0)
        secs = time.perf_counter() - start
        true = stage.fill(
            clip.frames, clip.hand_mask, poses, clip.intrinsics, d0, depth0_confidence=conf0
        )
        contact_sheet(
            out / f"{name}_{case.replace(':', '_')}.png",
            [clip.frames[0], pred.image, true.image, clip.first_frame_clean, telea],
        )
        rows.append({
            "config": name, "case": case,
            "pred": _psnr(pred.image, clip.first_frame_clean, region),
            "true": _psnr(true.image, clip.first_frame_clean, region),
            "telea": _psnr(telea, clip.first_frame_clean, region),
            "fill_s": secs,
        })  # fmt: skip
    return rows


def sweep_depth(
    frames: np.ndarray,
    intrinsics: np.ndarray,
    world_from_cam: np.ndarray,
    points: np.ndarray,
    config: DepthCameraConfig | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Frame 0's depth and confidence ``(H, W)`` as the ``depth_camera`` stage makes them.

    Its plane sweep (:func:`window_depth`, ``config`` or the stage defaults) over
    ``frames (T, H, W, 3)`` posed by ``world_from_cam (T, 4, 4)``, with no pixels left out (the
    workflow's ``cameras`` step gets no hand masks); ``points (P, 3)`` (world) seen by frame 0
    set the depth range and pick the source frames (subsampled to 4,000, seeded).
    """
    config = config or DepthCameraConfig()
    pick = np.random.default_rng(0).choice(len(points), min(len(points), 4000), replace=False)
    cam_from_world = invert_se3(world_from_cam)  # (T, 4, 4)
    posed = np.ones(len(frames), bool)
    depth = window_depth(frames, None, intrinsics, cam_from_world, posed, points[pick], config)
    if isinstance(depth, str):
        raise NoSweepDepth(f"no plane-sweep depth{depth}")
    return depth[0], depth[1]


class NoSweepDepth(SystemExit):
    """The plane sweep made no depth (too little parallax after the sub-clip's first frame)."""


def drifted_poses(world_from_cam: np.ndarray, step_deg: float, seed: int) -> np.ndarray:
    """``world_from_cam (T, 4, 4)`` with a rotation error that random-walks from frame 0 on.

    Each frame adds a rotation of ``step_deg`` degrees about a random axis (through the camera
    centre) to the previous frame's error, so later frames drift further, as estimated cameras
    and a plane-sweep depth do on real clips; frame 0 keeps its pose.
    """
    rng = np.random.default_rng(seed)
    out = world_from_cam.copy()
    error = np.eye(3)
    for k in range(1, len(out)):
        axis = rng.normal(size=3)
        rvec = np.radians(step_deg) * axis / np.linalg.norm(axis)
        error = cv2.Rodrigues(rvec.reshape(3, 1))[0] @ error
        out[k, :3, :3] = out[k, :3, :3] @ error  # cam axes turned by the error
    return out


def dwm_rows(
    cid: str, configs, data: Path, out: Path, runs: Path | None = None, starts: int = 1
) -> list[dict]:
    """Figures of one real DWM clip under every config (see the module docstring).

    ``runs``: a ``bench.real_video`` output folder; when it holds this clip's run, the depth
    fill with that run's cameras is measured too (``dwm-depth`` and ``dwm-run`` rows).
    ``starts``: sub-clips measured, from :func:`start_frames` (1: the first frame with a
    hand only); rows of a later start ``s`` are named ``<case>@<s>``.
    """
    video, static, inside, hands, _ = dwm_truth(cid, data)
    versions = f"hm{HandMaskStage.version}_hands{HandsStage.version}"  # masks, keypoints
    path = out / "cache" / f"dwm_{cid}_{versions}.npz"
    if path.exists():
        masks = np.load(path)["masks"]
    else:
        uv, present = mediapipe_keypoints(video)
        masks = (masks_from_keypoints(video, uv, present, HandMaskConfig()) > 0).astype(np.uint8)
        np.savez_compressed(path, masks=masks)
    run = None if runs is None else runs / f"dwm_{cid}"
    if run is not None and not (run / "cameras").is_dir():
        print(f"no run of dwm_{cid} in {runs}: depth-path rows left out", flush=True)
        run = None
    rows = []
    first = None  # the first start's scene level (frame against videos_static round the hole)
    for n, s in enumerate(start_frames(hands, starts)):
        level = scene_level(video[s], static[s], inside, hands[s], masks[s])
        first = level if first is None else first
        if level < first - SCENE_DROP_DB:
            moved = f"{level:.1f} dB, first start {first:.1f}: the scene moved, not scored"
            print(f"dwm_{cid} from frame {s}: frame against videos_static round the hole {moved}")
            continue
        at = "" if n == 0 else f"@{s}"
        rows += _dwm_start_rows(cid, at, s, configs, video, static, inside, hands, masks, out, run)
    return rows


SCENE_DROP_DB = 3.0  # a later start whose frame matches videos_static round the hole this much
# worse than the first start's does (dB) shows a moved scene (an opened drawer, a lifted cushion)


def scene_level(
    frame: np.ndarray, static: np.ndarray, inside: np.ndarray, hands: np.ndarray, mask: np.ndarray
) -> float:
    """PSNR (dB) of ``frame`` against ``static (H, W, 3)`` in a band 15-45 px round the hand
    truth and the mask (``hands``, ``mask (H, W)``) within ``inside (H, W)``.

    ``videos_static`` renders the scene as it was before the hands touched it: where the hands
    have moved something (00017 opens a drawer from frame 16 on, 00013 lifts the cushion from
    frame 12) it is not the hand-free frame, so a start whose band falls well below the first
    start's is not scored (00013: 30.7 / 30.3 dB at frames 8 / 9, 14.6-21.8 from 13 on; 00017:
    29.5-30.6 at 2-13, 24.9 at 16, 15-17 at 19 and 35).
    """
    near = (hands > 0) | (dilate(mask, 10) > 0)  # (H, W)
    band = (dilate(near, 45) > 0) & ~(dilate(near, 15) > 0) & inside
    return _psnr(frame, static, band)


def start_frames(hands: np.ndarray, starts: int, min_left: int = 12, min_gap: int = 4) -> list[int]:
    """The frames sub-clips start at: the first frame whose ``hands (T, H, W)`` truth shows a
    hand (``MIN_HAND_FRACTION``), then up to ``starts - 1`` more evenly spread over the later
    frames with a hand at least ``min_gap`` frames after the first (a start one frame later is
    nearly the same case) that leave ``min_left`` frames after them to fill from (each scored as
    if a clip started there: other holes, other frames after them)."""
    shown = np.nonzero(hands.reshape(len(hands), -1).mean(axis=1) >= MIN_HAND_FRACTION)[0]
    if not len(shown):
        return [0]
    later = shown[(shown >= shown[0] + min_gap) & (shown <= len(hands) - 1 - min_left)]
    if starts <= 1 or not len(later):
        return [int(shown[0])]
    pick = np.unique(np.round(np.linspace(0, len(later) - 1, min(starts - 1, len(later)))))
    return [int(shown[0])] + [int(later[int(i)]) for i in pick]


def _dwm_start_rows(
    cid: str,
    at: str,
    s: int,
    configs: list[tuple[str, InpaintConfig]],
    video: np.ndarray,
    static: np.ndarray,
    inside: np.ndarray,
    hands: np.ndarray,
    masks: np.ndarray,
    out: Path,
    run: Path | None,
) -> list[dict]:
    """:func:`dwm_rows`' figures of the sub-clip ``video[s:]`` (row names end in ``at``);
    ``video``, ``static (T, H, W, 3)``, ``hands``, ``masks (T, H, W)``, ``inside (H, W)`` as
    :func:`bench.hand_free_real.dwm_truth` and the mask cache give them."""
    region = (dilate(hands[s], HAND_DILATE_PX) > 0) & inside
    # case -> (masks, poses, intrinsics, depth of the sub-clip's first frame)
    paths: dict[str, tuple] = {f"dwm:{cid}{at}": (masks, None, np.zeros(4), (None, None))}
    if run is not None:
        try:
            poses, intrinsics, depth, run_masks = run_cameras(run, video, s)
        except NoSweepDepth as exc:  # too little parallax after frame s: aligned row only
            print(f"dwm_{cid} from frame {s}: {exc}: depth-path rows left out", flush=True)
        else:
            paths[f"dwm-depth:{cid}{at}"] = (masks, poses, intrinsics, depth)
            paths[f"dwm-run:{cid}{at}"] = (run_masks, poses, intrinsics, depth)
    rows = []
    for case, (case_masks, poses, intrinsics, depth) in paths.items():
        for name, cfg in configs:
            start = time.perf_counter()
            result = InpaintStage(cfg).fill(
                video[s:], case_masks[s:], poses, intrinsics, depth[0], depth0_confidence=depth[1]
            )
            secs = time.perf_counter() - start
            telea = opencv_fill(video[s], result.filled.astype(np.uint8))
            label = case.replace(":", "_")
            contact_sheet(
                out / f"{name}_{label}.png",
                [video[s], case_masks[s], result.image, static[s], telea],
            )
            rows.append({
                "config": name, "case": case,
                "pred": _psnr(result.image, static[s], region),
                "telea": _psnr(telea, static[s], region),
                "frame": _psnr(result.image, static[s], inside),
                "telea_frame": _psnr(telea, static[s], inside),
                "fill_s": secs,
            })  # fmt: skip
    return rows


def run_cameras(
    run: Path, video: np.ndarray, s: int
) -> tuple[np.ndarray, np.ndarray, tuple[np.ndarray, np.ndarray], np.ndarray]:
    """What the dataset workflow's run ``run`` gives the depth fill of ``video[s:]``.

    Returns the run's cleaned poses ``(T - s, 4, 4)`` and intrinsics ``(4,)``, the depth and
    its confidence ``(H, W)`` of frame ``s`` made by the run's ``depth_camera`` parameters (see
    the module docstring) and the run's hand masks ``(T, H, W)``. The run's frames must be
    the video's.
    """
    cams = DepthCameraRecord.of(_one_row(run, "cameras"))
    world_from_cam = PosesRecord.of(_one_row(run, "poses")).world_from_cam  # (T, 4, 4)
    run_masks = HandMaskRecord.of(_one_row(run, "hand_mask")).hand_mask  # (T, H, W)
    if world_from_cam is None or cams.depth0 is None:
        raise SystemExit(f"{run}: the run has no poses or no depth (not the SfM path)")
    if len(world_from_cam) != len(video) or run_masks.shape != video.shape[:3]:
        raise SystemExit(f"{run}: the run's clip is not the whole video ({len(world_from_cam)} "
                         f"poses, masks {run_masks.shape}, video {video.shape[:3]})")  # fmt: skip
    workflow = yaml.safe_load((run / "workflow.resolved.yaml").read_text())
    config = DepthCameraStage.from_params(workflow["steps"]["cameras"]["params"]).config
    intrinsics = cams.intrinsics
    depth0 = cams.depth0  # (H, W) frame 0's, in the poses' scale
    points = transform_points(
        cams.world_from_cam[0], unproject_depth(depth0, intrinsics)[depth0 > 0]
    )  # (P, 3)
    if not np.asarray(cams["registered"], dtype=bool)[s:].all():
        raise SystemExit(f"{run}: frames after {s} not all posed")
    # The sweep uses the cameras step's own poses, as that step does; the fill the cleaned ones.
    depth, conf = sweep_depth(video[s:], intrinsics, cams.world_from_cam[s:], points, config)
    return world_from_cam[s:], intrinsics, (depth, conf), run_masks


def _one_row(run: Path, step: str) -> dict:
    """The one row of ``step`` in ``run`` (a DWM clip ingests as one window)."""
    rows = read_step(run, step)
    if len(rows) != 1:
        raise SystemExit(f"{run}/{step}: {len(rows)} rows, expected one clip")
    return next(iter(rows.values()))


def main() -> int:
    """Run the cases under every config; print and write the figures."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--set", default="tuned,held", help="case sets: tuned, held, or cases")
    parser.add_argument("--config", action="append", default=[], help="name:key=value,...")
    parser.add_argument("--size", default="240x416", help="synthetic HxW")
    parser.add_argument("--frames", type=int, default=25, help="synthetic frames")
    parser.add_argument("--skip-real", action="store_true", help="synthetic cases only")
    parser.add_argument("--real-only", action="store_true", help="DWM cases only")
    parser.add_argument(
        "--aligned", action="store_true", help="synthetic cases without depth and poses"
    )
    parser.add_argument(
        "--pose-noise",
        type=float,
        default=0.0,
        help="synthetic depth-fill poses drift by this many degrees a frame (drifted_poses)",
    )
    parser.add_argument(
        "--sweep",
        action="store_true",
        help="synthetic depth fill on the depth_camera plane sweep's depth (sweep_depth)",
    )
    parser.add_argument(
        "--starts",
        type=int,
        default=1,
        help="DWM sub-clips per clip: the first frame with a hand, then evenly spread later "
        "starts (start_frames; their groups are printed apart)",
    )
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA, help="the shared data folder")
    parser.add_argument(
        "--runs",
        type=Path,
        default=ROOT / "runs" / "real_s24b",
        help="bench.real_video output with dwm_<id> runs (depth-path DWM rows; 'none': off)",
    )
    parser.add_argument("--out", type=Path, default=ROOT / "runs" / "inpaint_margin", help="output")
    args = parser.parse_args()
    (args.out / "cache").mkdir(parents=True, exist_ok=True)
    configs = [parse_config(c) for c in args.config] or [("default", InpaintConfig())]
    size = tuple(int(v) for v in args.size.split("x"))
    cases = []
    for item in args.set.split(","):
        cases += SETS[item].split(",") if item in SETS else [item]
    rows: list[dict] = []
    if not args.real_only:
        for case in cases:
            for row in world_rows(
                case,
                configs,
                size,
                args.frames,
                args.out,
                args.aligned,
                args.pose_noise,
                args.sweep,
            ):
                rows.append(row)
                print(_line(row), flush=True)
    if not args.skip_real and (args.data / DWM).is_dir():
        for clip in real_clips.dwm_dynamic_clips(args.data):  # every clip found there
            cid = clip.clip_id
            if not (clip.static and clip.hands):
                print(f"dwm_{cid}: no videos_static or videos_hands twin: figures n/a")
                continue
            runs = None if str(args.runs) == "none" else args.runs
            for row in dwm_rows(cid, configs, args.data, args.out, runs, args.starts):
                rows.append(row)
                print(_line(row), flush=True)
    groups = {  # case -> in the group: default-world cases, alt cases, DWM clips
        "tuned": lambda case: not case.startswith(("alt:", "dwm")),
        "held": lambda case: case.startswith("alt:"),
        "dwm": lambda case: case.startswith("dwm:") and "@" not in case,
        "dwm-depth": lambda case: case.startswith("dwm-depth:") and "@" not in case,
        "dwm-run": lambda case: case.startswith("dwm-run:") and "@" not in case,
        "dwm@": lambda case: case.startswith("dwm:") and "@" in case,  # later starts
        "dwm-depth@": lambda case: case.startswith("dwm-depth:") and "@" in case,
        "dwm-run@": lambda case: case.startswith("dwm-run:") and "@" in case,
    }
    for name, _ in configs:
        for group, member in groups.items():
            sel = [r for r in rows if r["config"] == name and member(r["case"])]
            if sel:
                margin = np.nanmean([r["pred"] - r["telea"] for r in sel])
                extra = ""
                if "true" in sel[0]:
                    gain = np.nanmean([r["true"] - r["telea"] for r in sel])
                    extra = f" true-mask margin {gain:+.2f}"
                print(f"{name:>12} {group:>9}: pred margin {margin:+.2f} dB{extra} n={len(sel)}")
    (args.out / "inpaint_margin.json").write_text(json.dumps(rows, indent=1))
    return 0


def _line(row: dict) -> str:
    true = f" true {row['true']:.2f}" if "true" in row else ""
    return (
        f"{row['config']:>12} {row['case']:>18}: pred {row['pred']:.2f} "
        f"({row['pred'] - row['telea']:+.2f}){true} telea {row['telea']:.2f} {row['fill_s']:.1f}s"
    )


if __name__ == "__main__":
    raise SystemExit(main())
