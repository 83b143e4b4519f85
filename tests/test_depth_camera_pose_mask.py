"""``mask_hands``' landmark mask reaches what poses the camera, not the plane sweep
(stages/depth_camera/stage.py, depth_camera v16).

The metric scale compares the hands with frame 0's plane-sweep depth beside them; the landmark
mask (hull plus a band to the border, grown) took that depth away on DWM 00017 (hand/surf
0.91 -> 0.53). These tests fake SfM and the sweep and record which mask each one receives.
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np
import pytest

from egosim.pipeline import media
from egosim.pipeline.clip_io import row_from_clip
from egosim.stages.common.hand_landmarks import RawLandmarks
from egosim.stages.depth_camera import stage as dc
from egosim.stages.depth_camera.sfm import SfmError, SfmResult
from tests.conftest import make_clip

T, H, W = 8, 96, 160
K = np.array([100.0, 100.0, 80.0, 48.0])


def _moving_frames() -> np.ndarray:
    """``(T, H, W, 3)`` a blob texture panning 2 px a frame (not a static camera)."""
    rng = np.random.default_rng(0)
    base = cv2.GaussianBlur(rng.uniform(0, 255, (120, 200)).astype(np.float32), (0, 0), 2.0)
    base = cv2.normalize(base, None, 0, 255, cv2.NORM_MINMAX)
    out = []
    for k in range(T):
        m = np.float32([[1, 0, -2.0 * k], [0, 1, 0]])
        grey = cv2.warpAffine(base, m, (W, H), borderMode=cv2.BORDER_REFLECT)
        out.append(np.repeat(grey[..., None], 3, axis=2).astype(np.uint8))
    return np.stack(out)


def _fake_sfm() -> SfmResult:
    """Every frame registered, the camera stepping along x; 40 points 2 units ahead."""
    rng = np.random.default_rng(1)
    cam_from_world = np.tile(np.eye(4), (T, 1, 1))  # (T, 4, 4)
    cam_from_world[:, 0, 3] = -0.05 * np.arange(T)
    points = np.column_stack([rng.uniform(-1, 1, 40), rng.uniform(-0.5, 0.5, 40), np.full(40, 2.0)])
    return SfmResult(
        intrinsics=K.copy(),
        cam_from_world=cam_from_world,
        registered=np.ones(T, dtype=bool),
        points3d=points,
        points_frame0_uv=np.zeros((40, 2)),
        reprojection_error_px=0.5,
        num_points3d=40,
        focal_prior=100.0,
        seconds_features=0.0,
        seconds_mapping=0.0,
        all_points3d=points,
        all_point_ids=np.arange(40),
        obs_frame=np.zeros(0, dtype=np.int64),
        obs_uv=np.zeros((0, 2)),
        obs_point_id=np.zeros(0, dtype=np.int64),
        mapper="incremental",
        focal_check_factors=np.zeros(0),
        focal_rise=np.zeros(0),
        seconds_focal_check=0.0,
    )


def _landmark_mask(first: int = 0) -> np.ndarray:
    """``(T, H, W)`` an arm from the bottom border in frames ``first`` on."""
    mask = np.zeros((T, H, W), np.uint8)
    mask[first:, 50:, 60:100] = 1
    return mask


def _record(monkeypatch: pytest.MonkeyPatch, first: int = 0) -> dict[str, Any]:
    """Fake the detector (hands from frame ``first`` on), SfM and the sweep; returns what each
    was given."""
    seen: dict[str, Any] = {}
    none_found = RawLandmarks(
        np.zeros((T, 2, 21, 2)), np.zeros((T, 2, 21, 3)), np.zeros((T, 2)), np.zeros((T, 2), bool)
    )

    def detect(frames: np.ndarray) -> tuple[np.ndarray, RawLandmarks]:
        seen["detected"] = True
        return _landmark_mask(first), none_found

    def run_sfm(frames: np.ndarray, hand_mask: Any, options: Any, worker: Any = None) -> Any:
        seen["sfm"] = hand_mask
        return _fake_sfm()

    def window_depth(frames: np.ndarray, usable: Any, *args: Any) -> Any:
        seen["sweep"] = usable
        return np.full((H, W), 2.0, np.float32), np.zeros((H, W), np.float32), [2, 5]

    check_motion, estimate_rotations = dc.check_motion, dc.estimate_rotations

    def static_check(frames: np.ndarray, hand_mask: Any, *args: Any) -> Any:
        seen["static"] = hand_mask
        return check_motion(frames, hand_mask, *args)

    def rotations(frames: np.ndarray, usable: Any, *args: Any) -> Any:
        seen["rotation"] = usable
        return estimate_rotations(frames, usable, *args)

    monkeypatch.setattr(dc, "hand_mask_from_landmarks", detect)
    monkeypatch.setattr(dc, "run_sfm", run_sfm)
    monkeypatch.setattr(dc, "window_depth", window_depth)
    monkeypatch.setattr(dc, "check_motion", static_check)
    monkeypatch.setattr(dc, "estimate_rotations", rotations)
    return seen


def _row(hand_mask: np.ndarray | None) -> dict[str, Any]:
    row = row_from_clip(make_clip(num_frames=T, height=H, width=W))
    row["video"] = media.encode_rgb_video(_moving_frames(), 16.0)
    row["hand_mask"] = None if hand_mask is None else media.encode_mask_video(hand_mask)
    row["intrinsics"] = K.tolist()
    return row


CONFIG = dict(backend="sfm", source_track="off", sfm_focal_check_factors=())


def test_mask_hands_masks_sfm_features_but_not_the_plane_sweep(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """No hand_mask input, mask_hands on: SfM's features get the landmark mask, the plane sweep
    (frame 0's depth, which the metric scale reads) gets none (before v16 it got the mask)."""
    seen = _record(monkeypatch)
    config = dc.DepthCameraConfig(mask_hands=True, **CONFIG)
    est = dc.DepthCameraStage(config).estimate(_row(None))
    assert seen.get("detected") and est.camera_model == "sfm"
    np.testing.assert_array_equal(seen["sfm"], _landmark_mask())
    assert seen["sweep"] is None


def test_mask_hands_leaves_the_static_check_and_the_rotation_model_unmasked(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """SfM finds no model: the rotation model poses the clip, on every pixel, as does the static
    check (with the landmark mask there the EgoDex sample's rotation-model focal went from +7.4%
    to +15.4% of its true one)."""
    seen = _record(monkeypatch)

    def no_model(frames: np.ndarray, hand_mask: Any, options: Any, worker: Any = None) -> Any:
        seen["sfm"] = hand_mask
        raise SfmError("no model")

    monkeypatch.setattr(dc, "run_sfm", no_model)
    config = dc.DepthCameraConfig(mask_hands=True, **CONFIG)
    est = dc.DepthCameraStage(config).estimate(_row(None))
    assert est.camera_model == "rotation"
    np.testing.assert_array_equal(seen["sfm"], _landmark_mask())
    assert seen["static"] is None and seen["rotation"] is None


def test_mask_hands_leaves_a_clip_whose_hands_come_in_later_unmasked(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Frame 0 shows no hand: SfM and the sweep run as with mask_hands off (DWM 00017: masking
    its later hands moved its metric scale 0.030 -> 0.052 m/unit, hand/surf 0.91 -> 0.53)."""
    seen = _record(monkeypatch, first=3)
    config = dc.DepthCameraConfig(mask_hands=True, **CONFIG)
    dc.DepthCameraStage(config).estimate(_row(None))
    assert seen.get("detected")
    assert seen["sfm"] is None and seen["sweep"] is None


def test_a_hand_mask_input_still_reaches_the_plane_sweep(monkeypatch: pytest.MonkeyPatch) -> None:
    """With a hand_mask input (hands known), SfM and the sweep both get it; no detection."""
    seen = _record(monkeypatch)
    given = np.zeros((T, H, W), np.uint8)
    given[:, :30, :40] = 1
    config = dc.DepthCameraConfig(mask_hands=True, **CONFIG)
    dc.DepthCameraStage(config).estimate(_row(given))
    assert "detected" not in seen
    np.testing.assert_array_equal(seen["sfm"], given)
    assert seen["sweep"] is not None and not seen["sweep"][0, :30, :40].any()
    assert seen["sweep"][0, 80:, 100:].all()


def test_pose_mask_is_joined_to_the_hand_mask_for_sfm_only(monkeypatch: pytest.MonkeyPatch) -> None:
    """estimate_sfm: ``pose_mask`` joins ``hand_mask`` for SfM's features; the sweep keeps
    ``hand_mask`` alone."""
    seen = _record(monkeypatch)
    given = np.zeros((T, H, W), np.uint8)
    given[:, :30, :40] = 1
    config = dc.DepthCameraConfig(**CONFIG)
    dc.estimate_sfm("c", _moving_frames(), given, K, config, pose_mask=_landmark_mask())
    np.testing.assert_array_equal(seen["sfm"], np.maximum(given, _landmark_mask()))
    assert not seen["sweep"][0, :30, :40].any()  # the input hand
    assert seen["sweep"][0, 70:, 75:85].all()  # the landmark arm is swept


def test_default_config_without_mediapipe_raises_naming_the_install(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """mask_hands is on by default (v16): a clip with no hand_mask input needs the detector, and
    its absence raises (naming the install) instead of posing the clip with the arms in SfM."""
    from egosim.stages.common.hand_landmarks import MediaPipeUnavailableError

    real = dc.hand_mask_from_landmarks
    seen = _record(monkeypatch)
    monkeypatch.setattr(dc, "hand_mask_from_landmarks", real)  # the real one; its detector fails

    def missing(frames: np.ndarray, params: Any = None) -> RawLandmarks:
        raise MediaPipeUnavailableError("hand landmarks need mediapipe==0.10.21 (pip install ...)")

    monkeypatch.setattr(dc, "detect_hand_landmarks", missing)
    assert dc.DepthCameraConfig().mask_hands
    with pytest.raises(MediaPipeUnavailableError, match=r"mediapipe==0\.10\.21"):
        dc.DepthCameraStage(dc.DepthCameraConfig(**CONFIG)).estimate(_row(None))
    assert "sfm" not in seen


def test_a_static_clip_runs_no_hand_detection(monkeypatch: pytest.MonkeyPatch) -> None:
    """A fixed camera is found before the hands are looked for: no detection (it would be
    unused; it cost DWM's fixed-camera videos 6-11 s each) and no SfM."""
    seen = _record(monkeypatch)
    row = _row(None)
    row["video"] = media.encode_rgb_video(np.repeat(_moving_frames()[:1], T, axis=0), 16.0)
    config = dc.DepthCameraConfig(mask_hands=True, **CONFIG)
    est = dc.DepthCameraStage(config).estimate(row)
    assert est.camera_model == "static"
    assert "detected" not in seen and "sfm" not in seen
