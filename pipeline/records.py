"""Typed, decoded clip records: what tests, benchmarks and notebooks work with.

A :class:`Clip` holds one clip with every array decoded (frames as ``uint8`` RGB, depth in metres,
poses as 4x4 matrices). :mod:`egosim.pipeline.clip_io` turns clips into rows of the ``clips``
shard schema and back. Shapes use ``T`` frames, ``H`` x ``W`` pixels and ``N`` objects.

The typed input records (:class:`Record` and one subclass per schema, :func:`record_class`) are
what a clip stage's ``process`` is handed per input role: the row mapping itself plus accessors
that parse a value once, on first use, and decode a media column only when asked for
(docs/design.md, "Typed records").
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, fields
from typing import Any, ClassVar, Self

import numpy as np

from egosim.pipeline import media
from egosim.pipeline.export.pack_rows import decode_pack_row
from egosim.pipeline.stage import ClipRejected, DeclaredRow
from egosim.schemas import (
    CAPTIONS,
    CLIPS,
    DEPTH_CAMERA,
    HAND_MASK,
    HANDS,
    INPAINT,
    KEYPOINTS,
    PACK,
    SIMULATION,
    ShardSchema,
)
from egosim.schemas.clips import source_crop_problems
from egosim.schemas.poses import POSES
from egosim.schemas.scene import SCENE_RENDER

NUM_HAND_JOINTS = 21
LEFT, RIGHT = 0, 1


class ClipValueError(ValueError):
    """A clip's arrays disagree with each other (shape, dtype or values); names the clip."""


class InputsDisagree(ClipRejected):
    """A decoded column's shape differs from its row's size: ``inputs disagree: <problem>``.

    ``problem`` alone (naming the clip and column) lets a stage list several at once.
    """

    def __init__(self, problem: str) -> None:
        super().__init__(f"inputs disagree: {problem}")
        self.problem = problem  # e.g. "clip 'c' video decodes to (4, 24, 32, 3), expected ..."

    def __reduce__(self) -> tuple[type[InputsDisagree], tuple[str]]:
        return InputsDisagree, (self.problem,)  # pickled (Dask) with the same message


@dataclass
class Clip:
    """One clip, decoded. Optional fields are ground truth or outputs of later stages."""

    clip_id: str  # unique id of the clip within a dataset
    source: str  # ingest source that produced it: "video", "frames", "synthetic", "egodex", ...
    source_uri: str  # file or recording the clip came from ("" for generated clips)
    fps: float  # frames per second of the stored frames
    timestamps: np.ndarray  # (T,) float64 seconds from the source's start
    intrinsics: np.ndarray  # (4,) float64 fx, fy, cx, cy in pixels of the stored frames
    frames: np.ndarray  # (T, H, W, 3) uint8 RGB
    world_from_cam: np.ndarray | None = None  # (T, 4, 4) float64 camera-to-world, OpenCV axes
    depth: np.ndarray | None = None  # (T, H, W) float32 z-depth in metres, 0 = unknown
    static_frames: np.ndarray | None = None  # (T, H, W, 3) uint8 same camera path, no hands
    static_depth: np.ndarray | None = None  # (T, H, W) float32 depth of the static scene
    first_frame_clean: np.ndarray | None = None  # (H, W, 3) uint8 hand-free first frame
    hand_joints: np.ndarray | None = None  # (T, 2, 21, 3) float32 world metres, 0=left 1=right
    hand_valid: np.ndarray | None = None  # (T, 2) bool hand present in the frame
    hand_confidence: np.ndarray | None = None  # (T, 2, 21) float32 per-joint confidence 0..1
    hand_mask: np.ndarray | None = None  # (T, H, W) uint8 1 = hand or arm pixel
    object_mask: np.ndarray | None = None  # (T, H, W) uint8 object instance id, 0 = none
    object_poses: np.ndarray | None = None  # (T, N, 4, 4) float64 world_from_object
    text: str | None = None  # description of the interaction
    source_fps: float | None = None  # frame rate of the source the clip was cut from
    source_num_frames: int | None = None  # frames in that source (None when unknown)
    source_frame_indices: np.ndarray | None = None  # (T,) int index of each frame in the source
    clip_policy: str | None = None  # what ingest's clip policy did: "full|short|tail[:preset]"
    gripper_opening: np.ndarray | None = None  # (T, 2) float32 metres per hand slot, NaN = none
    embodiment_mask: np.ndarray | None = None  # (T, H, W) uint8 1 = robot arm (URDF + joints)
    source_crop: np.ndarray | None = None  # (4,) float64 x0, y0, x1, y1: the source region the
    # frames show, source pixels (ingest's crop; frame_plan.plan_from_crop rebuilds its plan)

    @property
    def num_frames(self) -> int:
        """Number of frames ``T``."""
        return int(self.frames.shape[0])

    @property
    def height(self) -> int:
        """Frame height ``H`` in pixels."""
        return int(self.frames.shape[1])

    @property
    def width(self) -> int:
        """Frame width ``W`` in pixels."""
        return int(self.frames.shape[2])

    def problems(self) -> list[str]:
        """Every inconsistency between the clip's arrays, as readable sentences."""
        out: list[str] = []
        f = self.frames
        if f.ndim != 4 or f.shape[-1] != 3 or f.dtype != np.uint8:
            return [f"frames must be (T, H, W, 3) uint8, got {f.shape} {f.dtype}"]
        t, h, w = f.shape[:3]
        if t == 0:
            out.append("clip has no frames")
        if not (np.isfinite(self.fps) and self.fps > 0):
            out.append(f"fps must be positive, got {self.fps}")
        ts = np.asarray(self.timestamps)
        if ts.shape != (t,):
            out.append(f"timestamps shape {ts.shape} != ({t},)")
        elif t > 1 and not np.all(np.diff(ts) > 0):
            out.append("timestamps are not strictly increasing")
        k = np.asarray(self.intrinsics, dtype=np.float64)
        if k.shape != (4,) or not np.all(np.isfinite(k)) or k[0] <= 0 or k[1] <= 0:
            out.append(f"intrinsics must be 4 finite values with fx, fy > 0, got {k.tolist()}")
        expected = {
            "world_from_cam": (t, 4, 4),
            "depth": (t, h, w),
            "static_frames": (t, h, w, 3),
            "static_depth": (t, h, w),
            "first_frame_clean": (h, w, 3),
            "hand_joints": (t, 2, NUM_HAND_JOINTS, 3),
            "hand_valid": (t, 2),
            "hand_confidence": (t, 2, NUM_HAND_JOINTS),
            "gripper_opening": (t, 2),
            "hand_mask": (t, h, w),
            "embodiment_mask": (t, h, w),
            "object_mask": (t, h, w),
        }
        for name, shape in expected.items():
            value = getattr(self, name)
            if value is not None and tuple(value.shape) != shape:
                out.append(f"{name} shape {tuple(value.shape)} != {shape}")
        if self.source_frame_indices is not None:
            idx = np.asarray(self.source_frame_indices)
            if idx.shape != (t,) or not np.issubdtype(idx.dtype, np.integer):
                out.append(
                    f"source_frame_indices must be ({t},) integers, got {idx.shape} {idx.dtype}"
                )
            elif t and (idx.min() < 0 or np.any(np.diff(idx) < 0)):
                out.append("source_frame_indices must be >= 0 and non-decreasing")
        out.extend(source_crop_problems(self.source_crop))
        if self.source_fps is not None and not (
            np.isfinite(self.source_fps) and self.source_fps > 0
        ):
            out.append(f"source_fps must be positive, got {self.source_fps}")
        if self.object_poses is not None:
            shape = self.object_poses.shape
            if len(shape) != 4 or shape[0] != t or shape[2:] != (4, 4):
                out.append(f"object_poses shape {shape} != ({t}, N, 4, 4)")
        return out

    def check(self) -> Clip:
        """Raise :class:`ClipValueError` naming the clip and every problem; return self if none."""
        problems = self.problems()
        if problems:
            raise ClipValueError(f"clip {self.clip_id!r}: " + "; ".join(problems))
        return self


CLIP_FIELDS = tuple(f.name for f in fields(Clip))


# --- Typed input records: what ``ClipStage.process`` is handed (docs/design.md, "Typed records").


class Record(DeclaredRow):
    """One input row as a stage's ``process`` gets it: the raw columns plus typed accessors.

    A record is still the row mapping (``row["fps"]``, ``row.get(...)``, ``in``), with the
    :class:`~egosim.pipeline.stage.DeclaredRow` rule that reading a column of the schema the
    stage did not declare raises :class:`~egosim.pipeline.stage.UndeclaredColumnError`; stages
    not yet migrated read it exactly as before. The typed accessors of the subclasses (one per
    schema, :func:`record_class`) parse a value once, on first use: a media column is decoded
    only when its accessor is called, so a stage that declares only ``video`` never reads or
    decodes depth. Build one from any mapping with :meth:`of` (tests call ``process`` with plain
    dicts; the executor passes records, which :meth:`of` returns as they are).
    """

    schema: ClassVar[ShardSchema | None] = None  # the schema whose rows this class types

    def __init__(
        self,
        values: Mapping[str, Any],
        stage: str = "",
        role: str = "",
        schema_columns: tuple[str, ...] = (),
    ) -> None:
        super().__init__(values, stage, role, schema_columns)
        self._parsed: dict[str, Any] = {}  # accessor name -> parsed value (parse once)

    @classmethod
    def of(cls, row: Mapping[str, Any]) -> Self:
        """``row`` typed as this record: itself when it already is one, else wrapped.

        A declared row keeps its declaration; a wrapped plain mapping refuses no column (it has
        none): a missing column reads as it would from the mapping.
        """
        if isinstance(row, cls):
            return row
        if isinstance(row, DeclaredRow):
            return cls(dict.copy(row), row.stage, row.role, row.schema_columns)
        return cls(row)

    def _once(self, key: str, parse: Callable[[], Any]) -> Any:
        """``parse()`` the first time ``key`` is asked for, the stored value after that."""
        if key not in self._parsed:
            self._parsed[key] = parse()
        return self._parsed[key]

    @property
    def clip_id(self) -> str:
        """The clip's id (the join key; always read)."""
        return str(self["clip_id"])

    def what(self, column: str) -> str:
        """``clip 'ID' column``: how error messages name one column of this clip."""
        return f"clip {self.clip_id!r} {column}"

    def array(self, column: str, dtype: Any, shape: tuple[int, ...]) -> np.ndarray | None:
        """A list column as an array of ``shape`` (None when null); refuses another size."""

        def parse() -> np.ndarray | None:
            value = self[column]
            if value is None:
                return None
            arr = np.asarray(value, dtype=dtype)
            if arr.size != int(np.prod(shape)):
                raise ClipRejected(
                    f"{self.what(column)} has {arr.size} values, expected {shape} = "
                    f"{int(np.prod(shape))}"
                )
            return arr.reshape(shape)

        return self._once(f"array:{column}", parse)


class FramedRecord(Record):
    """A row with ``num_frames``, and ``height`` / ``width`` / ``fps`` where its schema has them."""

    @property
    def num_frames(self) -> int:
        """Frames ``T``."""
        return int(self["num_frames"])

    @property
    def height(self) -> int:
        """Frame height ``H`` in pixels."""
        return int(self["height"])

    @property
    def width(self) -> int:
        """Frame width ``W`` in pixels."""
        return int(self["width"])

    @property
    def size(self) -> tuple[int, int, int]:
        """``(T, H, W)``: frames, height and width, parsed once for every check."""
        return self.num_frames, self.height, self.width

    @property
    def fps(self) -> float:
        """Frames per second."""
        return float(self["fps"])

    def rgb_video(self, column: str) -> np.ndarray:
        """Decode an H.264 column to ``(T, H, W, 3)`` uint8, checked against :attr:`size`.

        Raises :class:`InputsDisagree` when it decodes to another shape.
        """

        def parse() -> np.ndarray:
            t, h, w = self.size
            what = self.what(column)
            frames = media.decode_rgb_video(self[column], h, w, what)
            if frames.shape != (t, h, w, 3):
                raise InputsDisagree(f"{what} decodes to {frames.shape}, expected {(t, h, w, 3)}")
            return frames

        return self._once(f"rgb:{column}", parse)

    def mask_video(self, column: str, what: str | None = None) -> np.ndarray | None:
        """Decode a lossless mask column to ``(T, H, W)`` uint8 {0, 1} (None when null).

        Checked against :attr:`size` (:class:`InputsDisagree`); ``what``
        names the column in that message (default ``clip 'ID' column``).
        """

        def parse() -> np.ndarray | None:
            data = self[column]
            if data is None:
                return None
            t, h, w = self.size
            name = what or self.what(column)
            mask = media.decode_lossless_video(data, name)
            if mask.shape != (t, h, w):
                raise InputsDisagree(f"{name} decodes to {mask.shape}, expected {(t, h, w)}")
            return (mask > 0).astype(np.uint8)

        return self._once(f"mask:{column}", parse)

    def depth_video(self, column: str) -> np.ndarray | None:
        """Decode a depth column to ``(T, H, W)`` float32 metres, 0 = unknown (None when null).

        Steps of the row's ``depth_unit_m``; checked against :attr:`size`
        (:class:`InputsDisagree`).
        """

        def parse() -> np.ndarray | None:
            data = self[column]
            if data is None:
                return None
            t, h, w = self.size
            what = self.what(column)
            depth = media.decode_depth_video(data, self["depth_unit_m"], what)
            if depth.shape != (t, h, w):
                raise InputsDisagree(f"{what} decodes to {depth.shape}, expected {(t, h, w)}")
            return depth

        return self._once(f"depth:{column}", parse)

    def first_depth(self, column: str) -> np.ndarray | None:
        """Frame 0 of a depth column, ``(H, W)`` float32 metres (None when null).

        Only that frame is decoded; not checked against the row's size (nor was it before the
        records: ``common.cameras.first_frame_depth`` reads no size columns).
        """

        def parse() -> np.ndarray | None:
            data = self[column]
            if data is None:
                return None
            what = self.what(column)
            return media.decode_depth_video(data, self["depth_unit_m"], what, max_frames=1)[0]

        return self._once(f"depth0:{column}", parse)


class HandArraysRecord(FramedRecord):
    """A framed row with hand joint columns, one slot per hand (0 left, 1 right).

    Each accessor is None when its column is null (a ``clips`` row without hand labels).
    """

    @property
    def hand_joints(self) -> np.ndarray | None:
        """``(T, 2, 21, 3)`` float64 world metres."""
        return self.array("hand_joints", np.float64, (self.num_frames, 2, NUM_HAND_JOINTS, 3))

    @property
    def hand_valid(self) -> np.ndarray | None:
        """``(T, 2)`` bool: the hand is present in the frame."""
        return self.array("hand_valid", bool, (self.num_frames, 2))

    @property
    def hand_confidence(self) -> np.ndarray | None:
        """``(T, 2, 21)`` float64 per-joint confidence in [0, 1]."""
        return self.array("hand_confidence", np.float64, (self.num_frames, 2, NUM_HAND_JOINTS))


class CameraRecord(FramedRecord):
    """A framed row with a camera: ``intrinsics`` and a per-frame ``world_from_cam``."""

    @property
    def intrinsics(self) -> np.ndarray:
        """``(4,)`` float64 fx, fy, cx, cy in pixels."""
        return self._once("intrinsics", lambda: np.asarray(self["intrinsics"], dtype=np.float64))

    @property
    def world_from_cam(self) -> np.ndarray | None:
        """``(T, 4, 4)`` float64 camera-to-world poses, None when the row has none."""
        return self.array("world_from_cam", np.float64, (self.num_frames, 4, 4))


def require_camera_poses(world_from_cam: np.ndarray | None, clip_id: str) -> np.ndarray:
    """``world_from_cam`` when there is one, else :class:`ClipRejected` ("no camera poses").

    The one place the reject for a clip without a trajectory is worded.
    """
    if world_from_cam is None:
        raise ClipRejected(f"clip {clip_id!r}: no camera poses (world_from_cam is null)")
    return world_from_cam


class ClipsRecord(CameraRecord, HandArraysRecord):
    """A ``clips`` row (ingest's output); :func:`egosim.pipeline.clip_io.clip_from_row` decodes
    a whole one into a :class:`Clip`. Its hand arrays are the source's labels (None without)."""

    schema = CLIPS

    @property
    def depth(self) -> np.ndarray | None:
        """``(T, H, W)`` float32 z-depth in metres (0 = unknown), None when the clip has none."""
        return self.depth_video("depth")

    @property
    def text(self) -> str | None:
        """The source's description of the interaction (None when it has none)."""
        value = self["text"]
        return None if value is None else str(value)

    @property
    def frames(self) -> np.ndarray:
        """``(T, H, W, 3)`` uint8 RGB: the ``video`` column, decoded once."""
        return self.rgb_video("video")


class HandsRecord(HandArraysRecord):
    """A ``hands`` row: cleaned 3D hand joints per frame and hand slot (0 left, 1 right).

    ``hand_joints``, ``hand_valid`` and ``hand_confidence`` (:class:`HandArraysRecord`) and
    ``hand_lifted`` are never null in this schema.
    """

    schema = HANDS

    @property
    def hand_lifted(self) -> np.ndarray:
        """``(T, 2)`` bool: the valid hand's 3D joints are trusted (False: 2D only, joints on its
        landmarks' rays at a guessed depth, or not valid); what needs the hand in 3D uses these."""
        lifted = self.array("hand_lifted", bool, (self.num_frames, 2))
        if lifted is None:  # not nullable in the schema: only a hand-made row gets here
            raise ClipRejected(f"{self.what('hand_lifted')} is null")
        return lifted


class KeypointsRecord(FramedRecord):
    """A ``keypoints`` row: projected hand joints and the skeleton video."""

    schema = KEYPOINTS

    @property
    def keypoint_visible(self) -> np.ndarray:
        """``(T, K)`` bool: the keypoint is in view (K = 42 joints of two hands)."""
        return self._once("keypoint_visible", lambda: np.asarray(self["keypoint_visible"], bool))


class SceneRenderRecord(FramedRecord):
    """A ``scene_render`` row: the scene video along the trajectory and its visibility."""

    schema = SCENE_RENDER

    @property
    def visible_fraction(self) -> np.ndarray:
        """``(T,)`` float64: fraction of each frame's pixels a scene point landed on."""
        return self.array("visible_fraction", np.float64, (self.num_frames,))


class DepthCameraRecord(CameraRecord):
    """A ``depth_camera`` row: estimated intrinsics, poses and frame-0 depth."""

    schema = DEPTH_CAMERA

    @property
    def registered(self) -> np.ndarray:
        """``(T,)`` bool: the backend estimated this frame's pose."""
        return self._once("registered", lambda: np.asarray(self["registered"], dtype=bool))

    @property
    def static_camera(self) -> bool:
        """The camera did not move (no parallax: every pose equals the first, no ``depth0``)."""
        return bool(self["static_camera"])

    @property
    def depth0(self) -> np.ndarray | None:
        """``(H, W)`` float32 z-depth of frame 0 in the poses' scale (0 = unknown), None when null
        (a static or rotation-only camera)."""
        return self.first_depth("depth0")


class PosesRecord(CameraRecord):
    """A ``poses`` row: a cleaned trajectory (from ``pose_clean``)."""

    schema = POSES


class CaptionsRecord(Record):
    """A ``captions`` row: the text prompt of a clip."""

    schema = CAPTIONS

    @property
    def text(self) -> str:
        """The prompt."""
        return str(self["text"])


class InpaintRecord(Record):
    """An ``inpaint`` row: the hand-free first frame."""

    schema = INPAINT


class HandMaskRecord(FramedRecord):
    """A ``hand_mask`` row: the hand (and arm) mask video."""

    schema = HAND_MASK

    @property
    def hand_mask(self) -> np.ndarray:
        """``(T, H, W)`` uint8, 1 = hand or arm: the masks, decoded once and checked against
        :attr:`size`."""
        masks = self.mask_video("hand_mask")
        if masks is None:  # not nullable in the schema: only a hand-made row gets here
            raise ClipRejected(f"{self.what('hand_mask')} is null")
        return masks


class PackRecord(CameraRecord):
    """A ``pack`` row: one training sample at its packed size."""

    schema = PACK

    @property
    def videos(self) -> dict[str, np.ndarray]:
        """Every condition decoded and checked (``pipeline.export.pack_rows.decode_pack_row``)."""
        return self._once("videos", lambda: decode_pack_row(self))

    @property
    def depth0(self) -> np.ndarray | None:
        """``(H, W)`` float32 metres of frame 0 (0 = unknown), None when the pack has none."""
        return self.first_depth("depth0")


class SimulationRecord(FramedRecord):
    """A ``simulation`` row: one generated clip."""

    schema = SIMULATION


_RECORDS: dict[str, type[Record]] = {
    cls.schema.name: cls
    for cls in (
        ClipsRecord,
        HandsRecord,
        KeypointsRecord,
        SceneRenderRecord,
        DepthCameraRecord,
        PosesRecord,
        CaptionsRecord,
        InpaintRecord,
        HandMaskRecord,
        PackRecord,
        SimulationRecord,
    )
    if cls.schema is not None
}


def record_class(schema: ShardSchema) -> type[Record]:
    """The record class of ``schema``'s rows (:class:`Record` for a schema without its own)."""
    return _RECORDS.get(schema.name, Record)
