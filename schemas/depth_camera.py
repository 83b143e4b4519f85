"""The ``depth_camera`` schema: what ``depth_camera`` writes, one row per clip.

Camera intrinsics, a pose per frame and a dense depth map of the first frame with a per-pixel
confidence. Poses and depth share one frame and one scale: metric when the backend is ``given``
with metric source poses, SfM's arbitrary (but consistent) scale for ``sfm``. A clip filmed by a
static camera (no parallax) gets every pose equal to the first, ``static_camera`` true and no
depth (DWM's fixed-camera recipe: ``scene_render`` repeats the inpainted first frame). A clip
whose camera only turned (``camera_model`` ``rotation``) has pure-rotation poses (zero
translation) and no depth: any depth gives the same picture, so downstream places frame 0 on a
plane. ``posed_by`` says per frame what posed it; ``registered`` is True where a frame was posed
by estimation (not interpolated).

Version 2 added ``camera_model``, ``posed_by``, ``focal_prior_px`` and the metric-scale columns
``metric_scale``, ``scale_source``, ``scale_spread``. Version 3 dropped ``seconds`` (wall-clock time
made identical runs write different bytes; the time per task is in the run's manifest) and fills
``metric_scale`` for ``sfm`` from the hands' size (poses and depth then in metres).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import pyarrow as pa

from egosim.schemas.base import Column, ShardSchema
from egosim.schemas.clips import POSE
from egosim.schemas.invariants import frame_count_problems, frame_size_problems, se3_problems

BACKENDS = ("sfm", "given", "da3")
CAMERA_MODELS = ("sfm", "rotation", "static", "given", "da3")  # what made a row's poses
# posed_by codes, per frame
POSED_BY_MAPPER = 0  # registered by the SfM mapper
POSED_BY_PNP = 1  # PnP on the model's points tracked into the frame
POSED_BY_MOTION_MODEL = 2  # rotation-only model, or the static camera (every pose the first)
POSED_BY_INTERPOLATION = 3  # not estimated: interpolated (or held at the ends) from neighbours
POSED_BY_SOURCE = 4  # the source's own poses (given backend) or the da3 network
SCALE_SOURCES = ("source", "hand_size", "hand_size_wide", "none")  # where metric_scale came from


def _check_counts(row: Mapping[str, Any]) -> list[str]:
    problems = frame_count_problems(row, ("world_from_cam", "registered", "posed_by"))
    return problems + frame_size_problems(row)


# How far outside the image (in image sizes) the principal point may lie: ingest's crop placed
# off-centre (a band low in a portrait frame) leaves the source's principal point outside the
# clip's image (a 1080x1920 video into 832x480: cy = -134.5 at the hands anchor y 0.875, 0.28
# heights; -259.5 at the very bottom, y 1, 0.54 heights).
PRINCIPAL_POINT_REACH = 2.0


def _check_camera(row: Mapping[str, Any]) -> list[str]:
    problems: list[str] = []
    w, h = row["width"], row["height"]
    fx, fy, cx, cy = row["intrinsics"]
    if not np.all(np.isfinite([fx, fy, cx, cy])) or fx <= 0 or fy <= 0:
        problems.append(f"intrinsics must be finite with fx, fy > 0, got {[fx, fy, cx, cy]}")
    elif not (
        -PRINCIPAL_POINT_REACH * w < cx < (1 + PRINCIPAL_POINT_REACH) * w
        and -PRINCIPAL_POINT_REACH * h < cy < (1 + PRINCIPAL_POINT_REACH) * h
    ):
        problems.append(
            f"principal point ({cx}, {cy}) lies more than {PRINCIPAL_POINT_REACH:g} image sizes "
            f"outside the {w}x{h} image"
        )
    mats = np.asarray(row["world_from_cam"], dtype=np.float64).reshape(-1, 4, 4)
    problems.extend(f"world_from_cam: {p}" for p in se3_problems(mats))
    return problems


def _check_depth(row: Mapping[str, Any]) -> list[str]:
    problems: list[str] = []
    has_depth = row.get("depth0") is not None
    no_depth_ok = row["static_camera"] or row.get("camera_model") == "rotation"
    if row.get("camera_model") == "rotation" and has_depth:
        problems.append("a rotation-only clip must have no depth0 (depth is unknown)")
    if row["static_camera"]:
        if has_depth:
            problems.append("a static-camera clip must have no depth0 (depth needs parallax)")
        poses = np.asarray(row["world_from_cam"], dtype=np.float64).reshape(-1, 16)
        if len(poses) and np.abs(poses - poses[0]).max() > 1e-9:
            problems.append("a static-camera clip must have every pose equal to the first")
    if not no_depth_ok:
        for name in ("depth0", "confidence0", "depth_unit_m"):
            if row.get(name) is None:
                problems.append(f"{name} is null but the camera is not static")
    unit = row.get("depth_unit_m")
    if unit is not None and not (np.isfinite(unit) and unit > 0):
        problems.append(f"depth_unit_m must be > 0, got {unit}")
    if row.get("confidence0") is not None and not has_depth:
        problems.append("confidence0 is set but depth0 is null")
    if row["backend"] not in BACKENDS:
        problems.append(f"backend must be one of {list(BACKENDS)}, got {row['backend']!r}")
    return problems


def _check_figures(row: Mapping[str, Any]) -> list[str]:
    problems: list[str] = []
    for name in ("reprojection_error_px", "confident_fraction"):
        value = row.get(name)
        if value is not None and not (np.isfinite(value) and value >= 0):
            problems.append(f"{name} must be finite and >= 0, got {value}")
    frac = row.get("confident_fraction")
    if frac is not None and frac > 1:
        problems.append(f"confident_fraction must be <= 1, got {frac}")
    if row.get("num_points3d") is not None and row["num_points3d"] < 0:
        problems.append(f"num_points3d must be >= 0, got {row['num_points3d']}")
    return problems


def _check_models(row: Mapping[str, Any]) -> list[str]:
    problems: list[str] = []
    model = row.get("camera_model")
    if model not in CAMERA_MODELS:
        problems.append(f"camera_model must be one of {list(CAMERA_MODELS)}, got {model!r}")
    if bool(row["static_camera"]) != (model == "static"):
        problems.append(f"static_camera is {row['static_camera']} but camera_model is {model!r}")
    posed_by = np.asarray(row.get("posed_by") or [], dtype=np.int64)
    registered = np.asarray(row.get("registered") or [], dtype=bool)
    if posed_by.size and (posed_by.min() < 0 or posed_by.max() > POSED_BY_SOURCE):
        problems.append(
            f"posed_by codes must be in 0..{POSED_BY_SOURCE}, got {sorted(set(posed_by))}"
        )
    if posed_by.shape == registered.shape and np.any(
        registered != (posed_by != POSED_BY_INTERPOLATION)
    ):
        problems.append("registered must be False exactly where posed_by is 3 (interpolated)")
    scale = row.get("metric_scale")
    if scale is not None and not (np.isfinite(scale) and scale > 0):
        problems.append(f"metric_scale must be finite and > 0, got {scale}")
    source = row.get("scale_source")
    if source is not None and source not in SCALE_SOURCES:
        problems.append(f"scale_source must be one of {list(SCALE_SOURCES)}, got {source!r}")
    for name in ("scale_spread", "focal_prior_px"):
        value = row.get(name)
        if value is not None and not (np.isfinite(value) and value >= 0):
            problems.append(f"{name} must be finite and >= 0, got {value}")
    return problems


DEPTH_CAMERA = ShardSchema(
    name="depth_camera",
    version=3,
    doc="Intrinsics, per-frame camera-to-world poses and first-frame depth with confidence.",
    columns=(
        Column("clip_id", pa.string(), "Clip id, as in the clips shard."),
        Column("num_frames", pa.int32(), "Number of frames T."),
        Column("width", pa.int32(), "Frame width W in pixels (of the clip's stored frames)."),
        Column("height", pa.int32(), "Frame height H in pixels."),
        Column(
            "intrinsics",
            pa.list_(pa.float64(), 4),
            "fx, fy, cx, cy in pixels of the stored frames (estimated by sfm, else the source's).",
        ),
        Column(
            "world_from_cam",
            pa.list_(POSE),
            "(T, 16) camera-to-world, row-major 4x4, OpenCV axes, in the depth's scale. Frames "
            "that are not registered are interpolated from their registered neighbours.",
        ),
        Column(
            "registered",
            pa.list_(pa.bool_()),
            "(T,) True where the backend estimated the frame's pose (False: interpolated).",
        ),
        Column(
            "static_camera",
            pa.bool_(),
            "True when the camera did not move (no parallax): every pose equals the first and "
            "depth0 is null; downstream repeats the inpainted first frame.",
        ),
        Column(
            "depth0",
            pa.binary(),
            "(1, H, W) z-depth of frame 0 in the poses' scale, lossless FFV1 uint16 video in "
            "steps of depth_unit_m; 0 = unknown. Null for a static camera.",
            True,
        ),
        Column(
            "depth_unit_m",
            pa.float64(),
            "Depth units (poses' scale) per uint16 step of depth0. Null when depth0 is null.",
            True,
        ),
        Column(
            "confidence0",
            pa.binary(),
            "(1, H, W) uint8 confidence of depth0, 0 (none) .. 255 (sure), lossless FFV1 video. "
            "Null when depth0 is null.",
            True,
        ),
        Column("backend", pa.string(), "Backend that made the row: sfm, given or da3."),
        Column(
            "reprojection_error_px",
            pa.float64(),
            "Mean reprojection error of the SfM model in pixels; null for other backends.",
            True,
        ),
        Column(
            "num_points3d",
            pa.int64(),
            "Number of triangulated SfM points; null for other backends.",
            True,
        ),
        Column(
            "confident_fraction",
            pa.float64(),
            "Fraction of depth0 pixels whose confidence reaches the stage's threshold.",
            True,
        ),
        Column(
            "depth_source_frames",
            pa.list_(pa.int32()),
            "Frame indices the first-frame depth was matched against (plane sweep).",
            True,
        ),
        Column(
            "camera_model",
            pa.string(),
            "What made the poses: sfm (SfM + PnP tracking), rotation (rotation-only model from "
            "homographies, zero translation, no depth), static, given (source poses), da3.",
        ),
        Column(
            "posed_by",
            pa.list_(pa.int8()),
            "(T,) what posed each frame: 0 SfM mapper, 1 PnP on tracked model points, 2 rotation "
            "or static model, 3 interpolated (not estimated), 4 source / given.",
        ),
        Column(
            "focal_prior_px",
            pa.float64(),
            "The focal prior (pixels) the estimate was checked against: the clips row's fx (from "
            "metadata or a field-of-view guess); null when not used.",
            True,
        ),
        Column(
            "metric_scale",
            pa.float64(),
            "Metres per reconstruction unit, already applied to world_from_cam and depth0 when "
            "not null (1.0 for metric sources such as given poses); null: scale unknown.",
            True,
        ),
        Column(
            "scale_source",
            pa.string(),
            "Where metric_scale came from: source, hand_size, hand_size_wide (the hand-size "
            "estimate with its wide-window fallback) or none.",
            True,
        ),
        Column(
            "scale_spread",
            pa.float64(),
            "Relative spread of the metric scale estimate (0 for a metric source); null when "
            "unknown.",
            True,
        ),
    ),
    validators=(_check_counts, _check_camera, _check_depth, _check_figures, _check_models),
)
