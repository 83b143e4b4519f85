"""hands, backend ``regressor``: a tiny random HandRegressor saved, loaded and run on a clip."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from egosim.model.checkpoint import UnsafeCheckpointError  # noqa: E402
from egosim.pipeline.clip_io import clip_from_row, write_clips  # noqa: E402
from egosim.pipeline.execute import ShardTask, run_shard_task  # noqa: E402
from egosim.pipeline.geometry import invert_se3, project_points, transform_points  # noqa: E402
from egosim.pipeline.shards import open_shard  # noqa: E402
from egosim.pipeline.stage import ConfigError  # noqa: E402
from egosim.schemas.hands import HANDS  # noqa: E402
from egosim.stages.hands.regressor_backend import (  # noqa: E402
    CONFIG_FILE,
    WEIGHTS_FILE,
    HandRegressor,
    RegressorParams,
    RegressorSpec,
    RegressorWeightsError,
    crop_hand,
    full_perspective_translation,
    load_regressor,
    regressor_detections,
    save_regressor,
)
from egosim.stages.hands.stage import HandsConfig  # noqa: E402
from egosim.world.clip import render_clip  # noqa: E402
from egosim.world.config import WorldConfig  # noqa: E402

TINY = RegressorSpec(
    image_size=64, patch_size=16, hidden_size=32, num_layers=2, num_heads=2, head_size=32
)


@pytest.fixture(scope="module")
def weights(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A folder holding a tiny randomly initialised regressor."""
    torch.manual_seed(0)
    folder = tmp_path_factory.mktemp("regressor")
    save_regressor(HandRegressor(TINY), folder)
    return folder


@pytest.fixture(scope="module")
def clip():
    return render_clip(WorldConfig(seed=0, height=96, width=160, num_frames=5))


def test_weak_to_full_perspective_hand_computed() -> None:
    # Box of 40 px centred at (100, 60); s = 0.5, t = (0.2, -0.4); fx = fy = 200, c = (80, 48).
    # T_z = 2 f / (s b) = 400 / 20 = 20 m; the wrist's pixel is c_box + s t b / 2 = (102, 56), so
    # T_x = 20 (102 - 80) / 200 = 2.2 (HaMeR: tx + 2 (c_u - cx) / (s b) = 0.2 + 2) and
    # T_y = 20 (56 - 48) / 200 = 0.8.
    k = np.array([200.0, 200.0, 80.0, 48.0])
    cam = np.array([[0.5, 0.2, -0.4]])
    t = full_perspective_translation(cam, np.array([[100.0, 60.0]]), np.array([40.0]), k)
    np.testing.assert_allclose(t, [[2.2, 0.8, 20.0]], atol=1e-6)
    uv, _ = project_points(t, k)
    np.testing.assert_allclose(uv, [[102.0, 56.0]], atol=1e-6)
    # A point 1 cm right of the wrist at its depth moves s * b / 2 = 10 px per metre: 0.1 px.
    uv_x, _ = project_points(t + np.array([0.01, 0.0, 0.0]), k)
    np.testing.assert_allclose(uv_x, [[102.1, 56.0]], atol=1e-6)
    # Non-square pixels: depth from the mean focal (150), each axis through its own focal.
    k2 = np.array([200.0, 100.0, 80.0, 48.0])
    t2 = full_perspective_translation(cam, np.array([[100.0, 60.0]]), np.array([40.0]), k2)
    np.testing.assert_allclose(t2, [[1.65, 1.2, 15.0]], atol=1e-6)
    np.testing.assert_allclose(project_points(t2, k2)[0], [[102.0, 56.0]], atol=1e-6)


def test_crop_puts_a_pixel_where_expected() -> None:
    frame = np.zeros((96, 160, 3), np.uint8)
    frame[50, 90] = 255  # pixel centre (90.5, 50.5)
    # A 16 px box centred at (90, 50) starts at (82, 42): the pixel's centre is at crop 8.5.
    crop = crop_hand(frame, np.array([90.0, 50.0]), 16.0, 16, mirror=False)
    assert crop.shape == (16, 16, 3)
    assert tuple(np.argwhere(crop[..., 0] == 255)[0]) == (8, 8) and crop[..., 0].sum() == 255
    mirrored = crop_hand(frame, np.array([90.0, 50.0]), 16.0, 16, mirror=True)
    assert tuple(np.argwhere(mirrored[..., 0] == 255)[0]) == (8, 7)


def test_saved_model_loads_and_predicts_the_same(weights: Path) -> None:
    torch.manual_seed(0)
    original = HandRegressor(TINY).eval()
    loaded = load_regressor(weights)
    x = torch.randn(3, 3, 64, 64)
    with torch.inference_mode():
        joints, cam = loaded(x)
        joints0, cam0 = original(x)
    assert joints.shape == (3, 21, 3) and cam.shape == (3, 3)
    torch.testing.assert_close(joints, joints0)
    torch.testing.assert_close(cam, cam0)
    assert torch.all(joints[:, 0] == 0) and torch.all(cam[:, 0] > 0)  # wrist at 0, in front


def test_detections_shapes_and_determinism(weights: Path, clip) -> None:
    params = RegressorParams(str(weights), boxes="given")
    det = regressor_detections(clip, params)
    det.check(clip.num_frames)
    assert det.joints.shape == (5, 2, 21, 3) and det.present.shape == (5, 2)
    assert det.present.any() and not (det.present & ~clip.hand_valid).any()
    assert np.isfinite(det.joints[det.present]).all()
    np.testing.assert_array_equal(det.side, np.tile([0, 1], (5, 1)))
    again = regressor_detections(clip, params)
    np.testing.assert_array_equal(det.joints, again.joints)
    np.testing.assert_array_equal(det.present, again.present)
    # In the camera every joint is in front of it.
    for f, s in zip(*np.nonzero(det.present), strict=True):
        points_cam = transform_points(invert_se3(clip.world_from_cam[f]), det.joints[f, s])
        assert (points_cam[:, 2] > 0).all()


def test_pickles_are_refused(tmp_path: Path) -> None:
    folder = tmp_path / "pickled"
    save_regressor(HandRegressor(TINY), folder)
    torch.save(HandRegressor(TINY).state_dict(), folder / WEIGHTS_FILE)  # zip-of-pickle
    with pytest.raises(UnsafeCheckpointError, match="pickle"):
        load_regressor(folder)
    (folder / WEIGHTS_FILE).rename(folder / "pytorch_model.bin")
    with pytest.raises(RegressorWeightsError, match=r"pytorch_model\.bin.*pickles"):
        load_regressor(folder)


def test_missing_or_wrong_weights_are_config_errors(tmp_path: Path, weights: Path) -> None:
    missing = tmp_path / "nowhere"
    with pytest.raises(ConfigError, match="regressor_weights must be an existing folder"):
        HandsConfig(backend="regressor", regressor_weights=str(missing))
    with pytest.raises(ConfigError, match="needs regressor_weights"):
        HandsConfig(backend="regressor")
    with pytest.raises(ConfigError, match="regressor_device"):
        HandsConfig(regressor_device="gpu")
    with pytest.raises(ConfigError, match="is not a folder"):
        load_regressor(missing)
    other = tmp_path / "other"
    other.mkdir()
    (other / WEIGHTS_FILE).write_bytes((weights / WEIGHTS_FILE).read_bytes())
    with pytest.raises(ConfigError, match=CONFIG_FILE):
        load_regressor(other)
    (other / CONFIG_FILE).write_text('{"architecture": "hamer"}')
    with pytest.raises(ConfigError, match="need converting"):
        load_regressor(other)
    wider = tmp_path / "wider"
    save_regressor(HandRegressor(TINY), wider)
    config = (wider / CONFIG_FILE).read_text().replace('"hidden_size": 32', '"hidden_size": 64')
    (wider / CONFIG_FILE).write_text(config)
    with pytest.raises(ConfigError, match="does not match config"):
        load_regressor(wider)


def test_stage_end_to_end(tmp_path: Path, weights: Path, clip) -> None:
    clips = tmp_path / "clips.parquet"
    write_clips(clips, [clip])
    out = tmp_path / "hands.parquet"
    result = run_shard_task(
        ShardTask(
            step="hands",
            stage="hands",
            params={
                "backend": "regressor",
                "regressor_weights": str(weights),
                "regressor_boxes": "given",
                "despike": False,  # an untrained network's hands jump about
            },
            shard_index=0,
            shard_count=1,
            output=out,
            rejects=tmp_path / "hands.rejects.parquet",
            inputs={"clips": clips},
        )
    )
    assert result.rows == 1 and result.rejected == 0
    with open_shard(out, HANDS) as reader:
        row = next(reader.iter_rows())
    assert row["backend"] == "regressor"
    valid = np.asarray(row["hand_valid"])  # (T, 2)
    joints = np.asarray(row["hand_joints"], dtype=np.float64).reshape(5, 2, 21, 3)
    assert valid.any() and np.isfinite(joints[valid]).all() and np.isnan(joints[~valid]).all()
    with open_shard(clips) as reader:
        stored = clip_from_row(next(reader.iter_rows()))  # frames as the stage decodes them
    direct = regressor_detections(stored, RegressorParams(str(weights), boxes="given"))
    np.testing.assert_allclose(joints[valid], direct.joints[valid], atol=1e-5)  # float32 row


def test_a_left_hand_is_the_mirror_image_of_a_right_hand(weights: Path, clip) -> None:
    # Mirror the clip in the camera: frames flipped left-right, cx -> W - cx, hands swap sides
    # and x -> -x. The network sees the same right-hand crops in both, so each hand's joints
    # must come out mirrored (up to the resampling of the flipped crops).
    from dataclasses import replace

    t, w = clip.num_frames, clip.width
    cam_joints = np.stack(
        [
            transform_points(invert_se3(clip.world_from_cam[f]), clip.hand_joints[f])
            for f in range(t)
        ]
    )  # (T, 2, 21, 3)
    eye = np.tile(np.eye(4), (t, 1, 1))  # (T, 4, 4) the camera is the world
    fx, fy, cx, cy = clip.intrinsics
    flip = np.array([-1.0, 1.0, 1.0])
    straight = replace(clip, world_from_cam=eye, hand_joints=cam_joints)
    mirrored = replace(
        clip,
        frames=np.ascontiguousarray(clip.frames[:, :, ::-1]),
        intrinsics=np.array([fx, fy, w - cx, cy]),
        world_from_cam=eye,
        hand_joints=cam_joints[:, ::-1] * flip,
        hand_valid=clip.hand_valid[:, ::-1],
        hand_confidence=None if clip.hand_confidence is None else clip.hand_confidence[:, ::-1],
    )
    params = RegressorParams(str(weights), boxes="given")
    a = regressor_detections(straight, params)
    b = regressor_detections(mirrored, params)
    np.testing.assert_array_equal(a.present, b.present[:, ::-1])
    assert a.present.all()
    np.testing.assert_allclose(a.joints, b.joints[:, ::-1] * flip, atol=1e-4)


def test_default_boxes_come_from_mediapipe(weights: Path, clip) -> None:
    pytest.importorskip("mediapipe")
    det = regressor_detections(clip, RegressorParams(str(weights)))  # boxes="mediapipe"
    det.check(clip.num_frames)
    assert det.present.any()  # MediaPipe finds the left hand of this clip in every frame
    assert np.isfinite(det.joints[det.present]).all()


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_cuda_matches_cpu(weights: Path, clip) -> None:
    cpu = regressor_detections(clip, RegressorParams(str(weights), boxes="given"))
    gpu = regressor_detections(clip, RegressorParams(str(weights), "cuda", boxes="given"))
    np.testing.assert_array_equal(cpu.present, gpu.present)
    np.testing.assert_allclose(gpu.joints, cpu.joints, atol=1e-3)
