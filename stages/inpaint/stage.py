"""The ``inpaint`` stage: remove the hands from each clip's first frame.

Inputs: the ``clips`` row (frames) and the ``hand_mask`` row of the same clip. Intrinsics and
poses come from :func:`egosim.stages.common.cameras.resolve_cameras` and frame 0's depth from
:func:`egosim.stages.common.cameras.first_frame_depth`: the optional ``poses`` / ``cameras``
inputs when a workflow connects them, else the clip's own. Backends:

- ``reproject`` (default): fill from later frames reprojected through depth and pose (median of
  the first ``candidates`` frames that see a pixel and show frame 0's ring near it within
  ``local_residual``), then OpenCV inpainting for what no frame saw (see ``reproject_fill``).
  Without frame-0 depth or poses (a static camera has no depth) the later frames are aligned in
  the image instead: the identity for a static camera (the
  ``cameras`` row's ``static_camera``, or poses that do not move), which makes the fill a plain
  temporal median, else homographies fitted to features and checked round the hole (see
  ``aligned_fill``; ``aligned_confirm``, off by default, means a colour only one frame gave
  with OpenCV's). With depth
  and poses, each hole pixel then takes the per-channel median of the depth fill, the
  image-aligned fill and Telea (``vote``, see the ``vote`` module): estimated cameras can put
  the depth fill far off, and the two others fail in other ways.
  Masks grow by ``dilate_px`` plus ``dilate_fraction`` of the image diagonal
  first (motion blur, shadows and mask edges), and a hand that a later frame's mask dropped
  (masked a frame or two before or after, nothing near it in this frame) is carried into that
  frame's mask (:func:`carry_lost_hands`), so the frame does not paste it into frame 0;
- ``opencv``: OpenCV (Telea) inpainting only (the baseline);
- ``diffusers``: a diffusers inpainting pipeline from ``model_path`` (see
  ``diffusers_backend``).

Only the first frame's depth is required (frame-0 pixels are lifted with it and projected
into the later frames), so a clip without a depth column works when ``cameras`` is connected.
Of the ``cameras`` row's depth0 only the confident pixels (``confidence0`` at least
``min_depth_confidence``) count as measured; the rest is inpainted with the depth under the
hand (the plane sweep is wrong round a hand that moves, see ``reproject_fill``).
With ``depth_tolerance > 0`` the other frames' depth rejects fills that disagree with it; only
the clip has per-frame depth, so that test runs only when ``cameras`` is not connected (its
depth0 may have another scale than the clip's depth) and the clip has depth.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any, ClassVar, Literal

import cv2
import numpy as np

from egosim.pipeline import media
from egosim.pipeline.records import ClipsRecord, HandMaskRecord
from egosim.pipeline.stage import ClipRejected, ClipStage, ConfigError, StageConfig, join_columns
from egosim.schemas import CLIPS, ShardSchema
from egosim.schemas.hand_mask import HAND_MASK
from egosim.schemas.inpaint import (
    FILL_GENERATED,
    FILL_OPENCV,
    FILL_REPROJECTED,
    INPAINT,
)
from egosim.stages.common.cameras import (
    CAMERA_COLUMNS,
    CAMERA_ROLES,
    DEPTH0_COLUMNS,
    camera_is_static,
    first_frame_confidence,
    first_frame_depth,
    resolve_cameras,
)
from egosim.stages.inpaint.aligned_fill import aligned_fill
from egosim.stages.inpaint.diffusers_backend import DiffusersInpainter
from egosim.stages.inpaint.reproject_fill import (
    UNSEEN_METHODS,
    FillResult,
    InpaintInputError,
    dilate,
    opencv_fill,
    reproject_fill,
)
from egosim.stages.inpaint.vote import median_vote

STILL_TRANSLATION_M = 1e-4  # poses closer than this (and STILL_ROTATION_RAD) are a still camera
STILL_ROTATION_RAD = 1e-4


@dataclasses.dataclass(frozen=True)
class InpaintConfig(StageConfig):
    """Parameters of ``inpaint``."""

    backend: Literal["reproject", "opencv", "diffusers"] = "reproject"  # see module docstring
    dilate_px: int = 2  # hand masks grow by this many pixels before filling (soft edges)
    dilate_fraction: float = 0.008  # ... plus this fraction of the image diagonal (motion blur,
    # shadows and mask edges scale with the image: +4 px at 240x416, +7 px at 480x720)
    depth_tolerance: float = 0.0  # relative depth disagreement that rejects a fill; 0 = off
    # (off by default: the depth behind the hand is an inpainted guess, and a 5-30% test
    # rejected most good fills on the synthetic world, costing 2-4 dB)
    inpaint_radius: float = 5.0  # OpenCV inpainting neighbourhood radius, pixels
    candidates: int = 7  # later frames whose colours are medianed per pixel (1: closest only)
    unseen_method: str = "telea"  # OpenCV method for pixels no frame sees: "telea" or "ns"
    occluder_ratio: float = 0.8  # a sample nearer frame 0's hand colours than this times its
    # nearest background colour is another frame's missed hand or arm, not used (0: off)
    carry_frames: int = 2  # a hand a later frame's mask lost is carried in from frames this
    # near (either side), so that frame does not paste the hand into frame 0 (0: off)
    carry_cover: float = 0.3  # ... when less than this fraction of the nearby frame's mask
    # region lies within carry_reach of the frame's own mask (a moved hand stays near)
    carry_reach: float = 0.05  # ... a fraction of the image diagonal
    local_residual: float = 15.0  # a later frame fills only the hole pixels whose nearby ring
    # it shows within this many grey levels of frame 0 (mean; 0: off): through a homography in
    # the image-aligned fill, reprojected with frame 0's depth in the depth fill
    min_depth_confidence: float = 0.5  # frame-0 depth from the ``cameras`` row counts as
    # measured where its confidence0 is at or above this (depth_camera's confidence_threshold,
    # scene_cloud's min_confidence); the rest (round the hands above all: the plane sweep
    # matches the moving hand too) is inpainted like the depth under the hand (0: all kept)
    ring_shift_px: int = 6  # each frame's reprojection (depth fill, only with local_residual >
    # 0) or homography warp (aligned fill, always) moves by the whole-pixel shift, less than
    # this, that best aligns frame 0's ring (estimated poses drift; a whole-frame homography
    # sits off round the hole; 0: off)
    ring_shift_gain: float = 0.2  # ... kept when it lowers the ring's mean residual by this
    vote: bool = True  # depth fill: each hole pixel takes the per-channel median of the depth
    # fill, the image-aligned fill and Telea (the colour two of three agree on; false: the
    # depth fill alone; see the ``vote`` module)
    aligned_confirm: int = 1  # without depth or poses (the image-aligned fill alone), a hole
    # pixel that some but fewer than this many later frames filled takes the mean of its fill
    # and OpenCV's: one frame's sample may be a hand that stays put, its missed part pasted.
    # 1: off (the default: 2 gained only on DWM 00017, where it was chosen, and was flat or
    # worse on held-out alt and DWM 00013, and on a static camera whose one clean frame is
    # right; design.md "Inpaint v15"); not applied to the aligned fill the depth path votes on
    model_path: str = ""  # local folder of a diffusers inpainting pipeline (backend diffusers)
    device: str = "cpu"  # torch device of the diffusers pipeline
    prompt: str = "empty table, no hands"  # text prompt of the diffusers pipeline
    steps: int = 30  # diffusion steps
    guidance_scale: float = 7.5  # classifier-free guidance scale
    seed: int = 0  # diffusion noise seed

    def __post_init__(self) -> None:
        problems = []
        if not 0 <= self.dilate_px <= 64:
            problems.append(f"dilate_px must be in [0, 64], got {self.dilate_px}")
        if not 0.0 <= self.dilate_fraction <= 0.1:
            problems.append(f"dilate_fraction must be in [0, 0.1], got {self.dilate_fraction}")
        if not 0.0 <= self.depth_tolerance <= 1.0:
            problems.append(f"depth_tolerance must be in [0, 1], got {self.depth_tolerance}")
        if not 0.0 < self.inpaint_radius <= 100.0:
            problems.append(f"inpaint_radius must be in (0, 100], got {self.inpaint_radius}")
        if not 0 <= self.carry_frames <= 16:
            problems.append(f"carry_frames must be in [0, 16], got {self.carry_frames}")
        if not 0.0 <= self.carry_cover <= 1.0:
            problems.append(f"carry_cover must be in [0, 1], got {self.carry_cover}")
        if not 0.0 <= self.carry_reach <= 1.0:
            problems.append(f"carry_reach must be in [0, 1], got {self.carry_reach}")
        if not 0.0 <= self.local_residual <= 255.0:
            problems.append(f"local_residual must be in [0, 255], got {self.local_residual}")
        if not 0 <= self.ring_shift_px <= 32:
            problems.append(f"ring_shift_px must be in [0, 32], got {self.ring_shift_px}")
        if not 0.0 <= self.ring_shift_gain < 1.0:
            problems.append(f"ring_shift_gain must be in [0, 1), got {self.ring_shift_gain}")
        if not 0.0 <= self.min_depth_confidence <= 1.0:
            problems.append(
                f"min_depth_confidence must be in [0, 1], got {self.min_depth_confidence}"
            )
        if not 0.0 <= self.occluder_ratio <= 1.0:
            problems.append(f"occluder_ratio must be in [0, 1], got {self.occluder_ratio}")
        if not 1 <= self.aligned_confirm <= 32:
            problems.append(f"aligned_confirm must be in [1, 32], got {self.aligned_confirm}")
        if not 1 <= self.candidates <= 32:
            problems.append(f"candidates must be in [1, 32], got {self.candidates}")
        if self.unseen_method not in UNSEEN_METHODS:
            problems.append(
                f"unseen_method must be one of {sorted(UNSEEN_METHODS)}, got {self.unseen_method!r}"
            )
        if self.steps < 1:
            problems.append(f"steps must be >= 1, got {self.steps}")
        if self.backend == "diffusers" and not self.model_path:
            problems.append("backend 'diffusers' needs model_path (a local pipeline folder)")
        if problems:
            raise ConfigError("; ".join(problems))

    def grow_px(self, height: int, width: int) -> int:
        """Pixels a ``height x width`` clip's hand masks grow by before filling: ``dilate_px``
        plus ``dilate_fraction`` of the image diagonal."""
        return self.dilate_px + round(self.dilate_fraction * float(np.hypot(height, width)))


class InpaintStage(ClipStage):
    """Remove hands from the first frame: reprojected later frames, then OpenCV inpainting."""

    name = "inpaint"
    version = 16  # 3: median of several frames; clips without depth aligned in the image. 4: more
    # frames in the median, dilation with the image size. 5: hand-coloured samples not used.
    # 6: large holes no longer rejected (chunked sampling). 7: the image-aligned fill checks
    # each homography near every hole pixel (local_residual). 8: a hand a later frame's mask
    # dropped is carried in from nearby frames before sampling (carry_lost_hands). 9: the
    # depth fill checks each frame's reprojected ring near every hole pixel (local_residual).
    # 10: the cameras row's depth0 counts only where its confidence0 is at least
    # min_depth_confidence; the rest is inpainted with the hole's depth (and lifts the ring).
    # 11: each frame's reprojection is moved by the shift that aligns the ring (ring_shift_px).
    # 12: so is the image-aligned fill's homography warp. 13: the depth fill is voted on with
    # the image-aligned fill and Telea, per pixel (``vote``). 14: each ring shift is scored on
    # an even subsample of at most 4,000 ring points (``MAX_SHIFT_EVIDENCE``; identical fills on
    # every clip measured, HOT3D windows 40% faster). 15: without depth or poses, a hole pixel
    # that fewer than aligned_confirm (2) frames filled takes the mean of its fill and Telea.
    # 16: aligned_confirm off by default (15's fills on held-out data were flat or worse), and
    # when on it acts only where some frame filled, with unseen_method's fill (review10c)

    description = "remove hands from the first frame (reprojected frames + OpenCV inpainting)"
    config_class = InpaintConfig
    inputs: ClassVar[Mapping[str, ShardSchema]] = {"clips": CLIPS, "hand_mask": HAND_MASK}
    optional_inputs: ClassVar[Mapping[str, ShardSchema]] = CAMERA_ROLES  # replace the clip's camera
    output = INPAINT
    backends = ("reproject", "opencv", "diffusers")
    # What process reads (the executor decodes nothing else): the frames and per-frame depth of
    # the clip, the hand masks, the camera and frame-0 depth (shared rules of common.cameras).
    columns: ClassVar[Mapping[str, tuple[str, ...]]] = join_columns(
        {
            "clips": ("num_frames", "height", "width", "video", "depth", "depth_unit_m"),
            "hand_mask": ("num_frames", "height", "width", "hand_mask"),
        },
        CAMERA_COLUMNS,
        DEPTH0_COLUMNS,
        {"cameras": ("confidence0",)},  # which of depth0 is measured (min_depth_confidence)
    )

    def __init__(self, config: StageConfig | None = None) -> None:
        super().__init__(config)
        self._diffusers: DiffusersInpainter | None = None

    def fill(
        self,
        frames: np.ndarray,
        hand_mask: np.ndarray,
        world_from_cam: np.ndarray | None,
        intrinsics: np.ndarray,
        depth0: np.ndarray | None,
        clip_id: str = "",
        depth: np.ndarray | None = None,
        static_camera: bool = False,
        depth0_confidence: np.ndarray | None = None,
    ) -> FillResult:
        """Hand-free first frame of ``frames (T, H, W, 3)`` given ``hand_mask (T, H, W)``.

        ``world_from_cam (T, 4, 4)``, ``intrinsics (4,)``, ``depth0 (H, W)`` metres (frame 0);
        ``depth (T, H, W)`` feeds the agreement test when ``depth_tolerance > 0``. Without
        ``depth0`` or poses the image-aligned fill runs (identity when ``static_camera``); with
        them the depth fill, and with ``vote`` each hole pixel takes the per-channel median of
        the depth fill, the image-aligned fill and Telea (:mod:`.vote`).
        ``depth0_confidence (H, W)`` in [0, 1] (the ``cameras`` row's ``confidence0``): depth0
        below ``min_depth_confidence`` is not trusted (None: all of depth0 is).
        """
        cfg: InpaintConfig = self.config  # type: ignore[assignment]
        h, w = frames.shape[1:3]
        grow = cfg.grow_px(h, w)
        target = dilate(hand_mask[0] > 0, grow)  # (H, W)
        zeros16 = np.zeros((h, w), np.uint16)

        def telea(hole: np.ndarray) -> FillResult:  # OpenCV alone over ``hole (H, W)`` bool
            image = opencv_fill(frames[0], hole, cfg.inpaint_radius)
            return FillResult(image, (hole * FILL_OPENCV).astype(np.uint8), zeros16, hole)

        if cfg.backend == "opencv":
            return telea(target > 0)
        if cfg.backend == "diffusers":
            if self._diffusers is None:
                self._diffusers = DiffusersInpainter(
                    cfg.model_path, cfg.device, cfg.prompt, cfg.steps, cfg.guidance_scale, cfg.seed
                )
            image = self._diffusers.inpaint(frames[0], target)
            source = (target * FILL_GENERATED).astype(np.uint8)
            return FillResult(image, source, zeros16, target > 0)
        hand_mask = carry_lost_hands(hand_mask, cfg.carry_frames, cfg.carry_cover, cfg.carry_reach)
        measured = None  # (H, W) depth0 pixels kept as measured; None = every known one
        if depth0_confidence is not None and cfg.min_depth_confidence > 0:
            measured = depth0_confidence >= cfg.min_depth_confidence
        still = static_camera or (world_from_cam is not None and _still(world_from_cam))

        def image_aligned(confirm: int = 1) -> FillResult:
            return aligned_fill(
                frames,
                hand_mask,
                static_camera=still,
                dilate_px=grow,
                candidates=cfg.candidates,
                inpaint_radius=cfg.inpaint_radius,
                unseen_method=cfg.unseen_method,
                occluder_ratio=cfg.occluder_ratio,
                local_residual=cfg.local_residual,
                shift_px=cfg.ring_shift_px,
                shift_gain=cfg.ring_shift_gain,
                confirm=confirm,
            )

        if depth0 is None or world_from_cam is None:
            return image_aligned(cfg.aligned_confirm)
        try:
            result = reproject_fill(
                frames,
                hand_mask,
                depth0,
                world_from_cam,
                intrinsics,
                depth=depth if cfg.depth_tolerance > 0 else None,
                dilate_px=grow,
                depth_tolerance=cfg.depth_tolerance,
                inpaint_radius=cfg.inpaint_radius,
                candidates=cfg.candidates,
                unseen_method=cfg.unseen_method,
                occluder_ratio=cfg.occluder_ratio,
                local_residual=cfg.local_residual,
                measured=measured,
                shift_px=cfg.ring_shift_px,
                shift_gain=cfg.ring_shift_gain,
            )
        except InpaintInputError as exc:
            raise ClipRejected(f"clip {clip_id!r}: {exc}") from exc
        if not cfg.vote or not result.filled.any():
            return result
        return median_vote([result, image_aligned(), telea(result.filled)])

    def process(self, rows: Mapping[str, Mapping[str, Any]]) -> dict[str, Any]:
        """The inpainted first frame of one clip; see the module docstring."""
        cfg: InpaintConfig = self.config  # type: ignore[assignment]
        clip = ClipsRecord.of(rows["clips"])
        mask = HandMaskRecord.of(rows["hand_mask"])
        clip_id, size = clip.clip_id, clip.size
        if mask.size != size:
            raise ClipRejected(
                f"clip {clip_id!r}: hand_mask shape {mask.size} does not match the clip {size}"
            )
        depth0 = first_frame_depth(rows) if cfg.backend == "reproject" else None  # (H, W)
        cam_row = rows.get("cameras")
        confidence = None  # (H, W) of the cameras row's depth0, the depth first_frame_depth took
        if depth0 is not None and cam_row is not None and cam_row.get("depth0") is not None:
            confidence = first_frame_confidence(rows, depth0.shape)
        static = camera_is_static(rows)
        cams = resolve_cameras(rows)
        # Per-frame depth (agreement test) only from the clip, and only when no other role
        # supplies the cameras' depth (see the module docstring).
        per_frame = cfg.depth_tolerance > 0 and cam_row is None
        result = self.fill(
            clip.frames,  # (T, H, W, 3), checked against the clip's size
            mask.hand_mask,  # (T, H, W), checked against the mask row's (= the clip's) size
            cams.world_from_cam,
            cams.intrinsics,
            depth0,
            clip_id,
            clip.depth if per_frame else None,
            static,
            confidence,
        )
        n = int(result.filled.sum())
        counts = np.bincount(result.fill_source[result.filled], minlength=4)  # (4,)
        frac = counts / n if n else np.zeros(4)
        return {
            "clip_id": clip_id,
            "width": clip.width,
            "height": clip.height,
            "first_frame": media.encode_png(result.image),
            "fill_source": media.encode_png(result.fill_source),
            "source_frame": media.encode_png(result.source_frame),
            "masked_fraction": n / result.filled.size,
            "reprojected_fraction": float(frac[FILL_REPROJECTED]),
            "opencv_fraction": float(frac[FILL_OPENCV]),
            "generated_fraction": float(frac[FILL_GENERATED]),
            "backend": cfg.backend,
        }


def carry_lost_hands(
    hand_mask: np.ndarray, window: int, min_cover: float = 0.3, reach: float = 0.05
) -> np.ndarray:
    """``hand_mask (T, H, W)`` with hands a frame's mask lost carried in from nearby frames.

    A connected region of frame ``n``'s mask (``0 < |n - k| <= window``) of which less than
    ``min_cover`` lies within ``reach`` (a fraction of the image diagonal) of frame ``k``'s own
    mask is a hand that frame ``k``'s mask dropped (a detection dropout: a hand that moved
    still has its mask nearby); the region is added to frame ``k``'s mask, so frame ``k`` does
    not fill frame 0 with that hand. Frame 0 keeps its own mask (it decides what is filled).
    """
    own = (hand_mask > 0).astype(np.uint8)  # (T, H, W)
    out = own.copy()
    t, h, w = own.shape
    if window <= 0 or t < 2:
        return out
    radius = max(1.0, reach * float(np.hypot(h, w)))
    # frame -> its labels (H, W) int32 and each region's box and size (x, y, w, h, area), kept
    # for the frames within window of k only (all T at once, 4 bytes a pixel, outweighed the
    # clip's RGB frames)
    parts: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    for k in range(1, t):
        lo, hi = max(0, k - window), min(t, k + window + 1)
        for n in [n for n in parts if n < lo]:
            del parts[n]
        for n in range(lo, hi):
            if n not in parts:
                parts[n] = cv2.connectedComponentsWithStats(own[n], connectivity=8)[1:3]
        near = None  # (H, W) within reach of frame k's mask, made when first needed
        for n in range(lo, hi):
            labels, stats = parts[n]
            if n == k or len(stats) <= 1:
                continue
            if near is None:
                far = cv2.distanceTransform(1 - own[k], cv2.DIST_L2, 3)  # (H, W) px to mask
                near = far <= radius
            for i, (x, y, bw, bh, area) in enumerate(stats[1:], start=1):
                box = np.s_[y : y + bh, x : x + bw]
                region = labels[box] == i  # (bh, bw)
                if np.count_nonzero(near[box] & region) < min_cover * area:
                    out[k][box] |= region.astype(np.uint8)
    return out


def _still(world_from_cam: np.ndarray) -> bool:
    """Whether every pose of ``world_from_cam (T, 4, 4)`` equals the first (a still camera)."""
    rel = np.linalg.inv(world_from_cam[0]) @ world_from_cam  # (T, 4, 4)
    angle = np.arccos(np.clip((np.trace(rel[:, :3, :3], axis1=1, axis2=2) - 1) / 2, -1, 1))
    return bool(
        np.all(np.linalg.norm(rel[:, :3, 3], axis=1) < STILL_TRANSLATION_M)
        and np.all(angle < STILL_ROTATION_RAD)
    )
