"""Scene-cloud density and scene-render coverage on real clips and the synthetic world.

``python -m bench.scene_coverage [--data ../shared/data] [--out runs/scene_coverage] [--only NAME]
[--no-run] [--runs DIR] [--cloud k=v] [--render k=v]`` prints one table and writes
``OUT/scene_coverage.json`` and ``OUT/contact_sheet.png`` (per real clip: real frame 0 | render at
t=0 | visible at t=0, hands in red | render at the end); with ``--cloud``/``--render`` settings
both names carry them.

- **Real with truth** (``dwm_<id>``): the dataset workflow (``workflows/dataset.yaml``,
  ``ingest.preset=dwm``, through :func:`bench.real_video.run_case`; finished steps are skipped;
  ``--no-run`` reuses the run folder) on each DWM dynamic clip found under ``--data``
  (:func:`bench.real_video.cases`; a clip without both truth twins is measured as one without
  truth, below); then ``scene_cloud`` +
  ``scene_render`` are run again with the current code (and ``--cloud``/``--render`` settings) on
  that run's ``ingest``, ``cameras``, ``poses`` and ``inpaint`` shards (:func:`rerender`;
  ``--workflow-render`` measures the run's own render instead), and the render is compared with
  ``videos_static`` (the true static scene along the true trajectory). Hand pixels are
  ``videos_hands`` dilated by ``HAND_DILATE_PX``; the truth is first registered to the real frame 0
  (:func:`bench.real_video.truth_shift`, as ``bench.real_video`` does), so ``dB`` is its "scene
  dB". The scene steps as they were before the depth fill (scene_cloud v4, scene_render v1) are
  reproduced by ``--cloud min_confidence=0 --cloud fill=false --cloud speckle_px=0 --render
  max_crack_px=0 --render max_crack_width=0`` (checked: the same figures as the old stages' own
  render).
- **Real without truth** (EgoDex, the fixed-camera videos, HOT3D's RGB view: every window):
  the same re-render; hand pixels are the run's own ``hand_mask`` dilated by ``HAND_DILATE_PX``;
  no ``dB``. ``--runs DIR --no-run`` reads runs made elsewhere (``bench.real_video --out DIR``)
  and writes only the re-rendered scene steps under ``--out``.
- **Synthetic** (``world_*``): a small synthetic clip whose depth is removed, so ``depth_camera``
  (backend ``given``: the world's poses) estimates it by plane sweep like on real video; then
  ``scene_cloud`` (hands left out by the world's hand mask) and ``scene_render``; compared with
  the world's static video. ``alt`` rows use ``WorldConfig(variant="alt")`` when it exists (a
  differently made world nothing here was tuned on).

``--holes`` adds, per real clip, what each hole pixel of the render is (:func:`hole_causes`):
its ray cast through frame 0's depth grid as a surface (open3d ``RaycastingScene``) meets no
quad (``h_view``: out of frame 0's view, or through pixels the cloud left out), a quad whose
corners' inverse depths differ by more than 5% (``h_step``: a depth step of frame 0, true
or estimated, that tore the points apart), or a smooth quad (``h_mag``: points spread too thin
for the splats); shares of non-hand pixels, averaged over the clip.

Columns: ``measured`` share of frame-0 pixels whose depth was measured (the rest filled);
``cloud`` points / pixels; ``cov0``, ``cov`` and ``covN``: share of non-hand pixels the render
marks visible at t=0, on average over the clip, and at the last frame; ``dB``: PSNR of the render
against the static truth on visible non-hand pixels, averaged over frames (``dB0`` at t=0).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml

from bench.real_video import (
    DEFAULT_DATA,
    HAND_DILATE_PX,
    HAND_RENDER_THRESHOLD,
    ROOT,
    RealCase,
    _fit,
    _psnr,
    _shift,
    _video_frames,
    cases,
    read_step,
    run_case,
    truth_shift,
)
from egosim.pipeline import media
from egosim.pipeline.geometry import invert_se3, transform_points
from egosim.schemas.scene import cloud_from_row
from egosim.stages.common.cameras import resolve_cameras
from egosim.stages.inpaint.reproject_fill import dilate

SYNTHETIC = (  # (label, mode, seed, variant) at SYN_H x SYN_W, SYN_T frames
    ("world_wild_s1", "wild", 1, ""),
    ("world_wild_s2", "wild", 2, ""),
    ("world_table_s1", "tabletop", 1, ""),
    ("alt_wild_s3", "wild", 3, "alt"),
    ("alt_table_s3", "tabletop", 3, "alt"),
)
SYN_H, SYN_W, SYN_T = 192, 336, 17  # small synthetic clips


def coverage_figures(
    scene: np.ndarray,
    visible: np.ndarray,
    truth: np.ndarray | None,
    hand: np.ndarray,
    truth_valid: np.ndarray | None = None,
) -> dict[str, float]:
    """Coverage and PSNR of a render ``scene (T, H, W, 3)`` with ``visible (T, H, W)`` bool.

    ``truth (T, H, W, 3)`` the static scene (None: unknown, ``dB`` NaN), ``hand (T, H, W)``
    bool pixels left out of every figure, ``truth_valid (H, W)`` bool pixels where the truth is
    defined (None: all; a registered truth has no pixels where its shift pulled in the border).
    """
    free = ~hand  # (T, H, W)
    cov = (visible & free).reshape(len(scene), -1).sum(1) / np.maximum(
        free.reshape(len(scene), -1).sum(1), 1
    )  # (T,)
    valid = np.ones(scene.shape[1:3], bool) if truth_valid is None else truth_valid  # (H, W)
    psnrs = [
        float("nan") if truth is None else _psnr(scene[t], truth[t], visible[t] & free[t] & valid)
        for t in range(len(scene))
    ]
    return {
        "cov0": float(cov[0]),
        "cov": float(cov.mean()),
        "covN": float(cov[-1]),
        "dB0": psnrs[0],
        "dB": float(np.nanmean(psnrs)) if np.isfinite(psnrs).any() else float("nan"),
    }


HOLE_STEP = 0.05  # hole_causes: a quad whose corners' 1/z differ by more than this is a step


def hole_causes(
    cloud: Any,
    world_from_cam: np.ndarray,
    intrinsics: np.ndarray,
    holes: np.ndarray,
    counted: np.ndarray,
) -> dict[str, float]:
    """Why the render has holes: ``holes (T, H, W)`` bool of a render of ``cloud`` (a
    :class:`~egosim.schemas.scene.SceneCloud` unprojected from frame 0) along ``world_from_cam
    (T, 4, 4)``; returns ``h_view``, ``h_step``, ``h_mag`` (see the module docstring) as shares
    of the ``counted (T, H, W)`` bool pixels (the non-hand ones), averaged over frames."""
    import open3d as o3d

    from egosim.stages.scene_render.splat import grid_quads

    t, h, w = holes.shape
    quads = grid_quads(cloud.points, world_from_cam[0], intrinsics, h, w, np.inf)  # (Q, 4)
    cam0 = transform_points(invert_se3(world_from_cam[0]), cloud.points.astype(np.float64))
    inv = 1.0 / cam0[:, 2]  # (N,) frame-0 inverse depth
    step = inv[quads].max(1) / inv[quads].min(1) - 1.0  # (Q,)
    tris = np.concatenate([quads[:, [0, 2, 1]], quads[:, [1, 2, 3]]])  # (2Q, 3)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(cloud.points.astype(np.float32)), o3d.core.Tensor(tris.astype(np.uint32))
    )
    fx, fy, cx, cy = np.asarray(intrinsics, dtype=np.float64)
    uu, vv = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)  # (H, W) pixel centres
    rays_cam = np.stack([(uu - cx) / fx, (vv - cy) / fy, np.ones_like(uu)], -1)  # (H, W, 3)
    shares = {"h_view": 0.0, "h_step": 0.0, "h_mag": 0.0}
    for i in range(t):
        sel = holes[i] & counted[i]  # (H, W)
        if not sel.any():
            continue
        dirs = rays_cam[sel] @ world_from_cam[i, :3, :3].T  # (M, 3)
        origin = np.broadcast_to(world_from_cam[i, :3, 3], dirs.shape)
        rays = o3d.core.Tensor(np.concatenate([origin, dirs], 1).astype(np.float32))
        prim = scene.cast_rays(rays)["primitive_ids"].numpy().astype(np.int64)  # (M,)
        miss = prim == o3d.t.geometry.RaycastingScene.INVALID_ID
        torn = step[np.where(miss, 0, prim) % len(quads)] > HOLE_STEP
        n = max(int(counted[i].sum()), 1)
        shares["h_view"] += float(miss.sum()) / n / t
        shares["h_step"] += float((~miss & torn).sum()) / n / t
        shares["h_mag"] += float((~miss & ~torn).sum()) / n / t
    return shares


def _rows(path: Path) -> dict[str, dict]:
    """Rows of one shard by clip id ({} when it does not exist)."""
    from egosim.pipeline.shards import open_shard

    if not path.is_file():
        return {}
    with open_shard(path) as reader:
        return {row["clip_id"]: row for row in reader.iter_rows()}


def _cloud_figures(cloud: dict | None, hw: tuple[int, int]) -> dict[str, float]:
    """Measured share of the frame's pixels and points / pixels of one scene_cloud row."""
    if cloud is None:
        return {"cloud": float("nan"), "measured": float("nan")}
    out = {"cloud": float(cloud["kept_fraction"])}
    conf = cloud.get("point_confidence")
    if conf is not None:
        c = np.frombuffer(conf, dtype=np.uint8)
        out["measured"] = float((c == 255).sum()) / (hw[0] * hw[1])
    else:
        out["measured"] = out["cloud"]
    return out


def _step(
    stage: str, inputs: dict[str, Path], params: dict[str, Any], out: Path, fresh: bool = True
) -> Path:
    """Run one stage on one shard; returns the output path.

    ``fresh``: remove its old output first (the code is what is measured, and a finished shard
    with the same parameters would be skipped); else a finished shard is kept.
    """
    from egosim.pipeline.execute import ShardTask, run_shard_task

    name = stage
    path = out / f"{name}.parquet"
    for old in out.glob(f"{name}*.parquet*") if fresh else ():
        old.unlink()
    run_shard_task(
        ShardTask(
            step=name,
            stage=stage,
            params=params,
            shard_index=0,
            shard_count=1,
            output=path,
            rejects=out / f"{name}-rejects.parquet",
            inputs=inputs,
        )
    )
    return path


def rerender(
    run: Path, out: Path, cloud_params: dict[str, Any], render_params: dict[str, Any]
) -> Path:
    """``scene_cloud`` + ``scene_render`` with the current code on a run's upstream shards.

    Reads the run's ``ingest``, ``cameras``, ``poses`` and ``inpaint`` shard 0 (the dataset
    workflow's inputs of ``scene_cloud``) and writes ``out/scene_cloud`` and
    ``out/scene_render``, so the scene steps are measured on fixed inputs whatever else changes.
    """
    inputs = {
        role: run / step / "shard-00000.parquet"
        for role, step in (
            ("clips", "ingest"),
            ("cameras", "cameras"),
            ("poses", "poses"),
            ("inpaint", "inpaint"),
        )
    }
    missing = [str(p) for p in inputs.values() if not p.is_file()]
    if missing:
        raise FileNotFoundError(f"run {run} lacks {missing}")
    out.mkdir(parents=True, exist_ok=True)
    cloud = _step("scene_cloud", inputs, cloud_params, out)
    render_in = {k: inputs[k] for k in ("clips", "cameras", "poses")}
    _step("scene_render", {**render_in, "scene_cloud": cloud}, render_params, out)
    return out


def real_case(
    case: RealCase, data: Path, run: Path, scene: Path | None = None, holes: bool = False
) -> list[tuple[dict[str, Any], np.ndarray | None]]:
    """Figures of every clip of one real video, each with its contact-sheet row (None: none).

    The render is the run's own ``scene_render`` step, or ``scene/scene_render.parquet`` when
    ``scene`` is given (see :func:`rerender`). Hand pixels: the case's ``videos_hands`` (DWM
    dynamic clips, whose ``videos_static`` also gives ``dB``), else the run's own ``hand_mask``
    (no truth: ``dB`` is NaN), both dilated by ``HAND_DILATE_PX``. ``holes``: add
    :func:`hole_causes` (with the run's cameras and poses, as the scene steps read them).
    """
    clips = read_step(run, "ingest")
    if scene is None:
        renders = read_step(run, "scene_render")
        cloud_rows = read_step(run, "scene_cloud")
    else:
        renders = _rows(scene / "scene_render.parquet")
        cloud_rows = _rows(scene / "scene_cloud.parquet")
    truth_twins = bool(case.static_truth and case.hands_truth)  # both: videos_hands and dB
    masks = {} if truth_twins else read_step(run, "hand_mask")
    out: list[tuple[dict[str, Any], np.ndarray | None]] = []
    for cid in sorted(renders):
        render, clip = renders[cid], clips[cid]
        h, w = int(render["height"]), int(render["width"])
        video = media.decode_rgb_video(render["scene_video"], h, w, f"{cid} scene")
        visible = media.decode_lossless_video(render["visible"], f"{cid} visible") > 0
        real = media.decode_rgb_video(clip["video"], h, w, f"{cid} video")
        if truth_twins:
            indices = clip.get("source_frame_indices")
            indices = np.arange(len(video)) if indices is None else np.asarray(indices, np.int64)
            crop = clip.get("source_crop")
            truth = _fit(_video_frames(data / case.static_truth), indices, (h, w), crop)
            hands = _fit(_video_frames(data / case.hands_truth), indices, (h, w), crop)
            hand = hands.max(axis=3) > HAND_RENDER_THRESHOLD  # (T, H, W)
            # registered like bench.real_video: videos_static is offset by its principal point
            dx, dy = truth_shift(real[0], truth[0])
            truth = np.stack([_shift(f, dx, dy) for f in truth])  # (T, H, W, 3)
            inside = _shift(np.full((h, w), 255, np.uint8), dx, dy) == 255  # (H, W)
        elif cid in masks:
            mask = media.decode_lossless_video(masks[cid]["hand_mask"], f"{cid} hand_mask")
            hand, truth, inside = mask > 0, None, None  # (T, H, W)
        else:
            out.append(({"case": case.name, "clip": cid, "error": "no hand_mask row"}, None))
            continue
        hand = dilate(hand, HAND_DILATE_PX) > 0  # (T, H, W)
        row = {"case": case.name, "clip": cid, **_cloud_figures(cloud_rows.get(cid), (h, w))}
        row.update(coverage_figures(video, visible, truth, hand, inside))
        row["quads"] = render.get("surface_quads")  # None: a render before SCENE_RENDER v3
        if holes and cid in cloud_rows:
            cams = resolve_cameras(
                {
                    "clips": clip,
                    **{k: r[cid] for k in ("cameras", "poses") if cid in (r := read_step(run, k))},
                }
            )
            free = ~hand if inside is None else ~hand & inside[None]  # (T, H, W)
            row.update(
                hole_causes(
                    cloud_from_row(cloud_rows[cid]),
                    cams.world_from_cam,
                    cams.intrinsics,
                    ~visible,
                    free,
                )
            )
        out.append((row, sheet_row(real[0], video[0], visible[0], hand[0], video[-1])))
    if not out:
        return [({"case": case.name, "error": "no scene_render output"}, None)]
    return out


def sheet_row(
    real: np.ndarray, first: np.ndarray, visible: np.ndarray, hand: np.ndarray, last: np.ndarray
) -> np.ndarray:
    """``real | render t=0 | visible t=0 (white; hands red; holes black) | render end``."""
    vis = np.repeat(visible[..., None].astype(np.uint8) * 255, 3, axis=2)  # (H, W, 3)
    vis[hand] = np.clip(vis[hand] * 0.4 + np.array([150, 0, 0]), 0, 255).astype(np.uint8)
    return np.concatenate([real, first, vis, last], axis=1)


def synthetic_case(
    label: str,
    mode: str,
    seed: int,
    variant: str,
    work: Path,
    cloud_params: dict[str, Any],
    render_params: dict[str, Any],
) -> dict[str, Any] | None:
    """Figures of one synthetic clip with estimated (plane-sweep) depth; None if not available."""
    from egosim.pipeline.clip_io import write_clips
    from egosim.world.clip import render_clip
    from egosim.world.config import WorldConfig

    kwargs: dict[str, Any] = {"seed": seed, "mode": mode, "height": SYN_H, "width": SYN_W}
    if variant:
        if "variant" not in {f.name for f in dataclasses.fields(WorldConfig)}:
            return None
        kwargs["variant"] = variant
    clip = render_clip(WorldConfig(num_frames=SYN_T, **kwargs))
    truth, hand = clip.static_frames, clip.hand_mask.astype(bool)
    clip = dataclasses.replace(clip, depth=None, static_depth=None, first_frame_clean=None)
    work.mkdir(parents=True, exist_ok=True)
    clips = work / "clips.parquet"
    write_clips(clips, [clip])  # cheap; depth_camera below reruns only if the clip changed

    cams = _step("depth_camera", {"clips": clips}, {"backend": "given"}, work, fresh=False)
    cloud = _step("scene_cloud", {"clips": clips, "cameras": cams}, cloud_params, work)
    render = _step(
        "scene_render",
        {"clips": clips, "cameras": cams, "scene_cloud": cloud},
        render_params,
        work,
    )
    rows = list(_rows(render).values())
    if not rows:
        return {"case": label, "error": "no scene_render output"}
    row = rows[0]
    h, w = clip.height, clip.width
    scene = media.decode_rgb_video(row["scene_video"], h, w, label)
    visible = media.decode_lossless_video(row["visible"], label) > 0
    cloud_row = _rows(cloud).get(clip.clip_id)
    out = {"case": label, "clip": clip.clip_id, **_cloud_figures(cloud_row, (h, w))}
    out.update(coverage_figures(scene, visible, truth, hand))
    out["quads"] = row.get("surface_quads")  # None: a render before SCENE_RENDER v3
    return out


def print_table(rows: list[dict[str, Any]]) -> None:
    """One line per case."""
    cols = ("measured", "cloud", "cov0", "cov", "covN", "dB0", "dB")
    print(f"{'case':<16}" + "".join(f"{c:>9}" for c in cols) + f"{'s':>6}{'quads':>9}")
    for r in rows:
        if "error" in r:
            print(f"{r['case']:<16} {r['error']}")
            continue
        cells = [f"{r[c]:>9.1f}" if c.startswith("dB") else f"{100 * r[c]:>8.1f}%" for c in cols]
        quads = "-" if r.get("quads") is None else str(r["quads"])  # surface quads, 0 = none
        print(f"{r['case']:<16}" + "".join(cells) + f"{r.get('seconds', 0.0):>6.0f}{quads:>9}")


def main() -> int:
    """Run every case (or ``--only``), print the table, write the JSON and the contact sheet."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA, help="the shared data folder")
    parser.add_argument("--out", type=Path, default=ROOT / "runs" / "scene_coverage")
    parser.add_argument("--only", default="", help="run the cases whose name contains this")
    parser.add_argument("--workers", type=int, default=1, help="local Dask workers (real clips)")
    parser.add_argument("--no-run", action="store_true", help="real clips: read existing runs")
    parser.add_argument(
        "--runs",
        type=Path,
        default=None,
        help="real clips: folder of the runs (one NAME folder per case; default --out)",
    )
    parser.add_argument(
        "--workflow-render",
        action="store_true",
        help="real clips: measure the run's own scene_render instead of re-rendering its inputs",
    )
    parser.add_argument(
        "--holes", action="store_true", help="real clips: what the render's holes are"
    )
    parser.add_argument(
        "--cloud", action="append", default=[], help="scene_cloud param k=v (repeatable)"
    )
    parser.add_argument(
        "--render", action="append", default=[], help="scene_render param k=v (repeatable)"
    )
    args = parser.parse_args()
    cloud_params = {k: yaml.safe_load(v) for k, v in (kv.split("=", 1) for kv in args.cloud)}
    render_params = {k: yaml.safe_load(v) for k, v in (kv.split("=", 1) for kv in args.render)}
    params = {**cloud_params, **{f"render.{k}": v for k, v in render_params.items()}}
    tag = "scene_bench" + "".join(f"-{k}={v}" for k, v in sorted(params.items()))
    args.out.mkdir(parents=True, exist_ok=True)
    rows: list[dict[str, Any]] = []
    sheet: list[np.ndarray] = []
    for case in cases(args.data):  # found by layout (bench.real_clips)
        if args.only and args.only not in case.name:
            continue
        run = (args.runs or args.out) / case.name
        start = time.perf_counter()
        if not args.no_run:
            run_case(case, args.data, run, args.workers)
        try:
            scene = (
                None
                if args.workflow_render
                else rerender(run, args.out / case.name / tag, cloud_params, render_params)
            )
        except FileNotFoundError as exc:  # the workflow stopped before inpaint
            rows.append({"case": case.name, "error": str(exc)})
            continue
        for row, strip in real_case(case, args.data, run, scene, args.holes):
            row["seconds"] = time.perf_counter() - start
            rows.append(row)
            if strip is not None:
                sheet.append(strip)
    for label, mode, seed, variant in SYNTHETIC:
        if args.only and args.only not in label:
            continue
        start = time.perf_counter()
        work = args.out / label  # clips and cameras kept: only the scene steps are recomputed
        row = synthetic_case(label, mode, seed, variant, work, cloud_params, render_params)
        if row is None:
            print(f"{label}: WorldConfig has no variant {variant!r}, skipped")
            continue
        row["seconds"] = time.perf_counter() - start
        rows.append(row)
    (args.out / f"scene_coverage{tag.removeprefix('scene_bench')}.json").write_text(
        json.dumps(rows, indent=1)
    )
    if sheet:
        path = args.out / f"contact_sheet{tag.removeprefix('scene_bench')}.png"
        width = max(s.shape[1] for s in sheet)
        sheet = [
            cv2.resize(
                s,
                (width, round(s.shape[0] * width / s.shape[1])),
                interpolation=cv2.INTER_AREA,
            )
            for s in sheet
        ]  # one width for clips of different sizes
        cv2.imwrite(str(path), cv2.cvtColor(np.concatenate(sheet, axis=0), cv2.COLOR_RGB2BGR))
        print(f"contact sheet: {path}")
    print_table(rows)
    for r in rows:
        if "h_view" in r:
            print(
                f"{r['case']:<16} holes over the clip: out of frame 0's view "
                f"{100 * r['h_view']:.2f}%, at a depth step {100 * r['h_step']:.2f}%, "
                f"on a smooth surface {100 * r['h_mag']:.2f}% (of non-hand pixels)"
            )
    return 0 if rows and all("error" not in r for r in rows) else 1


if __name__ == "__main__":
    raise SystemExit(main())
