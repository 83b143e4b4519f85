"""The ``hand_mask`` stage: hand-and-arm masks for every frame of a clip.

Keypoints: 3D hand joints (world metres) projected with the shared geometry; joints below
``min_joint_confidence`` are dropped. The joints are the optional ``hands`` input's
(de-duplicated and de-spiked by the ``hands`` stage) when a workflow connects it, else the clip's
own ``hand_joints``. Intrinsics and poses come from
:func:`egosim.stages.common.cameras.resolve_cameras`: the optional ``poses`` or ``cameras``
inputs when connected, else the clip's own.

Backends:

- ``keypoints`` (default): bones drawn as capsules sized from the hand's scale in the image, the
  palm filled, the forearm drawn from the wrist to the image border (see ``capsules``), then
  refined by a colour model learned from the pixels under the skeleton (see ``colour_model``).
  The forearm heads towards a projected elbow guess: from the wrist, a forearm length (0.26 m)
  horizontally (world z up) towards the shoulder of the hand's side (``shoulder_offset_m`` beside
  the camera), rising by ``forearm_rise`` per metre; ``arm_pulls`` can instead draw a fan of
  directions between it and the hand's own wrist direction for the colour model to trim.
- ``sam``: a SAM-family model from ``sam_model_path`` through transformers, prompted with the
  keypoints and the capsule mask's box (see ``sam``).

A clip without hand joints or poses is rejected; frames where no hand is valid get empty masks.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any, ClassVar, Literal

import numpy as np

from egosim.pipeline import media
from egosim.pipeline.clip_io import clip_from_row
from egosim.pipeline.geometry import project_world_points
from egosim.pipeline.records import Clip
from egosim.pipeline.stage import ClipRejected, ClipStage, ConfigError, StageConfig
from egosim.schemas import CLIPS, ShardSchema
from egosim.schemas.hand_mask import HAND_MASK
from egosim.schemas.hands import HANDS
from egosim.stages.common.cameras import CAMERA_ROLES, resolve_cameras
from egosim.stages.hand_mask.capsules import (
    FOREARM_LENGTH_M,
    CapsuleParams,
    draw_hands,
    hand_scale_px,
)
from egosim.stages.hand_mask.colour_model import refine_with_colour
from egosim.stages.hand_mask.sam import SamSegmenter, mask_box

# Columns of a clips row this stage does not read: left undecoded.
_UNUSED_COLUMNS = (
    "depth",
    "static_video",
    "static_depth",
    "first_frame_clean",
    "hand_mask",
    "object_mask",
    "object_poses",
    "num_objects",
)


@dataclasses.dataclass(frozen=True)
class HandMaskConfig(StageConfig):
    """Parameters of ``hand_mask``."""

    backend: Literal["keypoints", "sam"] = "keypoints"  # mask maker (see module docstring)
    radius_scale: float = 1.0  # multiplies the average adult bone and forearm radii
    forearm: bool = True  # draw the forearm from the wrist to the image border
    arm_pulls: tuple[float, ...] = (100.0,)  # forearms drawn, one per weight of the elbow
    # guess against the wrist direction (100: the elbow guess alone; (0, 1, 3, 10): a fan)
    colour_refine: bool = True  # refine the capsule mask with a learned colour model (GrabCut)
    band_scale: float = 1.0  # colour model's uncertain band: this x 3 cm at the hand's scale
    grabcut_iterations: int = 3  # GrabCut iterations per frame
    grabcut_max_side: int = 256  # GrabCut works on a region downscaled to this longest side
    min_joint_confidence: float = 0.0  # joints with lower confidence are ignored
    shoulder_offset_m: float = 0.18  # shoulder's distance beside the camera, metres
    forearm_rise: float = 0.15  # elbow height gain per metre of forearm (world z up)
    sam_model_path: str = ""  # local folder of a SAM model (backend "sam")
    sam_device: str = "cpu"  # torch device of the SAM model

    def __post_init__(self) -> None:
        problems = []
        if not 0.1 <= self.radius_scale <= 10.0:
            problems.append(f"radius_scale must be in [0.1, 10], got {self.radius_scale}")
        if not 0.0 < self.band_scale <= 20.0:
            problems.append(f"band_scale must be in (0, 20], got {self.band_scale}")
        if self.grabcut_iterations < 1:
            problems.append(f"grabcut_iterations must be >= 1, got {self.grabcut_iterations}")
        if self.grabcut_max_side < 16:
            problems.append(f"grabcut_max_side must be >= 16, got {self.grabcut_max_side}")
        if not 0.0 <= self.min_joint_confidence <= 1.0:
            problems.append(
                f"min_joint_confidence must be in [0, 1], got {self.min_joint_confidence}"
            )
        if not 0.0 <= self.shoulder_offset_m <= 1.0:
            problems.append(f"shoulder_offset_m must be in [0, 1], got {self.shoulder_offset_m}")
        if not -5.0 <= self.forearm_rise <= 5.0:
            problems.append(f"forearm_rise must be in [-5, 5], got {self.forearm_rise}")
        if self.backend == "sam" and not self.sam_model_path:
            problems.append("backend 'sam' needs sam_model_path (a local folder of weights)")
        if not self.arm_pulls or not all(0.0 <= p <= 100.0 for p in self.arm_pulls):
            problems.append(f"arm_pulls must be 1+ values in [0, 100], got {self.arm_pulls}")
        if problems:
            raise ConfigError("; ".join(problems))


def project_keypoints(clip: Clip, min_confidence: float = 0.0) -> np.ndarray:
    """2D keypoints ``(T, 2, 21, 2)`` in pixels from the clip's 3D joints; NaN = unknown.

    Joints behind the camera or below ``min_confidence`` are NaN.
    """
    if clip.hand_joints is None or clip.world_from_cam is None:
        raise ClipRejected(f"clip {clip.clip_id!r}: no hand joints or poses to project")
    uv = np.stack(
        [
            project_world_points(clip.hand_joints[t], clip.world_from_cam[t], clip.intrinsics)[0]
            for t in range(clip.num_frames)
        ]
    )  # (T, 2, 21, 2)
    if clip.hand_confidence is not None and min_confidence > 0:
        uv[clip.hand_confidence < min_confidence] = np.nan
    return uv


def elbow_guess(clip: Clip, shoulder_offset_m: float, forearm_rise: float) -> np.ndarray:
    """Projected elbow guess ``(T, 2, 2)`` per hand (see the module docstring); NaN if unknown."""
    out = np.full((clip.num_frames, 2, 2), np.nan)
    for t in range(clip.num_frames):
        cam = clip.world_from_cam[t]  # (4, 4)
        elbows = []
        for k, side in enumerate((-1.0, 1.0)):
            shoulder = cam[:3, 3] + side * shoulder_offset_m * cam[:3, 0]  # (3,)
            wrist = clip.hand_joints[t, k, 0].astype(np.float64)  # (3,)
            towards = shoulder - wrist
            towards[2] = 0.0
            norm = float(np.linalg.norm(towards))
            if norm < 1e-9:
                elbows.append(np.full(3, np.nan))
                continue
            direction = towards / norm
            direction[2] = forearm_rise
            elbows.append(wrist + FOREARM_LENGTH_M * direction / np.linalg.norm(direction))
        out[t] = project_world_points(np.array(elbows), cam, clip.intrinsics)[0]
    return out


def _with_hands(clip: Clip, hands: Mapping[str, Any]) -> Clip:
    """``clip`` with its joints, validity and confidence replaced by a ``hands`` row's."""
    t = clip.num_frames
    if int(hands["num_frames"]) != t:
        raise ClipRejected(
            f"clip {clip.clip_id!r}: hands cover {hands['num_frames']} frames, not {t}"
        )
    return dataclasses.replace(
        clip,
        hand_joints=np.asarray(hands["hand_joints"], dtype=np.float32).reshape(t, 2, 21, 3),
        hand_valid=np.asarray(hands["hand_valid"], dtype=bool).reshape(t, 2),
        hand_confidence=np.asarray(hands["hand_confidence"], dtype=np.float32).reshape(t, 2, 21),
    )


class HandMaskStage(ClipStage):
    """Hand-and-arm masks per frame from projected keypoints (capsules + colour) or SAM."""

    name = "hand_mask"
    description = "hand and arm masks per frame from keypoints (capsules + colour) or SAM"
    config_class = HandMaskConfig
    inputs: ClassVar[Mapping[str, ShardSchema]] = {"clips": CLIPS}
    # cleaned joints and a replacement camera (see the module docstring)
    optional_inputs: ClassVar[Mapping[str, ShardSchema]] = {**CAMERA_ROLES, "hands": HANDS}
    output = HAND_MASK
    backends = ("keypoints", "sam")

    def __init__(self, config: StageConfig | None = None) -> None:
        super().__init__(config)
        self._sam: SamSegmenter | None = None

    def masks_for_clip(self, clip: Clip) -> np.ndarray:
        """Masks ``(T, H, W)`` uint8 (1 = hand or arm) for a decoded clip."""
        cfg: HandMaskConfig = self.config  # type: ignore[assignment]
        keypoints = project_keypoints(clip, cfg.min_joint_confidence)  # (T, 2, 21, 2)
        valid = np.ones((clip.num_frames, 2), bool) if clip.hand_valid is None else clip.hand_valid
        targets = elbow_guess(clip, cfg.shoulder_offset_m, cfg.forearm_rise)  # (T, 2, 2)
        params = CapsuleParams(
            radius_scale=cfg.radius_scale, forearm=cfg.forearm, body_pulls=cfg.arm_pulls
        )
        masks = np.zeros((clip.num_frames, clip.height, clip.width), np.uint8)
        for t in range(clip.num_frames):
            mask, core = draw_hands(
                keypoints[t], valid[t], clip.height, clip.width, params, targets[t]
            )
            if cfg.backend == "sam":
                masks[t] = self._segment_sam(clip.frames[t], keypoints[t], valid[t], params)
                continue
            if cfg.colour_refine and mask.any():
                scales = [
                    hand_scale_px(k) for k, ok in zip(keypoints[t], valid[t], strict=True) if ok
                ]
                scale = float(np.nanmax(scales)) if np.isfinite(scales).any() else 0.0
                band = max(1, round(0.03 * scale * cfg.band_scale))
                mask = refine_with_colour(
                    clip.frames[t], mask, core, band, cfg.grabcut_iterations, cfg.grabcut_max_side
                )
            masks[t] = mask
        return masks

    def _segment_sam(
        self, image: np.ndarray, keypoints: np.ndarray, valid: np.ndarray, params: CapsuleParams
    ) -> np.ndarray:
        cfg: HandMaskConfig = self.config  # type: ignore[assignment]
        if self._sam is None:
            self._sam = SamSegmenter(cfg.sam_model_path, cfg.sam_device)
        h, w = image.shape[:2]
        boxes = np.stack(
            [mask_box(draw_hands(k[None], [True], h, w, params)[0]) for k in keypoints]
        )  # (2, 4)
        return self._sam.segment(image, keypoints, valid, boxes)

    def process(self, rows: Mapping[str, Mapping[str, Any]]) -> dict[str, Any]:
        """Masks for one clips row; see the module docstring."""
        row = rows["clips"]
        clip = clip_from_row({**row, **dict.fromkeys(_UNUSED_COLUMNS)})
        cams = resolve_cameras(rows)
        clip = dataclasses.replace(
            clip, intrinsics=cams.intrinsics, world_from_cam=cams.world_from_cam
        )
        if rows.get("hands") is not None:
            clip = _with_hands(clip, rows["hands"])
        if clip.hand_joints is None:
            raise ClipRejected(f"clip {clip.clip_id!r}: no hand joints (run the hands stage)")
        if clip.world_from_cam is None:
            raise ClipRejected(f"clip {clip.clip_id!r}: no camera poses to project hand joints")
        masks = self.masks_for_clip(clip)
        cfg: HandMaskConfig = self.config  # type: ignore[assignment]
        return {
            "clip_id": clip.clip_id,
            "num_frames": clip.num_frames,
            "width": clip.width,
            "height": clip.height,
            "hand_mask": media.encode_mask_video(masks),
            "coverage": masks.reshape(clip.num_frames, -1).mean(axis=1).tolist(),
            "backend": cfg.backend,
        }
