"""The ``keypoint_render`` stage: 2D keypoints, visibility and the skeleton video of each clip.

Reads the ``clips`` row (size, fps) and the clip's ``hands`` row; projects with
:func:`egosim.stages.keypoint_render.draw.project_hands` and draws the skeleton on black. The
camera is :func:`egosim.stages.common.cameras.resolve_cameras`'s: the optional ``poses`` or
``cameras`` inputs when connected, else the clip's own (the same rule as ``scene_render``).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any, ClassVar, Literal

import numpy as np

from egosim.pipeline import media
from egosim.pipeline.geometry import se3_problems
from egosim.pipeline.records import ClipsRecord, HandsRecord, require_camera_poses
from egosim.pipeline.stage import ClipRejected, ClipStage, ConfigError, StageConfig, join_columns
from egosim.schemas import CLIPS, ShardSchema
from egosim.schemas.hands import HANDS
from egosim.schemas.keypoints import KEYPOINTS
from egosim.stages.common.cameras import CAMERA_COLUMNS, CAMERA_ROLES, resolve_cameras
from egosim.stages.keypoint_render.draw import draw_skeleton_video, project_hands


@dataclasses.dataclass(frozen=True)
class KeypointRenderConfig(StageConfig):
    """Parameters of ``keypoint_render``."""

    # hand: all 21 joints; gripper: thumb + index chains; auto: per clip, gripper when every
    # valid hand's middle, ring and little joints (9-20) have confidence 0 (robot clips)
    variant: Literal["hand", "gripper", "auto"] = "hand"
    line_width_px: float = 3.0  # bone width in pixels at 0.5 m depth (scaled by 0.5 / depth)
    near: float = 0.01  # joints closer than this camera z (metres) are not projected
    crf: int = 18  # H.264 quality of the skeleton video

    def __post_init__(self) -> None:
        problems = []
        if not 0.5 <= self.line_width_px <= 32:
            problems.append(f"line_width_px must be in [0.5, 32], got {self.line_width_px}")
        if not (np.isfinite(self.near) and self.near > 0):
            problems.append(f"near must be > 0 metres, got {self.near}")
        if not 0 <= self.crf <= 51:
            problems.append(f"crf must be in [0, 51], got {self.crf}")
        if problems:
            raise ConfigError("; ".join(problems))


class KeypointRenderStage(ClipStage):
    """Project the cleaned joints with the resolved camera and draw the skeleton video."""

    name = "keypoint_render"
    description = "project hand joints with the clip's K and poses; draw the skeleton video"
    config_class = KeypointRenderConfig
    inputs: ClassVar[Mapping[str, ShardSchema]] = {"clips": CLIPS, "hands": HANDS}
    optional_inputs: ClassVar[Mapping[str, ShardSchema]] = CAMERA_ROLES  # replace the clip's camera
    output = KEYPOINTS
    backends = ("opencv",)
    # What process reads (the executor decodes nothing else): the clip's size and camera, the
    # cleaned joints.
    columns: ClassVar[Mapping[str, tuple[str, ...]]] = join_columns(
        {
            "clips": ("num_frames", "height", "width", "fps"),
            "hands": ("num_frames", "hand_joints", "hand_valid", "hand_confidence"),
        },
        CAMERA_COLUMNS,
    )
    config: KeypointRenderConfig

    def process(self, rows: Mapping[str, Mapping[str, Any]]) -> dict[str, Any]:
        """Project and draw one clip."""
        clip, hands = ClipsRecord.of(rows["clips"]), HandsRecord.of(rows["hands"])
        cid = clip.clip_id
        t, h, w = clip.size
        if hands.num_frames != t:
            raise ClipRejected(f"clip {cid!r}: hands cover {hands['num_frames']} frames, not {t}")
        cams = resolve_cameras(rows)
        poses = require_camera_poses(cams.world_from_cam, cid)  # (T, 4, 4)
        problems = se3_problems(poses)
        if problems:
            raise ClipRejected(
                f"clip {cid!r}: {cams.source} world_from_cam: " + "; ".join(problems)
            )
        valid = hands.hand_valid
        cfg = self.config
        proj = project_hands(hands.hand_joints, valid, poses, cams.intrinsics, h, w, cfg.near)
        variant = cfg.variant
        if variant == "auto":
            conf = hands.hand_confidence
            robot = valid.any() and not conf[:, :, 9:][valid].any()
            variant = "gripper" if robot else "hand"
        video = draw_skeleton_video(proj, h, w, variant, cfg.line_width_px)
        return {
            "clip_id": cid,
            "num_frames": t,
            "width": w,
            "height": h,
            "fps": clip.fps,
            "variant": variant,
            "keypoints_2d": proj.uv.astype(np.float32).reshape(t, -1).tolist(),
            "keypoint_depth": proj.depth.astype(np.float32).reshape(t, -1).tolist(),
            "keypoint_visible": proj.visible.reshape(t, -1).tolist(),
            "skeleton_video": media.encode_rgb_video(video, clip.fps, cfg.crf),
        }
