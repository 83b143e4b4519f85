"""The real clips present under a data folder, found by layout rather than listed by id.

The real-data benches measured the clips they named ("00013", "00017", ``pour_coke.mp4``...): a
clip added to the data folder in the same layout was silently not measured. These functions list
what is there, sorted, so that a new clip is measured like the others (and a missing one is not
listed). Layouts (paths under the data folder, as ``../shared/data/README.md`` describes them):

- DWM dynamic clips, ``dwm_realworld/realworld_dynamic``: one clip per ``videos/<id>.mp4``, with
  optional twins of the same name in ``videos_hands/`` (hand-mesh renders on black, the hand
  truth), ``videos_static/`` (static-scene render, the scene truth) and
  ``prompts_rewrite/<id>.txt``. A twin is listed only where its file exists; a file in a twin
  folder with no ``videos/`` clip is not a clip;
- DWM fixed-camera videos: every ``dwm_realworld/realworld_fixed/*.mp4``;
- EgoDex-style clips: every ``egodex_sample/*.mp4``;
- HOT3D Aria recordings: every ``hot3d_video/*.mp4`` (three camera views side by side).

Only regular files with the ``.mp4`` suffix (any case) count; hidden files (``.name``, e.g.
macOS ``._00013.mp4`` resource forks) and other types (``.txt``, ``.json``, ``.mov`` beside the
clips) do not. A missing layout folder gives an empty list, not an error.

:func:`table_entry` reads a per-clip table keyed by id (e.g. frames checked by eye for one clip)
with a neutral default for an id it does not hold, saying so once.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TypeVar

DWM_DYNAMIC = "dwm_realworld/realworld_dynamic"  # DWM dynamic clips (videos + twins)
DWM_FIXED = "dwm_realworld/realworld_fixed"  # DWM fixed-camera videos
EGODEX = "egodex_sample"  # EgoDex-style egocentric clips
HOT3D = "hot3d_video"  # HOT3D Aria recordings (three views side by side)
VIDEO_SUFFIX = ".mp4"  # the suffix (compared case-insensitively) of a clip file
REHEARSAL_INDEX = "rehearsal.json"  # in a DWM dynamic folder: which clip and frames each
# rehearsal copy (bench.rehearsal_copies) was made from

T = TypeVar("T")


@dataclass(frozen=True)
class DwmDynamicClip:
    """One DWM dynamic clip and which of its twins exist (paths relative to the data folder)."""

    clip_id: str  # the file stem of videos/<id>.mp4
    video: str  # the real interaction video
    hands: str = ""  # videos_hands/<id>.mp4: hand renders on black; "" = absent
    static: str = ""  # videos_static/<id>.mp4: static-scene render; "" = absent
    prompt: str = ""  # prompts_rewrite/<id>.txt; "" = absent


def _videos(folder: Path) -> list[Path]:
    """The clip files directly in ``folder``, sorted by name ([] when it is no folder)."""
    if not folder.is_dir():
        return []
    return sorted(
        p
        for p in folder.iterdir()
        if p.suffix.lower() == VIDEO_SUFFIX and not p.name.startswith(".") and p.is_file()
    )


def _relative(data: Path, path: Path) -> str:
    return path.relative_to(data).as_posix()


def dwm_dynamic_ids(data: Path) -> list[str]:
    """Ids of the DWM dynamic clips under ``data``: every ``videos/<id>.mp4``'s stem, sorted."""
    return [p.stem for p in _videos(data / DWM_DYNAMIC / "videos")]


def dwm_dynamic_clips(data: Path) -> list[DwmDynamicClip]:
    """Every DWM dynamic clip under ``data`` (sorted by id), with the twins that exist.

    A twin is the file of the clip's name in ``videos_hands/``, ``videos_static/`` (``.mp4``,
    the clip's own suffix first) or ``prompts_rewrite/`` (``.txt``).
    """
    root = data / DWM_DYNAMIC
    out = []
    for video in _videos(root / "videos"):
        mp4 = tuple(dict.fromkeys((video.suffix, VIDEO_SUFFIX)))  # the clip's own suffix first
        out.append(
            DwmDynamicClip(
                clip_id=video.stem,
                video=_relative(data, video),
                hands=_twin(data, root / "videos_hands", video.stem, mp4),
                static=_twin(data, root / "videos_static", video.stem, mp4),
                prompt=_twin(data, root / "prompts_rewrite", video.stem, (".txt",)),
            )
        )
    return out


def _twin(data: Path, folder: Path, stem: str, suffixes: tuple[str, ...]) -> str:
    """The relative path of ``folder/<stem><suffix>`` for the first suffix whose file exists."""
    for suffix in suffixes:
        path = folder / f"{stem}{suffix}"
        if path.is_file():
            return _relative(data, path)
    return ""


def dwm_fixed_videos(data: Path) -> list[str]:
    """Every DWM fixed-camera video under ``data`` (relative paths, sorted)."""
    return [_relative(data, p) for p in _videos(data / DWM_FIXED)]


def egodex_videos(data: Path) -> list[str]:
    """Every EgoDex-style clip under ``data`` (relative paths, sorted)."""
    return [_relative(data, p) for p in _videos(data / EGODEX)]


def hot3d_videos(data: Path) -> list[str]:
    """Every HOT3D Aria recording under ``data`` (relative paths, sorted)."""
    return [_relative(data, p) for p in _videos(data / HOT3D)]


def rehearsal_source(root: Path, clip_id: str) -> tuple[str, tuple[int, ...]] | None:
    """``(source id, source frame of each of the copy's frames)`` for a rehearsal copy listed in
    ``root/rehearsal.json`` (``root``: a DWM dynamic folder; written by
    ``bench.rehearsal_copies``), or None for a clip it does not list or without the file. An
    index that is not such a mapping raises ``ValueError`` naming the file."""
    path = root / REHEARSAL_INDEX
    if not path.is_file():
        return None
    try:
        index = json.loads(path.read_text())
    except (OSError, ValueError) as err:
        raise ValueError(f"{path}: not a readable rehearsal index ({err})") from err
    entry = index.get(clip_id) if isinstance(index, dict) else None
    if entry is None:
        return None
    source, frames = (
        (entry.get("source"), entry.get("frames")) if isinstance(entry, dict) else ("", None)
    )
    if not (isinstance(source, str) and isinstance(frames, list)) or not all(
        isinstance(f, int) and f >= 0 for f in frames
    ):
        raise ValueError(f"{path}: entry {clip_id!r} is not {{source: id, frames: [int, ...]}}")
    return source, tuple(frames)


_SAID: set[tuple[str, str]] = set()  # (table, key) pairs table_entry has reported missing


def table_entry(table: Mapping[str, T], key: str, default: T, name: str) -> T:
    """``table[key]``, or ``default`` for a key the table does not hold.

    The first miss of each ``(name, key)`` prints one line naming the table (``name``) and the
    key, so a clip that a per-clip table (e.g. frames checked by eye) has no entry for is
    measured with the neutral default, and the reader knows it, rather than crashing or being
    skipped.
    """
    if key in table:
        return table[key]
    if (name, key) not in _SAID:
        _SAID.add((name, key))
        print(f"{name} has no entry for {key!r}: using {default!r}", flush=True)
    return default
