"""Contact sheets and side-by-side videos of one clip: see what the dataset workflow made of it.

A sheet has a top row with frame 0 beside the inpainted hand-free frame 0, then one row per
chosen time (first, middle, last frame by default) with the columns real frame | scene render |
visible (white = a scene point landed) | skeleton video | hand mask over the real frame (red).
A mask band across the table, a ghost hand in the inpainted frame or a scene render that slides
off the real frame is visible at a glance here and invisible in a mean.

The side-by-side video puts real | scene render | skeleton | hand mask next to each other for
every frame; it is H.264 in yuv420p (what browsers play).

Inputs are the rows of one clip by role (:data:`ROLES`), as the steps of a run wrote them.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from egosim.pipeline import media

# Role -> the stage whose output row a sheet needs for it.
ROLES: dict[str, str] = {
    "clips": "ingest",
    "hand_mask": "hand_mask",
    "keypoints": "keypoint_render",
    "inpaint": "inpaint",
    "scene_render": "scene_render",
}
MAX_SHEET_WIDTH = 2400  # pixels: wider sheets are scaled down
MAX_VIDEO_WIDTH = 1280  # pixels: wider side-by-side videos are scaled down
VIDEO_CRF = 23  # H.264 quality of side-by-side videos (a preview: smaller files than data)
HAND_TINT = np.array([127, 0, 0])  # RGB added to half the colour of hand-mask pixels


@dataclass(frozen=True)
class ClipViews:
    """The decoded pictures of one clip, all at the clip's size ``(H, W)``."""

    clip_id: str  # the clip
    fps: float  # frames per second of the clip
    real: np.ndarray  # (T, H, W, 3) uint8 the clip's video
    scene: np.ndarray  # (T, H, W, 3) uint8 the scene render along the trajectory
    visible: np.ndarray  # (T, H, W) bool a scene point landed on the pixel
    skeleton: np.ndarray  # (T, H, W, 3) uint8 the skeleton video
    hand_mask: np.ndarray  # (T, H, W) bool 1 = hand or arm
    inpainted: np.ndarray  # (H, W, 3) uint8 the hand-free first frame


def decode_views(clip_id: str, rows: Mapping[str, Mapping[str, Any]]) -> ClipViews:
    """Decode the videos and images of one clip from its rows by role (:data:`ROLES`).

    Raises ``KeyError`` naming the missing roles and :class:`~egosim.pipeline.media.MediaError`
    naming the clip and the column that cannot be decoded.
    """
    missing = [role for role in ROLES if rows.get(role) is None]
    if missing:
        raise KeyError(f"clip {clip_id}: no row for {missing}")
    clip = rows["clips"]
    h, w = int(clip["height"]), int(clip["width"])
    real = media.decode_rgb_video(clip["video"], h, w, f"{clip_id} video")  # (T, H, W, 3)
    masks = media.decode_lossless_video(rows["hand_mask"]["hand_mask"], f"{clip_id} hand mask")
    skeleton = media.decode_rgb_video(
        rows["keypoints"]["skeleton_video"], h, w, f"{clip_id} skeleton video"
    )
    render = rows["scene_render"]
    scene = media.decode_rgb_video(render["scene_video"], h, w, f"{clip_id} scene video")
    visible = media.decode_lossless_video(render["visible"], f"{clip_id} visible")
    first = media.decode_png(rows["inpaint"]["first_frame"], f"{clip_id} inpainted first frame")
    return ClipViews(
        clip_id=clip_id,
        fps=float(clip["fps"]),
        real=real,
        scene=scene,
        visible=np.asarray(visible) > 0,
        skeleton=skeleton,
        hand_mask=np.asarray(masks) > 0,
        inpainted=first,
    )


def label(image: np.ndarray, text: str) -> np.ndarray:
    """``image`` with ``text`` in its top-left corner (white on black)."""
    out = image.copy()
    cv2.rectangle(out, (0, 0), (8 * len(text) + 8, 18), (0, 0, 0), -1)
    cv2.putText(out, text, (4, 13), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 255), 1)
    return out


def mask_overlay(frame: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """``frame`` (H, W, 3) with the pixels of ``mask`` (H, W) tinted red."""
    out = frame.copy()
    out[mask] = (0.5 * out[mask] + HAND_TINT).astype(np.uint8)
    return out


def _grey(mask: np.ndarray) -> np.ndarray:
    return np.repeat((mask * 255).astype(np.uint8)[..., None], 3, axis=2)  # (H, W, 3)


def _scale(image: np.ndarray, max_width: int) -> np.ndarray:
    scale = min(1.0, max_width / image.shape[1])
    if scale >= 1.0:
        return image
    return cv2.resize(image, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)


def sheet_times(num_frames: int) -> list[int]:
    """The frames a sheet shows: first, middle and last (fewer for short clips)."""
    return sorted({0, num_frames // 2, num_frames - 1})


def clip_sheet(
    views: ClipViews, times: Sequence[int] | None = None, max_width: int = MAX_SHEET_WIDTH
) -> np.ndarray:
    """The contact sheet ``(H', W', 3)`` RGB of one clip (see the module doc)."""
    t = len(views.real)
    times = sheet_times(t) if times is None else list(times)
    bad = [k for k in times if not 0 <= k < t]
    if bad:
        raise ValueError(f"clip {views.clip_id}: sheet times {bad} outside its {t} frames")
    names = ("scene render", "visible", "skeleton", "hand mask")
    rows = []
    for k in times:
        cells = [
            label(views.real[k], f"real t={k}"),
            *(
                label(cell, name)
                for cell, name in zip(
                    (
                        views.scene[k],
                        _grey(views.visible[k]),
                        views.skeleton[k],
                        mask_overlay(views.real[k], views.hand_mask[k]),
                    ),
                    names,
                    strict=True,
                )
            ),
        ]
        rows.append(np.concatenate(cells, axis=1))
    blank = np.zeros_like(views.real[0])
    top = np.concatenate(
        [label(views.real[0], "frame 0"), label(views.inpainted, "inpainted frame 0")]
        + [blank] * 3,
        axis=1,
    )
    return _scale(np.concatenate([top, *rows], axis=0), max_width)


def side_by_side(views: ClipViews, max_width: int = MAX_VIDEO_WIDTH) -> np.ndarray:
    """``(T, H', W', 3)`` frames: real | scene render | skeleton | hand mask, even sizes."""
    t, h = views.real.shape[:2]
    frames = np.concatenate(
        [
            views.real,
            views.scene,
            views.skeleton,
            np.stack([mask_overlay(views.real[k], views.hand_mask[k]) for k in range(t)]),
        ],
        axis=2,
    )  # (T, H, 4W, 3)
    scale = min(1.0, max_width / frames.shape[2])
    out_w = max(2, round(frames.shape[2] * scale / 2) * 2)
    out_h = max(2, round(h * scale / 2) * 2)
    return np.stack(
        [cv2.resize(f, (out_w, out_h), interpolation=cv2.INTER_AREA) for f in frames]
    )  # (T, H', W', 3)


def side_by_side_mp4(views: ClipViews, max_width: int = MAX_VIDEO_WIDTH) -> bytes:
    """:func:`side_by_side` as H.264 MP4 bytes (yuv420p) at the clip's fps."""
    return media.encode_rgb_video(side_by_side(views, max_width), views.fps, crf=VIDEO_CRF)


def encode_jpeg(image: np.ndarray, quality: int = 88) -> bytes:
    """An RGB ``(H, W, 3)`` uint8 image as JPEG bytes."""
    ok, data = cv2.imencode(
        ".jpg", cv2.cvtColor(image, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, quality]
    )
    if not ok:
        raise media.MediaError(f"could not encode a {image.shape} image as JPEG")
    return data.tobytes()
