"""Ingest backend for folders of image frames (sorted by file name, fps given)."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Protocol

import cv2
import numpy as np

from egosim.pipeline.records import Clip
from egosim.pipeline.stage import ClipRejected
from egosim.stages.common.frame_plan import frame_files, plan_resize
from egosim.stages.ingest.crop_anchor import choose_anchor, sample_frames
from egosim.stages.ingest.standardise import resample_windows
from egosim.stages.ingest.video_source import ClipFormat, source_intrinsics, window_policy


class FramesFormat(ClipFormat, Protocol):
    """Ingest parameters for frame folders."""

    frames_fps: float


def find_frame_folders(path: Path) -> list[Path]:
    """``path`` itself if it holds images, else every sub-folder (recursively) that does."""
    if path.is_file():
        return []
    if frame_files(path):
        return [path]
    return sorted(p for p in path.rglob("*") if p.is_dir() and frame_files(p))


def _read_rgb(path: Path) -> np.ndarray:
    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if image is None:
        raise ClipRejected(f"cannot read image {path}")
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)


def read_frame_clips(folder: Path, cfg: FramesFormat) -> Iterator[Clip]:
    """Cut a folder of frames (taken at ``frames_fps``) into clips by the clip policy.

    A folder with fewer frames than the shortest clip is rejected naming its frame count and
    the minimum, whether or not ``frames_fps`` is set (frames are never repeated, so no rate
    makes a clip of it); a long enough folder without ``frames_fps`` is rejected asking for it.
    """
    files = frame_files(folder)
    if not files:
        raise ClipRejected(f"frame folder {folder} holds no images")
    policy = window_policy(cfg)
    if len(files) < policy.minimum:
        raise ClipRejected(
            f"frame folder {folder} is shorter than one clip: it holds {len(files)} frame(s); "
            f"the minimum is {policy.minimum} frames (a full clip {policy.num_frames}), and "
            "frames are never repeated to lengthen a clip"
        )
    if not cfg.frames_fps > 0:
        raise ClipRejected(
            f"frame folder {folder} ({len(files)} frames): set frames_fps, the rate the frames "
            "were taken (e.g. --set ingest.frames_fps=30)"
        )
    first = _read_rgb(files[0])
    height, width = first.shape[:2]

    def image_at(i: int) -> np.ndarray:
        """Frame ``i``, rejected when its size is not the first frame's."""
        image = first if i == 0 else _read_rgb(files[i])
        if image.shape[:2] != (height, width):
            raise ClipRejected(f"{files[i]}: size {image.shape[:2]} differs from {(height, width)}")
        return image

    # The crop search's samples are size-checked too (one odd frame among them was a ValueError).
    sample = sample_frames(len(files), image_at)
    anchor = choose_anchor(cfg, width, height, sample, f"frame folder {folder}")
    plan = plan_resize(width, height, cfg.width, cfg.height, anchor)
    intrinsics = plan.intrinsics(source_intrinsics(cfg, width, height))

    def frames() -> Iterator[tuple[float, np.ndarray]]:
        for i in range(len(files)):
            yield i / cfg.frames_fps, plan.apply(image_at(i))

    what = f"frame folder {folder}"
    for window in resample_windows(frames(), policy, cfg.frames_fps, what):
        yield Clip(
            clip_id=f"{folder.name}-w{window.index:03d}",
            source="frames",
            source_uri=str(folder),
            fps=window.fps,
            timestamps=window.timestamps,
            intrinsics=intrinsics,
            frames=window.frames,
            source_fps=float(cfg.frames_fps),
            source_num_frames=len(files),
            source_frame_indices=window.source_indices,
            clip_policy=policy.label(window.kind),
            source_crop=np.array(plan.source_crop),
        ).check()
