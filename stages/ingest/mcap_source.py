"""Foxglove MCAP recordings (phone and robot captures) read into a :class:`Clip`.

What is read (messages are found by schema name, whatever their topic):

- Frames: ``foxglove.CompressedImage`` (any format OpenCV decodes: jpeg, png, webp) or
  ``foxglove.RawImage`` (``rgb8``, ``bgr8``, ``rgba8``, ``bgra8``, ``mono8``). With several image
  topics, ``image_topic`` picks one; by default the topic with the most messages.
- Intrinsics: the first ``foxglove.CameraCalibration`` (preferring one whose ``frame_id`` is the
  images' ``frame_id``): ``K`` gives ``fx, fy, cx, cy`` (``cx, cy`` + 0.5: ROS/Foxglove put pixel
  centres at integers, egosim at integer + 0.5), rescaled when the calibration's
  ``width x height`` differs from the images' size. Non-zero distortion ``D`` is removed at ingest:
  frames are undistorted with OpenCV (``plumb_bob``/``rational_polynomial``/empty model:
  ``cv2.undistort``; ``kannala_brandt``/``equidistant``/``fisheye``: ``cv2.fisheye``) onto the
  same ``K``; other models are rejected. Without a calibration the recording is rejected.
- Poses: ``foxglove.FrameTransform`` (and ``foxglove.FrameTransforms``) messages. Foxglove's (like
  ROS tf's) transform is the child frame's pose in the parent frame: ``parent_from_child``. The
  clip's ``world_from_cam`` is the chain from ``world_frame`` (default ``"world"``) to
  ``camera_frame`` (default: the images' ``frame_id``, else ``"camera"``), composed through any
  intermediate frames (each link interpolated at the image's time: linear translation, SLERP
  rotation; held constant outside its samples). Without a path between the two frames the clip has
  no poses (``world_from_cam = None``); ``require_pose=True`` rejects it instead.
- Camera axes: Foxglove's camera frames are OpenCV's (x right, y down, z forward), the default.
  ``camera_axes="opengl"`` (x right, y up, z backward) or ``"ros_body"`` (x forward, y left, z up,
  as a ROS ``camera_link``) convert at read time via :data:`CAM_FROM_OURS`.
- Timestamps: each image message's ``log_time`` (default), ``publish_time`` or its ``timestamp``
  field (``time_source="header"``), in seconds from the first image. fps is the median rate.

Every failure is :class:`ClipRejected` naming the file and the problem.
"""

from __future__ import annotations

from collections import Counter, defaultdict
from pathlib import Path
from typing import Any, Literal

import cv2
import numpy as np
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory

from egosim.pipeline.export.foxglove import intrinsics_from_k
from egosim.pipeline.geometry import (
    invert_se3,
    make_se3,
    matrix_from_quat,
    scale_intrinsics,
    slerp_rotations,
)
from egosim.pipeline.records import Clip
from egosim.pipeline.stage import ClipRejected

CameraAxes = Literal["opencv", "opengl", "ros_body"]
TimeSource = Literal["log", "publish", "header"]

IMAGE_SCHEMAS = ("foxglove.CompressedImage", "foxglove.RawImage")
CALIBRATION_SCHEMA = "foxglove.CameraCalibration"
TRANSFORM_SCHEMAS = ("foxglove.FrameTransform", "foxglove.FrameTransforms")
# ``recording_cam_from_opencv_cam``: maps a point in our OpenCV camera axes into the recording's
# camera axes, so that ``world_from_cam = world_from_recording_cam @ CAM_FROM_OURS[axes]``.
CAM_FROM_OURS: dict[str, np.ndarray] = {
    "opencv": np.eye(4),
    "opengl": np.diag([1.0, -1.0, -1.0, 1.0]),
    # ROS body: x forward = our z, y left = -our x, z up = -our y.
    "ros_body": make_se3(
        np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]]), np.zeros(3)
    ),
}
_PINHOLE_MODELS = ("", "plumb_bob", "rational_polynomial")
_FISHEYE_MODELS = ("kannala_brandt", "equidistant", "fisheye")
_RAW_CHANNELS = {"rgb8": 3, "bgr8": 3, "rgba8": 4, "bgra8": 4, "mono8": 1, "8uc1": 1, "8uc3": 3}


def _decode_image(schema: str, msg: Any) -> np.ndarray:
    """One image message -> ``(H, W, 3)`` uint8 RGB; raises ``ValueError`` on a bad image."""
    if schema == "foxglove.CompressedImage":
        buf = np.frombuffer(msg.data, dtype=np.uint8)
        bgr = cv2.imdecode(buf, cv2.IMREAD_COLOR) if buf.size else None
        if bgr is None:
            raise ValueError(f"cannot decode a {msg.format!r} CompressedImage of {buf.size} bytes")
        return np.ascontiguousarray(bgr[..., ::-1])
    enc = msg.encoding.lower()
    if enc not in _RAW_CHANNELS:
        raise ValueError(f"unsupported RawImage encoding {msg.encoding!r}")
    ch, h, w = _RAW_CHANNELS[enc], int(msg.height), int(msg.width)
    step = int(msg.step) or w * ch
    if h <= 0 or w <= 0 or step < w * ch or len(msg.data) < step * (h - 1) + w * ch:
        raise ValueError(f"RawImage {w}x{h} {enc} step {step} has only {len(msg.data)} bytes")
    data = np.frombuffer(msg.data, dtype=np.uint8)
    rows = np.lib.stride_tricks.as_strided(data, (h, w * ch), (step, 1))  # (H, W*C)
    img = rows.reshape(h, w, ch)
    if ch == 1:
        return np.repeat(img, 3, axis=2)
    if enc.startswith("bgr") or enc == "8uc3":
        img = img[..., 2::-1]
    return np.ascontiguousarray(img[..., :3])


def _undistorter(calib: Any, k: np.ndarray, width: int, height: int, where: str):
    """A function undistorting ``(H, W, 3)`` frames onto the same ``K``; None if undistorted."""
    d = np.asarray(calib.D, dtype=np.float64)
    if d.size == 0 or not np.any(d != 0):
        return None
    model = calib.distortion_model.lower()
    kmat = np.array([[k[0], 0, k[2]], [0, k[1], k[3]], [0, 0, 1.0]])
    if model in _PINHOLE_MODELS:
        maps = cv2.initUndistortRectifyMap(kmat, d, None, kmat, (width, height), cv2.CV_32FC1)
    elif model in _FISHEYE_MODELS and d.size >= 4:
        maps = cv2.fisheye.initUndistortRectifyMap(
            kmat, d[:4], np.eye(3), kmat, (width, height), cv2.CV_32FC1
        )
    else:
        raise ClipRejected(
            f"{where}: unsupported distortion model {calib.distortion_model!r} with {d.size} "
            "non-zero parameters (supported: plumb_bob, rational_polynomial, kannala_brandt)"
        )
    return lambda img: cv2.remap(img, maps[0], maps[1], cv2.INTER_LINEAR)


def _edge_poses(samples: list[tuple[float, np.ndarray]], query: np.ndarray) -> np.ndarray:
    """``parent_from_child`` samples ``[(t, (4, 4))]`` at ``query (T,)`` -> ``(T, 4, 4)``."""
    samples = sorted(samples, key=lambda s: s[0])
    times = np.array([s[0] for s in samples])  # (S,)
    mats = np.stack([s[1] for s in samples])  # (S, 4, 4)
    times, first = np.unique(times, return_index=True)
    mats = mats[first]
    if len(times) == 1:
        return np.repeat(mats, len(query), axis=0)
    rot = slerp_rotations(times, mats[:, :3, :3], query)  # (T, 3, 3)
    trans = np.stack([np.interp(query, times, mats[:, i, 3]) for i in range(3)], axis=-1)  # (T, 3)
    return make_se3(rot, trans)


def _chain(
    edges: dict[tuple[str, str], list[tuple[float, np.ndarray]]],
    world: str,
    camera: str,
    query: np.ndarray,
) -> np.ndarray | None:
    """``world_from_camera (T, 4, 4)`` through the transform tree, or None without a path."""
    neighbours: dict[str, list[tuple[str, str, str, bool]]] = defaultdict(list)
    for parent, child in edges:
        neighbours[parent].append((child, parent, child, False))
        neighbours[child].append((parent, parent, child, True))
    previous: dict[str, tuple[str, str, str, bool]] = {}
    queue, seen = [world], {world}
    while queue:
        node = queue.pop(0)
        for nxt, parent, child, inverse in neighbours[node]:
            if nxt not in seen:
                seen.add(nxt)
                previous[nxt] = (node, parent, child, inverse)
                queue.append(nxt)
    if camera not in seen or world == camera:
        return None
    out = np.tile(np.eye(4), (len(query), 1, 1))  # (T, 4, 4) world_from_node
    links = []
    node = camera
    while node != world:
        prev, parent, child, inverse = previous[node]
        links.append((parent, child, inverse))
        node = prev
    for parent, child, inverse in reversed(links):
        link = _edge_poses(edges[(parent, child)], query)  # (T, 4, 4) parent_from_child
        out = out @ (invert_se3(link) if inverse else link)
    return out


def _ns(stamp: Any) -> int:
    """A ``google.protobuf.Timestamp`` as integer nanoseconds."""
    return int(stamp.seconds) * 1_000_000_000 + int(stamp.nanos)


def _transform_matrix(tf: Any) -> np.ndarray:
    q = tf.rotation
    quat = np.array([q.w, q.x, q.y, q.z])
    if not np.all(np.isfinite(quat)) or np.linalg.norm(quat) < 1e-9:
        quat = np.array([1.0, 0.0, 0.0, 0.0])  # an unset rotation is the identity
    t = tf.translation
    return make_se3(matrix_from_quat(quat), np.array([t.x, t.y, t.z]))


Messages = list[tuple[int, str, Any]]  # (time ns, schema name, decoded message) per image
Edges = dict[tuple[str, str], list[tuple[int, np.ndarray]]]  # (parent, child) -> (ns, matrix)


def read_mcap_clip(
    path: Path,
    clip_id: str | None = None,
    image_topic: str | None = None,
    world_frame: str = "world",
    camera_frame: str | None = None,
    camera_axes: CameraAxes = "opencv",
    time_source: TimeSource = "log",
    require_pose: bool = False,
) -> Clip:
    """Read one Foxglove MCAP recording into a :class:`Clip` (see the module docstring).

    ``clip_id`` defaults to the file's stem. Raises :class:`ClipRejected` naming the file for an
    unreadable or corrupt MCAP, no image messages, an undecodable image, images of different sizes,
    no ``CameraCalibration``, an unsupported distortion model, non-increasing timestamps, or (with
    ``require_pose``) no transform chain from ``world_frame`` to the camera frame.
    """
    path = Path(path)
    if camera_axes not in CAM_FROM_OURS:
        raise ClipRejected(f"{path}: camera_axes must be one of {sorted(CAM_FROM_OURS)}")
    if not path.is_file():
        raise ClipRejected(f"{path}: MCAP file does not exist")
    images, calibrations, edges = _read_messages(path, time_source)
    image_topic, messages = _image_messages(path, images, image_topic)
    frame_id = messages[0][2].frame_id
    if not calibrations:
        raise ClipRejected(
            f"{path}: no foxglove.CameraCalibration message: intrinsics are needed for "
            f"image topic {image_topic!r}"
        )
    calib = next((c for c in calibrations if c.frame_id == frame_id), calibrations[0])
    frames, intrinsics = _calibrated_frames(path, messages, calib, image_topic)
    timestamps, fps = _timestamps(path, messages, time_source, image_topic)
    camera = camera_frame or frame_id or "camera"
    world_from_cam = None
    if edges:
        chain = _camera_chain(messages, edges, world_frame, camera, time_source)
        if chain is not None:
            world_from_cam = chain @ CAM_FROM_OURS[camera_axes]  # (T, 4, 4)
    if world_from_cam is None and require_pose:
        found = sorted({f"{p}->{c}" for p, c in edges})
        raise ClipRejected(
            f"{path}: no FrameTransform chain from {world_frame!r} to {camera!r} (found {found})"
        )
    return Clip(
        clip_id=clip_id or path.stem,
        source="mcap",
        source_uri=str(path),
        fps=fps,
        timestamps=timestamps,
        intrinsics=intrinsics,
        frames=np.stack(frames),
        world_from_cam=world_from_cam,
    ).check()


def _read_messages(path: Path, time_source: TimeSource) -> tuple[dict[str, Messages], list, Edges]:
    """Every image (by topic, stamped by ``time_source``), calibration and transform sample.

    Raises :class:`ClipRejected` for a file the MCAP reader or a decoder cannot read.
    """
    images: dict[str, Messages] = defaultdict(list)  # topic -> (ns, schema, message)
    calibrations: list[Any] = []
    edges: Edges = defaultdict(list)  # ns
    try:
        with open(path, "rb") as f:
            reader = make_reader(f, decoder_factories=[DecoderFactory()])
            for schema, channel, message, decoded in reader.iter_decoded_messages():
                name = schema.name if schema is not None else ""
                if name in IMAGE_SCHEMAS:
                    if time_source == "header":
                        t = _ns(decoded.timestamp)
                    elif time_source == "publish":
                        t = message.publish_time
                    else:
                        t = message.log_time
                    images[channel.topic].append((t, name, decoded))
                elif name == CALIBRATION_SCHEMA:
                    calibrations.append(decoded)
                elif name in TRANSFORM_SCHEMAS:
                    tfs = decoded.transforms if name.endswith("s") else [decoded]
                    for tf in tfs:
                        t = _ns(tf.timestamp) if tf.HasField("timestamp") else message.log_time
                        key = (tf.parent_frame_id, tf.child_frame_id)
                        edges[key].append((t, _transform_matrix(tf)))
    except ClipRejected:
        raise
    except Exception as exc:  # McapError, OSError, protobuf DecodeError, zstd: no common base
        raise ClipRejected(
            f"{path}: corrupt or unreadable MCAP: {type(exc).__name__}: {exc}"
        ) from exc
    return images, calibrations, edges


def _image_messages(
    path: Path, images: dict[str, Messages], image_topic: str | None
) -> tuple[str, Messages]:
    """The image topic (``image_topic``, else the one with most messages) and its messages in
    time order."""
    if not images:
        raise ClipRejected(f"{path}: no foxglove.CompressedImage or foxglove.RawImage messages")
    if image_topic is None:
        image_topic = Counter({k: len(v) for k, v in images.items()}).most_common(1)[0][0]
    elif image_topic not in images:
        raise ClipRejected(f"{path}: no image topic {image_topic!r} (found {sorted(images)})")
    return image_topic, sorted(images[image_topic], key=lambda m: m[0])


def _calibrated_frames(
    path: Path, messages: Messages, calib: Any, image_topic: str
) -> tuple[list[np.ndarray], np.ndarray]:
    """Decoded ``(H, W, 3)`` frames (undistorted when ``calib`` has distortion) and their
    ``(4,)`` intrinsics in egosim's pixel convention, rescaled to the images' size."""
    try:
        frames = [_decode_image(schema, msg) for _, schema, msg in messages]
    except ValueError as exc:
        raise ClipRejected(f"{path}: topic {image_topic!r}: {exc}") from exc
    shapes = Counter(f.shape for f in frames)
    if len(shapes) > 1:
        raise ClipRejected(f"{path}: images on {image_topic!r} differ in size: {dict(shapes)}")
    height, width = frames[0].shape[:2]
    kmat = np.asarray(calib.K, dtype=np.float64)
    if kmat.size != 9 or not np.all(np.isfinite(kmat)) or kmat[0] <= 0 or kmat[4] <= 0:
        raise ClipRejected(f"{path}: CameraCalibration K is not a valid 3x3 matrix: {list(kmat)}")
    intrinsics = intrinsics_from_k(kmat)  # ROS/Foxglove integer pixel centres -> egosim's + 0.5
    if calib.width and calib.height and (calib.width, calib.height) != (width, height):
        intrinsics = scale_intrinsics(intrinsics, width / calib.width, height / calib.height)
    undistort = _undistorter(calib, intrinsics, width, height, str(path))
    if undistort is not None:
        frames = [undistort(f) for f in frames]
    return frames, intrinsics


def _timestamps(
    path: Path, messages: Messages, time_source: TimeSource, image_topic: str
) -> tuple[np.ndarray, float]:
    """``(T,)`` seconds from the first image and the median frame rate (1 for one frame)."""
    # Integer nanoseconds until made relative: epoch seconds in float64 lose ~0.2 us.
    origin_ns = messages[0][0]
    timestamps = np.array([m[0] - origin_ns for m in messages], dtype=np.int64) * 1e-9  # (T,)
    if len(timestamps) > 1 and not np.all(np.diff(timestamps) > 0):
        raise ClipRejected(f"{path}: {time_source} times of {image_topic!r} are not increasing")
    fps = 1.0 / float(np.median(np.diff(timestamps))) if len(timestamps) > 1 else 1.0
    return timestamps, fps


def _camera_chain(
    messages: Messages, edges: Edges, world_frame: str, camera: str, time_source: TimeSource
) -> np.ndarray | None:
    """``(T, 4, 4)`` ``world_frame``-from-``camera`` at each image, in the recording's camera
    axes; None without a chain of transforms between the two frames."""
    origin_ns = messages[0][0]
    # Transforms are matched by their header stamps: use the images' header stamps when set.
    query_ns = [m[0] for m in messages]
    header_ns = [_ns(m[2].timestamp) for m in messages]
    if time_source != "header" and any(h > 0 for h in header_ns):
        query_ns = header_ns
    rel = {
        key: [((ns - origin_ns) * 1e-9, mat) for ns, mat in samples]
        for key, samples in edges.items()
    }
    query = np.array([ns - origin_ns for ns in query_ns], dtype=np.int64) * 1e-9  # (T,)
    return _chain(rel, world_frame, camera, query)
