"""The ``hand_mask`` stage: hand-and-arm masks for every frame of a clip.

Keypoints: 3D hand joints (world metres) projected with the shared geometry; joints below
``min_joint_confidence`` are dropped. The joints are the optional ``hands`` input's
(de-duplicated and de-spiked by the ``hands`` stage) when a workflow connects it, else the clip's
own ``hand_joints``. Intrinsics and poses come from
:func:`egosim.stages.common.cameras.resolve_cameras`: the optional ``poses`` or ``cameras``
inputs when connected, else the clip's own.

Backends:

- ``keypoints`` (default): masks in image space with no assumption about the world's axes (see
  ``arm_region``): the hand as capsules round its projected keypoints, the arm as the region of
  the sleeve's or skin's colour connected to the wrist, found by GrabCut seeded with the hand
  skeleton and a strip beyond the wrist along the arm's image direction (searched round the
  hand's own, wrist minus middle knuckle, by colour, then re-aimed along the arm-coloured
  region; an arm whose direction swings away for a few frames and back, between frames that
  agree, is drawn along theirs: see ``arm_region.steady_directions``; in the first frame of a
  hand's track, which that cannot reach, a strip that stands out from both of its sides, not
  only on average, is preferred when it is another direction; an arm on the other hand's side
  at a track's end holds the direction of the track's frame next to it; an arm that would run
  up to the top border is not drawn: forearms enter a head-worn view from the bottom or the
  sides; in a dim frame the arm's colour region is read from the frame lifted to
  ``dark_floor``); a hand the keypoints miss
  in a frame is first carried there from the nearest frame
  that found it (at most ``carry_frames`` away) by tracking its pixels (see ``carry``); then
  each hand's mask is carried by optical flow up to ``propagate_frames`` frames backwards and
  forwards into the frames that missed that hand, and into those it was carried into by
  tracking, joined to their own mask (see ``propagate``), and into a short run of frames whose
  arm search found no colour region while a neighbour's did and the hand barely moved (a dark
  sleeve on a dark floor, found in one frame and not the next): a hand still missed, an arm that
  enters later or the arm of a carried hand is masked there too; only the certain seeds
  (keypoint skeleton, arm strip) travel with confidence, so a background patch wrongly joined
  to a hand in one frame is not carried into frames without a hand. Last, each hand's mask
  grows by at most ``grow_margin_m`` (at the hand's scale) into the pixels round it whose colour
  is more like the hand's than the nearby background's (see ``grow``): the few-pixel band that
  average-sized capsules, GrabCut's downscaling and motion blur leave round a real hand.
- ``sam``: a SAM-family model from ``sam_model_path`` through transformers, prompted with the
  keypoints and the capsule mask's box (see ``sam``).

With the ``keypoints`` backend the clip's black border (pixels black in every frame: a
letterbox bar with its compression ringing, the outside of a fisheye circle; see ``border``) is
never masked: it is not picture.

A robot clip's ``embodiment_mask`` (the arm's silhouette ingest rendered from its URDF and joint
states, clips v4) is added to every backend's masks: the arm is removed from the hand-free first
frame and the scene like a human arm.

A clip without hand joints or poses is rejected; frames where no hand is valid get empty masks.
"""

from __future__ import annotations

import dataclasses
import itertools
from collections.abc import Mapping
from typing import Any, ClassVar, Literal

import numpy as np

from egosim.pipeline import media
from egosim.pipeline.geometry import project_world_points
from egosim.pipeline.records import Clip, ClipsRecord, HandArraysRecord, HandsRecord
from egosim.pipeline.stage import (
    ClipRejected,
    ClipStage,
    ConfigError,
    StageConfig,
    join_columns,
)
from egosim.schemas import CLIPS, ShardSchema
from egosim.schemas.hand_mask import HAND_MASK
from egosim.schemas.hands import HANDS
from egosim.stages.common.cameras import (
    CAMERA_COLUMNS,
    CAMERA_ROLES,
    STATIC_COLUMNS,
    camera_is_static,
    resolve_cameras,
)
from egosim.stages.hand_mask.arm_region import (
    ArmParams,
    arms_through_top,
    crosses_other_wrist,
    hand_labels,
    hand_length_px,
    masks_from_labels,
    off_side_runs,
    steady_directions,
    true_runs,
)
from egosim.stages.hand_mask.border import BorderParams, not_image
from egosim.stages.hand_mask.capsules import CapsuleParams, draw_hand, draw_hands
from egosim.stages.hand_mask.carry import CarryParams, carry_keypoints
from egosim.stages.hand_mask.grow import GrowParams, grow_masks
from egosim.stages.hand_mask.propagate import PropagationParams, propagate_hands
from egosim.stages.hand_mask.sam import SamSegmenter, mask_box


@dataclasses.dataclass(frozen=True)
class HandMaskConfig(StageConfig):
    """Parameters of ``hand_mask``."""

    backend: Literal["keypoints", "sam"] = "keypoints"  # mask maker (see module docstring)
    radius_scale: float = 1.0  # multiplies the average adult bone and forearm radii
    forearm: bool = True  # look for the arm beyond the wrist (False: hands only)
    colour_refine: bool = True  # GrabCut with colour models (False: capsules and arm band only)
    fan_half_angle_deg: float = 55.0  # probable-background fan either side of the arm direction
    grabcut_iterations: int = 3  # GrabCut iterations per frame
    grabcut_max_side: int = 256  # GrabCut works on a region downscaled to this longest side
    carry_frames: int = 8  # track a missed hand's keypoints this many frames from a frame
    # that found it, backwards and forwards (0: off; see carry); also the longest run of arms
    # up to the top border left undrawn for their neighbours' mask (short_top_runs; 0: none)
    propagate_frames: int = 8  # carry each hand's mask this many frames backwards and forwards
    # in time by optical flow, into frames that missed that hand (0 or colour_refine False:
    # off; see propagate)
    grow_margin_m: float = 0.012  # each hand's mask grows this far (metres at the hand's
    # scale) into pixels of the hand's colour rather than the nearby background's (0 or
    # colour_refine False: off; see grow)
    min_joint_confidence: float = 0.0  # joints with lower confidence are ignored
    border: bool = True  # the clip's black border (pixels black in every frame: a letterbox
    # bar, the outside of a fisheye circle; see border) is never masked by the keypoints
    # backend (False: border pixels are masked like any other)
    weak_arm_frames: int = 8  # a run of at most this many frames of a hand whose arm has no
    # colour region (no strip stands out from its sides: a dark sleeve on a dark floor), next
    # to a frame of that hand with one, receives that hand's mask from its neighbours by
    # propagation, joined to its own (weak_arm_runs; 0 or propagate_frames 0: off)
    weak_arm_move: float = 0.5  # ... only while the wrist moves at most this many hand lengths
    # per frame from that neighbour through the run (the hand barely moved)
    weak_arm_share: float = 0.5  # ... and only frames whose own arm (the hand's mask outside
    # its capsules) is under this share of that neighbour's, which must show at least the
    # capsules' area of arm (the arm was lost, not found by GrabCut without the region)
    weak_arm_agree: float = 1.3  # ... and only from a neighbour whose arm is at most this
    # many times the arm of the frame beyond it (a one-frame outlier is not spread)
    dark_floor: float = 70.0  # a frame whose upper-quartile lightness (OpenCV 8-bit Lab L) is
    # below this is lifted by a gamma to it before the arm's colour region is read (its walk
    # and region tolerances are absolute Lab units, and a dim frame's shadows all lie within
    # them of a dark strip); the direction search and GrabCut read the frame as it is (0: off;
    # see arm_region.lift_dark)
    no_arm_from_top: bool = True  # an arm whose ray from the wrist leaves through the top
    # border is not drawn (forearms enter a head-worn view from the bottom or the sides; see
    # arm_region.leaves_through_top). Off for fixed or third-person cameras: an arm may enter
    # from the top. Never applied to a clip whose cameras row says the camera is static.
    sam_model_path: str = ""  # local folder of a SAM model (backend "sam")
    sam_device: str = "cpu"  # torch device of the SAM model

    def __post_init__(self) -> None:
        problems = []
        if not 0.1 <= self.radius_scale <= 10.0:
            problems.append(f"radius_scale must be in [0.1, 10], got {self.radius_scale}")
        if not 0.0 <= self.fan_half_angle_deg <= 89.0:
            problems.append(f"fan_half_angle_deg must be in [0, 89], got {self.fan_half_angle_deg}")
        if self.grabcut_iterations < 1:
            problems.append(f"grabcut_iterations must be >= 1, got {self.grabcut_iterations}")
        if not 0 <= self.carry_frames <= 1000:
            problems.append(f"carry_frames must be in [0, 1000], got {self.carry_frames}")
        if not 0 <= self.propagate_frames <= 1000:
            problems.append(f"propagate_frames must be in [0, 1000], got {self.propagate_frames}")
        if not 0.0 <= self.grow_margin_m <= 0.025:
            problems.append(f"grow_margin_m must be in [0, 0.025], got {self.grow_margin_m}")
        if not 0 <= self.weak_arm_frames <= 1000:
            problems.append(f"weak_arm_frames must be in [0, 1000], got {self.weak_arm_frames}")
        if not 1.0 <= self.weak_arm_agree <= 100.0:
            problems.append(f"weak_arm_agree must be in [1, 100], got {self.weak_arm_agree}")
        if not 0.0 <= self.weak_arm_share <= 1.0:
            problems.append(f"weak_arm_share must be in [0, 1], got {self.weak_arm_share}")
        if not 0.0 <= self.dark_floor <= 255.0:
            problems.append(f"dark_floor must be in [0, 255], got {self.dark_floor}")
        if not 0.0 <= self.weak_arm_move <= 10.0:
            problems.append(f"weak_arm_move must be in [0, 10], got {self.weak_arm_move}")
        if self.grabcut_max_side < 16:
            problems.append(f"grabcut_max_side must be >= 16, got {self.grabcut_max_side}")
        if not 0.0 <= self.min_joint_confidence <= 1.0:
            problems.append(
                f"min_joint_confidence must be in [0, 1], got {self.min_joint_confidence}"
            )
        if self.backend == "sam" and not self.sam_model_path:
            problems.append("backend 'sam' needs sam_model_path (a local folder of weights)")
        if problems:
            raise ConfigError("; ".join(problems))


def padding(image: np.ndarray, level: int = 2) -> np.ndarray:
    """``(H, W)`` bool: letterbox bars of ``image (H, W, 3)``, which are not part of the picture.

    Whole rows (from the top and bottom edges) and whole columns (from the left and right)
    whose every pixel is at most ``level`` in every channel, contiguous from the edge: a
    video padded to another aspect ratio (HOT3D's 480 x 832 frames end in a 32-row black
    bar). GrabCut, propagation and growth join it to a dark arm or floor; it is never hand.
    """
    dark = image.max(axis=2) <= level  # (H, W)
    out = np.zeros(dark.shape, bool)
    for axis in (0, 1):
        line = dark.all(axis=1 - axis)  # (H,) rows for axis 0, (W,) columns for axis 1
        n = len(line)
        first = n if line.all() else int(np.argmin(line))  # bar length from the start
        last = n if line.all() else int(np.argmin(line[::-1]))  # ... and from the end
        bar = np.zeros(n, bool)
        bar[:first] = True
        bar[n - last :] = True
        out |= bar[:, None] if axis == 0 else bar[None, :]
    return out


def short_top_runs(top: np.ndarray, valid: np.ndarray, max_run: int) -> np.ndarray:
    """``(T, K)`` bool: the frames of ``top (T, K)`` (arms that would run up to the top border)
    in runs of at most ``max_run`` consecutive frames of a hand with a frame of the same hand
    next to the run that is ``valid (T, K)`` and not in ``top`` (a source for propagation).
    """
    out = np.zeros(top.shape, bool)
    n = len(top)
    for k in range(top.shape[1]):
        for t, end in true_runs(top[:, k]):
            source = (t > 0 and valid[t - 1, k]) or (end < n and valid[end, k])
            if end - t <= max_run and source:
                out[t:end, k] = True
    return out


def arm_areas(
    per_hand: np.ndarray, keypoints: np.ndarray, valid: np.ndarray, capsule: CapsuleParams
) -> tuple[np.ndarray, np.ndarray]:
    """``(arm_px (T, K), hand_px (T, K))``: pixels of each hand's mask ``per_hand (T, K, H,
    W)`` outside its own capsules (drawn round ``keypoints (T, K, 21, 2)`` without a forearm),
    and the capsules' own pixels; 0 where ``valid (T, K)`` is False."""
    t_count, k_count, h, w = per_hand.shape
    arm_px = np.zeros((t_count, k_count), np.int64)
    hand_px = np.zeros((t_count, k_count), np.int64)
    params = CapsuleParams(capsule.radius_scale, forearm=False)
    for t, k in zip(*np.nonzero(valid), strict=True):
        hand = draw_hand(np.asarray(keypoints[t, k], np.float64), 0, h, w, params)[0] > 0
        hand_px[t, k] = int(hand.sum())
        arm_px[t, k] = int((per_hand[t, k].astype(bool) & ~hand).sum())
    return arm_px, hand_px


def weak_arm_runs(
    weak: np.ndarray,
    valid: np.ndarray,
    keypoints: np.ndarray,
    arm_px: np.ndarray,
    hand_px: np.ndarray,
    max_run: int,
    max_move: float,
    max_share: float,
    max_ratio: float = 1.3,
) -> np.ndarray:
    """``(T, K)`` bool: the frames of ``weak (T, K)`` (hands whose arm has no colour region)
    that lost their arm, to be opened to their neighbours' masks of that hand.

    A run of at most ``max_run`` consecutive weak frames of a hand, next to a frame of the same
    hand that is ``valid (T, K)``, not weak and shows an arm (the source: its mask of the hand
    outside the hand's capsules, ``arm_px (T, K)``, at least the capsules' own ``hand_px (T,
    K)``, and at most ``max_ratio`` times the arm of the frame beyond it, the next one away
    from the run, when that frame has the hand: a one-frame outlier, e.g. a floor region taken
    for the arm in one frame, is not spread into its neighbours), is walked from the source
    into the run; each frame reached is opened while the wrist
    of ``keypoints (T, K, 21, 2)`` moved at most ``max_move`` hand lengths
    (:func:`arm_region.hand_length_px`) since the frame before and its own arm (``arm_px``) is
    under ``max_share`` of the source's; the walk stops at the first frame that fails. Such a
    frame found no arm where its neighbour did, while the hand barely moved: the arm is still
    there (DWM 00013 t=31-32, a navy sleeve on a dark floor whose search and colour test flip
    with a 1 px shift of the keypoints), and propagation carries the neighbour's mask in,
    checked against the frame's own colours. A weak frame whose own arm holds (GrabCut found
    it without the region), or a hand whose arm is out of view in the source too (a hand
    entering at the border), is left as it is.
    """
    out = np.zeros(weak.shape, bool)
    n = len(weak)

    def step_ok(a: int, b: int, k: int) -> bool:
        """Whether hand ``k``'s wrist moves at most ``max_move`` hand lengths, a to b."""
        wa, wb = keypoints[a, k, 0], keypoints[b, k, 0]  # (2,) wrists
        sizes = [hand_length_px(keypoints[a, k]), hand_length_px(keypoints[b, k])]
        sizes = [v for v in sizes if np.isfinite(v)]
        if not (np.all(np.isfinite(wa)) and np.all(np.isfinite(wb)) and sizes):
            return False
        return bool(np.hypot(*(wa - wb)) <= max_move * max(sizes))

    def source_ok(t: int, k: int, beyond: int) -> bool:
        """Whether frame ``t`` of hand ``k`` is a source (see above), ``beyond`` the frame
        next to it away from the run."""
        if not (valid[t, k] and not weak[t, k] and 0 < hand_px[t, k] <= arm_px[t, k]):
            return False
        if not (0 <= beyond < n and valid[beyond, k]):
            return True  # nothing beyond the source to compare with (a track's end)
        return bool(arm_px[t, k] <= max_ratio * arm_px[beyond, k])

    for k in range(weak.shape[1]):
        for t, end in true_runs(weak[:, k] & valid[:, k]):
            if end - t > max_run:
                continue
            chains = []
            if t > 0 and source_ok(t - 1, k, t - 2):
                chains.append(range(t - 1, end))  # from the frame before, forwards
            if end < n and source_ok(end, k, end + 1):
                chains.append(range(end, t - 1, -1))  # from the frame after, backwards
            for chain in chains:
                source = chain[0]
                for a, b in itertools.pairwise(chain):  # from the source into the run
                    if not step_ok(a, b, k) or arm_px[b, k] >= max_share * arm_px[source, k]:
                        break  # the hand moved, or its own arm holds: not reached from here
                    out[b, k] = True
    return out


def masks_from_keypoints(
    frames: np.ndarray, keypoints: np.ndarray, valid: np.ndarray, config: HandMaskConfig
) -> np.ndarray:
    """Hand-and-arm masks ``(T, H, W)`` uint8 (1 = hand or arm) of the ``keypoints`` backend.

    ``frames (T, H, W, 3)`` uint8 RGB; ``keypoints (T, K, 21, 2)`` pixels (NaN = unknown);
    ``valid (T, K)``. Works in image space only (see the module docstring).
    """
    carried = np.zeros(valid.shape, bool)  # (T, K) hands carried by tracking, not found
    if config.carry_frames > 0:
        keypoints, valid, carried = carry_keypoints(
            frames, keypoints, valid, CarryParams(max_frames=config.carry_frames)
        )
    capsule = CapsuleParams(radius_scale=config.radius_scale, forearm=config.forearm)
    arm = ArmParams(
        fan_half_angle_deg=config.fan_half_angle_deg,
        no_arm_from_top=config.no_arm_from_top,
        dark_floor=config.dark_floor,
    )

    # The first frame of each hand's track: no steady run reaches it, so its search asks that
    # the arm's strip stand out from both sides (HOT3D window 1's frame 0: a floor strip).
    starts = valid.copy()  # (T, K)
    starts[1:] &= ~valid[:-1]
    if not arm.start_both_sides:
        starts[:] = False

    def labels(
        t: int,
        directions: np.ndarray | None = None,
        no_region: np.ndarray | None = None,
        allow_top: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Frame ``t``'s GrabCut labels ``(K, H, W)``, arm directions ``(K, 2)`` and whether
        each arm has a colour region ``(K,)``."""
        return hand_labels(
            frames[t], keypoints[t], valid[t], capsule, arm, directions, starts[t], no_region,
            allow_top,
        )  # fmt: skip

    # Labels first (arm searches), GrabCut once per frame after: an arm that swung away for a
    # few frames and back is drawn between its neighbours (steady_directions) before the cut.
    own, drawn, coloured = zip(*(labels(t) for t in range(len(frames))), strict=True)
    own = list(own)  # T of (K, H, W) uint8
    drawn = np.stack(drawn)  # (T, K, 2)
    coloured = np.stack(coloured)  # (T, K) the arm drawn has a colour region
    off_side = None
    if arm.steady_off_side:
        off_side = crosses_other_wrist(
            keypoints, valid, drawn, *frames.shape[1:3], arm.off_side_min_tilt_deg
        )  # (T, K)
    steady = steady_directions(
        drawn, arm.steady_frames, arm.steady_jump_deg, arm.steady_agree_deg, off_side
    )  # (T, K, 2)
    guessed = np.zeros(valid.shape, bool)  # (T, K) frames redrawn only through the off-side mark
    if off_side is not None:
        plain = steady_directions(
            drawn, arm.steady_frames, arm.steady_jump_deg, arm.steady_agree_deg
        )  # (T, K, 2) the runs found by angle alone keep their colour region
        guessed = off_side_runs(steady, off_side) & ~np.all(np.isfinite(plain), axis=2)
    for t in np.nonzero(np.any(np.isfinite(steady[..., 0]), axis=1))[0]:
        own[t], _, coloured[t] = labels(int(t), steady[t], guessed[t])
    # Arms that would run up to the top border (not drawn, see no_arm_from_top): only a short
    # run of them next to a frame of the same hand that is not is taken for a hand turned over
    # on its own forearm (HOT3D window 1, t=56-60 flagged) and opened to its neighbours' masks
    # below; a longer run, or one with no such neighbour, is the view's geometry (a false hand
    # on a curtain, a camera rolled over) and its arm is drawn as before v22.
    opened_top = np.zeros(valid.shape, bool)  # (T, K)
    if arm.no_arm_from_top:
        final = np.where(np.isfinite(steady), steady, drawn)  # (T, K, 2) directions drawn
        top = arms_through_top(keypoints, valid, final, *frames.shape[1:3])  # (T, K)
        opened_top = short_top_runs(top, valid, config.carry_frames)
        for t in np.nonzero(np.any(top & ~opened_top, axis=1))[0]:
            again = np.any(np.isfinite(steady[t]))  # as drawn above: steady, else searched
            own[t], _, coloured[t] = labels(
                int(t), steady[t] if again else None, guessed[t] if again else None,
                opened_top[t] | ~top[t],
            )  # fmt: skip
    found = [
        masks_from_labels(
            frames[t], own[t], config.colour_refine, config.grabcut_iterations,
            config.grabcut_max_side,
        )
        for t in range(len(frames))
    ]  # fmt: skip
    masks = np.stack([f[0] for f in found])  # (T, H, W)
    if config.propagate_frames > 0 and config.colour_refine:
        params = PropagationParams(
            max_side=config.grabcut_max_side, max_frames=config.propagate_frames
        )
        per_hand = np.stack([f[1] for f in found])  # (T, K, H, W)
        certain = np.stack([f[2] for f in found])  # (T, K, H, W)
        # A short run of frames whose arm found no colour region and whose own mask of the hand
        # shrank, next to a frame of that hand that found one while the hand barely moved
        # (DWM 00013 t=31-32: a navy sleeve on a dark floor, found or not by a 1 px shift).
        weak = np.zeros(valid.shape, bool)  # (T, K)
        if config.weak_arm_frames > 0 and config.forearm:
            arm_px, hand_px = arm_areas(per_hand, keypoints, valid, capsule)  # (T, K) each
            weak = weak_arm_runs(
                valid & ~coloured, valid, keypoints, arm_px, hand_px, config.weak_arm_frames,
                config.weak_arm_move, config.weak_arm_share, config.weak_arm_agree,
            ) & ~opened_top  # fmt: skip
        # A frame whose hand was carried there still receives that hand's mask from its
        # neighbours (its arm, from frames where the search found it), joined to its own; so
        # does a short run whose arm would run up to the top border (not drawn: the hand's
        # keypoints are doubtful, HOT3D window 1 t=56-60 a hand turned over on its own forearm).
        # ... and so does a short run of frames whose arm found no colour region while a
        # neighbour's did (weak_arm_runs).
        masks = propagate_hands(
            frames, masks, per_hand, certain, params, carried | opened_top | weak
        )
    if config.grow_margin_m > 0 and config.colour_refine:
        grow = GrowParams(config.grow_margin_m, radius_scale=config.radius_scale)
        masks = grow_masks(frames, masks, keypoints, valid, grow)
    # The clip's black border (pixels black in every frame: a letterbox bar with its compression
    # ringing, the outside of a fisheye circle) is not picture either.
    outside = not_image(frames, BorderParams()) if config.border else None  # (H, W) bool
    for t, frame in enumerate(frames):
        masks[t][padding(frame)] = 0  # letterbox bars are not part of the picture
        if outside is not None:
            masks[t][outside] = 0
    return masks


@dataclasses.dataclass(frozen=True)
class HandInputs:
    """What the mask makers read of one clip; a :class:`Clip` has the same fields."""

    clip_id: str  # the clip's id, for error messages
    frames: np.ndarray  # (T, H, W, 3) uint8 RGB
    intrinsics: np.ndarray  # (4,) float64 fx, fy, cx, cy in pixels
    world_from_cam: np.ndarray | None  # (T, 4, 4) float64 camera-to-world
    hand_joints: np.ndarray | None  # (T, 2, 21, 3) float32 world metres, 0=left 1=right
    hand_valid: np.ndarray | None  # (T, 2) bool hand present in the frame
    hand_confidence: np.ndarray | None  # (T, 2, 21) float32 per-joint confidence 0..1

    @property
    def num_frames(self) -> int:
        """Number of frames ``T``."""
        return int(self.frames.shape[0])


def project_keypoints(clip: Clip | HandInputs, min_confidence: float = 0.0) -> np.ndarray:
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


def _float32(values: np.ndarray | None) -> np.ndarray | None:
    """``values`` as float32 (the precision the masks were always projected at), or None."""
    return None if values is None else values.astype(np.float32)


def _hand_labels(
    clip: ClipsRecord, hands: HandsRecord | None
) -> tuple[np.ndarray | None, np.ndarray | None, np.ndarray | None]:
    """Joints ``(T, 2, 21, 3)``, validity ``(T, 2)`` and confidence ``(T, 2, 21)``: the
    ``hands`` row's when connected (its frame count checked against the clip's), else the
    clip's own labels (None where it has none)."""
    source: HandArraysRecord = clip
    if hands is not None:
        if hands.num_frames != clip.num_frames:
            raise ClipRejected(
                f"clip {clip.clip_id!r}: hands cover {hands.num_frames} frames, "
                f"not {clip.num_frames}"
            )
        source = hands
    return (
        _float32(source.hand_joints),
        source.hand_valid,
        _float32(source.hand_confidence),
    )


class HandMaskStage(ClipStage):
    """Hand-and-arm masks per frame from projected keypoints (capsules + colour) or SAM."""

    name = "hand_mask"
    description = "hand and arm masks per frame: keypoint capsules + image-space arm search, or SAM"
    config_class = HandMaskConfig
    inputs: ClassVar[Mapping[str, ShardSchema]] = {"clips": CLIPS}
    # cleaned joints and a replacement camera (see the module docstring)
    optional_inputs: ClassVar[Mapping[str, ShardSchema]] = {**CAMERA_ROLES, "hands": HANDS}
    output = HAND_MASK
    version = 25  # 2: image-space arm masks (no world axis). 3: arm found by a colour walk, masks
    # carried into frames whose hands were missed. 4: arm re-aimed along its colour region.
    # 5: that region is probably arm wherever it runs. 6: each hand carried into the frames that
    # missed it, and only its certain seeds (skeleton, arm strip) carried with confidence.
    # 7: a robot clip's embodiment_mask (URDF arm) added. 8: probable-background fan 25 -> 55
    # degrees either side of the arm (GrabCut may take an arm bent at the wrist or widened by
    # perspective). 9: the arm direction search's turn cost is its own parameter (the forearm's
    # half-width was passed in its place: a cost of 15-40 per radian, scale-dependent), now 3.
    # 10: lengths along the arm at least the palm's length at the hand's scale (a foreshortened
    # hand's arm strip lay inside the hand); no direction search when the hand points out of view
    # 11: missed hands' keypoints carried by tracking (carry); the arm is not re-aimed along its
    # colour region when that turns more than refine_slack_deg past the searched direction
    # 12: a frame whose hand was carried there still receives that hand's propagated mask
    # 13: a found hand without a wrist is no longer replaced by a carried one (nor crossed)
    # 14: each hand's mask grows by up to grow_margin_m into pixels of its own colour (grow)
    # 15: grow's colour histograms smoothed along lightness only (not into held objects)
    # 16: a hand whose arm search is unsure prefers the other hand's arm colour, when rare
    # 17: a carry stops where the carried skeleton's colour jumps (the hand left, background
    # tracked); letterbox bars (rows / columns of black from the edge) are never hand
    # 18: a hand's arm that swings more than 45 degrees away for at most 10 frames, between
    # frames that agree, is drawn along the direction between those (steady_directions)
    # 19: in the first frame of a hand's track a strip that stands out from both sides (the
    # nearer side's contrast), not on average, is drawn when it is another direction
    # (more than start_switch_deg from the plain search's; start_both_sides)
    # 20: an arm whose ray crosses past the other hand's wrist counts as swung away in
    # steady_directions and never brackets a run; the runs only that mark finds are drawn
    # without the probable colour region (steady_off_side; HOT3D window 1, t=37-45); and the
    # both-sides search of v19 wants both sides in the image (a border strip passed on one)
    # 21: the off-side mark also wants the arm tilted at least off_side_min_tilt_deg (45) from
    # straight down towards the other hand (two hands close together, steep arms: review10c)
    # 22: an arm whose ray leaves through the top border is not drawn (no_arm_from_top: a hand
    # the hands stage put on its own forearm, fingers down) and that hand's frame receives its
    # neighbours' mask of it by propagation, as a carried hand's; an off-side run that starts or
    # ends a hand's track, swung more than steady_jump_deg from the track's frame next to it,
    # holds that frame's direction (HOT3D window 1, t=1 and t=56-60 flagged, t=55-60 changed
    # through propagation)
    # 23: the clip's black border (border.not_image: pixels no brighter than 10 in every frame,
    # connected to the frame's edge, round a core of at most 2) is never masked: HOT3D's ringing
    # rows above its letterbox bar and the fisheye circle's black corners (1-4k px per frame).
    # v23 also: only a run of at most carry_frames arms up to the top border next to a frame of
    # the same hand that is not is left undrawn and opened to propagation (short_top_runs);
    # longer runs, or runs with no such frame, draw their arm as v21 (review11b finding 1);
    # and the rule can be turned off (HandMaskConfig.no_arm_from_top) and is never applied to a
    # clip whose cameras row says the camera is static (static_camera; review11b finding 2);
    # and a clip under BorderParams.min_frames (5) frames has no border (review11d)
    # 24: a run of at most weak_arm_frames (8) frames of a hand whose arm found no colour region
    # (no strip standing out from its sides), next to a frame of that hand that found one and
    # reached from it with the wrist moving at most weak_arm_move (0.5) hand lengths a frame,
    # receives that hand's mask from its neighbours by propagation, joined to its own
    # (weak_arm_runs): DWM 00013's navy sleeve on a dark floor was masked or not from frame to
    # frame (t=31 10k px, 27k with the keypoints shifted 1 px), the search and the colour test
    # flipping on a 1 px change; now 27k / 27k. Not from a neighbour whose arm is over
    # weak_arm_agree (1.3) times the arm of the frame beyond it (rehearsal copy 50013, t=28's
    # one-frame floor region spread into t=29-30 without that)
    # 25: in a dim frame (upper-quartile Lab lightness under dark_floor, 70) the arm's strip
    # colour, its walk and its colour region are read from the frame lifted by a gamma to that
    # floor (arm_region.lift_dark); the direction search and GrabCut read it as it is. The
    # walk's 18 Lab held every shadow of a dim frame, so a left arm's region ran along the
    # shadow under the cushion to the right border and re-aimed the arm there (rehearsal copy
    # 50013 t=28: 10,761 px far from any hand -> 0). Well-lit frames are unchanged.
    backends = ("keypoints", "sam")
    # What process reads (the executor decodes nothing else): the frames, joints and camera
    # of the clip, the robot arm's mask, the cleaned joints.
    columns: ClassVar[Mapping[str, tuple[str, ...]]] = join_columns(
        {
            "clips": (
                "num_frames",
                "height",
                "width",
                "video",
                "world_from_cam",
                "hand_joints",
                "hand_valid",
                "hand_confidence",
                "embodiment_mask",
            ),
            "hands": ("num_frames", "hand_joints", "hand_valid", "hand_confidence"),
        },
        CAMERA_COLUMNS,
        STATIC_COLUMNS,  # camera_is_static: a fixed camera skips the top-border rule
    )

    def __init__(self, config: StageConfig | None = None) -> None:
        super().__init__(config)
        self._sam: SamSegmenter | None = None

    def masks_for_clip(self, clip: Clip | HandInputs, static_camera: bool = False) -> np.ndarray:
        """Masks ``(T, H, W)`` uint8 (1 = hand or arm) for a decoded clip (or its
        :class:`HandInputs`). ``static_camera``: the clip's camera is fixed (not head-worn), so
        an arm may enter from the top (``no_arm_from_top`` is not applied)."""
        cfg: HandMaskConfig = self.config  # type: ignore[assignment]
        if static_camera:
            cfg = dataclasses.replace(cfg, no_arm_from_top=False)
        keypoints = project_keypoints(clip, cfg.min_joint_confidence)  # (T, 2, 21, 2)
        valid = np.ones((clip.num_frames, 2), bool) if clip.hand_valid is None else clip.hand_valid
        if cfg.backend == "sam":
            params = CapsuleParams(radius_scale=cfg.radius_scale, forearm=cfg.forearm)
            return np.stack(
                [
                    self._segment_sam(clip.frames[t], keypoints[t], valid[t], params)
                    for t in range(clip.num_frames)
                ]
            )
        return masks_from_keypoints(clip.frames, keypoints, valid, cfg)

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
        clip = ClipsRecord.of(rows["clips"])
        cams = resolve_cameras(rows)
        hands_row = rows.get("hands")
        hands = None if hands_row is None else HandsRecord.of(hands_row)
        joints, valid, confidence = _hand_labels(clip, hands)
        if joints is None:
            raise ClipRejected(f"clip {clip.clip_id!r}: no hand joints (run the hands stage)")
        if cams.world_from_cam is None:
            raise ClipRejected(f"clip {clip.clip_id!r}: no camera poses to project hand joints")
        inputs = HandInputs(
            clip.clip_id,
            clip.frames,
            cams.intrinsics,
            cams.world_from_cam,
            joints,
            valid,
            confidence,
        )
        masks = self.masks_for_clip(inputs, camera_is_static(rows))
        robot = clip.mask_video("embodiment_mask")  # (T, H, W) a robot arm from its URDF (ingest)
        if robot is not None:
            masks = np.maximum(masks, robot.astype(masks.dtype))
        t, h, w = clip.size
        cfg: HandMaskConfig = self.config  # type: ignore[assignment]
        return {
            "clip_id": clip.clip_id,
            "num_frames": t,
            "width": w,
            "height": h,
            "hand_mask": media.encode_mask_video(masks),
            "coverage": masks.reshape(t, -1).mean(axis=1).tolist(),
            "backend": cfg.backend,
        }
