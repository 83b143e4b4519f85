"""Contact sheets of real runs: look at what the dataset workflow made of each real video.

``python -m bench.real_sheets [--runs runs/real] [--out runs/real/sheets]`` reads the run folders
that ``bench.real_video`` (``make eval-real``) wrote, or one run folder of ``egosim run`` (e.g. on
your own videos), and writes one PNG per clip: rows at the first,
middle and last frame; columns real frame | scene render | visible (white = a scene point
landed) | skeleton video | hand mask over the real frame (red). Above them, frame 0 beside the
inpainted hand-free first frame: the layout of the sheets of ``egosim report``, which this
calls. A mask band across the table, a ghost hand in the inpainted frame or a scene render that
slides off the real frame is visible in a second here and invisible in a mean.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np

from bench.real_video import read_step
from egosim.pipeline.report import sheets

ROOT = Path(__file__).resolve().parents[1]

# Role of pipeline.report.sheets -> the step of the dataset workflow that writes it.
STEPS = {
    "clips": "ingest",
    "hand_mask": "hand_mask",
    "keypoints": "keypoints",
    "inpaint": "inpaint",
    "scene_render": "scene_render",
}


def read_roles(run: Path) -> dict[str, dict[str, dict]]:
    """Rows of each role's step of ``run`` by clip id, every shard read once."""
    return {role: read_step(run, step) for role, step in STEPS.items()}


def clip_sheet(by_role: dict[str, dict[str, dict]], cid: str) -> np.ndarray | None:
    """The contact sheet ``(H', W', 3)`` RGB of one clip, or None when a step is missing.

    ``by_role`` is :func:`read_roles` of the run. The layout is
    :func:`egosim.pipeline.report.sheets.clip_sheet` (the dataset report's).
    """
    rows = {role: by_role[role].get(cid) for role in STEPS}
    if any(row is None for row in rows.values()):
        return None
    return sheets.clip_sheet(sheets.decode_views(cid, rows))


def main() -> int:
    """Write a sheet per clip of ``--runs`` (a run folder, or a folder of them); exit 1 if none."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs", type=Path, default=ROOT / "runs" / "real", help="run folders")
    parser.add_argument("--out", type=Path, default=None, help="sheet folder (RUNS/sheets)")
    args = parser.parse_args()
    if not args.runs.is_dir():
        parser.error(f"--runs {args.runs}: no such folder (a run folder, or a folder of them)")
    out = args.out or args.runs / "sheets"
    out.mkdir(parents=True, exist_ok=True)
    written = 0
    runs = [args.runs] if (args.runs / "ingest").is_dir() else sorted(args.runs.iterdir())
    for run in (p for p in runs if (p / "ingest").is_dir()):
        by_role = read_roles(run)
        for cid in by_role["clips"]:
            sheet = clip_sheet(by_role, cid)
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
