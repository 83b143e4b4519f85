"""The ``ingest`` stage: standardise sources into ``clips`` shards.

Sources (``source`` parameter; ``auto`` picks per input path):

- ``video``: a video file or a folder of video files (any fps, any size);
- ``frames``: a folder of image files (or a folder of such folders), with ``frames_fps`` given;
- ``egodex``: EgoDex ``.hdf5`` + ``.mp4`` pairs (a file or a folder searched recursively);
- ``mcap``: Foxglove MCAP recordings (``.mcap``: images, calibration, frame transforms; see
  :mod:`egosim.stages.ingest.mcap_source`);
- ``synthetic``: the built-in synthetic world, ``synthetic_count`` clips (no input needed);
- ``agibot``: AgiBot World episodes (``proprio_stats.h5`` + head video + camera JSON + task info;
  see :mod:`egosim.stages.ingest.agibot_source`), one unit per episode;
- ``lerobot``: LeRobot datasets (``meta/info.json``, v3.0 or v2.x; see
  :mod:`egosim.stages.ingest.lerobot_source`), one unit per episode.

Robot episodes become clips whose hand columns hold the gripper skeleton
(:mod:`egosim.stages.common.gripper`; geometry preset ``robot``).

Units are the input files (or folders of frames, or synthetic seeds); ``units_per_shard`` of them
make one shard. A unit that cannot be read goes to the rejects table with the reason.

Clip format: ``preset`` names a common format (:data:`CLIP_PRESETS`: ``egosim`` 61 frames at
16 fps, 480x832; ``dwm`` 49 frames at 8 fps, 480x720). The fields ``fps``, ``num_frames``,
``min_frames``, ``height`` and ``width`` default to 0, meaning "the preset's"; a value given
explicitly overrides the preset. The resolved values are what the config holds (and what the
shard's provenance records). How clips are cut in time (rate, windows, short sources, the tail)
is the clip policy of :mod:`egosim.stages.ingest.standardise`; where the crop of a source of
another aspect sits (``crop``, ``crop_anchor``: over the hands by default) is
:mod:`egosim.stages.ingest.crop_anchor`'s.
"""

from __future__ import annotations

import dataclasses
from collections import Counter
from collections.abc import Iterator
from pathlib import Path
from typing import Any, Literal

from egosim.pipeline.clip_io import row_from_clip
from egosim.pipeline.execute import fingerprint
from egosim.pipeline.records import Clip
from egosim.pipeline.stage import ClipRejected, ConfigError, SourceStage, StageConfig
from egosim.schemas import CLIPS
from egosim.schemas.ids import sanitize_id, short_hash
from egosim.stages.common.gripper import GRIPPER_PRESETS, gripper_geometry
from egosim.stages.ingest import (
    agibot_source,
    crop_anchor,
    frames_source,
    lerobot_source,
    synthetic_source,
    video_source,
)
from egosim.stages.ingest.egodex import read_egodex_clips
from egosim.stages.ingest.mcap_source import read_mcap_clip
from egosim.stages.ingest.robot_source import ArmModel

SourceKind = Literal["auto", "video", "frames", "egodex", "mcap", "synthetic", "agibot", "lerobot"]


@dataclasses.dataclass(frozen=True)
class ClipPreset:
    """A common clip format: what the fields left at 0 in :class:`IngestConfig` become."""

    fps: float  # target frames per second
    num_frames: int  # frames of a full clip (1 + 4k for the Wan VAE)
    min_frames: int  # fewest frames of a short or tail clip
    height: int  # frame height in pixels
    width: int  # frame width in pixels


CLIP_PRESETS: dict[str, ClipPreset] = {
    # EgoSim / Wan2.1-Fun-InP: 61 frames at 16 fps (3.75 s), 480x832.
    "egosim": ClipPreset(fps=16.0, num_frames=61, min_frames=33, height=480, width=832),
    # DWM (papers/dwm-paper.txt, 720x480 with 49 frames; its real-world clips are at 8 fps).
    "dwm": ClipPreset(fps=8.0, num_frames=49, min_frames=33, height=480, width=720),
}
PRESET_FIELDS = ("fps", "num_frames", "min_frames", "height", "width")  # 0 = the preset's


@dataclasses.dataclass(frozen=True)
class IngestConfig(StageConfig):
    """Parameters of ``ingest``."""

    source: SourceKind = "auto"  # which reader; auto: by file type of each input path
    preset: Literal["egosim", "dwm"] = "egosim"  # clip format filling the fields left at 0
    fps: float = 0.0  # target frames per second (a slower source keeps its own); 0 = preset's
    num_frames: int = 0  # frames of a full clip; 0 = the preset's
    min_frames: int = 0  # fewest frames of a short or tail clip (1 + 4k long); 0 = preset's
    height: int = 0  # target frame height in pixels; 0 = the preset's
    width: int = 0  # target frame width in pixels; 0 = the preset's
    stride: int = 0  # clip frames between window starts in long videos; 0 = num_frames
    tail: Literal["keep", "drop"] = "keep"  # keep: a remainder >= min_frames gives a 1+4k clip
    max_clips_per_source: int = 0  # clips kept per input video; 0 = all
    horizontal_fov_deg: float = 70.0  # FOV guess for sources without intrinsics
    intrinsics: tuple[float, ...] = ()  # fx, fy, cx, cy of the source frames, when known
    frames_fps: float = 0.0  # frame rate of image-folder sources (required for them)
    units_per_shard: int = 4  # input files (or synthetic clips) per output shard
    crf: int = 18  # H.264 quality of stored RGB video (lower = better, bigger)
    # Where the cover crop's window sits when the source's aspect differs from the clip's:
    # "hands" places it over the hands MediaPipe finds on 8 sampled frames (crop_anchor when
    # none is found, or when the crop cuts under 10% of a side), moved towards the static scene
    # when the hands' band has too little for the cameras; "anchor" always at crop_anchor.
    crop: Literal["hands", "anchor"] = "hands"  # crop window: over the hands, or at crop_anchor
    crop_anchor: tuple[float, ...] = (0.5, 0.5)  # window x, y in [0, 1] of the overflow; centre
    synthetic_count: int = 4  # clips generated by the synthetic source
    synthetic_mode: Literal["tabletop", "wild"] = "tabletop"  # synthetic camera motion
    synthetic_articulated_every: int = 3  # every k-th synthetic clip has a hinged lid; 0 = none
    synthetic_variant: Literal["default", "alt"] = "default"  # world variant (WorldConfig.variant)
    synthetic_robot_every: int = 0  # every k-th synthetic clip shows the URDF robot arm; 0 = none
    robot_mask_dilate_px: int = 2  # growth of URDF arm masks (embodiment_mask), stored pixels
    seed: int = 0  # first seed of the synthetic source
    robot: str = ""  # gripper geometry preset (gripper.GRIPPER_PRESETS); "" = the source's own
    robot_camera: str = ""  # AgiBot camera name / LeRobot video key; "" = the head camera
    robot_camera_pose: tuple[float, ...] = ()  # LeRobot fixed world_from_cam, 16 values row-major
    robot_camera_axes: Literal["opencv", "opengl", "ros_body"] = "opencv"  # robot camera axes
    robot_urdf: str = ""  # robot URDF file: with the log's joint states, the arm mask is rendered
    robot_joint_names: tuple[str, ...] = ()  # URDF joint per joint-state column; () = log's names
    robot_base_pose: tuple[float, ...] = ()  # world_from_base of the URDF root, 16 values; () = I

    def __post_init__(self) -> None:
        problems = []
        if self.robot and self.robot not in GRIPPER_PRESETS:
            problems.append(f"robot must be one of {sorted(GRIPPER_PRESETS)}, got {self.robot!r}")
        if self.robot_base_pose and len(self.robot_base_pose) != 16:
            problems.append(
                f"robot_base_pose must be 16 values (a row-major 4x4), got "
                f"{len(self.robot_base_pose)}: {self.robot_base_pose}"
            )
        if self.robot_urdf and not Path(self.robot_urdf).is_file():
            problems.append(f"robot_urdf {self.robot_urdf!r} is not a file")
        if self.robot_camera_pose and len(self.robot_camera_pose) != 16:
            problems.append(
                f"robot_camera_pose must be 16 values (a row-major 4x4), got "
                f"{len(self.robot_camera_pose)}: {self.robot_camera_pose}"
            )
        if self.preset not in CLIP_PRESETS:
            problems.append(f"preset must be one of {sorted(CLIP_PRESETS)}, got {self.preset!r}")
        preset = CLIP_PRESETS.get(self.preset, CLIP_PRESETS["egosim"])
        for name in PRESET_FIELDS:  # 0 = not given: take the preset's value
            if getattr(self, name) == 0:
                object.__setattr__(self, name, getattr(preset, name))
        if not self.fps > 0:
            problems.append(f"fps must be > 0 (or 0 for the preset's), got {self.fps}")
        for name in ("num_frames", "min_frames", "height", "width", "units_per_shard", "crf"):
            if getattr(self, name) < 1:
                problems.append(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.tail not in ("keep", "drop"):
            problems.append(f"tail must be 'keep' or 'drop', got {self.tail!r}")
        for name in (
            "stride",
            "max_clips_per_source",
            "synthetic_count",
            "synthetic_robot_every",
            "robot_mask_dilate_px",
        ):
            if getattr(self, name) < 0:
                problems.append(f"{name} must be >= 0, got {getattr(self, name)}")
        if self.crop not in ("hands", "anchor"):
            problems.append(f"crop must be 'hands' or 'anchor', got {self.crop!r}")
        anchor = tuple(self.crop_anchor)
        if len(anchor) != 2 or not all(
            isinstance(v, int | float) and 0.0 <= v <= 1.0 for v in anchor
        ):
            problems.append(
                f"crop_anchor must be two fractions x, y in [0, 1] (0.5, 0.5 = centre), got "
                f"{self.crop_anchor!r}"
            )
        if self.intrinsics and len(self.intrinsics) != 4:
            problems.append(f"intrinsics must be 4 values fx, fy, cx, cy, got {self.intrinsics}")
        if not 1.0 < self.horizontal_fov_deg < 179.0:
            problems.append(
                f"horizontal_fov_deg must be in (1, 179), got {self.horizontal_fov_deg}"
            )
        if problems:
            raise ConfigError("; ".join(problems))


class IngestStage(SourceStage):
    """Standardise videos, frame folders, EgoDex files or synthetic clips into clips."""

    name = "ingest"
    description = (
        "standardise videos, frame folders, EgoDex, MCAP, robot episodes (AgiBot, LeRobot) or "
        "the synthetic world into clips"
    )
    config_class = IngestConfig
    output = CLIPS
    backends = ("video", "frames", "egodex", "mcap", "synthetic", "agibot", "lerobot")
    # 2: clip policy (short and tail clips, source rate kept), clips v2 columns;
    # 3: clip ids sanitised to the identifier rule and unique across a run (schemas.ids).
    # 4: clips v3 (gripper_opening; robot sources agibot and lerobot).
    # 5: clips v4 (embodiment_mask; synthetic robot clips).
    # 6: frames carry presentation times sorted back into order (AVI with B-frames had them
    #    shuffled); an AVI counting empty drop chunks is no longer rejected as truncated. MP4,
    #    MOV, MKV, WebM clips are unchanged.
    # 7: clips v5 (source_crop in every row); crop="hands" (the default) places the cover crop's
    #    window over the hands in sources that lose >= 10% of a side (portrait, 4:3, 720x480 into
    #    832x480): their frames and intrinsics change. Sources losing less (16:9) keep the centre
    #    crop: the same frames.
    # 8: robot clips (a gripper or an embodiment mask) keep crop_anchor: the human-hand search
    #    is not run on them.
    # 9: crop="hands": a hands' band with under 30 static SIFT matches (frame to next frame,
    #    outside the hands) moves towards the scene, keeping at least half of the hands
    #    (crop_anchor.texture_anchor): the EgoDex portrait variant's band 0.875 -> 0.625.
    #    Every other real source of the benches keeps its band.
    version = 9
    config: IngestConfig

    def list_units(self, source: str | None) -> list[str]:
        """Units as ``kind:path`` (or ``synthetic:mode:seed``) strings.

        Clip ids come from file or folder names. When two units of this listing would give the
        same name (``a/x.mp4`` and ``b/x.mp4``, or names equal once sanitised or up to case),
        each of them becomes ``kind#HASH:path``, HASH a short hash of its path, and its clip ids
        end in ``-HASH``: clip ids are unique across the run (see :func:`disambiguate_units`).
        """
        return disambiguate_units(self._list_units(source))

    def _list_units(self, source: str | None) -> list[str]:
        cfg = self.config
        if cfg.source == "synthetic" or (cfg.source == "auto" and not source):
            return synthetic_source.list_units(cfg)
        if not source:
            raise ConfigError(f"ingest source {cfg.source!r} needs an --input path")
        path = Path(source)
        if not path.exists():
            raise ConfigError(f"ingest input {path} does not exist")
        units: list[str] = []
        if cfg.source in ("auto", "agibot"):
            units += [f"agibot:{p}" for p in agibot_source.find_episodes(path)]
        if cfg.source in ("auto", "lerobot"):
            for root in lerobot_source.find_datasets(path):
                units += [f"lerobot:{root}#{i}" for i in lerobot_source.list_episodes(root)]
        if cfg.source in ("auto", "egodex"):
            files = _find(path, {".hdf5", ".h5"})
            units += [f"egodex:{p}" for p in files if cfg.source != "auto" or not _robot_file(p)]
        if cfg.source in ("auto", "video"):
            videos = _find(path, video_source.VIDEO_SUFFIXES)
            if cfg.source == "auto":  # an EgoDex episode's video belongs to its .hdf5
                videos = [v for v in videos if not _egodex_video(v) and not _robot_file(v)]
            units += [f"video:{p}" for p in videos]
        if cfg.source in ("auto", "mcap"):
            units += [f"mcap:{p}" for p in _find(path, {".mcap"})]
        if cfg.source in ("auto", "frames") and not units:
            units += [f"frames:{p}" for p in frames_source.find_frame_folders(path)]
        return units

    def unit_fingerprint(self, unit: str) -> str:
        """Path, size and modification time for files; the spec for synthetic units. With
        ``crop="hands"`` a file's also names the crop's hand detector (its version, or none)."""
        kind = unit.partition(":")[0].partition("#")[0]
        if kind == "synthetic":
            return unit
        files = self._file_fingerprint(unit)
        if self.config.crop == "hands":  # the crop, hence the frames, follow the detector
            return f"{files}|crop {crop_anchor.crop_detector()}"
        return files

    def _file_fingerprint(self, unit: str) -> str:
        """``unit`` with the names, sizes and modification times of its files."""
        kind, _, rest = unit.partition(":")
        kind = kind.partition("#")[0]
        if kind == "lerobot":  # the dataset's meta and data files (videos by size and time too)
            rest = rest.rpartition("#")[0]
        path = Path(rest)
        if path.is_dir() and kind == "lerobot":
            files = sorted(p for p in path.rglob("*") if p.is_file())
            stats = [
                (str(f.relative_to(path)), f.stat().st_size, f.stat().st_mtime_ns) for f in files
            ]
            return f"{unit}|{fingerprint({'files': stats})}"
        files = sorted(path.iterdir()) if path.is_dir() else [path]
        stats = [(f.name, f.stat().st_size, f.stat().st_mtime_ns) for f in files if f.is_file()]
        return f"{unit}|{fingerprint({'files': stats})}"

    def process_unit(self, unit: str) -> Iterator[dict[str, Any]]:
        """Read one unit and yield its clips as rows, with valid (sanitised) clip ids."""
        head, _, rest = unit.partition(":")
        kind, _, tag = head.partition("#")
        suffix = f"-{tag}" if tag else ""
        for clip in self._clips(kind, rest):
            clip_id = sanitize_id(clip.clip_id, suffix)
            if clip_id != clip.clip_id:
                clip = dataclasses.replace(clip, clip_id=clip_id)
            yield row_from_clip(clip, crf=self.config.crf)

    def _clips(self, kind: str, rest: str) -> Iterator[Clip]:
        unit = f"{kind}:{rest}"
        cfg = self.config
        if kind == "video":
            yield from video_source.read_video_clips(Path(rest), cfg)
        elif kind == "frames":
            yield from frames_source.read_frame_clips(Path(rest), cfg)
        elif kind == "egodex":
            yield from read_egodex_clips(Path(rest), cfg)  # streams the video
        elif kind == "mcap":
            yield from video_source.standardise_clip(read_mcap_clip(Path(rest)), cfg)
        elif kind == "synthetic":
            yield synthetic_source.render_unit(rest, cfg)
        elif kind == "agibot":
            geometry = gripper_geometry(cfg.robot or agibot_source.DEFAULT_ROBOT)
            clip = agibot_source.read_agibot_episode(
                Path(rest),
                cfg.robot_camera or agibot_source.DEFAULT_CAMERA,
                cfg.robot_camera_axes,
                geometry,
                _arm_model(cfg),
            )
            yield from video_source.standardise_clip(clip, cfg)
        elif kind == "lerobot":
            root, _, episode = rest.rpartition("#")
            options = lerobot_source.LeRobotOptions(
                video_key=cfg.robot_camera,
                camera_pose=cfg.robot_camera_pose,
                camera_axes=cfg.robot_camera_axes,
                intrinsics=cfg.intrinsics,
                horizontal_fov_deg=cfg.horizontal_fov_deg,
            )
            geometry = gripper_geometry(cfg.robot or lerobot_source.DEFAULT_ROBOT)
            clip = lerobot_source.read_lerobot_episode(
                Path(root), int(episode), options, geometry, _arm_model(cfg)
            )
            yield from video_source.standardise_clip(clip, cfg)
        else:
            raise ClipRejected(f"unknown ingest unit {unit!r}")


def _arm_model(cfg: IngestConfig) -> ArmModel | None:
    """The user's URDF arm model for robot sources, or None when no URDF was given."""
    if not cfg.robot_urdf:
        return None
    return ArmModel(
        urdf=cfg.robot_urdf,
        joint_names=tuple(cfg.robot_joint_names),
        world_from_base=tuple(cfg.robot_base_pose),
        dilate_px=cfg.robot_mask_dilate_px,
    )


def unit_name(unit: str) -> str:
    """The name a unit's clip ids start with, sanitised (as the sources build them)."""
    kind, _, rest = unit.partition(":")
    path = Path(rest)
    if kind == "synthetic":
        return unit
    if kind == "egodex":  # egodex.read_egodex_clips: <task folder>_<stem>
        return sanitize_id(f"{path.parent.name}_{path.stem}")
    if kind == "agibot":  # agibot_source: agibot_<task>_<episode>
        return sanitize_id(agibot_source.paths_of(path).name)
    if kind == "lerobot":  # lerobot_source: <dataset folder>_ep<episode>
        root, _, episode = rest.rpartition("#")
        return sanitize_id(f"{Path(root).name}_ep{int(episode):06d}")
    if kind == "frames":  # frames_source: the folder's name
        return sanitize_id(path.name)
    return sanitize_id(path.stem)  # video files and MCAP recordings: the file's stem


def disambiguate_units(units: list[str]) -> list[str]:
    """Tag units whose clip-id names collide (up to case) with a short hash of their path.

    ``kind:path`` becomes ``kind#HASH:path``; :meth:`IngestStage.process_unit` appends
    ``-HASH`` to the clip ids of such a unit. Units with a unique name are left as they are.
    """
    names = Counter(unit_name(u).lower() for u in units)
    out = []
    for unit in units:
        kind, _, rest = unit.partition(":")
        if kind != "synthetic" and names[unit_name(unit).lower()] > 1:
            unit = f"{kind}#{short_hash(rest)}:{rest}"
        out.append(unit)
    return out


def _robot_file(path: Path) -> bool:
    """A file of an AgiBot or LeRobot layout (read by those sources, not as video or EgoDex)."""
    return agibot_source.owns(path) or lerobot_source.owns(path)


def _egodex_video(video: Path) -> bool:
    return any(video.with_suffix(s).is_file() for s in (".hdf5", ".h5"))


def _find(path: Path, suffixes: set[str] | frozenset[str]) -> list[Path]:
    if path.is_file():
        return [path] if path.suffix.lower() in suffixes else []
    return sorted(p for p in path.rglob("*") if p.is_file() and p.suffix.lower() in suffixes)
