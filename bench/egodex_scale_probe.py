"""Why the EgoDex sample's metric scale is off (issue 17): samples, focal, geometry.

``python -m bench.egodex_scale_probe [--run runs/real_final3/egodex_sample] [--png OUT.png]
[--focal-sweep 327.4,517.4] [--nominal-focal-px 736.6339 --nominal-width 1920 --nominal-height
1080]`` reads a finished ``bench.real_video`` run of one clip (its ingest and cameras shards) and
prints:

- **samples**: every usable detection of the hand-size scale rule
  (:mod:`egosim.stages.depth_camera.metric_scale`, MediaPipe through the stage's own detector and
  lift) on the run's poses and frame-0 depth put back in SfM units: its estimate, the lifted
  hand's metric depth, the scaled depth of the surface under its used joints. ``--png`` draws the
  six highest on their frames (green: joints that gave a sample, labelled with the scaled surface
  depth under them; red: dropped).
- **focal**: the SfM focal the run kept, the prior it was checked against, the rotation model's
  self-calibrated focal from frame-to-frame homographies (and the share of pairs a homography
  explains), and the source's nominal focal mapped to the clip's frames by ingest's resize rule.
- **geometry** (``--corner``, the EgoDex sample only: pixel regions of its frame 0): the
  confident frame-0 depth along the table's left edge, the table-wall junction behind the cup and
  the vertical room corner, fitted as 3D lines; in a right reconstruction the left edge and the
  back junction meet at about 90 degrees, and the left edge's far end is deeper than its near end.
- **focal sweep** (``--focal-sweep F,...``): SfM again with the focal held at each value
  (``bench/_fixed_focal_worker.py``), the plane sweep, the scale rule, and the same geometry:
  does the clip's motion tell the focal (reprojection error) and what does the focal do to depth
  and scale.

Nothing here is tuned; the figures are in docs/design.md ("Cameras: model choice and one metric
scale") and /tmp/notes/egodexscale.md.
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import cv2
import numpy as np

from egosim.pipeline import media
from egosim.pipeline.geometry import unproject_depth
from egosim.pipeline.shards import open_shard
from egosim.stages.common.hand_landmarks import (
    RawLandmarks,
    detect_hand_landmarks,
    drop_overlapping,
)
from egosim.stages.depth_camera import metric_scale as ms
from egosim.stages.depth_camera import sfm as sfm_mod
from egosim.stages.depth_camera.rotation_model import RotationParams, estimate_rotations

ROOT = Path(__file__).resolve().parents[1]
FIXED_WORKER = Path(__file__).with_name("_fixed_focal_worker.py")
EGODEX_FOCAL_PX = 736.6339  # EgoDex's intrinsics at 1920x1080 (the same in every file)
# EgoDex sample, frame 0 (832x480): pixel regions of confident depth on three room lines.
# The table's left edge runs from about (20, 460) to (330, 235); 25 px either side of it.
LEFT_EDGE = ((20.0, 460.0), (250.0, 285.0))


@dataclasses.dataclass(frozen=True)
class Clip:
    """One clip of a run: frames, the cameras row in SfM units, and the applied scale."""

    frames: np.ndarray  # (T, H, W, 3) uint8 RGB
    intrinsics: np.ndarray  # (4,)
    world_from_cam: np.ndarray  # (T, 4, 4) in SfM units (the run's scale divided out)
    depth0: np.ndarray  # (H, W) SfM units, 0 = unknown
    confidence0: np.ndarray  # (H, W) in [0, 1]
    scale: float  # the run's metres per unit
    focal_prior: float  # the focal prior the run checked its SfM focal against
    source_size: tuple[int, int]  # (width, height) of the source video


def load_clip(run: Path) -> Clip:
    """The first clip of ``run`` (a ``bench.real_video`` output folder of one video)."""
    with open_shard(run / "ingest" / "shard-00000.parquet") as reader:
        ing = next(iter(reader.iter_rows()))
    with open_shard(run / "cameras" / "shard-00000.parquet") as reader:
        cam = next(iter(reader.iter_rows()))
    h, w = int(cam["height"]), int(cam["width"])
    frames = np.stack(media.decode_rgb_video(ing["video"], h, w, "video"))
    depth = media.decode_depth_video(cam["depth0"], cam["depth_unit_m"], "depth0")[0]
    conf = media.decode_lossless_video(cam["confidence0"], "confidence0")[0] / 255.0
    scale = float(cam["metric_scale"] or 1.0)
    poses = np.asarray(cam["world_from_cam"], dtype=np.float64).reshape(-1, 4, 4).copy()
    poses[:, :3, 3] /= scale
    probe = media.probe_video_file(Path(ing["source_uri"]))
    return Clip(
        frames=frames,
        intrinsics=np.asarray(cam["intrinsics"], dtype=np.float64),
        world_from_cam=poses,
        depth0=depth.astype(np.float64) / scale,
        confidence0=conf.reshape(h, w),
        scale=scale,
        focal_prior=float(cam["focal_prior_px"] or 0.0),
        source_size=(int(probe.width), int(probe.height)),
    )


def detections(frames: np.ndarray) -> RawLandmarks:
    """The metric scale's detections (the hands stage's detector, overlaps dropped)."""
    params = ms.MetricScaleParams()
    found = detect_hand_landmarks(frames, params.detector)
    return drop_overlapping(found, params.detector.duplicate_distance)


def sample_table(
    clip: Clip,
    landmarks: RawLandmarks,
    intrinsics: np.ndarray | None = None,
    world_from_cam: np.ndarray | None = None,
    depth0: np.ndarray | None = None,
    confidence0: np.ndarray | None = None,
) -> list[dict]:
    """Per usable detection (the strict window of the scale rule): frame, slot, estimate, the
    lifted metric depth (median joint), used joints, their surface depths (units) and pixels."""
    params = ms.MetricScaleParams()
    k_mat = clip.intrinsics if intrinsics is None else intrinsics
    poses = clip.world_from_cam if world_from_cam is None else world_from_cam
    depth = clip.depth0 if depth0 is None else depth0
    conf = clip.confidence0 if confidence0 is None else confidence0
    d0 = np.where(conf >= params.min_confidence, depth, 0.0)  # (H, W)
    rows: list[dict] = []
    frames = clip.frames
    for t in range(len(frames)):
        slots = np.flatnonzero(landmarks.present[t])
        if not len(slots):
            continue
        source = None
        if t == 0:
            depth_t = d0
        else:
            depth_t, source = ms.splat_depth(d0, k_mat, poses[0], poses[t])
        for k in slots:
            uv, world = landmarks.uv[t, k], landmarks.world[t, k]  # (21, 2), (21, 3)
            if np.linalg.norm(uv.max(axis=0) - uv.min(axis=0)) < params.min_hand_px:
                continue
            points = ms.place_detection(uv, world, k_mat, params.lift)  # (21, 3) metres
            if points is None:
                continue
            z_s = ms.surface_depth(depth_t, uv, params)  # (21,)
            used = np.isfinite(z_s)
            if source is not None:
                scene = frames[0].reshape(-1, 3)[np.maximum(source, 0)].reshape(frames.shape[1:])
                used &= ~ms.scene_visible(frames[t], scene, source >= 0, uv, params)
            if used.sum() < params.min_joint_samples:
                continue
            ratio = (points[used, 2] + params.contact_offset_m) / z_s[used]
            rows.append(
                {
                    "t": t,
                    "k": int(k),
                    "estimate": float(np.quantile(ratio, params.joint_quantile)),
                    "hand_z_m": float(np.median(points[:, 2])),
                    "hand_px": float(np.linalg.norm(uv.max(axis=0) - uv.min(axis=0))),
                    "surface_units": float(np.median(z_s[used])),
                    "used": used,
                    "z_s": z_s,
                    "uv": uv,
                }
            )
    return rows


def draw_samples(clip: Clip, rows: list[dict], path: Path, count: int = 6) -> None:
    """Contact sheet of the ``count`` highest detections (see the module docstring)."""
    tiles = []
    h, w = clip.frames.shape[1:3]
    for row in sorted(rows, key=lambda r: -r["estimate"])[:count]:
        img = cv2.cvtColor(clip.frames[row["t"]], cv2.COLOR_RGB2BGR)
        for j, (u, v) in enumerate(row["uv"]):
            colour = (0, 255, 0) if row["used"][j] else (0, 0, 255)
            cv2.circle(img, (int(u), int(v)), 4, colour, -1)
            if row["used"][j]:
                label = f"{row['z_s'][j] * clip.scale:.1f}"
                cv2.putText(img, label, (int(u) + 5, int(v)), 0, 0.4, (255, 255, 255), 1)
        text = f"t{row['t']} est {row['estimate']:.4f} hand z {row['hand_z_m']:.2f} m"
        cv2.putText(img, text, (10, 30), 0, 0.8, (255, 255, 255), 2)
        tiles.append(cv2.resize(img, (w // 2, h // 2)))
    while len(tiles) % 2:
        tiles.append(np.zeros_like(tiles[0]))
    sheet = np.vstack([np.hstack(tiles[i : i + 2]) for i in range(0, len(tiles), 2)])
    cv2.imwrite(str(path), sheet)


def corner_geometry(intrinsics: np.ndarray, depth0: np.ndarray, confidence0: np.ndarray) -> dict:
    """Angles (degrees) between 3D lines fitted to frame 0's confident depth on the EgoDex
    sample's room lines, and the left edge's far/near depth ratio (module docstring)."""
    ok = (confidence0 >= 0.5) & (depth0 > 0)
    points = unproject_depth(np.where(ok, depth0, 0.0), intrinsics)  # (H, W, 3)
    rows, cols = np.nonzero(ok)
    (x0, y0), (x1, y1) = LEFT_EDGE
    edge_y = y0 + (cols - x0) * (y1 - y0) / (x1 - x0)  # (N,)
    on_left = (cols < 340) & (rows > 200) & (np.abs(rows - edge_y) < 25)
    regions = {
        "left": on_left & (cols < 300),
        "back": (cols > 340) & (cols < 470) & (rows > 240) & (rows < 300),
        "back_right": (cols > 560) & (rows > 260) & (rows < 360),
        "vertical": (cols > 320) & (cols < 380) & (rows > 20) & (rows < 200),
    }
    dirs = {}
    for name, mask in regions.items():
        if mask.sum() < 50:
            return {"reason": f"{int(mask.sum())} confident pixels on the {name} line"}
        pts = points[rows[mask], cols[mask]]  # (M, 3)
        _, _, vt = np.linalg.svd(pts - np.median(pts, axis=0), full_matrices=False)
        dirs[name] = vt[0]

    def angle(a: str, b: str) -> float:
        return float(np.degrees(np.arccos(min(1.0, abs(float(dirs[a] @ dirs[b]))))))

    near = np.median(depth0[rows[on_left & (cols < 60)], cols[on_left & (cols < 60)]])
    far_mask = on_left & (cols > 300)
    far = np.median(depth0[rows[far_mask], cols[far_mask]])
    return {
        "left_back_deg": angle("left", "back"),
        "left_back_right_deg": angle("left", "back_right"),
        "vertical_left_deg": angle("vertical", "left"),
        "left_far_over_near": float(far / near),
    }


def nominal_focal(clip: Clip, focal_px: float, width: int, height: int) -> float:
    """A source focal (pixels at ``width x height``) on the clip's frames (ingest: scale to
    cover, centre crop)."""
    h, w = clip.frames.shape[1:3]
    return focal_px * max(w / width, h / height)


def fixed_focal_sfm(clip: Clip, focal: float) -> dict:
    """SfM with the focal held at ``focal`` px, then the stage's plane sweep and scale rule."""
    from egosim.stages.depth_camera import stage as st

    cfg = st.DepthCameraConfig(sfm_focal_factors=(focal / clip.frames.shape[2],))
    cfg = dataclasses.replace(cfg, sfm_try_global=False)
    saved = sfm_mod.WORKER
    sfm_mod.WORKER = FIXED_WORKER
    try:
        result = sfm_mod.run_sfm(clip.frames, None, cfg.sfm_options(focal))
    finally:
        sfm_mod.WORKER = saved
    est, why = st.sfm_camera(clip.frames, None, result, cfg, focal, None)
    out = {"focal": focal, "reprojection_px": result.reprojection_error_px}
    out["points"] = result.num_points3d
    out["registered"] = float(result.registered.mean())
    if est is None:
        out["reason"] = why
        return out
    conf = np.asarray(est.confidence0)
    out["confident"] = float((conf >= 0.5).mean())
    depth = np.asarray(est.depth0, dtype=np.float64)
    scale = ms.scale_from_landmarks(
        detections(clip.frames), clip.frames, est.intrinsics, est.world_from_cam, depth, conf
    )
    out["scale"] = scale.scale
    out["scale_samples"] = scale.num_samples
    out["geometry"] = corner_geometry(est.intrinsics, depth, conf)
    return out


def main() -> None:
    """Print the probe's figures (module docstring)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run", type=Path, default=ROOT / "runs/real_final3/egodex_sample")
    parser.add_argument("--png", type=Path, default=None)
    parser.add_argument("--corner", action="store_true", help="EgoDex sample room-line geometry")
    parser.add_argument("--focal-sweep", default="", help="comma-separated focals (px) to hold")
    parser.add_argument("--nominal-focal-px", type=float, default=EGODEX_FOCAL_PX)
    parser.add_argument("--nominal-width", type=int, default=1920)
    parser.add_argument("--nominal-height", type=int, default=1080)
    args = parser.parse_args()
    clip = load_clip(args.run)
    landmarks = detections(clip.frames)
    rows = sample_table(clip, landmarks)
    params = ms.MetricScaleParams()
    est = np.array([r["estimate"] for r in rows])
    print(f"samples: {len(rows)} usable detections, run scale {clip.scale:.4g} m/unit")
    if len(est):
        q = float(np.quantile(est, params.contact_quantile))
        print(f"  contact quantile {q:.4g}, median {np.median(est):.4g}")
    for r in sorted(rows, key=lambda r: -r["estimate"]):
        print(
            f"  t{r['t']:2d} slot {r['k']}: estimate {r['estimate']:.4f} "
            f"hand z {r['hand_z_m']:.2f} m ({r['hand_px']:.0f} px) "
            f"surface under its {int(r['used'].sum())} joints "
            f"{r['surface_units'] * clip.scale:.2f} m scaled"
        )
    if args.png and rows:
        draw_samples(clip, rows, args.png)
        print(f"  drawn: {args.png}")
    rot = estimate_rotations(clip.frames, None, clip.intrinsics, RotationParams(), True)
    nominal = nominal_focal(clip, args.nominal_focal_px, args.nominal_width, args.nominal_height)
    print(
        f"focal: SfM {clip.intrinsics[0]:.1f} px (prior {clip.focal_prior:.1f}); rotation model "
        f"{rot.intrinsics[0]:.1f} px (homographies explain {rot.explained_fraction:.0%} of pairs, "
        f"pose {rot.posed.mean():.0%} of frames); nominal {nominal:.1f} px"
    )
    if args.corner:
        print(f"geometry (run): {corner_geometry(clip.intrinsics, clip.depth0, clip.confidence0)}")
    for focal in [float(f) for f in args.focal_sweep.split(",") if f.strip()]:
        print(f"fixed focal: {fixed_focal_sfm(clip, focal)}", flush=True)


if __name__ == "__main__":
    main()
