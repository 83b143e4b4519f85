"""The ``hands`` stage: 3D hand joints per frame, de-duplicated and de-spiked.

Backend ``given`` reads the clip's own joint labels (synthetic world, EgoDex); ``mediapipe``
detects hands in the frames and lifts them to 3D (:mod:`egosim.stages.hands.mediapipe_backend`);
``hamer`` imports HaMeR outputs (:mod:`egosim.stages.hands.hamer_backend`); ``regressor`` runs a
learned HaMeR/WiLoR-style joint regressor from local safetensors weights on crops around the
``mediapipe`` backend's hands (:mod:`egosim.stages.hands.regressor_backend`; needs torch, imported
only then). The filters of
:mod:`egosim.stages.hands.filters` run on every backend's detections: frame-wise
de-duplication (projected joint boxes, IoU, breadth-first grouping, most confident per side) and
temporal outlier removal (bidirectional speed test in camera space). The ``mediapipe`` backend
also repairs a palm turned off its own track before that (interpolated between trusted
neighbours, or kept valid for its 2D with a tenth of the confidence and ``hand_lifted`` False:
"2D only, 3D withheld"). Intrinsics and poses come
from :func:`egosim.stages.common.cameras.resolve_cameras`: the optional ``poses`` (cleaned) or
``cameras`` (estimated) inputs when a workflow connects them, else the clips row. The ``given``
backend's world joints do not depend on them; the de-duplication (projected boxes) and the
speed test (camera space) do, and the detecting backends lift their joints with them.
"""

from __future__ import annotations

import dataclasses
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any, ClassVar, Literal

import numpy as np

from egosim.pipeline.clip_io import CLIP_REQUIRED_COLUMNS, clip_from_row
from egosim.pipeline.geometry import se3_problems
from egosim.pipeline.records import ClipsRecord, require_camera_poses
from egosim.pipeline.stage import ClipRejected, ClipStage, ConfigError, StageConfig, join_columns
from egosim.schemas import CLIPS, ShardSchema
from egosim.schemas.hands import HANDS, MANO_COLUMNS
from egosim.stages.common.cameras import CAMERA_COLUMNS, CAMERA_ROLES, Cameras, resolve_cameras
from egosim.stages.hands.filters import (
    Detections,
    HandFilterError,
    deduplicate,
    lifted_to_sides,
    mano_to_sides,
    temporal_outliers,
    to_hands,
)
from egosim.stages.hands.given import NoHandLabelsError, given_detections
from egosim.stages.hands.hamer_backend import HamerFileError, hamer_detections
from egosim.stages.hands.mediapipe_backend import MediaPipeParams, mediapipe_detections


@dataclasses.dataclass(frozen=True)
class HandsConfig(StageConfig):
    """Parameters of ``hands``."""

    # labels, MediaPipe, HaMeR files, a learned regressor, or auto (labels, else MediaPipe)
    backend: Literal["given", "mediapipe", "hamer", "regressor", "auto"] = "given"
    hamer_dir: str = ""  # backend hamer: folder of <clip_id>.npz HaMeR outputs
    regressor_weights: str = ""  # backend regressor: folder of config.json + model.safetensors
    regressor_device: str = "cpu"  # backend regressor: torch device ("cpu", "cuda", "cuda:1")
    # backend regressor: hand boxes and sides from MediaPipe, or from the clip's labels
    regressor_boxes: Literal["mediapipe", "given"] = "mediapipe"
    mediapipe_video_mode: bool = True  # mediapipe (and its regressor boxes): tracking mode
    iou_threshold: float = 0.5  # boxes overlapping more than this are the same hand
    max_speed: float = 2.5  # m/s in camera space; above it both ways = temporal outlier
    max_angular_speed: float = 720.0  # deg/s palm turn in camera space; above both ways = outlier
    despike: bool = True  # run the temporal outlier test

    def __post_init__(self) -> None:
        problems = []
        if not 0.0 < self.iou_threshold < 1.0:
            problems.append(f"iou_threshold must be in (0, 1), got {self.iou_threshold}")
        if not (np.isfinite(self.max_speed) and self.max_speed > 0):
            problems.append(f"max_speed must be > 0 m/s, got {self.max_speed}")
        if not self.max_angular_speed > 0:  # inf allowed: position test only
            problems.append(f"max_angular_speed must be > 0 deg/s, got {self.max_angular_speed}")
        if self.backend == "hamer" and not self.hamer_dir:
            problems.append("backend 'hamer' needs hamer_dir (a folder of <clip_id>.npz files)")
        if self.backend == "regressor" and not self.regressor_weights:
            problems.append("backend 'regressor' needs regressor_weights (a local folder)")
        elif self.backend == "regressor" and not Path(self.regressor_weights).is_dir():
            problems.append(
                f"regressor_weights must be an existing folder, got {self.regressor_weights!r}"
            )
        if not re.fullmatch(r"cpu|mps|cuda(:\d+)?", self.regressor_device):
            problems.append(
                f"regressor_device must be cpu, mps, cuda or cuda:N, got {self.regressor_device!r}"
            )
        if self.regressor_boxes not in ("mediapipe", "given"):
            problems.append(
                f"regressor_boxes must be 'mediapipe' or 'given', got {self.regressor_boxes!r}"
            )
        if problems:
            raise ConfigError("; ".join(problems))


def resolved_backend(row: Mapping[str, Any], config: HandsConfig) -> str:
    """The backend used for one clip (``auto``: labels when the clip has them, else MediaPipe)."""
    if config.backend != "auto":
        return config.backend
    return "given" if row.get("hand_joints") is not None else "mediapipe"


def _detections(
    row: Mapping[str, Any], config: HandsConfig, poses: np.ndarray, intrinsics: np.ndarray
) -> Detections:
    """Dispatch to the configured backend (mediapipe/hamer decode the row into a clip).

    ``poses (T, 4, 4)`` and ``intrinsics (4,)`` replace the clip's own camera.
    """
    backend = resolved_backend(row, config)
    if backend == "given":
        return given_detections(row)
    clip = dataclasses.replace(clip_from_row(row), world_from_cam=poses, intrinsics=intrinsics)
    mediapipe = MediaPipeParams(video_mode=config.mediapipe_video_mode)
    if backend == "mediapipe":
        return mediapipe_detections(clip, mediapipe)
    if backend == "regressor":  # imports torch: only when chosen
        from egosim.stages.hands.regressor_backend import RegressorParams, regressor_detections

        params = RegressorParams(
            config.regressor_weights, config.regressor_device, config.regressor_boxes, mediapipe
        )
        return regressor_detections(clip, params)
    from egosim.schemas.ids import path_under, validate_id  # clip ids name files: check them

    return hamer_detections(clip, path_under(config.hamer_dir, f"{validate_id(clip.clip_id)}.npz"))


@dataclasses.dataclass(frozen=True)
class CleanedHands:
    """One clip's hands after the backend and both filters (hand 0 left, 1 right)."""

    joints: np.ndarray  # (T, 2, 21, 3) float64 world metres; NaN where not valid
    valid: np.ndarray  # (T, 2) bool hand kept in the frame
    confidence: np.ndarray  # (T, 2, 21) float32 per-joint confidence; 0 where not valid
    lifted: np.ndarray  # (T, 2) bool valid and its 3D trusted (False: 2D only, see HANDS)
    duplicates: int  # detections dropped by the de-duplication
    outliers: int  # hand-frames dropped as temporal outliers
    mano: np.ndarray | None  # (T, 2, 51 + B) MANO fits, NaN where not valid; None: no fits


def cleaned_hands(
    row: Mapping[str, Any], config: HandsConfig, cameras: Cameras | None = None
) -> CleanedHands:
    """Run the backend and both filters on one clips row (:class:`CleanedHands`).

    ``row`` is a :class:`ClipsRecord` or a plain mapping (wrapped in one). ``cameras`` (from
    :func:`resolve_cameras`) defaults to the clips row's own camera. Raises
    :class:`ClipRejected` naming the clip when it cannot.
    """
    clip = ClipsRecord.of(row)
    cid, t = clip.clip_id, clip.num_frames
    cams = cameras if cameras is not None else resolve_cameras({"clips": clip})
    poses = require_camera_poses(cams.world_from_cam, cid)  # (T, 4, 4)
    problems = se3_problems(poses)
    if problems:
        raise ClipRejected(f"clip {cid!r}: {cams.source} world_from_cam: " + "; ".join(problems))
    intrinsics = cams.intrinsics  # (4,)
    try:
        det = _detections(clip, config, poses, intrinsics)
        det.check(t)
        det, dups = deduplicate(det, poses, intrinsics, config.iou_threshold)
        joints, valid, conf = to_hands(det)
        lifted = lifted_to_sides(det)  # (T, 2)
        mano = mano_to_sides(det)  # (T, 2, 51 + B) or None
        outliers = 0
        if config.despike:  # on 3D-trusted hands only: a 2D-only hand's depth is a guess
            spikes = temporal_outliers(
                np.where(lifted[..., None, None], joints, np.nan),
                lifted,
                poses,
                clip.fps,
                config.max_speed,
                config.max_angular_speed,
            )
            valid &= ~spikes
            joints[spikes] = np.nan
            conf[spikes] = 0.0
            outliers = int(spikes.sum())
        lifted &= valid
        if mano is not None:
            mano[~valid] = np.nan
    except (NoHandLabelsError, HandFilterError, HamerFileError) as exc:
        raise ClipRejected(f"clip {cid!r}: {exc}") from exc
    return CleanedHands(joints, valid, conf, lifted, dups, outliers, mano)


class HandsStage(ClipStage):
    """3D hand joints per frame, de-duplicated and with temporal outliers removed."""

    name = "hands"
    # 2: mediapipe lifts by palm PnP (not translation only), drops overlapping detections,
    # links tracks across gaps less far; the spike filter also tests the palm's orientation.
    # 3: mediapipe follows found hands through detector misses, forwards and backwards in time.
    # 4: ... carrying a lost hand's ROI by the optical flow for a few frames, on contrast-stretched
    # crops (dark, sleeved hands of head-mounted video); a palm seen edge-on (no palm PnP) is
    # posed like the nearest frame instead of in MediaPipe's own axes.
    # 5: the palm lift re-estimates finger joint depths from bone lengths (hand_lift).
    # 6: a followed hand replaces a small fit on its own fingers, and a hand lost at the clip's
    # first/last frame is carried there by the flow (mediapipe); MANO fits stored (regressor).
    # 7: a followed hand's world landmarks are turned from its crop's axes into the frame's, as
    # MediaPipe's own graph does (roi_landmarks.world_in_frame_axes), before smoothing and lifting.
    # 8: the palm lift refines IPPE's palm poses on the reprojection error (refine_palm on) and
    # takes MediaPipe's proximal phalanges 1 / 0.70 longer (hand_lift.landmark_bone_lengths).
    # 9: a gap is bridged only between ends as near as _tracks links (two hands given one side
    # are not interpolated into a hand between them).
    # 10: a palm turning off its track's neighbours faster than max_turn_rate (filters.
    # turn_outliers) is interpolated between trusted frames (mediapipe), or where there are none
    # its 3D is withheld: joints kept on its landmarks' rays (masks keep the hand), confidence
    # x 0.1. 11: the hands schema's hand_lifted column says which hands' 3D is trusted; the
    # spike test runs on those only (it had dropped withheld hands, and good frames beside them).
    # 12: (mediapipe) landmarks smoothed over time only within runs of frames one link apart
    # (_tracks' link_limit at one frame): two tracks given one side in adjacent frames are not
    # blended into a hand between them.
    # 13: the palm lift's four fingers are MediaPipe's fingers bent to fit their 2D landmarks,
    # pulled towards MediaPipe's own bends (hand_lift.fit_finger_bends); the 2D is unchanged.
    # Also (mediapipe) a track off the clip's skin colour and still against the background is
    # dropped before sides are chosen (scene_check; the EgoDex portrait variant's curtain hand).
    # 14: (mediapipe) a frame whose palm PnP fails, posed like its neighbour, puts its palm at the
    # neighbour's palm depth (median of PALM_JOINTS on both sides), not all 21 joints' median.
    # And the four fingers' depths (wrist-relative, each joint on its ray: the 2D kept) are
    # smoothed over time within runs of trusted frames (filters.smooth_finger_depths, sigma 1).
    # Also (mediapipe) the scene check never drops a confident track (median presence >=
    # seed_presence) or one under min_track_frames frames (review10a, 3033934), and takes the
    # background's motion from forward-backward checked corners (klt, df46f3e).
    # 15: (mediapipe) a hand under spread_max_size from wrist to middle knuckle (a share of the
    # frame height: 40 px at 480 rows) whose landmarks move by more than max_spread (0.05) of
    # that size when the landmark model reads its ROI as it is, turned +20 degrees, scaled 1.25
    # and mirrored (roi_landmarks.landmark_spread; four runs, hands17: hands14's six, with -20
    # degrees and 0.8 at 0.06, cost a third more CPU) has its 3D withheld or interpolated like a
    # palm turned off its track; the 2D is kept.
    # Also the regressor backend (boxes="mediapipe") runs the same scene check (hands15, ac4ffba),
    # and the scene check drops a still, Lab-off-skin track only when it is also off-skin in
    # chromaticity (max_chromaticity_distance 2.0: a real hand resting in shadow is kept;
    # hands15, 1eab93d). And the palm detector also runs on contrast-stretched dim frames while
    # a side has no palm detection in the clip (hand_landmarks.stretch_gain, hands16, 21db71e).
    # 16: (mediapipe) a track's side vote also counts where its forearm comes into the image
    # (mediapipe_backend.forearm_entry, forearm_weight 1.0: the line through the middle knuckle
    # and the wrist at the bottom border), which does not use MediaPipe's handedness head
    # (HOT3D frames 120-241: a right hand reaching for a jug was called left; hands18). Also
    # the stretched palm pass runs only after a probe of every second frame it would search
    # finds a hand of the missing side (hand_landmarks.stretch_probe 2; one-hand clips skip it;
    # detections identical on every clip measured).
    # 17: a hand the tracker cannot find in any ROI is read once more in the predicted ROI
    # mirrored (roi_landmarks.TrackParams.mirror_retry): DWM 00013 flipped left to right lost
    # its real left hand at frames 12-20 (recall 0.625 -> 1); the unflipped real clips identical.
    # 18: (mediapipe, sides) a short track is dropped for wanting a side only when a longer
    # track holds that side then (as documented), not one of the same length: two hands entering
    # in one frame, each too fast to link to its later track, are two one-frame tracks, and the
    # one in the later slot was dropped when the earlier one's vote wanted its side (DWM 00013
    # re-encoded by 2 levels lost its right hand at frame 8, the hand-free fill's start: the left
    # hand came first, labelled right; reenc1). Now both keep a side, ordered by position.
    # 19: (mediapipe) a tracked reading may be at most roi_landmarks.TrackParams.max_drift (1.6)
    # times off the size of the track's last trusted one (a palm detection, or a reading of
    # presence >= trust_presence 0.5), not only 1.6 per frame: DWM 00013 from frame 8
    # re-encoded (rehearsal 70013, as ingested) had the right hand's low-presence readings
    # spread over its dark sleeve, 95 -> 122 -> 181 -> 220 px, until it was lost (right recall
    # 0.708). A refused reading is searched for again from the trusted landmarks carried by the
    # flow: the hand is found on the frames after it (0.958); drift1.
    # 20: a tracked reading found only in the tracker's wider ROIs (away from where the hand was
    # predicted), while following a reading, must lead back to it: searched for from it on the
    # frame it came from, the model must find that hand there (roi_landmarks.TrackParams.
    # confirm_wider); if not, the hand is not followed further that way. pour_coke at 8 fps
    # (bench.hand_free_real): the right hand entering at frame 5 was followed back onto the jug
    # and can (frames 0-4, 1.58x its size), a false frame-0 mask of 65,045 px that a static
    # camera's fill repeats in every frame (issue 9); falsehand1. DWM / fixed @16 fps / EgoDex
    # rows identical.
    # 21: each trusted hand's palm turn smoothed over time (filters.smooth_palm_turns, sigma 1
    # frame; joints kept on their rays, so the 2D is unchanged): tuned default 26.21 -> 26.10 mm,
    # held-out alt 20.13 -> 19.96 mm; real lifted shares identical; mpjpe1.
    # 22: the tracker reads every predicted ROI mirrored when none holds the hand at the presence
    # its step needs, and keeps a mirrored reading only if mirrored crops turned and scaled read
    # it alike (roi_landmarks.mirror_max_spread); mirror1 + lead. Held-out copies 60013 as
    # ingested right recall 0.708 -> 0.917, 40013 as ingested left 0.875 -> 1; real rows and the
    # synthetic figures the same (default recall 0.534 -> 0.533).
    version = 22
    description = "3D hand joints per frame from the clip's labels, de-duplicated and de-spiked"
    config_class = HandsConfig
    inputs: ClassVar[Mapping[str, ShardSchema]] = {"clips": CLIPS}
    optional_inputs: ClassVar[Mapping[str, ShardSchema]] = CAMERA_ROLES  # replace the clip's camera
    output = HANDS
    backends = ("given", "mediapipe", "hamer", "regressor")
    # What process reads of the clip: every backend's inputs (the config picks the backend, the
    # declaration is per class): the labels (given, regressor boxes "given"), and for the
    # detecting backends what clip_from_row needs plus the depth they lift with; the static
    # video, masks and object poses are neither read nor decoded.
    columns: ClassVar[Mapping[str, tuple[str, ...]]] = join_columns(
        {
            "clips": (
                *CLIP_REQUIRED_COLUMNS,
                "world_from_cam",
                "depth",
                "depth_unit_m",
                "hand_joints",
                "hand_valid",
                "hand_confidence",
            )
        },
        CAMERA_COLUMNS,
    )
    config: HandsConfig

    def process(self, rows: Mapping[str, Mapping[str, Any]]) -> dict[str, Any]:
        """Clean the joints of one clip."""
        row = ClipsRecord.of(rows["clips"])
        t = row.num_frames
        out = cleaned_hands(row, self.config, resolve_cameras(rows))
        return {
            "clip_id": row["clip_id"],
            "num_frames": t,
            "backend": resolved_backend(row, self.config),
            "hand_joints": out.joints.astype(np.float32).reshape(t, -1).tolist(),
            "hand_valid": out.valid.tolist(),
            "hand_confidence": out.confidence.astype(np.float32).reshape(t, -1).tolist(),
            "hand_lifted": out.lifted.tolist(),
            "num_duplicates_removed": out.duplicates,
            "num_outliers_removed": out.outliers,
            **mano_columns(out.mano, t),
        }


def mano_columns(mano: np.ndarray | None, t: int) -> dict[str, Any]:
    """The ``hands`` schema's ``mano_*`` columns from fits ``(T, 2, 51 + B)`` (all null for
    None: a backend without MANO)."""
    if mano is None:
        return dict.fromkeys(MANO_COLUMNS)
    m = mano.astype(np.float32)  # (T, 2, 51 + B)
    return {
        "mano_global_orient": m[..., 0:3].reshape(t, -1).tolist(),
        "mano_hand_pose": m[..., 3:48].reshape(t, -1).tolist(),
        "mano_transl": m[..., 48:51].reshape(t, -1).tolist(),
        "mano_betas": m[..., 51:].reshape(t, -1).tolist(),
    }
