"""Foxglove MCAP building blocks shared by every MCAP egosim writes (and the ingest reader).

One place decides how egosim data becomes Foxglove protobuf messages:

- **Pixel centres.** egosim puts pixel centres at integer + 0.5 (``geometry.pixel_grid``); ROS
  and Foxglove calibrations (``K``, ``P``) put them at integers. :func:`calibration_message`
  writes ``cx - 0.5, cy - 0.5`` and :func:`intrinsics_from_k` adds the 0.5 back when a
  recording is read. This is the only place the convention is converted.
- **Poses.** A ``foxglove.FrameTransform`` is the child frame's pose in its parent
  (``parent_from_child``); egosim's ``world_from_cam`` (OpenCV camera axes, which Foxglove's
  camera frames use too) is written as parent ``world``, child the camera frame, unchanged.
- **Time.** Every message is stamped (``log_time``, ``publish_time`` and the header timestamp)
  with integer nanoseconds: :func:`time_ns` turns clip seconds into them.
- **Images** are ``foxglove.CompressedImage`` (JPEG or PNG; masks as PNG ``mono8`` 0/255), point
  clouds ``foxglove.PointCloud`` (x, y, z float32 then red, green, blue, alpha uint8, plus
  optional extra uint8 fields), hand skeletons ``foxglove.SceneUpdate`` line lists.
"""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np
from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
from foxglove_schemas_protobuf.Color_pb2 import Color
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.LinePrimitive_pb2 import LinePrimitive
from foxglove_schemas_protobuf.PackedElementField_pb2 import PackedElementField
from foxglove_schemas_protobuf.Point3_pb2 import Point3
from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud
from foxglove_schemas_protobuf.Pose_pb2 import Pose
from foxglove_schemas_protobuf.PosesInFrame_pb2 import PosesInFrame
from foxglove_schemas_protobuf.Quaternion_pb2 import Quaternion
from foxglove_schemas_protobuf.SceneEntity_pb2 import SceneEntity
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from foxglove_schemas_protobuf.Vector3_pb2 import Vector3
from google.protobuf.timestamp_pb2 import Timestamp

from egosim.pipeline.geometry import quat_from_matrix

WORLD_FRAME = "world"  # parent frame id of every camera transform, point cloud and skeleton
PIXEL_CENTRE_OFFSET = 0.5  # egosim pixel centres (integer + 0.5) minus ROS/Foxglove ones (integer)
# Bones of the 21-joint MANO/OpenPose hand: wrist to each finger's first joint, then along it.
HAND_BONES = tuple(
    (0 if j == base else j - 1, j) for base in (1, 5, 9, 13, 17) for j in range(base, base + 4)
)
HAND_COLOURS = ((0.2, 0.5, 1.0), (1.0, 0.35, 0.2))  # RGB 0..1: hand 0 (left) blue, 1 orange
HAND_NAMES = ("left", "right")  # scene entity id per hand slot
POINT_STRIDE = 16  # bytes per point of point_cloud_message without extra fields


class FoxgloveExportError(ValueError):
    """Data that cannot become a Foxglove message; the message names what and why."""


def time_ns(seconds: float) -> int:
    """Seconds (a clip timestamp) as integer nanoseconds, rounded."""
    return round(float(seconds) * 1e9)


def stamp(ns: int) -> Timestamp:
    """Integer nanoseconds as a ``google.protobuf.Timestamp``."""
    return Timestamp(seconds=ns // 1_000_000_000, nanos=ns % 1_000_000_000)


def pose_parts(world_from_x: np.ndarray) -> tuple[Vector3, Quaternion]:
    """A ``(4, 4)`` rigid transform as Foxglove's translation and ``(x, y, z, w)`` rotation."""
    t = np.asarray(world_from_x, dtype=np.float64)[:3, 3]
    w, x, y, z = quat_from_matrix(np.asarray(world_from_x, dtype=np.float64)[:3, :3])
    return Vector3(x=t[0], y=t[1], z=t[2]), Quaternion(x=x, y=y, z=z, w=w)


def pose(world_from_x: np.ndarray) -> Pose:
    """A ``(4, 4)`` rigid transform as a ``foxglove.Pose``."""
    position, orientation = pose_parts(world_from_x)
    return Pose(position=position, orientation=orientation)


IDENTITY_POSE = Pose(position=Vector3(), orientation=Quaternion(w=1.0))  # a frame's own origin


def frame_transform(
    ns: int, parent: str, child: str, parent_from_child: np.ndarray
) -> FrameTransform:
    """``foxglove.FrameTransform``: the pose of ``child`` in ``parent`` at ``ns``."""
    translation, rotation = pose_parts(parent_from_child)
    return FrameTransform(
        timestamp=stamp(ns),
        parent_frame_id=parent,
        child_frame_id=child,
        translation=translation,
        rotation=rotation,
    )


def poses_in_frame(ns: int, world_from_cam: np.ndarray) -> PosesInFrame:
    """A whole camera path ``(T, 4, 4)`` as one ``foxglove.PosesInFrame`` in ``world``."""
    return PosesInFrame(
        timestamp=stamp(ns), frame_id=WORLD_FRAME, poses=[pose(m) for m in world_from_cam]
    )


def calibration_message(
    ns: int, frame_id: str, intrinsics: np.ndarray, width: int, height: int
) -> CameraCalibration:
    """``foxglove.CameraCalibration`` of an undistorted pinhole camera (no distortion).

    ``intrinsics`` are egosim's ``fx, fy, cx, cy`` (pixel centres at integer + 0.5); ``K`` and
    ``P`` get ``cx - 0.5, cy - 0.5``, the ROS/Foxglove convention (centres at integers).
    """
    fx, fy, cx, cy = (float(v) for v in np.asarray(intrinsics, dtype=np.float64))
    cx, cy = cx - PIXEL_CENTRE_OFFSET, cy - PIXEL_CENTRE_OFFSET
    return CameraCalibration(
        timestamp=stamp(ns),
        frame_id=frame_id,
        width=int(width),
        height=int(height),
        distortion_model="plumb_bob",
        D=[0.0] * 5,
        K=[fx, 0.0, cx, 0.0, fy, cy, 0.0, 0.0, 1.0],
        R=[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
        P=[fx, 0.0, cx, 0.0, 0.0, fy, cy, 0.0, 0.0, 0.0, 1.0, 0.0],
    )


def intrinsics_from_k(k: Sequence[float]) -> np.ndarray:
    """egosim ``(4,)`` ``fx, fy, cx, cy`` from a ROS/Foxglove row-major ``K`` (adds the 0.5)."""
    kmat = np.asarray(k, dtype=np.float64)
    if kmat.size != 9:
        raise FoxgloveExportError(f"K must hold 9 values, got {kmat.size}")
    return np.array(
        [kmat[0], kmat[4], kmat[2] + PIXEL_CENTRE_OFFSET, kmat[5] + PIXEL_CENTRE_OFFSET]
    )


def encode_image(image: np.ndarray, fmt: str = "jpeg", jpeg_quality: int = 95) -> bytes:
    """``(H, W, 3)`` uint8 RGB or ``(H, W)`` uint8 grey -> JPEG or PNG bytes."""
    if fmt not in ("jpeg", "png"):
        raise FoxgloveExportError(f"image format must be 'jpeg' or 'png', got {fmt!r}")
    image = np.asarray(image)
    if image.dtype != np.uint8 or image.ndim not in (2, 3):
        raise FoxgloveExportError(f"images must be uint8 (H, W[, 3]), got {image.shape}")
    data = np.ascontiguousarray(image[..., ::-1] if image.ndim == 3 else image)  # RGB -> BGR
    params = [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)] if fmt == "jpeg" else []
    ok, buf = cv2.imencode(".jpg" if fmt == "jpeg" else ".png", data, params)
    if not ok:
        raise FoxgloveExportError(f"OpenCV could not encode a {image.shape} image as {fmt}")
    return buf.tobytes()


def image_message(
    ns: int, frame_id: str, image: np.ndarray, fmt: str = "jpeg", jpeg_quality: int = 95
) -> CompressedImage:
    """``foxglove.CompressedImage`` of an RGB or grey uint8 image."""
    return CompressedImage(
        timestamp=stamp(ns),
        frame_id=frame_id,
        data=encode_image(image, fmt, jpeg_quality),
        format=fmt,
    )


def mask_message(ns: int, frame_id: str, mask: np.ndarray) -> CompressedImage:
    """A ``{0, 1}`` mask ``(H, W)`` as a lossless PNG image, 1 -> 255 (white)."""
    return image_message(ns, frame_id, (np.asarray(mask) > 0).astype(np.uint8) * 255, "png")


def point_cloud_message(
    ns: int,
    points_world: np.ndarray,
    colours: np.ndarray,
    extra: dict[str, np.ndarray] | None = None,
) -> PointCloud:
    """``foxglove.PointCloud`` in ``world``: ``points_world (N, 3)`` metres, ``colours (N, 3)``.

    Each point is x, y, z float32 (offsets 0, 4, 8), red, green, blue, alpha uint8 (12..15),
    then one uint8 field per ``extra`` entry ``name -> (N,)`` in the mapping's order.
    """
    points = np.asarray(points_world, dtype=np.float32).reshape(-1, 3)  # (N, 3)
    rgb = np.asarray(colours, dtype=np.uint8).reshape(-1, 3)  # (N, 3)
    extra = extra or {}
    if len(rgb) != len(points) or any(len(v) != len(points) for v in extra.values()):
        raise FoxgloveExportError(
            f"point cloud arrays disagree: {len(points)} points, {len(rgb)} colours, "
            f"{ {k: len(v) for k, v in extra.items()} }"
        )
    dtype = [("xyz", "<f4", 3), ("rgba", "u1", 4)] + [(n, "u1") for n in extra]
    record = np.zeros(len(points), dtype=dtype)
    record["xyz"] = points
    record["rgba"][:, :3] = rgb
    record["rgba"][:, 3] = 255
    for name, values in extra.items():
        record[name] = np.asarray(values, dtype=np.uint8)
    fields = [
        PackedElementField(name=n, offset=4 * i, type=PackedElementField.FLOAT32)
        for i, n in enumerate("xyz")
    ] + [
        PackedElementField(name=n, offset=12 + i, type=PackedElementField.UINT8)
        for i, n in enumerate(("red", "green", "blue", "alpha"))
    ]
    fields += [
        PackedElementField(name=n, offset=POINT_STRIDE + i, type=PackedElementField.UINT8)
        for i, n in enumerate(extra)
    ]
    return PointCloud(
        timestamp=stamp(ns),
        frame_id=WORLD_FRAME,
        pose=IDENTITY_POSE,
        point_stride=record.dtype.itemsize,
        fields=fields,
        data=record.tobytes(),
    )


def skeleton_message(
    ns: int, joints_world: np.ndarray, valid: np.ndarray, thickness_px: float = 4.0
) -> SceneUpdate:
    """The valid hands of one frame as ``foxglove.SceneUpdate`` line lists in ``world``.

    ``joints_world (2, 21, 3)`` metres, ``valid (2,)``; one entity per valid hand (id ``left`` or
    ``right``), its bones (:data:`HAND_BONES`) as point pairs of one ``LINE_LIST``. Entities
    carry no lifetime: the next frame's update replaces them (a hand missing in a frame is
    deleted by name).
    """
    joints = np.asarray(joints_world, dtype=np.float64)  # (2, 21, 3)
    entities, deletions = [], []
    for hand in range(2):
        if not bool(valid[hand]) or not np.all(np.isfinite(joints[hand])):
            deletions.append(HAND_NAMES[hand])
            continue
        pts = [
            Point3(x=p[0], y=p[1], z=p[2])
            for a, b in HAND_BONES
            for p in (joints[hand, a], joints[hand, b])
        ]
        r, g, b = HAND_COLOURS[hand]
        line = LinePrimitive(
            type=LinePrimitive.LINE_LIST,
            pose=IDENTITY_POSE,
            thickness=thickness_px,
            scale_invariant=True,
            points=pts,
            color=Color(r=r, g=g, b=b, a=1.0),
        )
        entities.append(
            SceneEntity(
                timestamp=stamp(ns), frame_id=WORLD_FRAME, id=HAND_NAMES[hand], lines=[line]
            )
        )
    update = SceneUpdate(entities=entities)
    for name in deletions:
        deletion = update.deletions.add()
        deletion.timestamp.CopyFrom(stamp(ns))
        deletion.type = deletion.MATCHING_ID
        deletion.id = name
    return update
