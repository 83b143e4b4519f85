"""Parameters of ``state_fusion``: every threshold of the paper's method, with its source.

Values quoted as "paper" come from the EgoSim paper (section 3.3 and supplementary section 2) as
restated by issue 13; the paper's TSDF voxel size, depth truncation and overlap depth threshold
are not legible in our copy of the text, so those defaults are ours and say so.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from egosim.pipeline.stage import ConfigError, StageConfig

# object instances: "geometric" (plane + DBSCAN, no weights) or "grounded_sam" (Grounding-DINO
# boxes for object_labels, SAM masks; local weights; stages/state_fusion/segmenters.py)
SEGMENTATION_BACKENDS = ("geometric", "grounded_sam")
DEPTH_SOURCES = ("auto", "clip", "estimate")  # where per-frame depth comes from
BOX_OVERLAPS = ("iou", "ioa")  # how the interaction test compares object and hand boxes


@dataclasses.dataclass(frozen=True)
class StateFusionConfig(StageConfig):
    """Parameters of ``state_fusion`` (see the module docstring for where defaults come from)."""

    backend: str = "geometric"  # object instances: "geometric" (RANSAC plane + DBSCAN), no weights
    # or "grounded_sam" (learned 2D masks, weights from local folders)
    object_labels: tuple[str, ...] = ()  # grounded_sam: object names to find, e.g. cup,box
    dino_model_path: str = ""  # grounded_sam: local Grounding-DINO folder (transformers layout)
    sam_model_path: str = ""  # grounded_sam: local SAM folder (transformers layout)
    box_threshold: float = 0.3  # grounded_sam: Grounding-DINO box score threshold
    text_threshold: float = 0.25  # grounded_sam: Grounding-DINO text score threshold
    # Per-frame depth (issue 13 step 1): the clip's depth column, or a plane sweep with the
    # clip's cameras (stages/common/plane_sweep.py: clip_depth); tuned on the default world
    depth_source: str = "auto"  # "clip" (reject without depth), "estimate", or "auto" (clip's,
    # else estimate)
    sweep_stride: int = 2  # every stride-th frame (and the last) gets depth; the others none
    sweep_sources: int = 6  # source frames per swept frame
    sweep_window_frames: int = 8  # sources within this many frames of the swept one
    sweep_max_width: int = 416  # sweep at min(1, sweep_max_width / width) of the frame size
    sweep_planes: int = 64  # inverse-depth planes
    sweep_window: int = 7  # ZNCC window side in pixels at the sweep resolution (odd)
    sweep_min_confidence: float = 0.5  # swept depth kept where its confidence reaches this
    sweep_consistency_rel: float = 0.01  # ... and a neighbouring swept frame agrees this closely
    sweep_min_consistent: int = 1  # neighbouring swept frames that must agree (0 = no check)
    sweep_depth_margin: float = 0.3  # depth range = prior depth's 1-99 percentiles widened so
    sweep_depth_range: tuple[float, float] = (0.2, 5.0)  # near, far when there is no prior depth
    # Interaction test (paper, supp. 2.2)
    hand_box_iou: float = 0.1  # object/hand box overlap above this: candidate (paper: 0.1)
    box_overlap: str = "ioa"  # "ioa": overlap / object box; "iou": paper's (see fusion.py)
    depth_gap_m: float = 0.15  # object-hand median depth gap below: interacting (paper: 0.15 m)
    hand_box_pad: float = 0.3  # hand keypoint box widened by this fraction of its size (ours)
    hand_dilation_px: int = 4  # hand/arm masks dilated by this many pixels before fusion (ours)
    # Support plane and object instances (geometric backend; ours)
    plane_distance_m: float = 0.01  # RANSAC inlier distance of the support plane (ransac_plane)
    plane_iterations: int = 500  # RANSAC iterations of the support plane (ransac_plane)
    plane_min_fraction: float = 0.15  # a support plane holds at least this fraction of the points
    plane_max_tilt_deg: float = 70.0  # support plane normal within this of the camera's up (-y)
    object_min_height_m: float = 0.012  # points higher than this above the plane may be objects
    object_max_height_m: float = 0.4  # ... and lower than this
    cluster_eps_m: float = 0.02  # DBSCAN neighbourhood radius for object points
    min_object_points: int = 20  # clusters with fewer points are not objects (per frame)
    track_voxel_m: float = 0.02  # voxel size of the 3D overlap test that tracks objects
    track_min_overlap: float = 0.2  # shared voxels / smaller voxel set to continue a track
    track_max_jump_m: float = 0.08  # else: centroid within this of the track's last centroid
    settled_distance_m: float = 0.02  # frames this close (median) to the last place: at rest
    instance_match_m: float = 0.02  # new object point within this of a previous instance: match
    instance_match_fraction: float = 0.3  # fraction of matching points to reuse an instance id
    # Carried objects (carry.py; ours, tuned on the default world): an object of the previous
    # state a closed hand takes, lifts and puts down moves with the palm's rigid motion
    carry_held: bool = True  # place carried objects by the hands' motion
    carry_contact_m: float = 0.05  # grip point within this of the object: contact
    carry_lift_m: float = 0.02  # the carried object must rise this far above its rest height
    carry_rest_m: float = 0.01  # ... and come back within this of it: put down
    carry_close_drop: float = 0.1  # closed hand: finger spread this far below its most open
    # TSDF fusion (open3d tensor VoxelBlockGrid; paper: "scalable TSDF", values not legible)
    voxel_size_m: float = 0.01  # TSDF voxel size in metres (ours)
    sdf_trunc_voxels: float = 4.0  # TSDF truncation in voxels (ours)
    depth_max_m: float = 3.0  # depth beyond this is not fused (paper: "max depth truncation")
    tsdf_min_weight: float = 3.0  # surface voxels seen in at least this many frames (open3d's)
    # ... with estimated depth (every sweep_stride-th frame, each depth already confirmed by a
    # neighbouring frame: clip_depth's consistency check), tuned on the default world
    tsdf_min_weight_estimated: float = 1.0
    block_count: int = 16000  # voxel blocks preallocated (8^3 voxels each); grows when needed
    # Incremental fusion with the previous state (paper, supp. 2.3)
    overlap_depth_m: float = 0.03  # old point replaced where observed depth differs by more (ours)
    overlap_colour: float = 0.25  # ... or mean |RGB| difference in [0, 1] is above this (ours)
    min_agreement: float = 0.5  # previous points seen by the clip that must agree, else reject
    min_seen_points: int = 200  # previous points the clip must see, else "no overlap" reject
    overlap_max_distance_m: float = 0.5  # a clip camera this close to a state camera overlaps
    overlap_max_angle_deg: float = 45.0  # ... and turned by at most this
    min_overlap_cameras: int = 1  # overlapping cameras needed to fuse onto a previous state
    min_centre_spread_m: float = 0.005  # below this camera spread the Sim3 scale is fixed to 1
    max_registration_rms_m: float = 0.05  # Sim3 pose residual above this (reference units): reject
    sim3_scale_range: tuple[float, float] = (0.2, 5.0)  # Sim3 scales outside this: reject
    # Cleaning (paper, supp. 2.3)
    outlier_neighbours: int = 20  # statistical outlier removal neighbours (paper: 20)
    outlier_std_ratio: float = 2.0  # statistical outlier removal std ratio (paper: 2.0)
    min_cluster_points: int = 30  # connected components (2 voxels) smaller than this are removed

    def __post_init__(self) -> None:
        problems: list[str] = []
        if self.backend not in SEGMENTATION_BACKENDS:
            problems.append(f"backend must be one of {SEGMENTATION_BACKENDS}, got {self.backend!r}")
        if self.backend == "grounded_sam" and not (
            self.object_labels and self.dino_model_path and self.sam_model_path
        ):
            problems.append(
                "backend 'grounded_sam' needs object_labels, dino_model_path and sam_model_path"
            )
        if self.depth_source not in DEPTH_SOURCES:
            problems.append(
                f"depth_source must be one of {DEPTH_SOURCES}, got {self.depth_source!r}"
            )
        for name in ("sweep_stride", "sweep_window_frames", "sweep_max_width"):
            if getattr(self, name) < 1:
                problems.append(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.sweep_sources < 2:
            problems.append(f"sweep_sources must be >= 2, got {self.sweep_sources}")
        if self.sweep_window < 3 or self.sweep_window % 2 == 0:
            problems.append(f"sweep_window must be odd and >= 3, got {self.sweep_window}")
        if not self.sweep_consistency_rel > 0 or self.sweep_min_consistent < 0:
            problems.append(
                "need sweep_consistency_rel > 0 and sweep_min_consistent >= 0, got "
                f"{self.sweep_consistency_rel} and {self.sweep_min_consistent}"
            )
        if self.sweep_planes < 3:
            problems.append(f"sweep_planes must be >= 3, got {self.sweep_planes}")
        if not 0.0 <= self.sweep_depth_margin < 1.0:
            problems.append(f"sweep_depth_margin must be in [0, 1), got {self.sweep_depth_margin}")
        rng = self.sweep_depth_range
        if len(rng) != 2 or not (0 < rng[0] < rng[1] and np.isfinite(rng[1])):
            problems.append(f"sweep_depth_range must be (near, far), 0 < near < far, got {rng}")
        if self.box_overlap not in BOX_OVERLAPS:
            problems.append(f"box_overlap must be one of {BOX_OVERLAPS}, got {self.box_overlap!r}")
        positive = (
            "depth_gap_m",
            "plane_distance_m",
            "object_max_height_m",
            "cluster_eps_m",
            "track_voxel_m",
            "track_max_jump_m",
            "instance_match_m",
            "settled_distance_m",
            "voxel_size_m",
            "sdf_trunc_voxels",
            "depth_max_m",
            "overlap_depth_m",
            "overlap_max_distance_m",
            "min_centre_spread_m",
            "max_registration_rms_m",
            "outlier_std_ratio",
            "tsdf_min_weight",
            "tsdf_min_weight_estimated",
            "carry_contact_m",
            "carry_lift_m",
            "carry_rest_m",
            "carry_close_drop",
        )
        for name in positive:
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0):
                problems.append(f"{name} must be finite and > 0, got {value}")
        fractions = (
            "hand_box_iou",
            "plane_min_fraction",
            "track_min_overlap",
            "instance_match_fraction",
            "overlap_colour",
            "min_agreement",
            "sweep_min_confidence",
        )
        for name in fractions:
            value = getattr(self, name)
            if not 0.0 <= value <= 1.0:
                problems.append(f"{name} must be in [0, 1], got {value}")
        if not 0.0 <= self.hand_box_pad <= 2.0:
            problems.append(f"hand_box_pad must be in [0, 2], got {self.hand_box_pad}")
        if not 0.0 <= self.object_min_height_m < self.object_max_height_m:
            problems.append(
                f"need 0 <= object_min_height_m < object_max_height_m, got "
                f"{self.object_min_height_m} and {self.object_max_height_m}"
            )
        for name in ("plane_max_tilt_deg", "overlap_max_angle_deg"):
            value = getattr(self, name)
            if not 0.0 < value <= 180.0:
                problems.append(f"{name} must be in (0, 180], got {value}")
        counts = (
            "hand_dilation_px",
            "min_seen_points",
            "min_overlap_cameras",
            "min_cluster_points",
        )
        for name in counts:
            if getattr(self, name) < 0:
                problems.append(f"{name} must be >= 0, got {getattr(self, name)}")
        for name in ("plane_iterations", "min_object_points", "block_count", "outlier_neighbours"):
            if getattr(self, name) < 1:
                problems.append(f"{name} must be >= 1, got {getattr(self, name)}")
        lo, hi = self.sim3_scale_range if len(self.sim3_scale_range) == 2 else (0.0, -1.0)
        if not 0.0 < lo < 1.0 < hi:
            problems.append(
                f"sim3_scale_range must be (lo, hi) with 0 < lo < 1 < hi, got "
                f"{self.sim3_scale_range}"
            )
        if problems:
            raise ConfigError("; ".join(problems))
