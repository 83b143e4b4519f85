"""Export a :class:`~egosim.pipeline.records.Clip` as an MCAP file that Foxglove opens.

Topics (Foxglove protobuf schemas; every message stamped at the frame's time):

- ``/camera/image`` ``foxglove.CompressedImage`` (JPEG or PNG), frame id ``camera``;
- ``/camera/calibration`` ``foxglove.CameraCalibration`` (``K``, ``P``; no distortion: clips are
  undistorted; principal point in the ROS/Foxglove integer-pixel-centre convention, converted by
  :func:`egosim.pipeline.export.foxglove.calibration_message`), one per frame so that
  Foxglove's 3D panel can place the image;
- ``/tf`` ``foxglove.FrameTransform`` ``world`` -> ``camera`` (the clip's ``world_from_cam``, OpenCV
  camera axes, as Foxglove's camera frames expect), when the clip has poses;
- ``/camera/trajectory`` ``foxglove.PosesInFrame``: the whole camera path in ``world``, every frame;
- ``/scene/image`` ``foxglove.CompressedImage``: the static-scene video, when present;
- ``/scene/points`` ``foxglove.PointCloud``: the first frame's depth unprojected into ``world``
  (subsampled, coloured), when the clip has depth and poses;
- ``/hands/skeleton`` ``foxglove.SceneUpdate``: the valid hands' bones as line lists in ``world``.

The message builders live in :mod:`egosim.pipeline.export.foxglove` (shared with ``egosim view``,
which exports a whole run's clip). :func:`egosim.stages.ingest.mcap_source.read_mcap_clip` reads
the camera topics back.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from mcap_protobuf.writer import Writer

from egosim.pipeline.export.foxglove import (
    HAND_BONES,
    WORLD_FRAME,
    calibration_message,
    frame_transform,
    image_message,
    point_cloud_message,
    poses_in_frame,
    skeleton_message,
    stamp,
    time_ns,
)
from egosim.pipeline.geometry import transform_points, unproject_depth
from egosim.pipeline.records import Clip

__all__ = ["CAMERA_FRAME", "HAND_BONES", "WORLD_FRAME", "write_clip_mcap"]

CAMERA_FRAME = "camera"  # frame id of images, calibration and the camera transform's child
IMAGE_TOPIC = "/camera/image"
CALIBRATION_TOPIC = "/camera/calibration"
TF_TOPIC = "/tf"


def _depth_points(clip: Clip, max_points: int) -> tuple[np.ndarray, np.ndarray]:
    """First-frame depth as world points ``(N, 3)`` and colours ``(N, 3)``, subsampled."""
    depth = clip.depth[0]  # (H, W)
    points_cam = unproject_depth(depth, clip.intrinsics)  # (H, W, 3)
    keep = depth > 0  # (H, W)
    points = transform_points(clip.world_from_cam[0], points_cam[keep])  # (N, 3)
    colours = clip.frames[0][keep]  # (N, 3)
    step = max(1, int(np.ceil(len(points) / max_points)))
    return points[::step], colours[::step]


def write_clip_mcap(
    clip: Clip,
    path: Path,
    image_format: str = "jpeg",
    jpeg_quality: int = 95,
    start_time_ns: int = 0,
    max_cloud_points: int = 200_000,
) -> Path:
    """Write ``clip`` to ``path`` as a Foxglove MCAP (topics in the module docstring).

    ``image_format`` is ``"jpeg"`` (``jpeg_quality`` 1-100) or ``"png"`` (lossless). Message log and
    publish times are ``start_time_ns + timestamp``. The file is written to a temporary name and
    renamed, so a reader never sees half a file. Returns ``path``.
    """
    if image_format not in ("jpeg", "png"):
        raise ValueError(f"image_format must be 'jpeg' or 'png', got {image_format!r}")
    clip.check()
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    times_ns = [start_time_ns + time_ns(t) for t in clip.timestamps]
    has_pose = clip.world_from_cam is not None
    has_hands = clip.hand_joints is not None and clip.hand_valid is not None
    # The whole (T, 4, 4) path at every frame: built once, restamped per frame (write serialises).
    path_msg = poses_in_frame(times_ns[0], clip.world_from_cam) if has_pose else None
    with open(tmp, "wb") as f, Writer(f) as writer:
        for i, ns in enumerate(times_ns):

            def write(topic: str, message: object, ns: int = ns) -> None:
                writer.write_message(topic, message, log_time=ns, publish_time=ns)

            write(
                CALIBRATION_TOPIC,
                calibration_message(ns, CAMERA_FRAME, clip.intrinsics, clip.width, clip.height),
            )
            if has_pose:
                write(
                    TF_TOPIC, frame_transform(ns, WORLD_FRAME, CAMERA_FRAME, clip.world_from_cam[i])
                )
            write(
                IMAGE_TOPIC,
                image_message(ns, CAMERA_FRAME, clip.frames[i], image_format, jpeg_quality),
            )
            if clip.static_frames is not None:
                write(
                    "/scene/image",
                    image_message(
                        ns, CAMERA_FRAME, clip.static_frames[i], image_format, jpeg_quality
                    ),
                )
            if path_msg is not None:
                path_msg.timestamp.CopyFrom(stamp(ns))
                write("/camera/trajectory", path_msg)
            if has_pose and clip.depth is not None and i == 0:
                points, colours = _depth_points(clip, max_cloud_points)
                write("/scene/points", point_cloud_message(ns, points, colours))
            if has_hands:
                write(
                    "/hands/skeleton", skeleton_message(ns, clip.hand_joints[i], clip.hand_valid[i])
                )
    tmp.replace(path)
    return path
