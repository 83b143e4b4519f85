"""Foxglove MCAP: export a clip, read it back (directly and through ``ingest``), and bad input."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.Quaternion_pb2 import Quaternion
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage
from foxglove_schemas_protobuf.Vector3_pb2 import Vector3
from mcap.reader import make_reader
from mcap_protobuf.writer import Writer

from egosim.pipeline.clip_io import clip_from_row
from egosim.pipeline.geometry import look_at
from egosim.pipeline.records import Clip
from egosim.pipeline.stage import ClipRejected
from egosim.stages.ingest.mcap_export import write_clip_mcap
from egosim.stages.ingest.mcap_source import CAM_FROM_OURS, read_mcap_clip
from egosim.stages.ingest.stage import IngestConfig, IngestStage
from tests.conftest import make_clip

# JPEG at quality 95 of the smooth test pattern measured 41-42 dB; H.264 in the shard adds loss.
MIN_JPEG_PSNR_DB = 38.0
MIN_SHARD_PSNR_DB = 33.0


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
    return float("inf") if mse == 0 else 10 * np.log10(255.0**2 / mse)


@pytest.fixture
def clip() -> Clip:
    """20 frames at 16 fps, 48x64, with poses, depth and hands."""
    return make_clip("rec", num_frames=20, height=48, width=64)


def test_round_trip_png_is_exact(clip: Clip, tmp_path: Path) -> None:
    path = write_clip_mcap(clip, tmp_path / "rec.mcap", image_format="png")
    got = read_mcap_clip(path)
    assert got.clip_id == "rec" and got.source == "mcap" and got.source_uri == str(path)
    np.testing.assert_array_equal(got.frames, clip.frames)
    np.testing.assert_allclose(got.intrinsics, clip.intrinsics, rtol=0, atol=1e-12)
    np.testing.assert_allclose(got.world_from_cam, clip.world_from_cam, atol=1e-6)
    np.testing.assert_allclose(got.timestamps, clip.timestamps, atol=1e-9)
    assert got.fps == pytest.approx(16.0)


def test_export_has_the_foxglove_topics(clip: Clip, tmp_path: Path) -> None:
    path = write_clip_mcap(clip, tmp_path / "rec.mcap")
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    schemas = {c.topic: summary.schemas[c.schema_id].name for c in summary.channels.values()}
    assert schemas == {
        "/camera/image": "foxglove.CompressedImage",
        "/camera/calibration": "foxglove.CameraCalibration",
        "/tf": "foxglove.FrameTransform",
        "/camera/trajectory": "foxglove.PosesInFrame",
        "/scene/image": "foxglove.CompressedImage",
        "/scene/points": "foxglove.PointCloud",
        "/hands/skeleton": "foxglove.SceneUpdate",
    }
    assert summary.statistics.message_count == 6 * 20 + 1


def test_round_trip_through_ingest(clip: Clip, tmp_path: Path) -> None:
    write_clip_mcap(clip, tmp_path / "rec.mcap", image_format="jpeg", jpeg_quality=95)
    direct = read_mcap_clip(tmp_path / "rec.mcap")
    psnr = [_psnr(a, b) for a, b in zip(direct.frames, clip.frames, strict=True)]
    assert min(psnr) >= MIN_JPEG_PSNR_DB, psnr

    cfg = IngestConfig(fps=16.0, num_frames=20, height=48, width=64)
    stage = IngestStage(cfg)
    (unit,) = stage.list_units(str(tmp_path))
    assert unit.startswith("mcap:")
    (row,) = list(stage.process_unit(unit))
    got = clip_from_row(row)
    assert got.clip_id == "rec-w000"
    np.testing.assert_allclose(got.world_from_cam, clip.world_from_cam, atol=1e-6)
    np.testing.assert_allclose(got.intrinsics, clip.intrinsics, atol=1e-9)
    np.testing.assert_allclose(got.timestamps, clip.timestamps, atol=1e-9)
    psnr = [_psnr(a, b) for a, b in zip(got.frames, clip.frames, strict=True)]
    assert min(psnr) >= MIN_SHARD_PSNR_DB, psnr


def _write_recording(
    path: Path,
    frames: np.ndarray,
    k: list[float],
    poses: list[np.ndarray] | None,
    distortion: list[float] | None = None,
    calibration: bool = True,
    parent: str = "world",
    child: str = "cam_optical",
) -> None:
    """A robot-style recording: RawImage bgr8, per-frame calibration, a world->base->camera tf."""
    with open(path, "wb") as f, Writer(f) as writer:
        for i, image in enumerate(frames):
            ns = 1_700_000_000_000_000_000 + i * 50_000_000  # 20 Hz, epoch times
            if calibration:
                calib = CameraCalibration(
                    frame_id=child,
                    width=image.shape[1],
                    height=image.shape[0],
                    distortion_model="plumb_bob",
                    D=distortion or [0.0] * 5,
                    K=k,
                )
                writer.write_message("/cam/info", calib, log_time=ns, publish_time=ns)
            if poses is not None:
                # Static base in world (1 m up), moving camera in base.
                for par, chi, mat in ((parent, "base", np.eye(4)), ("base", child, poses[i])):
                    if par == parent:
                        mat = mat.copy()
                        mat[2, 3] = 1.0
                    w, x, y, z = _quat(mat[:3, :3])
                    tf = FrameTransform(
                        parent_frame_id=par,
                        child_frame_id=chi,
                        translation=Vector3(x=mat[0, 3], y=mat[1, 3], z=mat[2, 3]),
                        rotation=Quaternion(w=w, x=x, y=y, z=z),
                    )
                    tf.timestamp.FromNanoseconds(ns)
                    writer.write_message("/tf", tf, log_time=ns, publish_time=ns)
            raw = RawImage(
                frame_id=child,
                width=image.shape[1],
                height=image.shape[0],
                encoding="bgr8",
                step=image.shape[1] * 3,
                data=np.ascontiguousarray(image[..., ::-1]).tobytes(),
            )
            raw.timestamp.FromNanoseconds(ns)
            writer.write_message("/cam/raw", raw, log_time=ns, publish_time=ns)


def _quat(rot: np.ndarray) -> np.ndarray:
    from egosim.pipeline.geometry import quat_from_matrix

    return quat_from_matrix(rot)


def test_raw_images_transform_chain_and_axes(clip: Clip, tmp_path: Path) -> None:
    frames = clip.frames[:6]
    poses = [look_at([0.1 * i, -0.5, 0.6], [0, 0, 0]) for i in range(6)]
    fx, fy, cx, cy = clip.intrinsics
    k = [fx, 0, cx, 0, fy, cy, 0, 0, 1]
    path = tmp_path / "robot.mcap"
    _write_recording(path, frames, k, poses)
    got = read_mcap_clip(path, require_pose=True)
    np.testing.assert_array_equal(got.frames, frames)
    expected = np.stack(poses)
    expected[:, 2, 3] += 1.0  # through the static base frame
    np.testing.assert_allclose(got.world_from_cam, expected, atol=1e-9)
    np.testing.assert_allclose(got.timestamps, np.arange(6) * 0.05, atol=1e-9)
    assert got.fps == pytest.approx(20.0)
    # The same transforms declared in OpenGL camera axes come out flipped into OpenCV's.
    gl = read_mcap_clip(path, camera_axes="opengl")
    np.testing.assert_allclose(gl.world_from_cam, expected @ CAM_FROM_OURS["opengl"], atol=1e-9)
    # No chain to a frame that is not there: no poses, or rejected when poses are required.
    assert read_mcap_clip(path, camera_frame="elsewhere").world_from_cam is None
    with pytest.raises(ClipRejected, match="no FrameTransform chain from 'world' to 'elsewhere'"):
        read_mcap_clip(path, camera_frame="elsewhere", require_pose=True)


def test_distorted_frames_are_undistorted(clip: Clip, tmp_path: Path) -> None:
    v, u = np.mgrid[0:96, 0:128].astype(np.float64)
    pattern = 127 + 100 * np.sin(u / 3.0) * np.cos(v / 3.0)  # (96, 128)
    grid = np.repeat(pattern[..., None], 3, axis=2).astype(np.uint8)
    k = [80.0, 0, 64.0, 0, 80.0, 48.0, 0, 0, 1]
    d = [-0.3, 0.08, 0.0, 0.0, 0.0]
    kmat = np.array(k).reshape(3, 3)
    # Distort the grid: for each distorted pixel, sample the ideal image where it comes from.
    h, w = grid.shape[:2]
    pix = np.stack(np.meshgrid(np.arange(w), np.arange(h)), -1).reshape(-1, 1, 2).astype(np.float64)
    src = cv2.undistortPoints(pix, kmat, np.array(d), P=kmat).reshape(h, w, 2).astype(np.float32)
    distorted = cv2.remap(grid, src[..., 0], src[..., 1], cv2.INTER_LINEAR)
    path = tmp_path / "distorted.mcap"
    _write_recording(path, np.stack([distorted] * 3), k, None, distortion=d)
    got = read_mcap_clip(path)
    assert got.world_from_cam is None
    centre = (slice(12, 84), slice(16, 112))  # where both images are defined
    err_before = np.abs(distorted[centre].astype(float) - grid[centre]).mean()
    err_after = np.abs(got.frames[0][centre].astype(float) - grid[centre]).mean()
    assert err_after < 0.5 * err_before, (err_before, err_after)


def test_missing_calibration_is_rejected(clip: Clip, tmp_path: Path) -> None:
    path = tmp_path / "nocalib.mcap"
    _write_recording(path, clip.frames[:3], [1, 0, 0, 0, 1, 0, 0, 0, 1], None, calibration=False)
    with pytest.raises(ClipRejected, match=r"nocalib\.mcap: no foxglove\.CameraCalibration"):
        read_mcap_clip(path)


def test_corrupt_and_imageless_files_are_rejected(clip: Clip, tmp_path: Path) -> None:
    good = write_clip_mcap(clip, tmp_path / "good.mcap")
    data = good.read_bytes()
    broken = tmp_path / "broken.mcap"
    broken.write_bytes(data[: len(data) // 2])
    with pytest.raises(ClipRejected, match=r"broken\.mcap: corrupt or unreadable MCAP"):
        read_mcap_clip(broken)
    garbage = tmp_path / "garbage.mcap"
    garbage.write_bytes(b"not an mcap file at all" * 10)
    with pytest.raises(ClipRejected, match=r"garbage\.mcap: corrupt or unreadable MCAP"):
        read_mcap_clip(garbage)
    empty = tmp_path / "empty.mcap"
    with open(empty, "wb") as f, Writer(f):
        pass
    with pytest.raises(ClipRejected, match=r"empty\.mcap: no foxglove\.CompressedImage"):
        read_mcap_clip(empty)
    stage = IngestStage(IngestConfig(source="mcap", num_frames=4, height=48, width=64))
    unit = f"mcap:{broken}"
    assert unit in stage.list_units(str(tmp_path))
    with pytest.raises(ClipRejected, match=r"broken\.mcap"):
        list(stage.process_unit(unit))
