"""The ``state_fusion`` stage: the world state after a clip, interaction-aware.

Inputs (joined on ``clip_id``): ``clips`` (frames and per-frame ``depth``), ``hands`` (3D joints:
the hand boxes of the interaction test are their projections), ``hand_mask`` (hands and arms,
dilated and left out of the state); optional ``poses`` / ``cameras`` (the clip's cameras by the
shared rule of :func:`egosim.stages.common.cameras.resolve_cameras`) and ``previous_state`` (the
state the clip starts from, a ``state`` row keyed by this clip's id: in simulation, the state the
clip was generated from), or else ``scene_cloud`` (the clip's hand-free first frame as the state
before it: :func:`initial_state`; the first update of a dataset clip through the runner).

Depth (``depth_source``): the clip's own per-frame ``depth`` column (the synthetic world, EgoDex,
MCAP with depth) or, when the clip has none (a generated clip, most real video) or
``depth_source`` is ``estimate``, a plane sweep of every ``sweep_stride``-th frame with the
clip's resolved cameras (:mod:`.depth`, the ``depth_camera`` sweep moved to
``stages/common/plane_sweep.py``): only depth is estimated, over the depth range of the
``cameras`` row's ``depth0``, else of the previous state seen from the clip's cameras (when those
are the clip's own, i.e. in the state's frame), else ``sweep_depth_range``; hand pixels get their
joints' depth for the interaction test. ``depth_source: clip`` rejects a clip without depth.
When the cameras come from the ``cameras`` role and it has ``depth0`` in another scale than the
clip's depth, the clip's depth is brought to the cameras' scale by the median ratio over frame 0.

Registration: when the cameras come from ``poses``/``cameras`` and the clip also carries its own
``world_from_cam`` (the action's trajectory, in the previous state's world frame), the Sim3 from
the former to the latter registers the clip (orientations and centres); otherwise the clip's
cameras are taken to be in the state's frame already (identity, recorded).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping
from typing import Any, ClassVar

import numpy as np

from egosim.pipeline.geometry import project_world_points
from egosim.pipeline.records import (
    ClipsRecord,
    DepthCameraRecord,
    HandMaskRecord,
    HandsRecord,
    InputsDisagree,
    require_camera_poses,
)
from egosim.pipeline.stage import ClipRejected, ClipStage, StageError, join_columns
from egosim.schemas import CLIPS, ShardSchema
from egosim.schemas.hand_mask import HAND_MASK
from egosim.schemas.hands import HANDS
from egosim.schemas.scene import SCENE_CLOUD
from egosim.schemas.state import STATE
from egosim.stages.common.cameras import CAMERA_COLUMNS, CAMERA_ROLES, resolve_cameras
from egosim.stages.common.plane_sweep import PlaneSweepError
from egosim.stages.state_fusion.config import StateFusionConfig
from egosim.stages.state_fusion.depth import (
    estimate_clip_depth,
    fill_hand_depth,
    prior_depth_range,
    state_depths,
)
from egosim.stages.state_fusion.fusion import (
    SOURCE_PREVIOUS,
    FusionError,
    Observation,
    State,
    fuse_state,
)
from egosim.stages.state_fusion.segmenters import Segmenter, SegmenterError, build_segmenter
from egosim.stages.state_fusion.state_io import row_from_state, state_from_row


def hand_boxes(
    joints: np.ndarray, valid: np.ndarray, world_from_cam: np.ndarray, intrinsics: np.ndarray
) -> np.ndarray:
    """Hand boxes ``(T, 2, 4)`` ``x0, y0, x1, y1`` from joints ``(T, 2, 21, 3)`` (paper, supp. 3).

    Each box is the bounding box of the hand's projected keypoints; NaN where the hand is not
    valid or lies behind the camera.
    """
    t = joints.shape[0]
    boxes = np.full((t, joints.shape[1], 4), np.nan)
    for k in range(t):
        for h in range(joints.shape[1]):
            if not valid[k, h]:
                continue
            uv, z = project_world_points(joints[k, h], world_from_cam[k], intrinsics)  # (21, 2)
            if not np.all(z > 0):
                continue
            boxes[k, h] = [*uv.min(0), *uv.max(0)]
    return boxes


def _size_problems(clip: ClipsRecord, hands: HandsRecord, mask: HandMaskRecord) -> list[str]:
    """Every way the ``hands`` and ``hand_mask`` rows' sizes differ from the clip's."""
    t, h, w = clip.size
    problems = []
    if mask.size != (t, h, w):
        problems.append(
            f"hand_mask has {mask.num_frames} frames of {(mask.height, mask.width)}, "
            f"clip has {t} of {(h, w)}"
        )
    if hands.num_frames != t:
        problems.append(f"hands has {hands.num_frames} frames, clip has {t}")
    return problems


def _decoded(read: Callable[[], np.ndarray | None], problems: list[str]) -> np.ndarray | None:
    """``read()`` (a record's media accessor), or None with its size problem added to
    ``problems`` (so that every disagreement is reported at once)."""
    try:
        return read()
    except InputsDisagree as exc:
        problems.append(exc.problem)
        return None


def observation_from_rows(
    rows: Mapping[str, Mapping[str, Any]],
    config: StateFusionConfig,
    previous: State | None = None,
) -> Observation:
    """Decode one clip's rows into an :class:`Observation`; raises ClipRejected when unusable.

    ``previous`` (the state the clip starts from) bounds the depth range of an estimated depth.
    The rows are read through their records (plain mappings are wrapped, ``Record.of``).
    """
    clip = ClipsRecord.of(rows["clips"])
    hands, mask = HandsRecord.of(rows["hands"]), HandMaskRecord.of(rows["hand_mask"])
    cid, h, w = clip.clip_id, clip.height, clip.width
    estimate = config.depth_source == "estimate" or (
        config.depth_source == "auto" and clip.get("depth") is None
    )
    if not estimate and clip.get("depth") is None:
        raise ClipRejected(
            f"clip {cid!r}: no per-frame depth (the clip's depth column is null) and "
            "depth_source is 'clip'; use 'auto' or 'estimate' to sweep it from the cameras"
        )
    cams = resolve_cameras(rows)  # in every camera role, by the shared rule
    world_from_cam = require_camera_poses(cams.world_from_cam, cid)
    # Each medium is checked against its row's size when decoded, the rows' sizes against
    # the clip's; every problem is listed at once.
    problems: list[str] = []
    frames = _decoded(lambda: clip.frames, problems)  # (T, H, W, 3)
    depth = None if estimate else _decoded(lambda: clip.depth, problems)  # (T, H, W) metres
    hand_mask = _decoded(lambda: mask.hand_mask, problems)  # (T, H, W)
    problems += _size_problems(clip, hands, mask)
    if problems:
        raise ClipRejected(f"clip {cid!r}: inputs disagree: " + "; ".join(problems))
    assert frames is not None and hand_mask is not None  # else a problem was raised above
    masks = hand_mask > 0
    cam_row = rows.get("cameras")
    depth0 = None  # the cameras' frame-0 depth (their scale), when they are the cameras used
    if cams.source != "clips" and cam_row is not None:
        depth0 = DepthCameraRecord.of(cam_row).depth0
    joints, valid = hands.hand_joints, hands.hand_valid  # (T, 2, 21, 3), (T, 2)
    boxes = hand_boxes(joints, valid, world_from_cam, cams.intrinsics)  # 2D: every valid hand
    lifted = hands.hand_lifted  # (T, 2) the hands whose depth and 3D contact can be trusted
    if estimate:
        prior = depth0
        if prior is None and previous is not None and cams.source == "clips":
            prior = state_depths(previous.points, world_from_cam, cams.intrinsics, (h, w))
        near_far = prior_depth_range(prior, config)
        try:
            depth = estimate_clip_depth(
                frames, masks, cams.intrinsics, world_from_cam, near_far, config
            )
        except PlaneSweepError as exc:
            raise ClipRejected(f"clip {cid!r}: per-frame depth by plane sweep: {exc}") from exc
        depth = fill_hand_depth(
            depth, masks, joints, lifted, boxes, world_from_cam, cams.intrinsics
        )
    elif depth0 is not None:
        both = (depth0 > 0) & (depth[0] > 0)
        if both.sum() < 100:
            raise ClipRejected(f"clip {cid!r}: depth0 and depth share {int(both.sum())} pixels")
        depth = depth * np.float32(np.median(depth0[both] / depth[0][both]))
    reference = None  # the clip's own trajectory, when the cameras came from another role
    if cams.source != "clips" and clip.world_from_cam is not None:
        reference = np.array(clip.world_from_cam)  # a copy: the record keeps its parse
    return Observation(
        clip_id=cid,
        frames=frames,
        depth=depth.astype(np.float32),
        hand_mask=masks,
        hand_boxes=boxes,
        intrinsics=cams.intrinsics,
        world_from_cam=world_from_cam,
        reference_world_from_cam=reference,
        depth_estimated=estimate,
        hand_joints=np.where(lifted[:, :, None, None], joints, np.nan),
        hand_valid=lifted,
    )


def initial_state(cloud_row: Mapping[str, Any], obs: Observation) -> State:
    """The state before a clip from its ``scene_cloud`` row (the hand-free first frame).

    Every point is background carried from before (no instances yet); the cloud's camera is
    the clip's frame 0, in the frame of the clip's cameras (``scene_cloud`` uses the same
    camera rule), so no registration is needed.
    """
    n = int(cloud_row["num_points"])
    return State(
        clip_id=obs.clip_id,  # previous_clip_id == clip_id: the state before was its own cloud
        previous_clip_id=None,
        world_frame=obs.clip_id,
        num_frames=1,
        points=np.frombuffer(cloud_row["points_xyz"], dtype="<f4").reshape(n, 3).copy(),
        colours=np.frombuffer(cloud_row["points_rgb"], dtype=np.uint8).reshape(n, 3).copy(),
        point_size=np.frombuffer(cloud_row["point_size"], dtype="<f4").copy(),
        instance=np.zeros(n, np.int32),
        source=np.full(n, SOURCE_PREVIOUS, np.uint8),
        instances=[],
        intrinsics=np.asarray(obs.intrinsics, np.float64),
        width=obs.frames.shape[2],
        height=obs.frames.shape[1],
        world_from_cam=obs.world_from_cam[:1].copy(),
        camera_frames=[f"{obs.clip_id}:0"],
        previous_from_clip=np.eye(4),
        sim3_scale=1.0,
        registration_rms=None,
    )


class StateFusionStage(ClipStage):
    """Fuse a clip into the world state: objects, interaction test, TSDF, Sim3, cleaning."""

    name = "state_fusion"
    description = "interaction-aware state update: TSDF background, moved objects, Sim3, cleaning"
    config_class = StateFusionConfig
    inputs: ClassVar[Mapping[str, ShardSchema]] = {
        "clips": CLIPS,
        "hands": HANDS,
        "hand_mask": HAND_MASK,
    }
    optional_inputs: ClassVar[Mapping[str, ShardSchema]] = {
        **CAMERA_ROLES,
        "previous_state": STATE,
        "scene_cloud": SCENE_CLOUD,  # the initial state when there is no previous_state
    }
    output = STATE
    # 2: a clip without per-frame depth is fused from a plane sweep (was rejected);
    # 3: objects a closed hand lifts and puts down are carried by its motion (carry.py);
    # 4: the support plane by seeded RANSAC (fusion.ransac_plane): the same state on every run
    # 5: hands trusted in 2D only (hands' hand_lifted False) neither fill depth nor carry objects
    version = 5
    backends = ("geometric", "grounded_sam")
    # What process reads (the executor decodes nothing else): the clip's frames, depth and
    # camera, the cleaned joints, the hand masks; the state roles are read whole.
    columns: ClassVar[Mapping[str, tuple[str, ...]]] = join_columns(
        {
            "clips": ("num_frames", "height", "width", "video", "depth", "depth_unit_m"),
            "hands": ("num_frames", "hand_joints", "hand_valid", "hand_lifted"),
            "hand_mask": ("num_frames", "height", "width", "hand_mask"),
            "cameras": ("depth0", "depth_unit_m"),
        },
        CAMERA_COLUMNS,
    )
    config: StateFusionConfig
    segmenter: Segmenter | None = None  # grounded_sam: built on first use; one set here wins

    def process(self, rows: Mapping[str, Mapping[str, Any]]) -> dict[str, Any]:
        """The ``state`` row of one clip (see the module docstring)."""
        cid = rows["clips"]["clip_id"]
        prev_row = rows.get("previous_state")
        previous = state_from_row(prev_row) if prev_row is not None else None
        obs = observation_from_rows(rows, self.config, previous)
        if previous is None and rows.get("scene_cloud") is not None:
            previous = initial_state(rows["scene_cloud"], obs)
            obs = dataclasses.replace(obs, reference_world_from_cam=None)  # its frame already
        if self.segmenter is None and self.config.backend != "geometric":
            try:
                self.segmenter = build_segmenter(self.config)
            except SegmenterError as exc:
                raise StageError(f"state_fusion: {exc}") from exc
        try:
            state = fuse_state(obs, previous, self.config, self.segmenter)
        except FusionError as exc:
            raise ClipRejected(f"clip {cid!r}: {exc}") from exc
        row = row_from_state(state)
        STATE.validate_row(row, f"clip {cid!r} state")
        return row
