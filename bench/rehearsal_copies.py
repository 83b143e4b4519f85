"""Rehearsal copies of the real DWM clips: transformed twins to check rules on before new clips.

Further real clips are kept aside to check the results; a rule chosen on DWM 00013 / 00017 can
pass on them by chance. ``python -m bench.rehearsal_copies [--data ../shared/data] --out DIR
[--kinds reencode,window,reverse,mirror,dim,small]`` writes copies of every DWM dynamic clip
under ``--data`` (:func:`bench.real_clips.dwm_dynamic_clips`) into ``DIR`` in the same layout
(``dwm_realworld/realworld_dynamic/{videos,videos_hands,videos_static,prompts_rewrite}``), each
kind with its own id prefix, so that every real bench runs on them with ``--data DIR``:

- ``reencode`` (6xxxx): the frames as they are, encoded once more (a control: pixels change by a
  few levels; a figure that moves here is fragile, not better or worse);
- ``window`` (7xxxx): from the first frame whose hand truth covers :data:`MIN_HAND_FRACTION` of
  the image on (00013 from frame 8, 00017 from 2): the clip starts with the hands in view;
- ``reverse`` (8xxxx): the frames in reverse order (hands leave instead of entering);
- ``mirror`` (9xxxx): every frame flipped left to right; in the hand truth the left (green) and
  right (red) colours are swapped, since a mirrored left hand is a right hand;
- ``dim`` (5xxxx): the real and static videos darker and warmer (gamma :data:`DIM_GAMMA`, gains
  :data:`DIM_GAINS`), as an indoor camera with another exposure would see them; the hand truth
  is unchanged;
- ``small`` (4xxxx): every twin scaled to :data:`SMALL_SCALE` of its size (area resampling).

Every twin of a clip gets the same frames and the same transform, so the truth still lines up;
the prompt is copied. ``rehearsal.json`` beside the copies
(:func:`bench.real_clips.rehearsal_source`) says which clip and frames each copy was made from,
so per-clip tables kept by eye for the originals (``bench.hands_real.RENDER_GAPS``) reach their
copies. Copies are written with H.264 at ``--crf`` (default 12, near-lossless).
Prints one line per copy: id, kind, frames, size.
"""

from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path

import cv2
import numpy as np

from bench import real_clips
from egosim.pipeline import media

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_DATA = ROOT.parent / "shared" / "data"
KIND_PREFIX = {
    "small": "4",
    "dim": "5",
    "reencode": "6",
    "window": "7",
    "reverse": "8",
    "mirror": "9",
}
MIN_HAND_FRACTION = 0.003  # the window starts where hand truth covers this share of the frame
HAND_RENDER_THRESHOLD = 30  # a hand-truth pixel brighter than this (any channel) is hand
DIM_GAMMA = 1.4  # dim: intensity ** gamma (darker midtones)
DIM_GAINS = (0.95, 0.85, 0.7)  # dim: per-channel (R, G, B) gain after the gamma (warmer, darker)
SMALL_SCALE = 0.75  # small: the copies' size as a share of the original's
TWINS = ("video", "hands", "static")  # the twin video fields of real_clips.DwmDynamicClip


def first_hand_frame(hands: np.ndarray) -> int:
    """The first frame of a ``(T, H, W, 3)`` hand-truth video showing a hand (0 when none does)."""
    shown = (hands > HAND_RENDER_THRESHOLD).any(axis=-1).reshape(len(hands), -1).mean(axis=1)
    hits = np.nonzero(shown >= MIN_HAND_FRACTION)[0]
    return int(hits[0]) if len(hits) else 0


def transform(kind: str, twin: str, frames: np.ndarray, start: int) -> np.ndarray:
    """One twin's ``(T, H, W, 3)`` uint8 frames as the copy of ``kind`` holds them.

    ``twin`` is ``"video"``, ``"hands"`` or ``"static"``; ``start`` is the window's first frame
    (used by ``window`` only).
    """
    if kind == "reencode":
        return frames
    if kind == "window":
        return frames[start:]
    if kind == "reverse":
        return frames[::-1]
    if kind == "mirror":
        out = frames[:, :, ::-1]
        return out[..., [1, 0, 2]] if twin == "hands" else out  # green (left) <-> red (right)
    if kind == "dim":
        if twin == "hands":
            return frames
        scaled = (frames.astype(np.float32) / 255.0) ** DIM_GAMMA * np.float32(DIM_GAINS)
        return np.clip(np.rint(scaled * 255.0), 0, 255).astype(np.uint8)
    if kind == "small":
        h, w = frames.shape[1:3]
        size = (2 * round(w * SMALL_SCALE / 2), 2 * round(h * SMALL_SCALE / 2))
        return np.stack([cv2.resize(f, size, interpolation=cv2.INTER_AREA) for f in frames])
    raise ValueError(f"unknown rehearsal kind {kind!r}; known: {sorted(KIND_PREFIX)}")


def source_frames(kind: str, length: int, start: int) -> list[int]:
    """The original's frame index of each frame of a copy of ``kind`` (``length`` frames in
    the original, the window starting at ``start``)."""
    if kind == "window":
        return list(range(start, length))
    if kind == "reverse":
        return list(range(length - 1, -1, -1))
    return list(range(length))


def copy_clip(
    data: Path, clip: real_clips.DwmDynamicClip, out: Path, kinds: list[str], crf: int
) -> tuple[list[str], dict[str, dict]]:
    """Write ``clip``'s copies of each kind under ``out``; returns one printed line per copy and
    the copies' entries of the rehearsal index (:data:`bench.real_clips.REHEARSAL_INDEX`)."""
    src = {t: getattr(clip, t) for t in TWINS if getattr(clip, t)}
    frames = {t: media.read_video_file(data / p)[0] for t, p in src.items()}
    fps = media.probe_video_file(data / clip.video).fps
    start = first_hand_frame(frames["hands"]) if "hands" in frames else 0
    lines, index = [], {}
    for kind in kinds:
        new_id = KIND_PREFIX[kind] + clip.clip_id[1:]
        frame_map = source_frames(kind, len(frames["video"]), start)
        index[new_id] = {"source": clip.clip_id, "kind": kind, "frames": frame_map}
        for twin, rel in src.items():
            target = out / Path(rel).parent / f"{new_id}.mp4"
            target.parent.mkdir(parents=True, exist_ok=True)
            copy = np.ascontiguousarray(transform(kind, twin, frames[twin], start))
            media.write_video_file(target, copy, fps, crf=crf)
        if clip.prompt:
            target = out / Path(clip.prompt).parent / f"{new_id}.txt"
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(data / clip.prompt, target)
        shape = transform(kind, "video", frames["video"][:1], 0).shape
        lines.append(f"{new_id}  {kind:<9} {len(frame_map)} frames  {shape[2]}x{shape[1]}")
    return lines, index


def main(argv: list[str] | None = None) -> int:
    """Write the rehearsal copies (see the module docstring); exit 1 when there is no DWM clip."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--kinds", default=",".join(KIND_PREFIX), help="comma-separated kinds")
    parser.add_argument("--crf", type=int, default=12, help="H.264 quality of the copies")
    args = parser.parse_args(argv)
    kinds = [k for k in args.kinds.split(",") if k]
    unknown = sorted(set(kinds) - set(KIND_PREFIX))
    if unknown:
        parser.error(f"unknown kinds {unknown}; known: {sorted(KIND_PREFIX)}")
    clips = real_clips.dwm_dynamic_clips(args.data)
    if not clips:
        print(f"no DWM dynamic clip under {args.data}")
        return 1
    path = args.out / real_clips.DWM_DYNAMIC / real_clips.REHEARSAL_INDEX
    index = json.loads(path.read_text()) if path.is_file() else {}  # earlier runs' copies kept
    for clip in clips:
        lines, entries = copy_clip(args.data, clip, args.out, kinds, args.crf)
        for line in lines:
            print(line, flush=True)
        index.update(entries)
    path.write_text(json.dumps(index, indent=1, sort_keys=True))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
