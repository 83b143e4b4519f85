"""The ``pose_clean`` stage: jump-outlier repair and smoothing of camera trajectories.

Methods (``method`` parameter):

- ``kalman_rts`` (default): Eq. 4 outliers repaired, then a constant-velocity Kalman filter on the
  camera centre and on the hemisphere-aligned quaternion (renormalised after each update),
  followed by the backward Rauch-Tung-Striebel pass: no lag.
- ``kalman_causal``: the same forward filter without the backward pass (the paper's filter, plus
  hemisphere alignment); it lags the motion by a few frames.
- ``egocap``: jump frames re-interpolated by cubic spline (translation) and SLERP (rotation),
  then a global Savitzky-Golay filter.

Noise levels are estimated per clip from the data (see :func:`kalman.estimate_noise`): the
measurement noise is the input's own, so near-exact poses pass nearly unchanged and noisy ones
are smoothed; the two ``*_noise_scale`` fields only scale them. Jumps are found relative to the
trajectory's own statistics (see :mod:`outliers`), with no length threshold, so the stage works
the same on metric poses and on SfM poses in arbitrary units.

Jitter figures (``jitter_*_mm``) are in thousandths of the poses' length unit: millimetres only
when the poses are metric (a clip's own poses, or cameras whose ``metric_scale`` is set), else
thousandths of an SfM unit. The pure function :func:`clean_trajectory` does the work
on numpy arrays; :func:`clean_batch` runs many clips at once (batched Kalman equations).

The trajectory cleaned is the optional ``cameras`` input's (``depth_camera``) when a workflow
connects it, else the clip's own ``world_from_cam``. With ``protect_mapper_frames``, frames the
cameras row marks as registered by the SfM mapper (``posed_by`` 0: bundle-adjusted against the
map) are never repaired as jumps (see :mod:`outliers`); they are still smoothed.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from typing import Any, ClassVar, Literal

import numpy as np

from egosim.pipeline.geometry import (
    make_se3,
    matrix_from_quat,
    quat_align_hemisphere,
    quat_from_matrix,
    se3_problems,
)
from egosim.pipeline.records import ClipsRecord
from egosim.pipeline.stage import ClipRejected, ClipStage, ConfigError, StageConfig
from egosim.schemas.base import ShardSchema
from egosim.schemas.clips import CLIPS
from egosim.schemas.depth_camera import DEPTH_CAMERA, POSED_BY_MAPPER
from egosim.schemas.poses import POSES
from egosim.stages.pose_clean import egocap, kalman
from egosim.stages.pose_clean.outliers import detect_outliers, jitter, repair_outliers

Method = Literal["kalman_rts", "kalman_causal", "egocap"]
METHODS: tuple[str, ...] = ("kalman_rts", "kalman_causal", "egocap")


class PoseInputError(ValueError):
    """A trajectory cannot be cleaned (wrong shape, NaN, not rigid); the message says why."""


@dataclasses.dataclass(frozen=True)
class PoseCleanConfig(StageConfig):
    """Parameters of ``pose_clean``."""

    method: Method = "kalman_rts"  # kalman_rts, kalman_causal or egocap (see module doc)
    engine: Literal["numpy", "filterpy"] = "numpy"  # Kalman code: batched numpy or filterpy
    motion_order: int = 3  # Kalman states per channel: 2 const. velocity (paper), 3 const. accel.
    outlier_ratio: float = 4.0  # jump threshold, multiple of the clip's median fit residual
    outlier_floor_ratio: float = 2.0  # threshold floor, multiple of the median second difference
    outlier_neighbours: int = 6  # frames of the local quadratic fit that predicts each frame
    outlier_max_fraction: float = 0.25  # at most this share of a clip's frames is flagged
    protect_mapper_frames: bool = True  # cameras' SfM-mapper frames (posed_by 0) are never
    # repaired as jumps: a fast head turn at a low frame rate looks like one to the jump test
    process_noise_scale: float = 1.0  # multiplies the acceleration variance estimated per clip
    # multiplies the noise variance estimated per clip; 1.4 measured best on the noisy harness
    # (the fitted process noise follows it) and adds < 0.03 mm to exact poses
    measurement_noise_scale: float = 1.4
    savgol_window: int = 9  # egocap: Savitzky-Golay window in frames (odd)
    savgol_polyorder: int = 2  # egocap: Savitzky-Golay polynomial order (< window)

    def __post_init__(self) -> None:
        problems: list[str] = []
        if self.method not in METHODS:
            problems.append(f"method must be one of {list(METHODS)}, got {self.method!r}")
        if self.engine not in ("numpy", "filterpy"):
            problems.append(f"engine must be 'numpy' or 'filterpy', got {self.engine!r}")
        if not (np.isfinite(self.outlier_ratio) and self.outlier_ratio > 1.0):
            problems.append(f"outlier_ratio must be > 1, got {self.outlier_ratio}")
        if self.motion_order not in (2, 3):
            problems.append(f"motion_order must be 2 or 3, got {self.motion_order}")
        if self.outlier_neighbours < 4:
            problems.append(f"outlier_neighbours must be >= 4, got {self.outlier_neighbours}")
        if not 0.0 <= self.outlier_max_fraction < 1.0:
            problems.append(
                f"outlier_max_fraction must be in [0, 1), got {self.outlier_max_fraction}"
            )
        for name in (
            "outlier_floor_ratio",
            "process_noise_scale",
            "measurement_noise_scale",
        ):
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0):
                problems.append(f"{name} must be > 0, got {value}")
        if self.savgol_window < 3 or self.savgol_window % 2 == 0:
            problems.append(f"savgol_window must be odd and >= 3, got {self.savgol_window}")
        if not 0 <= self.savgol_polyorder < self.savgol_window:
            problems.append(
                f"savgol_polyorder must be in [0, savgol_window), got {self.savgol_polyorder}"
            )
        if problems:
            raise ConfigError("; ".join(problems))


@dataclasses.dataclass(frozen=True)
class CleanResult:
    """One cleaned trajectory and its figures."""

    world_from_cam: np.ndarray  # (T, 4, 4) cleaned camera-to-world
    outliers: np.ndarray  # (T,) bool, frames flagged and repaired
    method: str  # method used
    jitter_before_mm: float  # RMS second difference of the input centre, 1e-3 pose units
    jitter_after_mm: float  # same for the output (both mm only when the poses are metric)
    jitter_before_deg: float  # RMS rotation second difference of the input, degrees
    jitter_after_deg: float  # same for the output


def check_trajectory(world_from_cam: np.ndarray) -> np.ndarray:
    """Return ``world_from_cam`` as ``(T, 4, 4)`` float64; raise :class:`PoseInputError`."""
    poses = np.asarray(world_from_cam, dtype=np.float64)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4) or len(poses) < 1:
        raise PoseInputError(f"world_from_cam must have shape (T>=1, 4, 4), got {poses.shape}")
    problems = se3_problems(poses)
    if problems:
        bad = _bad_frames(poses)
        raise PoseInputError(
            f"world_from_cam is not a valid rigid trajectory ({'; '.join(problems)}; "
            f"first bad frames {bad[:5]})"
        )
    return poses


def _bad_frames(poses: np.ndarray) -> list[int]:
    return [i for i in range(len(poses)) if se3_problems(poses[i])]


def _repair(
    poses: np.ndarray, config: PoseCleanConfig, protected: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """``(outlier mask (T,), repaired poses (T, 4, 4))`` for the configured method.

    ``protected (T,)`` bool: frames never flagged as jumps (None: none).
    """
    flags = detect_outliers(
        poses,
        ratio=config.outlier_ratio,
        floor_ratio=config.outlier_floor_ratio,
        neighbours=config.outlier_neighbours,
        max_fraction=config.outlier_max_fraction,
        protected=protected,
    )
    if config.method == "egocap" and (~flags).sum() >= 2:
        return flags, egocap.interpolate_outliers(poses, flags)
    return flags, repair_outliers(poses, flags)


def _channels(poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(centres (T, 3), hemisphere-aligned quaternions (T, 4))`` of ``poses (T, 4, 4)``."""
    return poses[:, :3, 3], quat_align_hemisphere(quat_from_matrix(poses[:, :3, :3]))


def _result(before: np.ndarray, after: np.ndarray, flags: np.ndarray, method: str) -> CleanResult:
    jb_mm, jb_deg = jitter(before)
    ja_mm, ja_deg = jitter(after)
    return CleanResult(after, flags, method, jb_mm, ja_mm, jb_deg, ja_deg)


def clean_batch(
    trajectories: Sequence[np.ndarray],
    config: PoseCleanConfig,
    fps: float = 16.0,
    protected: Sequence[np.ndarray | None] | None = None,
) -> list[CleanResult]:
    """Clean many trajectories ``[(T_i, 4, 4)]`` sampled at ``fps``; one :class:`CleanResult` each.

    ``protected``: per trajectory, ``(T_i,)`` bool frames never repaired as jumps, or None.
    Trajectories of equal length go through the Kalman equations together (``engine="numpy"``).
    Raises :class:`PoseInputError` naming the index of the first bad trajectory.
    """
    if not (np.isfinite(fps) and fps > 0):
        raise PoseInputError(f"fps must be > 0, got {fps}")
    dt = 1.0 / fps
    checked: list[np.ndarray] = []
    for i, traj in enumerate(trajectories):
        try:
            checked.append(check_trajectory(traj))
        except PoseInputError as exc:
            raise PoseInputError(f"trajectory {i}: {exc}") from exc
    keep = list(protected) if protected is not None else [None] * len(checked)
    if len(keep) != len(checked):
        raise PoseInputError(f"{len(keep)} protected masks for {len(checked)} trajectories")
    for i, (p, k) in enumerate(zip(checked, keep, strict=True)):
        if k is not None and np.shape(k) != (len(p),):
            raise PoseInputError(
                f"trajectory {i}: protected must have shape ({len(p)},), got {np.shape(k)}"
            )
    repaired = [_repair(p, config, k) for p, k in zip(checked, keep, strict=True)]
    results: list[CleanResult | None] = [None] * len(checked)
    if config.method == "egocap":
        for i, (flags, fixed) in enumerate(repaired):
            out = egocap.savgol_poses(fixed, config.savgol_window, config.savgol_polyorder)
            results[i] = _result(checked[i], out, flags, config.method)
        return [r for r in results if r is not None]
    smooth = config.method == "kalman_rts"
    by_length: dict[int, list[int]] = {}
    for i, p in enumerate(checked):
        by_length.setdefault(len(p), []).append(i)
    for length, members in by_length.items():
        if length < 3:  # nothing to smooth
            for i in members:
                results[i] = _result(checked[i], repaired[i][1], repaired[i][0], config.method)
            continue
        chans = [_channels(repaired[i][1]) for i in members]
        cen = np.stack([c for c, _ in chans])  # (B, T, 3)
        qua = np.stack([q for _, q in chans])  # (B, T, 4)
        outs = []
        order = config.motion_order
        for z, normalise in ((cen, False), (qua, True)):
            q0, r = kalman.estimate_noise(z, dt)  # (B, C) each
            r = r * config.measurement_noise_scale
            q = kalman.fit_process_noise(z, dt, q0, r, normalise, order)  # (B, C)
            q = q * config.process_noise_scale
            if config.engine == "numpy":
                outs.append(kalman.batched_smooth(z, dt, q, r, smooth, normalise, order))
            else:
                outs.append(
                    np.stack(
                        [
                            kalman.filterpy_smooth(zi, dt, qi, ri, smooth, normalise, order)
                            for zi, qi, ri in zip(z, q, r, strict=True)
                        ]
                    )
                )
        poses_out = make_se3(matrix_from_quat(outs[1]), outs[0])  # (B, T, 4, 4)
        for j, i in enumerate(members):
            results[i] = _result(checked[i], poses_out[j], repaired[i][0], config.method)
    return [r for r in results if r is not None]


def clean_trajectory(
    world_from_cam: np.ndarray,
    config: PoseCleanConfig | None = None,
    fps: float = 16.0,
    protected: np.ndarray | None = None,
) -> CleanResult:
    """Detect and repair jump outliers in ``world_from_cam (T, 4, 4)``, then smooth it.

    ``protected (T,)`` bool: frames never repaired as jumps (None: none). Raises
    :class:`PoseInputError` for a malformed, non-finite or non-rigid trajectory.
    """
    cfg = config if config is not None else PoseCleanConfig()
    try:
        return clean_batch([world_from_cam], cfg, fps, [protected])[0]
    except PoseInputError as exc:
        raise PoseInputError(str(exc).removeprefix("trajectory 0: ")) from None


class PoseCleanStage(ClipStage):
    """Repair jump outliers in camera trajectories and smooth them (Kalman RTS by default)."""

    name = "pose_clean"
    # v2: the measurement noise is estimated from the input's own high-order differences (exact
    # poses pass nearly unchanged); jumps are found by an iterated, scale-free leave-one-out fit
    # test (adjacent spikes no longer hide each other; no metre or degree thresholds).
    # v3: frames the SfM mapper registered (cameras posed_by 0) are never repaired as jumps
    version = 3
    description = "repair pose jump outliers (Eq. 4) and smooth trajectories (Kalman RTS/egocap)"
    config_class = PoseCleanConfig
    inputs: ClassVar[Mapping[str, ShardSchema]] = {"clips": CLIPS}
    # estimated cameras: their trajectory is cleaned instead of the clip's own
    optional_inputs: ClassVar[Mapping[str, ShardSchema]] = {"cameras": DEPTH_CAMERA}
    output = POSES
    backends = METHODS
    # What process reads (the executor decodes nothing else): a trajectory and its frame rate.
    columns: ClassVar[Mapping[str, tuple[str, ...]]] = {
        "clips": ("num_frames", "fps", "world_from_cam"),
        "cameras": ("world_from_cam", "posed_by"),
    }
    config: PoseCleanConfig

    def process(self, rows: Mapping[str, Mapping[str, Any]]) -> dict[str, Any]:
        """Clean one clip's trajectory; returns a ``poses`` row.

        The trajectory is the ``cameras`` row's ``world_from_cam`` when that role is connected,
        else the clips row's.
        """
        row = ClipsRecord.of(rows["clips"])
        clip_id = row.clip_id
        role = "cameras" if rows.get("cameras") is not None else "clips"
        raw = rows[role].get("world_from_cam")
        if raw is None:
            raise ClipRejected(f"clip {clip_id} has no world_from_cam: run depth_camera first")
        where = "world_from_cam" if role == "clips" else "cameras world_from_cam"
        t = row.num_frames
        try:
            flat = np.asarray(raw, dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise ClipRejected(f"clip {clip_id}: {where} is not numeric ({exc})") from exc
        if flat.ndim != 2 or flat.shape[1] != 16:
            raise ClipRejected(f"clip {clip_id}: {where} must be (T, 16), got shape {flat.shape}")
        if len(flat) != t:
            raise ClipRejected(
                f"clip {clip_id}: {where} has {len(flat)} poses but num_frames is {t}"
            )
        protected = None
        posed_by = rows[role].get("posed_by") if role == "cameras" else None
        if self.config.protect_mapper_frames and posed_by is not None:
            codes = np.asarray(posed_by)
            if codes.shape != (t,):
                raise ClipRejected(
                    f"clip {clip_id}: cameras posed_by has shape {codes.shape}, expected ({t},)"
                )
            protected = codes == POSED_BY_MAPPER
        try:
            result = clean_trajectory(flat.reshape(t, 4, 4), self.config, row.fps, protected)
        except PoseInputError as exc:
            raise ClipRejected(f"clip {clip_id}: {exc}") from exc
        return {
            "clip_id": clip_id,
            "num_frames": t,
            "world_from_cam": result.world_from_cam.reshape(t, 16).tolist(),
            "outlier_frames": np.flatnonzero(result.outliers).astype(int).tolist(),
            "method": result.method,
            "jitter_before_mm": result.jitter_before_mm,
            "jitter_after_mm": result.jitter_after_mm,
            "jitter_before_deg": result.jitter_before_deg,
            "jitter_after_deg": result.jitter_after_deg,
        }
