"""The ``scene_render`` stage: render each clip's scene cloud along its trajectory.

Reads the ``clips`` row (size, fps) and the points to render: the clip's ``state`` row when that
role is connected (a world state keyed by the clip, e.g. the state a simulated clip starts from;
converted by :func:`egosim.schemas.state.scene_cloud_row_from_state`), else its ``scene_cloud``
row; a clip with neither is rejected. One renderer for both. Writes a scene video and
a visibility mask video (1 = a scene point landed, a surface quad of a ``scene_cloud`` row's
depth grid covers the pixel (``mesh_max_step``, ``mesh_max_px``; not for a state, which is no
frame's grid), or a small crack between landed points was closed: ``max_crack_px``,
``max_crack_width``) made by
:func:`egosim.stages.scene_render.splat.render_point_cloud`, the same torch code on CPU and GPU.
Intrinsics and poses come from :func:`egosim.stages.common.cameras.resolve_cameras` (the optional
``poses`` or ``cameras`` inputs when connected, else the clip's own), the same rule as
``keypoint_render``, so scene and hand conditions share one camera.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any, ClassVar

import numpy as np

from egosim.pipeline import media
from egosim.pipeline.records import ClipsRecord, require_camera_poses
from egosim.pipeline.stage import ClipRejected, ClipStage, ConfigError, StageConfig, join_columns
from egosim.schemas import CLIPS, ShardSchema
from egosim.schemas.scene import SCENE_CLOUD, SCENE_RENDER, cloud_from_row
from egosim.schemas.state import STATE, scene_cloud_row_from_state
from egosim.stages.common.cameras import CAMERA_COLUMNS, CAMERA_ROLES, resolve_cameras
from egosim.stages.scene_render.splat import MESH_MODES, SplatError, render_point_cloud


@dataclasses.dataclass(frozen=True)
class SceneRenderConfig(StageConfig):
    """Parameters of ``scene_render``."""

    device: str = "cpu"  # torch device of the renderer: "cpu", "cuda", "cuda:1", ...
    max_splat_radius: int = 2  # widest square splat (pixels each side) for near points; 0 = off
    near: float = 0.01  # points closer than this camera z (metres) are skipped
    max_crack_px: int = 64  # holes inside the render up to this many pixels are closed; 0 = off
    max_crack_width: int = 4  # gaps between rendered pixels up to this wide are closed; 0 = off
    mesh_max_step: float = 0.3  # scene_cloud rows: 2x2 neighbours form a surface quad unless
    # their 1/z differ by more than this (relative); 0 = off (splats only)
    mesh_max_px: int = 32  # surface quads wider or taller than this in a frame are not drawn
    mesh_mode: str = "surface"  # "surface": quads drawn with their corners' colours blended,
    # splats only where no quad lands; "fill": quads fill only what the splats miss
    crf: int = 18  # H.264 quality of the scene video (lower = better, bigger)

    def __post_init__(self) -> None:
        problems = []
        if not self.device or self.device.split(":")[0] not in ("cpu", "cuda", "mps", "xpu"):
            problems.append(f"device must be a torch device string like 'cpu', got {self.device!r}")
        if not 0 <= self.max_splat_radius <= 8:
            problems.append(f"max_splat_radius must be in [0, 8], got {self.max_splat_radius}")
        if not 0 <= self.max_crack_width <= 16:
            problems.append(f"max_crack_width must be in [0, 16], got {self.max_crack_width}")
        if not 0 <= self.max_crack_px <= 10_000:
            problems.append(f"max_crack_px must be in [0, 10000], got {self.max_crack_px}")
        if not (np.isfinite(self.mesh_max_step) and self.mesh_max_step >= 0):
            problems.append(f"mesh_max_step must be finite and >= 0, got {self.mesh_max_step}")
        if self.mesh_mode not in MESH_MODES:
            problems.append(f"mesh_mode must be one of {MESH_MODES}, got {self.mesh_mode!r}")
        if not 1 <= self.mesh_max_px <= 4096:
            problems.append(f"mesh_max_px must be in [1, 4096], got {self.mesh_max_px}")
        if not (np.isfinite(self.near) and self.near > 0):
            problems.append(f"near must be > 0 metres, got {self.near}")
        if not 0 <= self.crf <= 51:
            problems.append(f"crf must be in [0, 51], got {self.crf}")
        if problems:
            raise ConfigError("; ".join(problems))


def points_row(rows: Mapping[str, Mapping[str, Any]]) -> Mapping[str, Any]:
    """The ``scene_cloud`` row to render for one clip: its ``state`` row converted, else its
    ``scene_cloud`` row; raises ClipRejected naming the clip when neither is given."""
    cid = rows["clips"]["clip_id"]
    if rows.get("state") is not None:
        return scene_cloud_row_from_state(rows["state"], cid)
    if rows.get("scene_cloud") is not None:
        return rows["scene_cloud"]
    raise ClipRejected(
        f"clip {cid!r}: nothing to render: no 'state' row and no 'scene_cloud' row for this clip "
        "(connect one of the two roles; a clip rejected upstream has neither)"
    )


class SceneRenderStage(ClipStage):
    """Render a scene cloud or a world state along the clip's poses: scene video, visibility."""

    name = "scene_render"
    description = "render the scene cloud or state along the trajectory: scene video + visibility"
    config_class = SceneRenderConfig
    inputs: ClassVar[Mapping[str, ShardSchema]] = {"clips": CLIPS}
    optional_inputs: ClassVar[Mapping[str, ShardSchema]] = {
        **CAMERA_ROLES,  # replace the clip's camera
        "scene_cloud": SCENE_CLOUD,  # the clip's hand-free first-frame cloud
        "state": STATE,  # a world state keyed by the clip; wins over scene_cloud
    }
    output = SCENE_RENDER
    backends = ("torch_splat",)
    # What process reads of the clip (its size and camera; the executor decodes nothing
    # else); the cloud's roles (state, scene_cloud) are read whole.
    columns: ClassVar[Mapping[str, tuple[str, ...]]] = join_columns(
        {"clips": ("num_frames", "height", "width", "fps")}, CAMERA_COLUMNS
    )
    # 3: renders a state row (optional role) as well as a scene_cloud row
    # 4: a scene_cloud row's depth grid is drawn as a surface of quads (mesh_max_step,
    #    mesh_mode "surface"; the "fill" mode came first, in no run); a point in no quad nearer
    #    than the surface is drawn over it; surface_quads written (SCENE_RENDER v3)
    version = 4
    config: SceneRenderConfig

    def process(self, rows: Mapping[str, Mapping[str, Any]]) -> dict[str, Any]:
        """Render one clip (its ``state`` row when given, else its ``scene_cloud`` row)."""
        clip = ClipsRecord.of(rows["clips"])
        cid = clip.clip_id
        cloud_row = points_row(rows)
        t, h, w = clip.size
        cams = resolve_cameras(rows)
        world_from_cam = require_camera_poses(cams.world_from_cam, cid)
        cloud = cloud_from_row(cloud_row)
        source = int(cloud_row.get("source_frame") or 0)  # the frame the cloud was unprojected from
        mesh_pose = world_from_cam[source] if 0 <= source < len(world_from_cam) else None
        cfg = self.config
        try:
            result = render_point_cloud(
                cloud.points,
                cloud.colours,
                world_from_cam,
                cams.intrinsics,
                h,
                w,
                point_size=cloud.point_size,
                max_splat_radius=cfg.max_splat_radius,
                near=cfg.near,
                device=cfg.device,
                max_crack_px=cfg.max_crack_px,
                max_crack_width=cfg.max_crack_width,
                # a state row is no frame's depth grid: no surface quads
                mesh_from_cam=None if rows.get("state") is not None else mesh_pose,
                mesh_max_step=cfg.mesh_max_step,
                mesh_max_px=cfg.mesh_max_px,
                mesh_mode=cfg.mesh_mode,
            )
        except SplatError as exc:
            raise ClipRejected(f"clip {cid!r}: {exc}") from exc
        return {
            "clip_id": cid,
            "num_frames": t,
            "width": w,
            "height": h,
            "fps": clip.fps,
            "scene_video": media.encode_rgb_video(result.rgb, clip.fps, cfg.crf),
            "visible": media.encode_mask_video(result.visible),
            "visible_fraction": result.visible.reshape(t, -1).mean(axis=1).tolist(),
            "splat_radius": cfg.max_splat_radius,
            "surface_quads": result.num_quads,
        }
