"""``egosim view``: one Foxglove MCAP per clip of a run, every step's output aligned.

Everything is stamped with the clip's own timestamps (``clips.timestamps``, seconds, as
integer nanoseconds; log, publish and header time alike) and placed in one ``world`` frame:

Topics (schema; frame; what, from the step that wrote which schema):

- ``/camera/image`` (CompressedImage; ``camera``): the real video (``clips``);
- ``/camera/calibration`` (CameraCalibration; ``camera``): intrinsics (``depth_camera``, else
  ``clips``), every frame;
- ``/tf`` (FrameTransform): ``world`` -> ``camera``, the poses the conditions were rendered with
  (``poses`` > ``depth_camera`` > ``clips``, the stages' rule); ``world`` -> ``camera_raw``, the
  estimate before cleaning (``depth_camera``); ``world`` -> ``camera_source``, the source's own
  poses (``clips``);
- ``/camera/trajectory``, ``/camera_raw/trajectory`` (PosesInFrame; ``world``): the whole
  ``camera`` and ``camera_raw`` paths, every frame;
- ``/scene/image`` (CompressedImage; ``camera``): the scene video (``scene_render``);
- ``/scene/visible`` (PNG mono; ``camera``): white = a scene point landed (``scene_render``);
- ``/hands/skeleton_image`` (CompressedImage; ``camera``): the skeleton video (``keypoints``);
- ``/hands/mask`` (PNG mono; ``camera``): white = hand or arm (``hand_mask``, else ``clips``);
- ``/inpaint/first_frame`` (PNG; ``camera``): the hand-free first frame, at frame 0 (``inpaint``);
- ``/scene/cloud`` (PointCloud; ``world``): the scene cloud at frame 0 with a uint8
  ``confidence`` field (``scene_cloud``);
- ``/state/cloud`` (PointCloud; ``world``): the world state at frame 0 with a uint8 ``source``
  field (``state``);
- ``/hands/skeleton`` (SceneUpdate; ``world``): the 3D hand bones per frame (``hands``: the
  hands whose 3D it trusts, ``hand_lifted``; else ``clips``).

A topic whose step the run lacks (or that has no row for the clip) is left out; the file's
``egosim`` metadata record says which step each topic came from, the clip id and the prompt.
Calibrations use the ROS/Foxglove pixel-centre convention (``cx - 0.5``; see
:mod:`egosim.pipeline.export.foxglove`).
"""

from __future__ import annotations

import json
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
from mcap_protobuf.writer import Writer

from egosim.pipeline import media
from egosim.pipeline.export import foxglove as fx
from egosim.pipeline.export.run_index import ExportError, RunIndex
from egosim.pipeline.records import NUM_HAND_JOINTS, Clip
from egosim.pipeline.stage import ConfigError
from egosim.schemas import CLIPS, DEPTH_CAMERA, POSES
from egosim.schemas.captions import CAPTIONS
from egosim.schemas.hand_mask import HAND_MASK
from egosim.schemas.hands import HANDS
from egosim.schemas.ids import path_under, validate_id
from egosim.schemas.inpaint import INPAINT
from egosim.schemas.keypoints import KEYPOINTS
from egosim.schemas.scene import SCENE_CLOUD, SCENE_RENDER
from egosim.schemas.state import STATE

CAMERA_FRAME = "camera"  # frame of every image: the camera the conditions were rendered with
RAW_CAMERA_FRAME = "camera_raw"  # depth_camera's estimate, before pose_clean
SOURCE_CAMERA_FRAME = "camera_source"  # the source's own poses (clips)
METADATA_NAME = "egosim"  # name of the MCAP metadata record describing the clip


@dataclass(frozen=True)
class ViewConfig:
    """How ``egosim view`` encodes a clip."""

    image_format: Literal["jpeg", "png"] = "jpeg"  # RGB videos' frames (masks are always PNG)
    jpeg_quality: int = 90  # JPEG quality 1-100 of the RGB frames
    max_cloud_points: int = 0  # subsample point clouds to at most this many points (0 = all)

    def __post_init__(self) -> None:
        problems = []
        if self.image_format not in ("jpeg", "png"):
            problems.append(f"image_format must be 'jpeg' or 'png', got {self.image_format!r}")
        if not 1 <= self.jpeg_quality <= 100:
            problems.append(f"jpeg_quality must be in 1..100, got {self.jpeg_quality}")
        if self.max_cloud_points < 0:
            problems.append(f"max_cloud_points must be >= 0, got {self.max_cloud_points}")
        if problems:
            raise ConfigError("view: " + "; ".join(problems))


def _subsample(n: int, limit: int) -> slice:
    """Every k-th point so that at most ``limit`` of ``n`` remain (``limit`` 0 = all)."""
    return slice(None, None, max(1, int(np.ceil(n / limit)))) if limit else slice(None)


def _poses(row: dict[str, Any], t: int, what: str) -> np.ndarray:
    poses = np.asarray(row["world_from_cam"], dtype=np.float64)
    if poses.shape != (t, 16):
        raise ExportError(f"{what}: world_from_cam is {poses.shape}, expected ({t}, 16)")
    return poses.reshape(t, 4, 4)


def _clip(row: dict[str, Any]) -> Clip:
    """The parts of a ``clips`` row the view shows, decoded (not its depth or object videos)."""
    cid, t, h, w = row["clip_id"], int(row["num_frames"]), int(row["height"]), int(row["width"])
    joints, valid = row.get("hand_joints"), row.get("hand_valid")
    return Clip(
        clip_id=cid,
        source=row["source"],
        source_uri=row["source_uri"],
        fps=float(row["fps"]),
        timestamps=np.asarray(row["timestamps"], dtype=np.float64),
        intrinsics=np.asarray(row["intrinsics"], dtype=np.float64),
        frames=media.decode_rgb_video(row["video"], h, w, f"clip {cid!r} video"),
        world_from_cam=None
        if row.get("world_from_cam") is None
        else _poses(row, t, f"clip {cid!r} clips"),
        hand_joints=None
        if joints is None
        else np.asarray(joints, dtype=np.float32).reshape(t, 2, NUM_HAND_JOINTS, 3),
        hand_valid=None if valid is None else np.asarray(valid, dtype=bool),
        text=row.get("text"),
    ).check()


VIEW_STEPS = (
    DEPTH_CAMERA,
    POSES,
    HANDS,
    KEYPOINTS,
    HAND_MASK,
    INPAINT,
    SCENE_CLOUD,
    SCENE_RENDER,
    STATE,
    CAPTIONS,
)  # the schemas whose rows a view shows beside the clip's own


@dataclass
class _ClipView:
    """What one clip's MCAP shows, gathered from the run's rows (topics in the module doc)."""

    clip: Clip  # the decoded clips row
    clip_row: dict[str, Any]  # the raw clips row
    rows: dict[str, dict[str, Any] | None]  # schema name -> the clip's row (None: no row)
    steps: dict[str, str]  # schema name -> the run step that wrote it
    used: dict[str, str]  # topic -> step it came from (the metadata's "sources")
    intrinsics: np.ndarray | None = None  # (4,) of /camera/calibration
    camera_from: str | None = None  # schema the `camera` frame's poses came from
    frames: dict[str, np.ndarray] = field(default_factory=dict)  # child -> (T, 4, 4) poses
    trajectories: dict[str, str] = field(default_factory=dict)  # topic -> child frame
    videos: dict[str, np.ndarray] = field(default_factory=dict)  # topic -> (T, H, W, 3)
    masks: dict[str, np.ndarray] = field(default_factory=dict)  # topic -> (T, H, W) {0, 1}
    joints: np.ndarray | None = None  # (T, 2, 21, 3) of /hands/skeleton
    valid: np.ndarray | None = None  # (T, 2) of /hands/skeleton
    first_frame: np.ndarray | None = None  # (H, W, 3) of /inpaint/first_frame
    clouds: dict[str, Callable[[int], object]] = field(default_factory=dict)  # topic -> message

    @property
    def what(self) -> str:
        """``clip 'ID'``, for error messages."""
        return f"clip {self.clip.clip_id!r}"

    def take(self, topic: str, schema_name: str) -> None:
        """Record that ``topic`` shows the output of the step that wrote ``schema_name``."""
        self.used[topic] = self.steps[schema_name]


def write_clip_view(
    index: RunIndex, clip_id: str, path: Path, config: ViewConfig | None = None
) -> Path:
    """Write clip ``clip_id`` of the indexed run to ``path`` as one Foxglove MCAP.

    Topics in the module docstring. Written to ``path.tmp`` and renamed. Raises
    :class:`ExportError` when the run has no clips step or no row for ``clip_id``, or a step's
    row disagrees with the clip (frame count, size).
    """
    config = config or ViewConfig()
    clip_row = index.row(CLIPS, clip_id)
    if clip_row is None:
        raise ExportError(f"{index.root}: no clip {clip_id!r} in the clips step")
    view = _ClipView(
        clip=_clip(clip_row),
        clip_row=clip_row,
        rows={s.name: index.row(s, clip_id) for s in VIEW_STEPS},
        steps=index.steps,
        used={"/camera/image": index.steps[CLIPS.name]},
    )
    _gather_cameras(view)
    _gather_images(view)
    _gather_hands(view)
    _gather_first_frame_and_clouds(view, config)
    _write_view_mcap(view, index, Path(path), config)
    return Path(path)


def _gather_cameras(view: _ClipView) -> None:
    """Intrinsics and the ``camera``, ``camera_raw`` and ``camera_source`` poses (stages' rule:
    ``poses`` > ``depth_camera`` > ``clips``)."""
    clip, rows, t = view.clip, view.rows, view.clip.num_frames
    cams, cleaned = rows["depth_camera"], rows["poses"]
    view.intrinsics = np.asarray((cams or view.clip_row)["intrinsics"], dtype=np.float64)
    view.take("/camera/calibration", "depth_camera" if cams else "clips")
    view.camera_from = next(
        (n for n, r in (("poses", cleaned), ("depth_camera", cams)) if r is not None),
        "clips" if clip.world_from_cam is not None else None,
    )
    if view.camera_from == "clips":
        view.frames[CAMERA_FRAME] = clip.world_from_cam
    elif view.camera_from is not None:
        row = rows[view.camera_from]
        view.frames[CAMERA_FRAME] = _poses(row, t, f"{view.what} {view.camera_from}")
    if view.camera_from is not None:
        view.take("/tf:" + CAMERA_FRAME, view.camera_from)
        view.trajectories["/camera/trajectory"] = CAMERA_FRAME
    if cams is not None:
        view.frames[RAW_CAMERA_FRAME] = _poses(cams, t, f"{view.what} depth_camera")
        view.take("/tf:" + RAW_CAMERA_FRAME, "depth_camera")
        view.trajectories["/camera_raw/trajectory"] = RAW_CAMERA_FRAME
    if clip.world_from_cam is not None:
        view.frames[SOURCE_CAMERA_FRAME] = clip.world_from_cam
        view.take("/tf:" + SOURCE_CAMERA_FRAME, "clips")


def _gather_images(view: _ClipView) -> None:
    """The image and mask videos; raises :class:`ExportError` when one is not ``(T, H, W)``."""
    clip, rows, what = view.clip, view.rows, view.what
    t, h, w = clip.num_frames, clip.height, clip.width
    view.videos["/camera/image"] = clip.frames
    if (render := rows["scene_render"]) is not None:
        view.videos["/scene/image"] = media.decode_rgb_video(
            render["scene_video"], h, w, f"{what} scene_video"
        )
        view.masks["/scene/visible"] = media.decode_lossless_video(
            render["visible"], f"{what} visible"
        )
        view.take("/scene/image", "scene_render")
        view.take("/scene/visible", "scene_render")
    if (keypoints := rows["keypoints"]) is not None:
        view.videos["/hands/skeleton_image"] = media.decode_rgb_video(
            keypoints["skeleton_video"], h, w, f"{what} skeleton_video"
        )
        view.take("/hands/skeleton_image", "keypoints")
    if (hand_mask := rows["hand_mask"]) is not None:
        view.masks["/hands/mask"] = media.decode_lossless_video(
            hand_mask["hand_mask"], f"{what} hand_mask"
        )
        view.take("/hands/mask", "hand_mask")
    elif view.clip_row.get("hand_mask") is not None:
        view.masks["/hands/mask"] = media.decode_lossless_video(
            view.clip_row["hand_mask"], f"{what} clips hand_mask"
        )
        view.take("/hands/mask", "clips")
    bad = {
        topic: tuple(arr.shape[:3])
        for topic, arr in (*view.videos.items(), *view.masks.items())
        if tuple(arr.shape[:3]) != (t, h, w)
    }
    if bad:
        raise ExportError(f"{what}: videos disagree with the clip's {(t, h, w)}: {bad}")


def _gather_hands(view: _ClipView) -> None:
    """The 3D hand joints of ``/hands/skeleton``: the ``hands`` step's whose 3D it trusts (a
    2D-only hand's depth is a guess; the skeleton image draws it), else the clip's own."""
    clip, t = view.clip, view.clip.num_frames
    if (hands := view.rows["hands"]) is not None:
        view.joints = np.asarray(hands["hand_joints"], dtype=np.float64).reshape(t, 2, 21, 3)
        view.valid = np.asarray(hands["hand_lifted"], dtype=bool).reshape(t, 2)
        view.take("/hands/skeleton", "hands")
    elif clip.hand_joints is not None and clip.hand_valid is not None:
        view.joints, view.valid = clip.hand_joints, clip.hand_valid
        view.take("/hands/skeleton", "clips")


def _gather_first_frame_and_clouds(view: _ClipView, config: ViewConfig) -> None:
    """The inpainted first frame and the scene and state clouds (shown at frame 0)."""
    if (inpaint := view.rows["inpaint"]) is not None:
        view.first_frame = media.decode_png(
            inpaint["first_frame"], f"{view.what} inpaint first_frame"
        )
        view.take("/inpaint/first_frame", "inpaint")
    if (cloud := view.rows["scene_cloud"]) is not None:
        view.clouds["/scene/cloud"] = _cloud(cloud, "confidence", "point_confidence", config)
        view.take("/scene/cloud", "scene_cloud")
    if (state := view.rows["state"]) is not None:
        view.clouds["/state/cloud"] = _cloud(state, "source", "point_source", config)
        view.take("/state/cloud", "state")


def _write_view_mcap(view: _ClipView, index: RunIndex, path: Path, config: ViewConfig) -> None:
    """Write ``view`` to ``path`` (through ``path.tmp``, renamed when complete)."""
    tmp = path.with_name(path.name + ".tmp")
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        with open(tmp, "wb") as f, Writer(f) as writer:
            _write_view_messages(writer, view, config)
            writer.add_metadata(METADATA_NAME, _view_metadata(view, index))
        tmp.replace(path)
    finally:
        tmp.unlink(missing_ok=True)


def _write_view_messages(writer: Writer, view: _ClipView, config: ViewConfig) -> None:
    """Every frame's messages, in time order (frame 0 also carries the first frame and clouds)."""
    clip = view.clip
    times = [fx.time_ns(s) for s in clip.timestamps]
    # A trajectory is the whole (T, 4, 4) path at every frame: build it once, restamp per frame.
    paths = {t: fx.poses_in_frame(0, view.frames[c]) for t, c in view.trajectories.items()}
    fmt, quality = config.image_format, config.jpeg_quality

    def write(topic: str, message: object, ns: int) -> None:
        writer.write_message(topic, message, log_time=ns, publish_time=ns)

    for i, ns in enumerate(times):
        calibration = fx.calibration_message(
            ns, CAMERA_FRAME, view.intrinsics, clip.width, clip.height
        )
        write("/camera/calibration", calibration, ns)
        for child, poses in view.frames.items():
            write("/tf", fx.frame_transform(ns, fx.WORLD_FRAME, child, poses[i]), ns)
        for topic, path_msg in paths.items():
            path_msg.timestamp.CopyFrom(fx.stamp(ns))  # serialised by write, then reused
            write(topic, path_msg, ns)
        for topic, video in view.videos.items():
            write(topic, fx.image_message(ns, CAMERA_FRAME, video[i], fmt, quality), ns)
        for topic, mask in view.masks.items():
            write(topic, fx.mask_message(ns, CAMERA_FRAME, mask[i]), ns)
        if view.joints is not None:
            write("/hands/skeleton", fx.skeleton_message(ns, view.joints[i], view.valid[i]), ns)
        if i == 0:
            if view.first_frame is not None:
                image = fx.image_message(ns, CAMERA_FRAME, view.first_frame, "png")
                write("/inpaint/first_frame", image, ns)
            for topic, message in view.clouds.items():
                write(topic, message(ns), ns)


def _view_metadata(view: _ClipView, index: RunIndex) -> dict[str, str]:
    """The MCAP's ``egosim`` metadata record: clip, run, prompt, fps and each topic's step."""
    clip = view.clip
    prompt = (view.rows["captions"] or {}).get("text") or clip.text or ""
    return {
        "clip_id": clip.clip_id,
        "run": str(index.root),
        "prompt": prompt,
        "fps": repr(clip.fps),
        "camera_from": view.camera_from or "none",
        "sources": json.dumps(view.used, sort_keys=True),
        "pixel_centres": "ROS/Foxglove: integers (egosim cx, cy minus 0.5)",
    }


def _cloud(
    row: dict[str, Any], field_name: str, column: str, config: ViewConfig
) -> Callable[[int], object]:
    """A builder of the point cloud message of a ``scene_cloud`` or ``state`` row at ``ns``."""
    n = int(row["num_points"])
    xyz = np.frombuffer(row["points_xyz"], dtype="<f4").reshape(n, 3)
    rgb = np.frombuffer(row["points_rgb"], dtype=np.uint8).reshape(n, 3)
    extra = np.frombuffer(row[column], dtype=np.uint8)
    keep = _subsample(n, config.max_cloud_points)
    return lambda ns: fx.point_cloud_message(ns, xyz[keep], rgb[keep], {field_name: extra[keep]})


def write_run_view(
    run: Path,
    out: Path,
    clip_ids: Sequence[str] = (),
    config: ViewConfig | None = None,
) -> list[Path]:
    """Write one MCAP per clip of ``run`` (``clip_ids``, default every clip of the clips step).

    ``out`` is the file when one clip is written and ``out`` ends in ``.mcap``; otherwise a
    folder receiving ``<clip_id>.mcap`` per clip. Raises :class:`ExportError` for an unknown
    clip id or a run without a clips step.
    """
    index = RunIndex.open(run)
    if index.step_of(CLIPS) is None:
        raise ExportError(f"{run}: no step wrote clips shards (steps: {index.steps})")
    known = index.clip_ids(CLIPS)
    wanted = list(clip_ids) or known
    missing = [c for c in wanted if c not in known]
    if missing:
        raise ExportError(f"{run}: no clip {missing} in the clips step (clips: {known})")
    out = Path(out)
    if len(wanted) == 1 and out.suffix == ".mcap":
        return [write_clip_view(index, wanted[0], out, config)]
    if out.suffix == ".mcap":
        raise ExportError(f"--out {out} is one file but {len(wanted)} clips were asked for")
    out.mkdir(parents=True, exist_ok=True)
    return [
        write_clip_view(index, cid, path_under(out, f"{validate_id(cid)}.mcap"), config)
        for cid in wanted
    ]
