"""Contact sheets of real runs: look at what the dataset workflow made of each real video.

``python -m bench.real_sheets [--runs runs/real] [--out runs/real/sheets]`` reads the run folders
that ``bench.real_video`` (``make eval-real``) wrote and writes one PNG per clip: rows at the first,
middle and last frame; columns real frame | hand mask over it (red) | skeleton video | scene
render | visible (white = a scene point landed). Above them, frame 0 beside the inpainted
hand-free first frame. A mask band across the table, a ghost hand in the inpainted frame or a
scene render that slides off the real frame is visible in a second here and invisible in a mean.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np

from bench.real_video import read_step
from egosim.pipeline import media

ROOT = Path(__file__).resolve().parents[1]


def _label(image: np.ndarray, text: str) -> np.ndarray:
    """``image`` with ``text`` in its top-left corner (white on black)."""
    out = image.copy()
    cv2.rectangle(out, (0, 0), (8 * len(text) + 8, 18), (0, 0, 0), -1)
    cv2.putText(out, text, (4, 13), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 255), 1)
    return out


def clip_sheet(run: Path, cid: str) -> np.ndarray | None:
    """The contact sheet ``(H', W', 3)`` RGB of one clip, or None when a step is missing."""
    steps = {s: read_step(run, s).get(cid) for s in ("ingest", "hand_mask", "keypoints")}
    steps["inpaint"] = read_step(run, "inpaint").get(cid)
    steps["scene_render"] = read_step(run, "scene_render").get(cid)
    if any(row is None for row in steps.values()):
        return None
    clip = steps["ingest"]
    h, w = int(clip["height"]), int(clip["width"])
    real = media.decode_rgb_video(clip["video"], h, w, f"{cid} video")  # (T, H, W, 3)
    masks = media.decode_lossless_video(steps["hand_mask"]["hand_mask"], f"{cid} hand mask") > 0
    skeleton = media.decode_rgb_video(steps["keypoints"]["skeleton_video"], h, w, f"{cid} skel")
    render = steps["scene_render"]
    scene = media.decode_rgb_video(render["scene_video"], h, w, f"{cid} scene")
    visible = media.decode_lossless_video(render["visible"], f"{cid} visible") > 0
    first = media.decode_png(steps["inpaint"]["first_frame"], f"{cid} first frame")
    t = len(real)
    rows = []
    for k in sorted({0, t // 2, t - 1}):
        overlay = real[k].copy()
        overlay[masks[k]] = (0.5 * overlay[masks[k]] + [127, 0, 0]).astype(np.uint8)
        vis = np.repeat((visible[k] * 255).astype(np.uint8)[..., None], 3, axis=2)
        cells = [real[k], overlay, skeleton[k], scene[k], vis]
        names = (f"real t={k}", "hand mask", "skeleton", "scene render", "visible")
        rows.append(np.concatenate([_label(c, n) for c, n in zip(cells, names, strict=True)], 1))
    top = np.concatenate(
        [_label(real[0], "frame 0"), _label(first, "inpainted frame 0")]
        + [np.zeros_like(real[0])] * 3,
        axis=1,
    )
    sheet = np.concatenate([top, *rows], axis=0)
    scale = min(1.0, 2400 / sheet.shape[1])
    return cv2.resize(sheet, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)


def main() -> int:
    """Write a sheet per clip of every run folder under ``--runs``; exit 1 if none was written."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs", type=Path, default=ROOT / "runs" / "real", help="run folders")
    parser.add_argument("--out", type=Path, default=None, help="sheet folder (RUNS/sheets)")
    args = parser.parse_args()
    out = args.out or args.runs / "sheets"
    out.mkdir(parents=True, exist_ok=True)
    written = 0
    for run in sorted(p for p in args.runs.iterdir() if (p / "ingest").is_dir()):
        for cid in read_step(run, "ingest", ["clip_id"]):
            sheet = clip_sheet(run, cid)
            if sheet is None:
                print(f"{run.name}/{cid}: a step is missing (rejected?), no sheet")
                continue
            path = out / f"{run.name}__{cid}.png"
            cv2.imwrite(str(path), cv2.cvtColor(sheet, cv2.COLOR_RGB2BGR))
            print(path)
            written += 1
    return 0 if written else 1


if __name__ == "__main__":
    raise SystemExit(main())
