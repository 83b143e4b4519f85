"""The EgoDex on-disk format: dataset keys, the ARKit joint map and the camera axes.

One description, shared by the reader (:mod:`egosim.stages.ingest.egodex`) and the synthetic
world's writer (:mod:`egosim.world.egodex_export`), so that both directions agree by construction.

EgoDex (Apple, 2025) layout, one episode per stem in a task folder:

- ``camera/intrinsic`` (3, 3) pinhole matrix in pixels of the 1920x1080 video.
- ``transforms/<name>`` (T, 4, 4) world-frame poses (ARKit world, y up, metres) of ``camera`` and
  of every tracked joint: upper body (``hip``, ``spine1..7``, ``neck1..4``, ``<side>Shoulder``,
  ``<side>Arm``, ``<side>Forearm``) and 25 per hand (``<side>Hand`` is the wrist).
- ``confidences/<name>`` (T,) in 0..1 for every transform except ``camera``. The wrist's value
  says whether the hand is tracked at all; finger values are relative to the wrist.
- File attributes: ``llm_description`` (and ``description``, ``task``, ``session_name``, ...).

``transforms/camera`` is camera-to-world with the camera axes already in OpenCV's order (x right,
y down, z forward): EgoDex's own utilities and independent overlays project
``inv(camera) @ joint`` straight through ``camera/intrinsic`` with hands at z > 0. The axis change
lives in :data:`EGODEX_CAM_FROM_CAM` (identity) so that both directions share one definition; the
reader checks it on every file (hands must lie in front of the camera).
"""

from __future__ import annotations

import numpy as np

from egosim.pipeline.geometry import invert_se3

EGODEX_SIDES = ("left", "right")  # hand 0, hand 1
# Joint name suffixes in our 21-joint MANO order (wrist; thumb, index, middle, ring, little chains,
# each knuckle -> tip). The four finger metacarpals of ARKit's 25-joint hand are not in this order.
_SUFFIXES_21 = (
    "Hand",
    "ThumbKnuckle",
    "ThumbIntermediateBase",
    "ThumbIntermediateTip",
    "ThumbTip",
    "IndexFingerKnuckle",
    "IndexFingerIntermediateBase",
    "IndexFingerIntermediateTip",
    "IndexFingerTip",
    "MiddleFingerKnuckle",
    "MiddleFingerIntermediateBase",
    "MiddleFingerIntermediateTip",
    "MiddleFingerTip",
    "RingFingerKnuckle",
    "RingFingerIntermediateBase",
    "RingFingerIntermediateTip",
    "RingFingerTip",
    "LittleFingerKnuckle",
    "LittleFingerIntermediateBase",
    "LittleFingerIntermediateTip",
    "LittleFingerTip",
)
# EgoDex/ARKit joint name -> (hand index, our joint index): the one mapping table, 42 entries.
EGODEX_HAND_JOINTS: dict[str, tuple[int, int]] = {
    f"{side}{suffix}": (hand, joint)
    for hand, side in enumerate(EGODEX_SIDES)
    for joint, suffix in enumerate(_SUFFIXES_21)
}
# Finger metacarpals (dropped on read) -> our index of the knuckle they precede.
EGODEX_METACARPALS = {
    "IndexFingerMetacarpal": 5,
    "MiddleFingerMetacarpal": 9,
    "RingFingerMetacarpal": 13,
    "LittleFingerMetacarpal": 17,
}
# EgoDex camera axes expressed in ours (OpenCV): identity, see the module docstring. Were EgoDex's
# camera ARKit-style (y up, z backward) this would be diag(1, -1, -1, 1).
EGODEX_CAM_FROM_CAM = np.eye(4)


def egodex_camera_to_ours(world_from_egodex_cam: np.ndarray) -> np.ndarray:
    """``(T, 4, 4)`` EgoDex ``transforms/camera`` -> our ``world_from_cam`` (OpenCV axes)."""
    return np.asarray(world_from_egodex_cam, dtype=np.float64) @ EGODEX_CAM_FROM_CAM


def ours_to_egodex_camera(world_from_cam: np.ndarray) -> np.ndarray:
    """Our ``(T, 4, 4)`` ``world_from_cam`` -> EgoDex ``transforms/camera``."""
    return np.asarray(world_from_cam, dtype=np.float64) @ invert_se3(EGODEX_CAM_FROM_CAM)
