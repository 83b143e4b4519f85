"""Run pycolmap SfM on a clip in an isolated subprocess and read its model back.

pycolmap aborts the process on internal failures (HAZARDS.md), so the work happens in
:mod:`egosim.stages.depth_camera.sfm_worker`, run as a script (not through the package, so a
half-edited stage registry cannot break it) on frames written to a temporary folder. A non-zero
exit, a signal, a timeout or a missing result becomes :class:`SfmError` with the tail of the
worker's stderr; the stage turns it into a reject.
"""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from egosim.pipeline.geometry import invert_se3, make_se3, slerp_rotations

WORKER = Path(__file__).with_name("sfm_worker.py")
STDERR_TAIL_CHARS = 1500  # how much of the worker's stderr a failure message quotes


class SfmError(RuntimeError):
    """SfM failed on a clip (worker crash, abort, timeout, no model); the message says why."""


@dataclass(frozen=True)
class SfmOptions:
    """Settings passed to the worker (see :class:`DepthCameraConfig` for their meaning)."""

    max_image_size: int = 640  # SIFT on frames downscaled to this longest side
    max_num_features: int = 1024  # SIFT features per frame
    sequential_overlap: int = 6  # neighbours matched per frame
    quadratic_overlap: bool = True  # also match frames 2^k apart (long baselines)
    focal_factors: tuple[float, ...] = (0.7, 1.0, 0.5)  # focal priors x width, in order
    init_min_tri_angle: float = 4.0  # degrees, initial pair (COLMAP default 16)
    max_mapping_seconds: int = 60  # mapping time cap per focal prior
    good_enough_fraction: float = 0.95  # stop trying focal priors once this many register ...
    good_max_reprojection_px: float = 1.0  # ... with at most this mean reprojection error
    num_threads: int = 2  # threads of extraction, matching and mapping
    mask_dilate_px: int = 8  # hand mask growth before excluding features
    timeout_s: float = 600.0  # the worker is killed after this long
    prior_focal: float = 0.0  # focal prior in pixels (clip intrinsics), tried first; 0 = none
    plausible_fov_deg: tuple[float, float] = (40.0, 100.0)  # horizontal FOV a model should have
    try_global: bool = False  # also run pycolmap's global mapper when incremental is not good
    focal_check_factors: tuple[float, ...] = (0.7, 1.4)  # focal check: focal held at these x
    # the kept model's, error rise against it free (sfm_worker.focal_rise); () = no check
    focal_check_points: int = 400  # focal check: at most this many of the model's points


@dataclass(frozen=True)
class SfmResult:
    """An SfM model of one clip, with every frame given a pose."""

    intrinsics: np.ndarray  # (4,) fx, fy, cx, cy in pixels of the input frames
    cam_from_world: np.ndarray  # (T, 4, 4) world-to-camera; unregistered frames interpolated
    registered: np.ndarray  # (T,) bool
    points3d: np.ndarray  # (P, 3) SfM points observed in frame 0 (world)
    points_frame0_uv: np.ndarray  # (P, 2) their pixels in frame 0
    reprojection_error_px: float  # mean reprojection error of the model
    num_points3d: int  # points in the model
    focal_prior: float  # the prior focal (pixels) of the model that was kept
    seconds_features: float  # extraction + matching time in the worker
    seconds_mapping: float  # mapping time in the worker
    all_points3d: np.ndarray  # (Q, 3) every point of the model (world)
    all_point_ids: np.ndarray  # (Q,) int64 their ids
    obs_frame: np.ndarray  # (N,) int64 frame of each observation of a model point
    obs_uv: np.ndarray  # (N, 2) its pixel in that frame
    obs_point_id: np.ndarray  # (N,) int64 the observed point's id
    mapper: str  # which mapper built the model: incremental, global, incremental-fixed-focal
    focal_check_factors: np.ndarray  # (C,) focal check: focal held at these x the model's
    focal_rise: np.ndarray  # (C,) relative reprojection error rise at each (see sfm_worker)
    seconds_focal_check: float  # time of the focal check in the worker


def write_inputs(
    work: Path, frames: np.ndarray, hand_mask: np.ndarray | None, options: SfmOptions
) -> None:
    """Write ``frames (T, H, W, 3)`` RGB, feature masks and options into ``work``."""
    (work / "images").mkdir(parents=True)
    kernel = None
    if hand_mask is not None:
        (work / "masks").mkdir()
        side = 2 * options.mask_dilate_px + 1
        kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (side, side))
    png = [cv2.IMWRITE_PNG_COMPRESSION, 1]
    for k, frame in enumerate(frames):
        name = f"{k:04d}.png"
        cv2.imwrite(str(work / "images" / name), cv2.cvtColor(frame, cv2.COLOR_RGB2BGR), png)
        if hand_mask is not None:
            hand = cv2.dilate(hand_mask[k].astype(np.uint8), kernel) > 0
            keep = np.where(hand, 0, 255).astype(np.uint8)  # COLMAP: 0 = ignore
            cv2.imwrite(str(work / "masks" / f"{name}.png"), keep, png)
    opts = dataclasses.asdict(options)
    opts["width"] = int(frames.shape[2])
    opts["focal_factors"] = list(options.focal_factors)
    opts["plausible_fov_deg"] = list(options.plausible_fov_deg)
    opts["focal_check_factors"] = list(options.focal_check_factors)
    (work / "options.json").write_text(json.dumps(opts))


def _stderr_tail(text: str) -> str:
    lines = [ln for ln in text.strip().splitlines() if ln.strip()]
    return "\n".join(lines)[-STDERR_TAIL_CHARS:]


def run_worker(work: Path, timeout_s: float, command: list[str] | None = None) -> None:
    """Run the worker on ``work``; raise :class:`SfmError` unless it wrote ``result.npz``.

    ``command`` replaces the worker command line (tests use it to simulate aborts).
    """
    cmd = command if command is not None else [sys.executable, str(WORKER), str(work)]
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s, check=False)
    except subprocess.TimeoutExpired as exc:
        err = exc.stderr.decode(errors="replace") if isinstance(exc.stderr, bytes) else ""
        raise SfmError(f"SfM timed out after {timeout_s:.0f} s; {_stderr_tail(err or '')}") from exc
    if proc.returncode != 0:
        how = (
            f"was killed by signal {-proc.returncode}"
            if proc.returncode < 0
            else f"exited with code {proc.returncode}"
        )
        raise SfmError(f"SfM worker {how}: {_stderr_tail(proc.stderr)}")
    if not (work / "result.npz").is_file():
        raise SfmError(f"SfM worker wrote no result: {_stderr_tail(proc.stderr)}")


def fill_unregistered(cam_from_world: np.ndarray, registered: np.ndarray) -> np.ndarray:
    """Give unregistered frames a pose interpolated (SLERP + linear centre) from registered ones.

    ``cam_from_world (T, 4, 4)`` with arbitrary values where ``registered (T,)`` is False; frames
    before the first or after the last registered one copy the nearest registered pose (the
    caller flags them: ``posed_by`` = interpolated).
    """
    t = len(registered)
    known = np.flatnonzero(registered)
    world_from_cam = invert_se3(cam_from_world[known])  # (R, 4, 4)
    times = known.astype(np.float64)
    query = np.arange(t, dtype=np.float64)
    if len(known) == 1:
        rot = np.repeat(world_from_cam[:, :3, :3], t, axis=0)
    else:
        rot = slerp_rotations(times, world_from_cam[:, :3, :3], query)  # (T, 3, 3)
    centre = np.stack([np.interp(query, times, world_from_cam[:, i, 3]) for i in range(3)], -1)
    filled = invert_se3(make_se3(rot, centre))  # (T, 4, 4)
    filled[known] = cam_from_world[known]
    return filled


def read_result(path: Path, num_frames: int, height: int) -> SfmResult:
    """Read the worker's ``result.npz`` into an :class:`SfmResult` for ``num_frames`` frames."""
    with np.load(path) as data:
        index = data["image_index"].astype(int)
        poses = np.tile(np.eye(4), (num_frames, 1, 1))
        registered = np.zeros(num_frames, dtype=bool)
        poses[index] = data["cam_from_world"]
        registered[index] = True
        f, cx, cy = (float(v) for v in data["camera_params"][:3])
        timings = data["timings"]
        return SfmResult(
            intrinsics=np.array([f, f, cx, cy]),
            cam_from_world=fill_unregistered(poses, registered) if registered.any() else poses,
            registered=registered,
            points3d=data["points3d"],
            points_frame0_uv=data["points_frame0_uv"],
            reprojection_error_px=float(data["reprojection_error_px"]),
            num_points3d=int(data["num_points3d"]),
            focal_prior=float(data["focal_prior"]),
            seconds_features=float(timings[0]),
            seconds_mapping=float(timings[1]),
            all_points3d=data["all_points3d"],
            all_point_ids=data["all_point_ids"],
            obs_frame=data["obs_frame"],
            obs_uv=data["obs_uv"],
            obs_point_id=data["obs_point_id"],
            mapper=str(data["mapper"]),
            focal_check_factors=data["focal_check_factors"],
            focal_rise=data["focal_rise"],
            seconds_focal_check=float(timings[2]),
        )


def run_sfm(
    frames: np.ndarray,
    hand_mask: np.ndarray | None,
    options: SfmOptions,
    command: list[str] | None = None,
) -> SfmResult:
    """SfM of ``frames (T, H, W, 3)`` uint8 RGB, features masked by ``hand_mask (T, H, W)``.

    Raises :class:`SfmError` when the worker fails or finds no model.
    """
    with tempfile.TemporaryDirectory(prefix="egosim_sfm_") as tmp:
        work = Path(tmp)
        write_inputs(work, frames, hand_mask, options)
        run_worker(work, options.timeout_s, command)
        return read_result(work / "result.npz", len(frames), frames.shape[1])


def keyframe_indices(num_frames: int, stride: int) -> np.ndarray:
    """``(K,)`` frames SfM runs on: every ``stride``-th from frame 0, plus the last frame."""
    index = np.arange(0, num_frames, max(stride, 1))
    if index[-1] != num_frames - 1:
        index = np.append(index, num_frames - 1)
    return index


def spread_to_frames(result: SfmResult, index: np.ndarray, num_frames: int) -> SfmResult:
    """An SfM result on keyframes ``index (K,)`` as one over all ``num_frames`` frames.

    Frames between keyframes are unregistered (poses interpolated until tracking poses them);
    observations keep their points and move to the frames' own indices.
    """
    registered = np.zeros(num_frames, dtype=bool)
    registered[index] = result.registered
    poses = np.tile(np.eye(4), (num_frames, 1, 1))  # (T, 4, 4)
    poses[index] = result.cam_from_world
    if registered.any():
        poses = fill_unregistered(poses, registered)
    return dataclasses.replace(
        result,
        cam_from_world=poses,
        registered=registered,
        obs_frame=index[result.obs_frame] if len(result.obs_frame) else result.obs_frame,
    )
