"""Continuous simulation: render the state, generate a clip, fuse it, go on (issue 13).

The runner joins rows on ``clip_id`` within one shard index, so it cannot chain segment k's
state into segment k+1; this loop does, per segment, with the registered stages' own
``process`` (through the registry, so no stage imports another):

1. ``scene_render`` renders state k (a ``state`` row keyed by segment k's clip) along segment
   k's trajectory; the first segment may start from a ``scene_cloud`` row instead;
2. a generator (:data:`GENERATORS`) makes clip k from the segment's action and that render;
3. ``state_fusion`` fuses clip k onto state k (its hands from the segment's joints, its hand
   mask from the generated clip) into state k+1.

Every input row, render, generated clip and state goes to ``OUT/<step>/shard-00000.parquet``
(steps ``initial``, ``render_KK``, ``clip_KK``, ``state_KK``) and the renders and clips side by
side to ``OUT/closed_loop.mp4``. Bad input (no segments, a count other than ``num_segments``,
a segment whose cameras overlap none of the state's, missing columns) is refused before
anything runs, with every problem in one :class:`ClosedLoopError`; a segment a stage rejects
stops the loop with that reason (never an unchanged state).
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from egosim.pipeline import media
from egosim.pipeline.records import ClipsRecord, HandMaskRecord
from egosim.pipeline.shards import ShardReader, ShardWriter, shard_file_name
from egosim.pipeline.stage import ClipRejected, ConfigError, StageConfig, get_stage
from egosim.schemas import CLIPS
from egosim.schemas.hands import MANO_COLUMNS
from egosim.schemas.ids import path_under, validate_id
from egosim.schemas.scene import SCENE_CLOUD, SCENE_RENDER
from egosim.schemas.state import STATE, state_for_clip
from egosim.stages.state_fusion.config import StateFusionConfig
from egosim.stages.state_fusion.fusion import overlapping_cameras


class ClosedLoopError(ValueError):
    """The closed loop's input is unusable, or a segment was rejected; says which and why."""


Generator = Callable[[Mapping[str, Any], Mapping[str, Any]], dict[str, Any]]


def oracle_generator(segment: Mapping[str, Any], render: Mapping[str, Any]) -> dict[str, Any]:
    """The ground-truth clip of the segment (its own video, depth and hand mask): measures the
    state update apart from the model. ``render`` is not used."""
    missing = [c for c in ("video", "depth", "hand_mask") if segment.get(c) is None]
    if missing:
        raise ClosedLoopError(
            f"segment {segment['clip_id']!r}: the oracle generator returns the segment's own "
            f"clip, which lacks {missing} (synthetic-world clips carry them)"
        )
    return dict(segment)


# Columns of a segment row that are the world's ground truth: a generated clip has none of them
# (so fusion estimates depth from the generated frames and the known trajectory).
GROUND_TRUTH_COLUMNS = (
    "depth",
    "static_video",
    "static_depth",
    "first_frame_clean",
    "hand_mask",
    "object_mask",
    "num_objects",
    "object_poses",
)


class ModelGenerator:
    """The trained model as the clip generator: segment k's clip from state k's render.

    Conditions, as ``simulate`` builds them from a pack row: the render's ``scene_video`` and
    ``visible`` (state k along segment k's trajectory), the skeleton video of the segment's hand
    joints (the registered ``keypoint_render`` stage), the render's first frame as the first
    frame, and the segment's ``text`` as the prompt. The returned clips row is the segment's
    action (cameras, joints, timestamps) with the generated ``video``, the ground-truth columns
    cleared (:data:`GROUND_TRUTH_COLUMNS`) and ``hand_mask`` from the registered ``hand_mask``
    stage (keypoints backend) on the generated frames. The model is loaded on first use from
    ``checkpoint`` (``simulate``'s loader: a missing path or a pickle is a clear error).
    """

    def __init__(self, config: ClosedLoopConfig) -> None:
        self.config = config
        self._model: Any = None

    @property
    def model(self) -> Any:
        """The loaded model (``egosim.model.inference.LoadedModel``), loaded once."""
        if self._model is None:
            from egosim.model.errors import ModelError
            from egosim.model.inference import load_trained

            cfg = self.config
            try:
                self._model = load_trained(
                    cfg.checkpoint or None, preset=cfg.preset or None, device=cfg.device
                )
            except (ModelError, OSError, ValueError) as exc:
                raise ClosedLoopError(
                    f"generator 'model': cannot load checkpoint {cfg.checkpoint!r}: {exc}"
                ) from exc
        return self._model

    def __call__(self, segment: Mapping[str, Any], render: Mapping[str, Any]) -> dict[str, Any]:
        """Generate the segment's clip (see the class docstring)."""
        from egosim.model.conditioning import Conditions
        from egosim.model.sampler import sample

        cid, t = segment["clip_id"], int(segment["num_frames"])
        h, w = int(segment["height"]), int(segment["width"])
        hands = hands_row(segment)
        keypoints = get_stage("keypoint_render")().process({"clips": segment, "hands": hands})
        scene = media.decode_rgb_video(render["scene_video"], h, w, f"render {cid} scene_video")
        conditions = Conditions(
            scene_video=scene,
            visibility=(media.decode_lossless_video(render["visible"], f"render {cid}") > 0).astype(
                np.uint8
            ),
            skeleton_video=media.decode_rgb_video(keypoints["skeleton_video"], h, w),
            first_frame=scene[0],
            prompt=str(segment.get("text") or ""),
        )
        model = self.model
        m = model.bundle.preset.pixel_multiple
        if h % m or w % m:
            raise ClosedLoopError(
                f"segment {cid!r}: frames {h}x{w} are not multiples of {m} (preset "
                f"{model.bundle.preset.name!r})"
            )
        cfg = self.config
        video = sample(model.bundle, conditions, steps=cfg.steps, seed=cfg.seed)
        if video.shape != (t, h, w, 3):
            raise ClosedLoopError(
                f"segment {cid!r}: the model made {video.shape}, the segment is {(t, h, w, 3)}"
            )
        clip = {**segment, **dict.fromkeys(GROUND_TRUTH_COLUMNS)}
        clip["video"] = media.encode_rgb_video(video, float(segment["fps"]), cfg.video_crf)
        mask = get_stage("hand_mask")().process({"clips": clip, "hands": hands})
        clip["hand_mask"] = mask["hand_mask"]
        return clip


def oracle_video_generator(segment: Mapping[str, Any], render: Mapping[str, Any]) -> dict[str, Any]:
    """A perfect model: the segment's own video and nothing else of the world's ground truth
    (:data:`GROUND_TRUTH_COLUMNS` cleared, ``hand_mask`` from the registered ``hand_mask``
    stage on the frames and joints, as for a generated clip), so fusion estimates depth as it
    would for the model's clip. ``render`` is not used."""
    if segment.get("video") is None:
        raise ClosedLoopError(f"segment {segment['clip_id']!r}: no video to return")
    clip = {**segment, **dict.fromkeys(GROUND_TRUTH_COLUMNS)}
    mask = get_stage("hand_mask")().process({"clips": clip, "hands": hands_row(segment)})
    clip["hand_mask"] = mask["hand_mask"]
    return clip


def build_generator(config: ClosedLoopConfig) -> Generator:
    """The clip generator ``config.generator`` names (:data:`GENERATORS`)."""
    return GENERATORS[config.generator](config)


# name -> factory of the clip generator from the loop's config
GENERATORS: dict[str, Callable[[ClosedLoopConfig], Generator]] = {
    "oracle": lambda config: oracle_generator,
    "oracle_video": lambda config: oracle_video_generator,
    "model": ModelGenerator,
}


@dataclasses.dataclass(frozen=True)
class ClosedLoopConfig(StageConfig):
    """Parameters of the closed loop (``egosim simulate --continuous N``)."""

    num_segments: int = 1  # N: action segments the loop must be given, in order
    generator: str = "oracle"  # clip generator: "oracle" (the ground-truth clip), "model", or
    # "oracle_video" (the ground-truth video only: fusion estimates depth, as for "model")
    checkpoint: str = ""  # model: run dir or .safetensors checkpoint ("" = untrained preset)
    preset: str = ""  # model: expected preset ("" = the checkpoint's, "tiny" without one)
    steps: int = 50  # model: Euler steps of the flow sampler (EgoSim: 50)
    seed: int = 0  # model: noise seed
    device: str = "auto"  # model: torch device (auto = cuda if available)
    video_crf: int = 18  # H.264 quality of the stitched video and generated clips (lower = better)
    fusion: StateFusionConfig = dataclasses.field(default_factory=StateFusionConfig)  # fusion

    def __post_init__(self) -> None:
        problems = []
        if self.num_segments < 1:
            problems.append(f"num_segments must be >= 1, got {self.num_segments}")
        if self.generator not in GENERATORS:
            problems.append(
                f"generator must be one of {sorted(GENERATORS)}, got {self.generator!r}"
            )
        if self.steps < 1:
            problems.append(f"steps must be >= 1, got {self.steps}")
        if not 0 <= self.video_crf <= 51:
            problems.append(f"video_crf must be in [0, 51], got {self.video_crf}")
        if problems:
            raise ConfigError("; ".join(problems))


@dataclasses.dataclass
class ClosedLoopResult:
    """What a closed-loop run wrote: one shard per step, and the stitched video."""

    states: list[Path]  # state after each segment, in order
    clips: list[Path]  # generated clip of each segment
    renders: list[Path]  # state rendered along each segment's trajectory
    video: Path  # renders | clips side by side, all segments


def read_rows(paths: Sequence[Path]) -> list[tuple[str, dict[str, Any]]]:
    """``(schema name, row)`` of every row of ``paths`` in order (files, then rows)."""
    out = []
    for path in paths:
        with ShardReader(Path(path)) as reader:
            out += [(reader.meta.schema, row) for row in reader.iter_rows()]
    return out


def _poses(row: Mapping[str, Any]) -> np.ndarray:
    return np.asarray(row["world_from_cam"], np.float64).reshape(-1, 4, 4)


def check_inputs(
    initial: tuple[str, Mapping[str, Any]],
    segments: Sequence[Mapping[str, Any]],
    config: ClosedLoopConfig,
) -> None:
    """Raise :class:`ClosedLoopError` listing every problem of the loop's input at once."""
    schema, first = initial
    problems = []
    if schema not in (STATE.name, SCENE_CLOUD.name):
        problems.append(f"the initial state must be a 'state' or 'scene_cloud' row, got {schema!r}")
    if not segments:
        problems.append("no action segments given (need clips rows: trajectory + hand joints)")
    elif len(segments) != config.num_segments:
        problems.append(f"--continuous {config.num_segments} but {len(segments)} segment(s) given")
    ids = [s["clip_id"] for s in segments]
    if len(set(ids)) != len(ids):
        problems.append(f"segment clip ids repeat: {ids}")
    known = _poses(first) if schema == STATE.name else np.zeros((0, 4, 4))
    fusion = config.fusion
    for k, seg in enumerate(segments, 1):
        where = f"segment {k} ({seg['clip_id']!r})"
        missing = [c for c in ("world_from_cam", "hand_joints", "hand_valid") if seg.get(c) is None]
        if missing:
            problems.append(f"{where}: no {missing} (a segment's action is its camera and hands)")
            continue
        size, size1 = (seg["height"], seg["width"]), (segments[0]["height"], segments[0]["width"])
        if size != size1:
            problems.append(f"{where}: frames are {size} (H, W), segment 1's are {size1}")
        poses = _poses(seg)
        if len(known):
            near = overlapping_cameras(
                poses, known, fusion.overlap_max_distance_m, fusion.overlap_max_angle_deg
            )
            if near.sum() < max(1, fusion.min_overlap_cameras):
                gap = np.linalg.norm(poses[:, None, :3, 3] - known[None, :, :3, 3], axis=-1).min()
                problems.append(
                    f"{where}: its cameras overlap none of the state's (nearest centre {gap:.3g} m,"
                    f" need <= {fusion.overlap_max_distance_m} m and "
                    f"{fusion.overlap_max_angle_deg} deg): another world frame?"
                )
        known = np.concatenate([known, poses])
    if problems:
        raise ClosedLoopError("closed loop input: " + "; ".join(problems))


def hands_row(clip: Mapping[str, Any]) -> dict[str, Any]:
    """A ``hands`` row from a clip row's own joints (the segment's action)."""
    t = int(clip["num_frames"])
    valid = np.asarray(clip["hand_valid"], bool).reshape(t, 2)
    conf = clip.get("hand_confidence")
    conf = np.repeat(valid[:, :, None], 21, 2) if conf is None else np.asarray(conf)
    return {
        "clip_id": clip["clip_id"],
        "num_frames": t,
        "backend": "given",
        "hand_joints": clip["hand_joints"],
        "hand_valid": valid.tolist(),
        "hand_confidence": np.asarray(conf, np.float32).reshape(t, 42).tolist(),
        "hand_lifted": valid.tolist(),  # given joints: their 3D is the action
        "num_duplicates_removed": 0,
        "num_outliers_removed": 0,
        **dict.fromkeys(MANO_COLUMNS),  # no MANO fit: the joints are given
    }


def hand_mask_row(clip: Mapping[str, Any]) -> HandMaskRecord:
    """A ``hand_mask`` row from a clip row's ``hand_mask`` column (the generated clip's).

    A record, so the masks decoded here for ``coverage`` are the ones fusion reads (decoded once
    per segment); a mask video of another size than the clip's raises :class:`InputsDisagree`.
    """
    row = HandMaskRecord(
        {
            "clip_id": clip["clip_id"],
            "num_frames": int(clip["num_frames"]),
            "width": clip["width"],
            "height": clip["height"],
            "hand_mask": clip["hand_mask"],
            "backend": "keypoints",
        }
    )
    mask = row.hand_mask  # (T, H, W) uint8 {0, 1}
    row["coverage"] = (mask > 0).reshape(len(mask), -1).mean(1).tolist()
    return row


def _write(out: Path, step: str, schema: Any, row: Mapping[str, Any], params: dict) -> Path:
    path = path_under(out, validate_id(step, "step name"), shard_file_name(0))
    with ShardWriter(path, schema, stage="closed_loop", params=params) as writer:
        writer.write_row(row)
    return path


def run_closed_loop(
    initial_path: Path, segment_paths: Sequence[Path], out: Path, config: ClosedLoopConfig
) -> ClosedLoopResult:
    """Run the loop over the segments (see the module docstring); returns what it wrote."""
    rows = read_rows([initial_path])
    if len(rows) != 1:
        raise ClosedLoopError(f"{initial_path}: the initial state needs 1 row, has {len(rows)}")
    initial = rows[0]
    given = read_rows(segment_paths)
    segments = [row for _, row in given]
    bad = sorted({name for name, _ in given} - {CLIPS.name})
    if bad:
        raise ClosedLoopError(f"segments must be 'clips' shards, got schemas {bad}")
    check_inputs(initial, segments, config)
    generate = build_generator(config)
    render_stage = get_stage("scene_render")()
    fusion_stage = get_stage("state_fusion")(config.fusion)
    params = {"generator": config.generator, "num_segments": config.num_segments}
    schema, current = initial
    _write(out, "initial", STATE if schema == STATE.name else SCENE_CLOUD, current, params)
    result = ClosedLoopResult([], [], [], path_under(out, "closed_loop.mp4"))
    frames = []
    for k, seg in enumerate(segments, 1):
        cid = seg["clip_id"]
        role = "state" if schema == STATE.name else "scene_cloud"
        before = state_for_clip(current, cid) if role == "state" else {**current, "clip_id": cid}
        try:
            render = render_stage.process({"clips": seg, role: before})
            # a record: its frames, decoded once by fusion, are the stitched video's right half
            clip = ClipsRecord({**generate(seg, render), "clip_id": cid})
            fuse_rows = {
                "clips": clip,
                "hands": hands_row(seg),
                "hand_mask": hand_mask_row(clip),
                "previous_state" if role == "state" else "scene_cloud": before,
            }
            current = fusion_stage.process(fuse_rows)
        except ClipRejected as exc:
            raise ClosedLoopError(f"segment {k} of {len(segments)} rejected: {exc}") from exc
        schema = STATE.name
        result.renders.append(_write(out, f"render_{k:02d}", SCENE_RENDER, render, params))
        result.clips.append(_write(out, f"clip_{k:02d}", CLIPS, clip, params))
        result.states.append(_write(out, f"state_{k:02d}", STATE, current, params))
        h, w = clip.height, clip.width
        scene = media.decode_rgb_video(render["scene_video"], h, w, f"render {cid}")
        frames.append(np.concatenate([scene, clip.frames], 2))
    fps = float(segments[0]["fps"])
    tmp = result.video.with_name(result.video.name + ".tmp-loop")
    tmp.write_bytes(media.encode_rgb_video(np.concatenate(frames), fps, config.video_crf))
    os.replace(tmp, result.video)
    return result
