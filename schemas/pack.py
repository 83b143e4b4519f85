"""The ``pack``, ``simulation`` and ``evaluation`` schemas: the model side of the pipeline.

``pack`` holds one training sample per clip, everything the observation model needs at one
resolution and frame count: target video, scene video, visibility mask, skeleton video, the
hand-free first frame and the prompt, plus the camera and quality figures of the clip.
``simulation`` holds a generated clip per row; ``evaluation`` the figures of one generated clip
against its packed ground truth.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import pyarrow as pa

from egosim.schemas.base import Column, ShardSchema
from egosim.schemas.clips import POSE

FIRST_FRAME_SOURCES = ("inpaint", "first_frame_clean", "frame0")


def _check_pack(row: Mapping[str, Any]) -> list[str]:
    problems: list[str] = []
    t = row["num_frames"]
    if t is None or t < 1 or (t - 1) % 4:
        return [f"num_frames must be 1 + 4k (the model's latent layout), got {t}"]
    if row["width"] < 1 or row["height"] < 1:
        problems.append(f"width and height must be positive, got {row['width']}x{row['height']}")
    if len(row["frame_indices"]) != t:
        problems.append(f"frame_indices has {len(row['frame_indices'])} entries, num_frames is {t}")
    if row["world_from_cam"] is not None and len(row["world_from_cam"]) != t:
        problems.append(f"world_from_cam has {len(row['world_from_cam'])} poses for {t} frames")
    for name in ("target_video", "scene_video", "visible", "skeleton_video", "first_frame"):
        if not len(row[name]):
            problems.append(f"{name} must be non-empty encoded bytes")
    for name in ("visible_fraction", "registered_fraction", "hand_valid_fraction"):
        if not 0.0 <= row[name] <= 1.0:
            problems.append(f"{name} must be in [0, 1], got {row[name]}")
    if row["first_frame_source"] not in FIRST_FRAME_SOURCES:
        problems.append(
            f"first_frame_source must be one of {FIRST_FRAME_SOURCES}, "
            f"got {row['first_frame_source']!r}"
        )
    if (row["depth0"] is None) != (row["depth_unit_m"] is None):
        problems.append("depth0 and depth_unit_m must both be set or both be null")
    if not np.all(np.isfinite(np.asarray(row["intrinsics"], dtype=np.float64))):
        problems.append("intrinsics must be finite")
    return problems


PACK = ShardSchema(
    name="pack",
    version=1,
    doc="One training sample per clip: target, scene, visibility, skeleton, first frame, prompt.",
    columns=(
        Column("clip_id", pa.string(), "Clip id, joins with the clips shard."),
        Column("num_frames", pa.int32(), "Frames T of the sample (1 + 4k, the latent layout)."),
        Column("width", pa.int32(), "Frame width W of every video of the sample."),
        Column("height", pa.int32(), "Frame height H of every video of the sample."),
        Column("fps", pa.float64(), "Frames per second of the sample (clip fps / frame stride)."),
        Column(
            "frame_indices", pa.list_(pa.int32()), "(T,) index of each sample frame in the clip."
        ),
        Column(
            "intrinsics",
            pa.list_(pa.float64(), 4),
            "fx, fy, cx, cy in pixels of the sample's frames (scaled with the resize).",
        ),
        Column(
            "world_from_cam",
            pa.list_(POSE),
            "(T, 16) camera-to-world of the sample frames (the poses the conditions were "
            "rendered with: cleaned, estimated or the source's).",
            True,
        ),
        Column("target_video", pa.binary(), "(T, H, W, 3) real clip frames, H.264 MP4 bytes."),
        Column("scene_video", pa.binary(), "(T, H, W, 3) rendered static scene, H.264 MP4 bytes."),
        Column(
            "visible",
            pa.binary(),
            "(T, H, W) uint8 visibility, 1 = scene point rendered on the pixel; lossless FFV1.",
        ),
        Column("skeleton_video", pa.binary(), "(T, H, W, 3) hand skeleton video, H.264 MP4 bytes."),
        Column("first_frame", pa.binary(), "(H, W, 3) hand-free first frame, RGB PNG."),
        Column(
            "first_frame_source",
            pa.string(),
            "Where first_frame came from: 'inpaint', 'first_frame_clean' (source ground truth) "
            "or 'frame0' (the clip's own frame 0, hands included).",
        ),
        Column(
            "hand_mask",
            pa.binary(),
            "(T, H, W) uint8 1 = hand or arm, lossless FFV1 (hand_mask stage, else the source's); "
            "used by evaluation for the hand region. Null when neither exists.",
            True,
        ),
        Column(
            "depth0",
            pa.binary(),
            "(1, H, W) reference z-depth of frame 0 (estimated or source), FFV1 uint16 steps of "
            "depth_unit_m; 0 = unknown. Null when unknown.",
            True,
        ),
        Column("depth_unit_m", pa.float64(), "Metres per uint16 step of depth0.", True),
        Column("prompt", pa.string(), "Text prompt of the clip."),
        Column("visible_fraction", pa.float64(), "Mean visible fraction of frames 1..T-1."),
        Column(
            "registered_fraction",
            pa.float64(),
            "Fraction of the clip's frames with an estimated pose (1 for source poses).",
        ),
        Column(
            "hand_valid_fraction",
            pa.float64(),
            "Fraction of sample frames with at least one hand keypoint in view.",
        ),
    ),
    validators=(_check_pack,),
)


def _check_simulation(row: Mapping[str, Any]) -> list[str]:
    problems: list[str] = []
    t = row["num_frames"]
    if t is None or t < 1:
        problems.append(f"num_frames must be >= 1, got {t}")
    if not len(row["video"]):
        problems.append("video must be non-empty H.264 bytes")
    if row["sampling_steps"] < 1:
        problems.append(f"sampling_steps must be >= 1, got {row['sampling_steps']}")
    return problems


SIMULATION = ShardSchema(
    name="simulation",
    version=2,  # 2: no wall-clock seconds column (shards are byte-reproducible; see the manifest)
    doc="A generated clip per row: the observation model's video for a state and action.",
    columns=(
        Column("clip_id", pa.string(), "Id of the packed sample (state and action) it came from."),
        Column("num_frames", pa.int32(), "Frames T of the generated video."),
        Column("width", pa.int32(), "Frame width W."),
        Column("height", pa.int32(), "Frame height H."),
        Column("fps", pa.float64(), "Frames per second."),
        Column("video", pa.binary(), "(T, H, W, 3) generated frames, H.264 MP4 bytes."),
        Column("preset", pa.string(), "Model preset that generated it."),
        Column("checkpoint", pa.string(), "Checkpoint file the weights came from ('' = none)."),
        Column("checkpoint_step", pa.int64(), "Training step of that checkpoint (0 = none)."),
        Column("sampling_steps", pa.int32(), "Euler steps of the flow sampler."),
        Column("guidance_scale", pa.float64(), "Classifier-free guidance scale."),
        Column("seed", pa.int64(), "Noise seed."),
    ),
    validators=(_check_simulation,),
)


def _check_evaluation(row: Mapping[str, Any]) -> list[str]:
    problems: list[str] = []
    for name in ("ssim", "ssim_baseline"):
        if not -1.0 <= row[name] <= 1.0:
            problems.append(f"{name} must be in [-1, 1], got {row[name]}")
    if not 0.0 <= row["hand_fraction"] <= 1.0:
        problems.append(f"hand_fraction must be in [0, 1], got {row['hand_fraction']}")
    return problems


EVALUATION = ShardSchema(
    name="evaluation",
    version=1,
    doc="Figures of one generated clip against its packed ground truth, with the baseline.",
    columns=(
        Column("clip_id", pa.string(), "Clip id."),
        Column("num_frames", pa.int32(), "Frames compared (frame 0 included)."),
        Column("psnr", pa.float64(), "PSNR in dB over all frames and pixels (inf if identical)."),
        Column(
            "psnr_hand",
            pa.float64(),
            "PSNR in dB over hand pixels (pack hand_mask); null without a hand mask or hand.",
            True,
        ),
        Column("ssim", pa.float64(), "Mean SSIM over frames (11x11 Gaussian window)."),
        Column(
            "psnr_baseline",
            pa.float64(),
            "PSNR of the copy-the-scene-video baseline (first frame, then the scene render, "
            "black where nothing was rendered): what the model is conditioned on.",
        ),
        Column("psnr_hand_baseline", pa.float64(), "Baseline PSNR over hand pixels.", True),
        Column("ssim_baseline", pa.float64(), "Baseline mean SSIM."),
        Column("lpips", pa.float64(), "LPIPS (AlexNet) when its weights exist locally.", True),
        Column(
            "depth_err",
            pa.float64(),
            "AbsRel error of frame-0 depth estimated from the generated clip vs the reference "
            "depth, after median scale alignment; null when not computed.",
            True,
        ),
        Column(
            "cam_err",
            pa.float64(),
            "Mean per-pixel Plücker-ray L2 distance between cameras estimated from the generated "
            "clip (aligned at frame 0, scaled by depth) and the reference; null if not computed.",
            True,
        ),
        Column(
            "camera_backend",
            pa.string(),
            "How Depth-ERR/Cam-ERR were estimated: 'none', or a depth_camera backend.",
        ),
        Column("hand_fraction", pa.float64(), "Fraction of pixels in the hand region."),
        Column("note", pa.string(), "Why a figure is null (empty when all were computed)."),
    ),
    validators=(_check_evaluation,),
)
