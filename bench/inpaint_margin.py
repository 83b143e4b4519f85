"""Frame-0 inpainting against OpenCV Telea, the fill alone (issue 9), several configs at once.

``python -m bench.inpaint_margin [--set default] [--config 'name:key=value,key=value' ...]
[--skip-real] [--out runs/inpaint_margin]`` prints, per case and config, the fill's PSNR in the
true hand(+arm) region of frame 0 and the margin over Telea; ``OUT/inpaint_margin.json`` holds
the figures and ``OUT/<config>_<case>.png`` the sheets (frame 0 | fill | truth | Telea).

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

Real DWM clips (``dwm_realworld/realworld_dynamic``): as ``bench.hand_free_real``'s ``dwm_case``:
the sub-clip from the first frame with a visible hand, image-aligned fill, ``videos_static``
registered to the real frames, PSNR in the hand truth dilated 15 px, Telea with the same mask.
``--aligned`` runs the synthetic cases without depth and poses too (the fill DWM gets: later
frames aligned by homographies), so that path has cases to tune on that are not the real ones.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import numpy as np

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
)
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


def world_rows(case: str, configs, size, frames, out: Path, aligned: bool = False) -> list[dict]:
    """Figures of one synthetic clip under every config (``aligned``: no depth, no poses)."""
    clip, masks = world_masks(case, size, frames, out / "cache")
    region = clip.hand_mask[0] > 0
    telea = opencv_fill(clip.frames[0], dilate(clip.hand_mask[0], 2))
    rows = []
    for name, cfg in configs:
        stage = InpaintStage(cfg)
        start = time.perf_counter()
        poses, depth0 = (None, None) if aligned else (clip.world_from_cam, clip.depth[0])
        pred = stage.fill(clip.frames, masks, poses, clip.intrinsics, depth0)
        secs = time.perf_counter() - start
        true = stage.fill(clip.frames, clip.hand_mask, poses, clip.intrinsics, depth0)
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


def dwm_rows(cid: str, configs, data: Path, out: Path) -> list[dict]:
    """Figures of one real DWM clip under every config (see the module docstring)."""
    video, static, inside, hands, _ = dwm_truth(cid, data)
    versions = f"hm{HandMaskStage.version}_hands{HandsStage.version}"  # masks, keypoints
    path = out / "cache" / f"dwm_{cid}_{versions}.npz"
    if path.exists():
        masks = np.load(path)["masks"]
    else:
        uv, present = mediapipe_keypoints(video)
        masks = (masks_from_keypoints(video, uv, present, HandMaskConfig()) > 0).astype(np.uint8)
        np.savez_compressed(path, masks=masks)
    shown = np.nonzero(hands.reshape(len(hands), -1).mean(axis=1) >= MIN_HAND_FRACTION)[0]
    s = int(shown[0]) if len(shown) else 0
    region = (dilate(hands[s], HAND_DILATE_PX) > 0) & inside
    rows = []
    for name, cfg in configs:
        start = time.perf_counter()
        result = InpaintStage(cfg).fill(video[s:], masks[s:], None, np.zeros(4), None)
        secs = time.perf_counter() - start
        telea = opencv_fill(video[s], result.filled.astype(np.uint8))
        contact_sheet(out / f"{name}_dwm_{cid}.png", [video[s], result.image, static[s], telea])
        rows.append({
            "config": name, "case": f"dwm:{cid}",
            "pred": _psnr(result.image, static[s], region),
            "telea": _psnr(telea, static[s], region),
            "frame": _psnr(result.image, static[s], inside),
            "telea_frame": _psnr(telea, static[s], inside),
            "fill_s": secs,
        })  # fmt: skip
    return rows


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
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA, help="the shared data folder")
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
            for row in world_rows(case, configs, size, args.frames, args.out, args.aligned):
                rows.append(row)
                print(_line(row), flush=True)
    if not args.skip_real and (args.data / DWM).is_dir():
        for cid in ("00013", "00017"):
            for row in dwm_rows(cid, configs, args.data, args.out):
                rows.append(row)
                print(_line(row), flush=True)
    groups = {  # case -> in the group: default-world cases, alt cases, DWM clips
        "tuned": lambda case: not case.startswith(("alt:", "dwm:")),
        "held": lambda case: case.startswith("alt:"),
        "dwm": lambda case: case.startswith("dwm:"),
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
                print(f"{name:>12} {group:>5}: pred margin {margin:+.2f} dB{extra}")
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
