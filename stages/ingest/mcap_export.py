"""Export a :class:`~egosim.pipeline.records.Clip` as an MCAP file that Foxglove opens.

Topics (Foxglove protobuf schemas; every message stamped at the frame's time):

- ``/camera/image`` ``foxglove.CompressedImage`` (JPEG or PNG), frame id ``camera``;
- ``/camera/calibration`` ``foxglove.CameraCalibration`` (``K``, ``P``; no distortion: clips are
  undistorted), one per frame so that Foxglove's 3D panel can place the image;
- ``/tf`` ``foxglove.FrameTransform`` ``world`` -> ``camera`` (the clip's ``world_from_cam``, OpenCV
  camera axes, as Foxglove's camera frames expect), when the clip has poses;
- ``/camera/trajectory`` ``foxglove.PosesInFrame``: the whole camera path in ``world``, every frame;
- ``/scene/image`` ``foxglove.CompressedImage``: the static-scene video, when present;
- ``/scene/points`` ``foxglove.PointCloud``: the first frame's depth unprojected into ``world``
  (subsampled, coloured), when the clip has depth and poses;
- ``/hands/skeleton`` ``foxglove.SceneUpdate``: the valid hands' bones as line lists in ``world``.

:func:`egosim.stages.ingest.mcap_source.read_mcap_clip` reads the camera topics back.
"""

from __future__ import annotations

from pathlib import Path

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
from mcap_protobuf.writer import Writer

from egosim.pipeline.geometry import quat_from_matrix, transform_points, unproject_depth
from egosim.pipeline.records import Clip

WORLD_FRAME = "world"  # parent frame id of the camera transforms
CAMERA_FRAME = "camera"  # frame id of images, calibration and the camera transform's child
IMAGE_TOPIC = "/camera/image"
CALIBRATION_TOPIC = "/camera/calibration"
TF_TOPIC = "/tf"
# Bones of the 21-joint MANO/OpenPose hand: wrist to each finger's first joint, then along it.
HAND_BONES = tuple(
    (0 if j == base else j - 1, j) for base in (1, 5, 9, 13, 17) for j in range(base, base + 4)
)
_HAND_COLOURS = ((0.2, 0.5, 1.0), (1.0, 0.35, 0.2))  # left blue, right orange


def _stamp(ns: int) -> Timestamp:
    return Timestamp(seconds=ns // 1_000_000_000, nanos=ns % 1_000_000_000)


def _pose(world_from_x: np.ndarray) -> tuple[Vector3, Quaternion]:
    t = world_from_x[:3, 3]
    w, x, y, z = quat_from_matrix(world_from_x[:3, :3])
    return Vector3(x=t[0], y=t[1], z=t[2]), Quaternion(x=x, y=y, z=z, w=w)


def _encode_image(image: np.ndarray, fmt: str, jpeg_quality: int) -> bytes:
    """``(H, W, 3)`` uint8 RGB -> JPEG or PNG bytes."""
    bgr = np.ascontiguousarray(image[..., ::-1])
    params = [cv2.IMWRITE_JPEG_QUALITY, jpeg_quality] if fmt == "jpeg" else []
    ok, data = cv2.imencode(".jpg" if fmt == "jpeg" else ".png", bgr, params)
    if not ok:
        raise ValueError(f"OpenCV could not encode a {image.shape} image as {fmt}")
    return data.tobytes()


def _point_cloud(clip: Clip, ns: int, max_points: int) -> PointCloud:
    """First-frame depth as a coloured world point cloud (x, y, z float32; r, g, b, a uint8)."""
    depth = clip.depth[0]  # (H, W)
    points_cam = unproject_depth(depth, clip.intrinsics)  # (H, W, 3)
    keep = depth > 0  # (H, W)
    points = transform_points(clip.world_from_cam[0], points_cam[keep])  # (N, 3)
    colours = clip.frames[0][keep]  # (N, 3)
    step = max(1, int(np.ceil(len(points) / max_points)))
    points, colours = points[::step], colours[::step]
    record = np.zeros(len(points), dtype=[("xyz", "<f4", 3), ("rgba", "u1", 4)])  # 16 bytes
    record["xyz"] = points
    record["rgba"][:, :3] = colours
    record["rgba"][:, 3] = 255
    fields = [
        PackedElementField(name=n, offset=4 * i, type=PackedElementField.FLOAT32)
        for i, n in enumerate("xyz")
    ] + [
        PackedElementField(name=n, offset=12 + i, type=PackedElementField.UINT8)
        for i, n in enumerate(("red", "green", "blue", "alpha"))
    ]
    return PointCloud(
        timestamp=_stamp(ns),
        frame_id=WORLD_FRAME,
        pose=Pose(position=Vector3(), orientation=Quaternion(w=1.0)),
        point_stride=16,
        fields=fields,
        data=record.tobytes(),
    )


def _skeleton(clip: Clip, index: int, ns: int) -> SceneUpdate:
    """The frame's valid hands as one line-list entity per hand (deleted after one frame)."""
    entities = []
    for hand in range(2):
        if not clip.hand_valid[index, hand]:
            continue
        joints = clip.hand_joints[index, hand].astype(np.float64)  # (21, 3)
        pts = [
            Point3(x=p[0], y=p[1], z=p[2]) for a, b in HAND_BONES for p in (joints[a], joints[b])
        ]
        r, g, b = _HAND_COLOURS[hand]
        line = LinePrimitive(
            type=LinePrimitive.LINE_LIST,
            pose=Pose(position=Vector3(), orientation=Quaternion(w=1.0)),
            thickness=4.0,
            scale_invariant=True,
            points=pts,
            color=Color(r=r, g=g, b=b, a=1.0),
        )
        entities.append(
            SceneEntity(
                timestamp=_stamp(ns),
                frame_id=WORLD_FRAME,
                id=("left", "right")[hand],
                lines=[line],
            )
        )
    return SceneUpdate(entities=entities)


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
    fx, fy, cx, cy = (float(v) for v in clip.intrinsics)
    k = [fx, 0.0, cx, 0.0, fy, cy, 0.0, 0.0, 1.0]
    p = [fx, 0.0, cx, 0.0, 0.0, fy, cy, 0.0, 0.0, 0.0, 1.0, 0.0]
    times_ns = [start_time_ns + round(float(t) * 1e9) for t in clip.timestamps]
    has_pose = clip.world_from_cam is not None
    has_hands = clip.hand_joints is not None and clip.hand_valid is not None
    with open(tmp, "wb") as f, Writer(f) as writer:
        for i, ns in enumerate(times_ns):

            def write(topic: str, message: object, ns: int = ns) -> None:
                writer.write_message(topic, message, log_time=ns, publish_time=ns)

            stamp = _stamp(ns)
            write(
                CALIBRATION_TOPIC,
                CameraCalibration(
                    timestamp=stamp,
                    frame_id=CAMERA_FRAME,
                    width=clip.width,
                    height=clip.height,
                    distortion_model="plumb_bob",
                    D=[0.0] * 5,
                    K=k,
                    R=[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
                    P=p,
                ),
            )
            if has_pose:
                translation, rotation = _pose(clip.world_from_cam[i])
                write(
                    TF_TOPIC,
                    FrameTransform(
                        timestamp=stamp,
                        parent_frame_id=WORLD_FRAME,
                        child_frame_id=CAMERA_FRAME,
                        translation=translation,
                        rotation=rotation,
                    ),
                )
            write(
                IMAGE_TOPIC,
                CompressedImage(
                    timestamp=stamp,
                    frame_id=CAMERA_FRAME,
                    data=_encode_image(clip.frames[i], image_format, jpeg_quality),
                    format=image_format,
                ),
            )
            if clip.static_frames is not None:
                write(
                    "/scene/image",
                    CompressedImage(
                        timestamp=stamp,
                        frame_id=CAMERA_FRAME,
                        data=_encode_image(clip.static_frames[i], image_format, jpeg_quality),
                        format=image_format,
                    ),
                )
            if has_pose:
                poses = [
                    Pose(position=a, orientation=b) for a, b in map(_pose, clip.world_from_cam)
                ]
                write(
                    "/camera/trajectory",
                    PosesInFrame(timestamp=stamp, frame_id=WORLD_FRAME, poses=poses),
                )
            if has_pose and clip.depth is not None and i == 0:
                write("/scene/points", _point_cloud(clip, ns, max_cloud_points))
            if has_hands:
                write("/hands/skeleton", _skeleton(clip, i, ns))
    tmp.replace(path)
    return path
