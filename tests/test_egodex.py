"""EgoDex episodes: write a hand-built clip, read it back, and reject broken files."""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np
import pytest

from egosim.pipeline.egodex_format import EGODEX_HAND_JOINTS
from egosim.pipeline.geometry import look_at, project_world_points
from egosim.pipeline.media import write_video_file
from egosim.pipeline.records import Clip
from egosim.pipeline.stage import ClipRejected
from egosim.stages.ingest.egodex import read_egodex_clip
from egosim.world.egodex_export import write_egodex

T, H, W = 6, 48, 64
MIN_PSNR_DB = 35.0  # H.264 at CRF 18 on smooth frames


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2)
    return float(10 * np.log10(255.0**2 / max(mse, 1e-12)))


def make_clip() -> Clip:
    """Six frames, a camera orbiting a table point, two hands in front; right hand lost once."""
    rng = np.random.default_rng(0)
    target = np.array([0.0, 0.0, 0.8])
    poses = np.stack([look_at([0.03 * i, -0.45, 1.25], target) for i in range(T)])  # (T, 4, 4)
    rest = rng.uniform(-0.06, 0.06, size=(2, 21, 3))  # (2, 21, 3) joints about each hand centre
    centres = np.array([[-0.1, 0.0, 0.8], [0.1, 0.0, 0.8]])  # (2, 3) left, right
    drift = 0.01 * np.arange(T)[:, None, None, None] * np.array([1.0, 0.5, 0.0])  # (T, 1, 1, 3)
    joints = (centres[None, :, None] + rest[None] + drift).astype(np.float32)  # (T, 2, 21, 3)
    valid = np.ones((T, 2), bool)
    valid[2, 1] = False
    joints[2, 1] = np.nan  # what an upstream tracker leaves for a lost hand
    v, u = np.mgrid[0:H, 0:W] / np.array([H, W])[:, None, None]
    frames = np.stack(
        [np.stack([u + 0.05 * i, v, 0.5 + 0.3 * np.sin(3 * u + i)], axis=-1) for i in range(T)]
    )  # (T, H, W, 3)
    return Clip(
        clip_id="synthetic_0",
        source="synthetic",
        source_uri="",
        fps=16.0,
        timestamps=np.arange(T) / 16.0,
        intrinsics=np.array([60.0, 60.0, 32.0, 24.0]),
        frames=(np.clip(frames, 0, 1) * 255).astype(np.uint8),
        world_from_cam=poses,
        hand_joints=joints,
        hand_valid=valid,
        hand_confidence=rng.uniform(0.2, 1.0, size=(T, 2, 21)).astype(np.float32),
        text="Pick up the red cup and put it on the plate.",
    )


@pytest.fixture
def episode(tmp_path: Path) -> tuple[Clip, Path, Path]:
    clip = make_clip()
    hdf5_path, mp4_path = write_egodex(clip, tmp_path / "pick_place", stem="0")
    return clip, hdf5_path, mp4_path


def test_mapping_table_is_42_joints_without_metacarpals() -> None:
    assert len(EGODEX_HAND_JOINTS) == 42
    assert EGODEX_HAND_JOINTS["leftHand"] == (0, 0)
    assert EGODEX_HAND_JOINTS["leftThumbKnuckle"] == (0, 1)
    assert EGODEX_HAND_JOINTS["rightIndexFingerKnuckle"] == (1, 5)
    assert EGODEX_HAND_JOINTS["rightLittleFingerTip"] == (1, 20)
    assert not any("Metacarpal" in name for name in EGODEX_HAND_JOINTS)
    assert sorted(EGODEX_HAND_JOINTS.values()) == [(h, j) for h in range(2) for j in range(21)]


def test_written_file_has_egodex_layout(episode: tuple[Clip, Path, Path]) -> None:
    clip, hdf5_path, mp4_path = episode
    assert hdf5_path.name == "0.hdf5" and mp4_path.name == "0.mp4"
    with h5py.File(hdf5_path, "r") as f:
        assert f["camera/intrinsic"].shape == (3, 3)
        assert len(f["transforms"]) == 1 + 2 * 25  # camera + 25 joints per hand
        assert len(f["confidences"]) == 2 * 25
        assert f["transforms/leftIndexFingerMetacarpal"].shape == (T, 4, 4)
        assert f["confidences/rightHand"].shape == (T,)
        assert f.attrs["llm_description"] == clip.text
        assert f.attrs["task"] == "pick_place"
        # A lost hand keeps finite transforms (as in EgoDex) with zero confidence.
        assert np.isfinite(f["transforms/rightThumbTip"][2]).all()
        assert f["confidences/rightHand"][2] == 0.0
        # EgoDex's own recipe, inv(camera) @ joint through K, lands where our projection does.
        k = f["camera/intrinsic"][()].astype(np.float64)
        p_cam = np.linalg.inv(f["transforms/camera"][0]) @ f["transforms/leftIndexFingerTip"][0]
        uvw = k @ p_cam[:3, 3]
    uv, depth = project_world_points(
        clip.hand_joints[0, 0, 8], clip.world_from_cam[0], clip.intrinsics
    )
    assert depth > 0
    np.testing.assert_allclose(uvw[:2] / uvw[2], uv, atol=1e-3)


def test_round_trip(episode: tuple[Clip, Path, Path]) -> None:
    clip, hdf5_path, _ = episode
    got = read_egodex_clip(hdf5_path)
    got.check()
    assert got.clip_id == "pick_place_0"
    assert got.source == "egodex" and got.source_uri == str(hdf5_path)
    assert got.fps == clip.fps
    np.testing.assert_allclose(got.timestamps, clip.timestamps)
    np.testing.assert_array_equal(got.intrinsics, clip.intrinsics)
    np.testing.assert_allclose(got.world_from_cam, clip.world_from_cam, atol=1e-6)
    np.testing.assert_array_equal(got.hand_valid, clip.hand_valid)
    valid = clip.hand_valid
    np.testing.assert_allclose(got.hand_joints[valid], clip.hand_joints[valid], atol=1e-5)
    np.testing.assert_allclose(got.hand_confidence[valid], clip.hand_confidence[valid], atol=1e-7)
    assert (got.hand_confidence[~valid] == 0).all()
    assert got.text == clip.text
    assert got.frames.shape == clip.frames.shape
    psnr = [_psnr(a, b) for a, b in zip(got.frames, clip.frames, strict=True)]
    assert min(psnr) >= MIN_PSNR_DB, psnr


def test_missing_dataset_names_key_and_file(episode: tuple[Clip, Path, Path]) -> None:
    _, hdf5_path, _ = episode
    with h5py.File(hdf5_path, "a") as f:
        del f["transforms/leftThumbTip"]
    with pytest.raises(ClipRejected, match="transforms/leftThumbTip") as err:
        read_egodex_clip(hdf5_path)
    assert str(hdf5_path) in str(err.value)


def test_nan_camera_is_rejected(episode: tuple[Clip, Path, Path]) -> None:
    _, hdf5_path, _ = episode
    with h5py.File(hdf5_path, "a") as f:
        camera = f["transforms/camera"][()]
        camera[3, 0, 3] = np.nan
        f["transforms/camera"][...] = camera
    with pytest.raises(ClipRejected, match=r"transforms/camera.*not finite.*\[3\]"):
        read_egodex_clip(hdf5_path)


def test_frame_count_mismatch_gives_both_counts(episode: tuple[Clip, Path, Path]) -> None:
    clip, hdf5_path, mp4_path = episode
    write_video_file(mp4_path, clip.frames[:4], clip.fps)
    with pytest.raises(ClipRejected, match=r"hdf5 has 6 frames, 0\.mp4 has 4"):
        read_egodex_clip(hdf5_path)


def test_flipped_camera_convention_is_rejected(episode: tuple[Clip, Path, Path]) -> None:
    _, hdf5_path, _ = episode
    with h5py.File(hdf5_path, "a") as f:
        # ARKit-style camera axes (y up, z backward): the camera turned 180 degrees about x.
        f["transforms/camera"][...] = f["transforms/camera"][()] @ np.diag([1, -1, -1, 1])
    with pytest.raises(ClipRejected, match="convention"):
        read_egodex_clip(hdf5_path)


def test_missing_mp4_and_unreadable_hdf5(episode: tuple[Clip, Path, Path], tmp_path: Path) -> None:
    _, hdf5_path, mp4_path = episode
    mp4_path.unlink()
    with pytest.raises(ClipRejected, match=r"0\.mp4 is missing"):
        read_egodex_clip(hdf5_path)
    junk = tmp_path / "junk.hdf5"
    junk.write_bytes(b"not an hdf5 file")
    junk.with_suffix(".mp4").write_bytes(b"")
    with pytest.raises(ClipRejected, match="cannot read EgoDex hdf5 file"):
        read_egodex_clip(junk)
