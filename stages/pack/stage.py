"""The ``pack`` stage: assemble one training sample per clip, behind a quality gate.

Joins the clip (target video, prompt fallback, cameras), its scene render (scene video and
visibility), its keypoints (skeleton video) and caption, plus the optional inpainted first frame,
estimated or cleaned cameras and hand masks, and writes them at one size and frame count:

- frames: ``frame_stride`` apart from frame 0; ``num_frames`` of them (0: as many as fit), always
  ``1 + 4k`` because that is the model's latent layout. Ingest's clip policy makes clips of
  different lengths (61 or 49 frames, and short or tail clips down to its ``min_frames``, 33 by
  default, all ``1 + 4k``): ``num_frames`` 0 packs each whole, which needs ``batch_size`` 1 in
  training when lengths differ; a fixed ``num_frames`` gives one length and rejects the clips
  shorter than it;
- size: ``height`` x ``width`` (0: the clip's), area-resized; masks are resized by area and
  thresholded at one half, intrinsics scaled with the image. Resizing here (not at train time)
  makes the pack shard exactly what the model sees, and cheap to read for ``tiny`` training.

First frame: ``inpaint``'s when connected, else the source's ``first_frame_clean``, else the
clip's frame 0 (hands included; ``first_frame_source`` says which).

Quality gate (``ClipRejected`` with every failing figure): registered fraction (frames whose
pose the camera backend estimated; 1 for source or cleaned poses), mean visible fraction of the
scene render over frames 1.., and fraction of frames with a hand keypoint in view. Inputs that
disagree in frame count or size are rejected with a message naming each disagreeing role.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any, ClassVar

import cv2
import numpy as np

from egosim.pipeline import media
from egosim.pipeline.geometry import scale_intrinsics
from egosim.pipeline.records import (
    CaptionsRecord,
    ClipsRecord,
    DepthCameraRecord,
    HandMaskRecord,
    KeypointsRecord,
    SceneRenderRecord,
)
from egosim.pipeline.stage import ClipRejected, ClipStage, ConfigError, StageConfig, join_columns
from egosim.schemas import CLIPS, ShardSchema
from egosim.schemas.captions import CAPTIONS
from egosim.schemas.depth_camera import DEPTH_CAMERA
from egosim.schemas.hand_mask import HAND_MASK
from egosim.schemas.inpaint import INPAINT
from egosim.schemas.keypoints import KEYPOINTS
from egosim.schemas.pack import PACK
from egosim.schemas.poses import POSES
from egosim.schemas.scene import SCENE_RENDER
from egosim.stages.common.cameras import (
    CAMERA_COLUMNS,
    DEPTH0_COLUMNS,
    first_frame_depth,
    resolve_cameras,
)


@dataclasses.dataclass(frozen=True)
class PackConfig(StageConfig):
    """Parameters of ``pack``."""

    height: int = 0  # sample frame height in pixels; 0 = the clip's
    width: int = 0  # sample frame width in pixels; 0 = the clip's
    num_frames: int = 0  # sample frames (1 + 4k); 0 = the most 1 + 4k frames that fit
    frame_stride: int = 1  # clip frames between consecutive sample frames
    min_registered_fraction: float = 0.5  # gate: frames with an estimated pose / all frames
    min_visible_fraction: float = 0.2  # gate: mean scene-visible fraction of frames 1..
    min_hand_valid_fraction: float = 0.1  # gate: frames with a hand keypoint in view / frames
    crf: int = 12  # H.264 quality of the packed videos (lower = better, bigger)

    def __post_init__(self) -> None:
        problems = []
        for name in ("height", "width", "num_frames"):
            if getattr(self, name) < 0:
                problems.append(f"{name} must be >= 0, got {getattr(self, name)}")
        if (self.height == 0) != (self.width == 0):
            problems.append(
                f"height and width must both be 0 or both be set, got {self.height}x{self.width}"
            )
        if self.num_frames and (self.num_frames - 1) % 4:
            problems.append(f"num_frames must be 0 or 1 + 4k, got {self.num_frames}")
        if self.frame_stride < 1:
            problems.append(f"frame_stride must be >= 1, got {self.frame_stride}")
        for name in ("min_registered_fraction", "min_visible_fraction", "min_hand_valid_fraction"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                problems.append(f"{name} must be in [0, 1], got {getattr(self, name)}")
        if not 0 <= self.crf <= 51:
            problems.append(f"crf must be in [0, 51], got {self.crf}")
        if problems:
            raise ConfigError("; ".join(problems))


def sample_frame_indices(clip_frames: int, num_frames: int, stride: int) -> np.ndarray:
    """Indices of the sample's frames in the clip: ``0, stride, 2 stride, ...`` (1 + 4k of them).

    ``num_frames`` 0 takes the most 1 + 4k frames that fit; raises :class:`ClipRejected` when the
    clip is too short for ``num_frames``.
    """
    available = (clip_frames - 1) // stride + 1
    n = num_frames or 1 + 4 * ((available - 1) // 4)
    if n > available:
        raise ClipRejected(
            f"clip has {clip_frames} frames: too short for {n} sample frames at stride {stride} "
            "(pack num_frames=0 takes the most 1 + 4k frames that fit)"
        )
    return np.arange(n) * stride


def resize_video(frames: np.ndarray, height: int, width: int) -> np.ndarray:
    """Area-resize ``(T, H, W, 3)`` or ``(T, H, W)`` uint8 frames to ``height x width``."""
    if frames.shape[1:3] == (height, width):
        return frames
    return np.stack([cv2.resize(f, (width, height), interpolation=cv2.INTER_AREA) for f in frames])


def resize_mask(mask: np.ndarray, height: int, width: int) -> np.ndarray:
    """Resize a ``(T, H, W)`` {0,1} mask by area averaging, then threshold at one half."""
    if mask.shape[1:3] == (height, width):
        return (mask > 0).astype(np.uint8)
    area = resize_video((mask > 0).astype(np.float32), height, width)  # (T, h, w) in [0, 1]
    return (area >= 0.5).astype(np.uint8)


def resize_depth(depth: np.ndarray, height: int, width: int) -> np.ndarray:
    """Nearest-resize an ``(H, W)`` depth map (no blending across depth edges)."""
    if depth.shape == (height, width):
        return depth
    return cv2.resize(depth, (width, height), interpolation=cv2.INTER_NEAREST)


class PackStage(ClipStage):
    """Assemble training samples; the quality gate rejects clips below thresholds."""

    name = "pack"
    description = "assemble training samples (target, scene, mask, skeleton, first frame, prompt)"
    config_class = PackConfig
    inputs: ClassVar[Mapping[str, ShardSchema]] = {
        "clips": CLIPS,
        "scene_render": SCENE_RENDER,
        "keypoints": KEYPOINTS,
        "captions": CAPTIONS,
    }
    optional_inputs: ClassVar[Mapping[str, ShardSchema]] = {
        "inpaint": INPAINT,
        "cameras": DEPTH_CAMERA,
        "poses": POSES,
        "hand_mask": HAND_MASK,
    }
    output = PACK
    backends = ("default",)
    # What process reads (the executor decodes nothing else); check_inputs_agree compares the
    # frame count and size of every role that has them, so each role lists those too.
    columns: ClassVar[Mapping[str, tuple[str, ...]]] = join_columns(
        {
            "clips": ("num_frames", "height", "width", "fps", "video", "first_frame_clean"),
            "scene_render": (
                "num_frames",
                "height",
                "width",
                "visible_fraction",
                "scene_video",
                "visible",
            ),
            "keypoints": ("num_frames", "height", "width", "keypoint_visible", "skeleton_video"),
            "captions": ("text",),
            "inpaint": ("height", "width", "first_frame"),
            "cameras": ("num_frames", "height", "width", "registered"),
            "hand_mask": ("num_frames", "height", "width", "hand_mask"),
        },
        {"clips": ("hand_mask",)},
        CAMERA_COLUMNS,
        DEPTH0_COLUMNS,
    )
    config: PackConfig

    def process(self, rows: Mapping[str, Mapping[str, Any]]) -> dict[str, Any]:
        """Pack one clip (or reject it with the reason)."""
        cfg = self.config
        clip = ClipsRecord.of(rows["clips"])
        t, h, w = clip.size
        check_inputs_agree(rows)
        render = SceneRenderRecord.of(rows["scene_render"])
        keypoints = KeypointsRecord.of(rows["keypoints"])
        cameras = resolve_cameras(rows)
        index = sample_frame_indices(t, cfg.num_frames, cfg.frame_stride)
        gate = self._quality_gate(rows, cameras.source, cameras.world_from_cam is None, index)

        # Decode (each role's media checked against its size, which agrees with the clip's),
        # select frames, resize.
        oh, ow = (cfg.height, cfg.width) if cfg.height else (h, w)
        target = clip.frames
        scene = render.rgb_video("scene_video")
        skeleton = keypoints.rgb_video("skeleton_video")
        visible = render.mask_video("visible")
        first, first_source = self._first_frame(rows, target[0], h, w)
        hand = _hand_mask(rows)
        depth0 = first_frame_depth(rows)
        fps = clip.fps / cfg.frame_stride

        def video(frames: np.ndarray) -> bytes:
            return media.encode_rgb_video(resize_video(frames[index], oh, ow), fps, cfg.crf)

        def mask(values: np.ndarray) -> bytes:
            return media.encode_mask_video(resize_mask(values[index], oh, ow))

        row = {
            "clip_id": clip.clip_id,
            "num_frames": len(index),
            "width": ow,
            "height": oh,
            "fps": fps,
            "frame_indices": index.tolist(),
            "intrinsics": scale_intrinsics(cameras.intrinsics, ow / w, oh / h).tolist(),
            "world_from_cam": None
            if cameras.world_from_cam is None
            else cameras.world_from_cam[index].reshape(len(index), 16).tolist(),
            "target_video": video(target),
            "scene_video": video(scene),
            "visible": mask(visible),
            "skeleton_video": video(skeleton),
            "first_frame": media.encode_png(resize_video(first[None], oh, ow)[0]),
            "first_frame_source": first_source,
            "hand_mask": None if hand is None else mask(hand),
            "depth0": None,
            "depth_unit_m": None,
            "prompt": CaptionsRecord.of(rows["captions"]).text,
            **gate,
        }
        if depth0 is not None:
            d = resize_depth(depth0.astype(np.float32), oh, ow)[None]  # (1, oh, ow)
            unit = media.depth_unit_for(d)
            row["depth0"], row["depth_unit_m"] = media.encode_depth_video(d, unit), unit
        return row

    def _quality_gate(
        self,
        rows: Mapping[str, Mapping[str, Any]],
        camera_source: str,
        unposed: bool,
        index: np.ndarray,
    ) -> dict[str, float]:
        """The clip's quality figures (pack columns), or :class:`ClipRejected` naming every one
        below its threshold.

        ``camera_source`` is the role the poses came from (``resolve_cameras``), ``unposed``
        True when no role has poses, ``index`` the sample's frames in the clip.
        """
        cfg = self.config
        t = ClipsRecord.of(rows["clips"]).num_frames
        vis_frac = SceneRenderRecord.of(rows["scene_render"]).visible_fraction
        visible_fraction = float(vis_frac[1:].mean()) if t > 1 else float(vis_frac.mean())
        if camera_source == "cameras":
            registered_fraction = float(np.mean(DepthCameraRecord.of(rows["cameras"]).registered))
        else:
            registered_fraction = 0.0 if unposed else 1.0
        keypoint_visible = KeypointsRecord.of(rows["keypoints"]).keypoint_visible
        hand_valid_fraction = float(keypoint_visible[index].any(axis=1).mean())
        figures = {
            "visible_fraction": visible_fraction,
            "registered_fraction": registered_fraction,
            "hand_valid_fraction": hand_valid_fraction,
        }
        failed = [
            f"{name} {figures[name]:.3f} < {minimum}"
            for name, minimum in (
                ("registered_fraction", cfg.min_registered_fraction),
                ("visible_fraction", cfg.min_visible_fraction),
                ("hand_valid_fraction", cfg.min_hand_valid_fraction),
            )
            if figures[name] < minimum
        ]
        if failed:
            cid = ClipsRecord.of(rows["clips"]).clip_id
            raise ClipRejected(f"quality gate: clip {cid!r}: " + "; ".join(failed))
        return figures

    def _first_frame(
        self, rows: Mapping[str, Mapping[str, Any]], frame0: np.ndarray, h: int, w: int
    ) -> tuple[np.ndarray, str]:
        cid = rows["clips"]["clip_id"]
        for role, key, source in (
            ("inpaint", "first_frame", "inpaint"),
            ("clips", "first_frame_clean", "first_frame_clean"),
        ):
            row = rows.get(role)
            if row is not None and row.get(key) is not None:
                image = media.decode_png(row[key], f"clip {cid!r} {role} {key}")
                if image.shape != (h, w, 3):
                    raise ClipRejected(
                        f"inputs disagree: clip {cid!r}: {role} {key} is {image.shape}, clip "
                        f"frames are ({h}, {w}, 3)"
                    )
                return image, source
        return frame0, "frame0"


def _hand_mask(rows: Mapping[str, Mapping[str, Any]]) -> np.ndarray | None:
    """``(T, H, W)`` {0, 1}: the ``hand_mask`` role's mask, else the clip's own, else None."""
    if rows.get("hand_mask") is not None:
        return HandMaskRecord.of(rows["hand_mask"]).mask_video("hand_mask")
    clip = ClipsRecord.of(rows["clips"])
    return clip.mask_video("hand_mask", f"clip {clip.clip_id!r} source hand_mask")


def check_inputs_agree(rows: Mapping[str, Mapping[str, Any]]) -> None:
    """Raise :class:`ClipRejected` naming every input role whose frame count or size differs."""
    clip = ClipsRecord.of(rows["clips"])
    want = dict(zip(("num_frames", "height", "width"), clip.size, strict=True))
    problems = []
    for role, row in rows.items():
        if role in ("clips", "captions", "poses"):
            continue
        for key, value in want.items():
            if key in row and row[key] is not None and int(row[key]) != value:
                problems.append(f"{role} {key} is {row[key]}, clips has {value}")
    kp = KeypointsRecord.of(rows["keypoints"]).keypoint_visible
    if len(kp) != want["num_frames"]:
        problems.append(
            f"keypoints has {len(kp)} frames of keypoints, clips has {want['num_frames']}"
        )
    if problems:
        raise ClipRejected(f"inputs disagree: clip {clip.clip_id!r}: " + "; ".join(problems))
