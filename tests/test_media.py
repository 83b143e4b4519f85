"""Codec round trips: lossless paths exact, lossy RGB above a stated PSNR."""

from __future__ import annotations

import numpy as np
import pytest

from egosim.pipeline import media
from tests.conftest import smooth_frames

MIN_RGB_PSNR_DB = 35.0  # H.264 at CRF 18 on smooth content


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2)
    return float(10 * np.log10(255.0**2 / max(mse, 1e-12)))


@pytest.mark.parametrize("size", [(48, 64), (31, 45)])  # odd sizes are padded and cropped back
def test_rgb_video_round_trip_psnr(size: tuple[int, int]) -> None:
    frames = smooth_frames(12, *size)
    data = media.encode_rgb_video(frames, fps=16.0)
    out = media.decode_rgb_video(data, *size)
    assert out.shape == frames.shape
    assert psnr(out, frames) >= MIN_RGB_PSNR_DB
    assert len({media.encode_rgb_video(frames, fps=16.0) for _ in range(8)}) == 1  # reproducible


def test_lossless_masks_labels_and_depth_are_exact() -> None:
    rng = np.random.default_rng(0)
    mask = (rng.random((7, 33, 41)) > 0.5).astype(np.uint8)
    np.testing.assert_array_equal(media.decode_lossless_video(media.encode_mask_video(mask)), mask)
    raw16 = rng.integers(0, 65535, (4, 20, 30), dtype=np.uint16)
    np.testing.assert_array_equal(
        media.decode_lossless_video(media.encode_lossless_video(raw16)), raw16
    )
    depth = rng.uniform(0.2, 5.0, (4, 20, 30)).astype(np.float32)
    depth[0, 0, 0] = 0.0
    unit = media.depth_unit_for(depth)
    out = media.decode_depth_video(media.encode_depth_video(depth, unit), unit)
    assert np.abs(out - depth).max() <= unit / 2 + 1e-6
    assert out[0, 0, 0] == 0.0
    first = media.decode_depth_video(media.encode_depth_video(depth, unit), unit, max_frames=1)
    np.testing.assert_array_equal(first, out[:1])  # stops after the first frame


def test_png_round_trip_is_exact() -> None:
    rng = np.random.default_rng(1)
    rgb = rng.integers(0, 256, (17, 23, 3), dtype=np.uint8)
    np.testing.assert_array_equal(media.decode_png(media.encode_png(rgb)), rgb)
    grey16 = rng.integers(0, 65535, (9, 5), dtype=np.uint16)
    np.testing.assert_array_equal(media.decode_png(media.encode_png(grey16)), grey16)


def test_corrupt_bytes_raise_media_error() -> None:
    with pytest.raises(media.MediaError, match="cannot decode clip x video"):
        media.decode_rgb_video(b"not a video at all", what="clip x video")
    with pytest.raises(media.MediaError):
        media.decode_png(b"\x89PNG broken")


def test_truncated_video_file_names_the_file(tmp_path) -> None:
    path = tmp_path / "cut.mp4"
    data = media.encode_rgb_video(smooth_frames(20, 32, 32), fps=10.0)
    path.write_bytes(data[: len(data) // 3])
    with pytest.raises(media.MediaError, match=r"cut\.mp4"):
        media.read_video_file(path)


def test_video_file_timestamps_follow_the_source_rate(video_file) -> None:
    frames, stamps = media.read_video_file(video_file)
    assert frames.shape == (60, 96, 128, 3)
    np.testing.assert_allclose(stamps, np.arange(60) / 30.0, atol=1e-6)


def test_video_file_seek_gives_the_same_frames_as_decoding_from_the_start(video_file) -> None:
    frames, stamps = media.read_video_file(video_file)
    # 1.5 s into a 30 fps file: frame 45 on, identical pixels (the same decoder output)
    tail = list(media.iter_video_file(video_file, start=1.5))
    assert len(tail) == 15
    np.testing.assert_allclose([t for t, _ in tail], stamps[45:], atol=1e-6)
    np.testing.assert_array_equal(np.stack([f for _, f in tail]), frames[45:])


def _write_rotated(path, frames: np.ndarray, rotation: float) -> None:
    """``frames`` stored as they are, with a display rotation (degrees counterclockwise) on the
    stream, as phones write portrait video: a player turns them by ``rotation`` to show them."""
    import av

    with av.open(str(path), mode="w") as container:
        stream = container.add_stream("libx264", rate=10)
        stream.width, stream.height = frames.shape[2], frames.shape[1]
        stream.pix_fmt = "yuv420p"
        stream.options = {"crf": "10"}
        stream.set_display_rotation(rotation)
        for image in frames:
            container.mux(stream.encode(av.VideoFrame.from_ndarray(image, format="rgb24")))
        container.mux(stream.encode())


@pytest.mark.parametrize("rotation", [-90, 90, 180])
def test_display_rotation_is_honoured_as_ffmpeg_does(tmp_path, rotation: int) -> None:
    upright = smooth_frames(10, 48, 32)  # (T, 48, 32, 3): portrait, as the user saw it
    upright[:, :8, :8] = (255, 0, 0)  # a red corner at the top left shows the orientation
    turns = rotation // 90
    # Stored turned back by the rotation (np.rot90 is counterclockwise, like the angle)
    stored = np.ascontiguousarray(np.rot90(upright, k=-turns, axes=(1, 2)))
    path = tmp_path / f"phone{rotation}.mp4"
    _write_rotated(path, stored, float(rotation))
    info = media.probe_video_file(path)
    assert info.rotation == rotation
    assert (info.width, info.height) == (32, 48)  # the displayed (upright) size
    frames, _ = media.read_video_file(path)
    assert frames.shape == upright.shape
    assert psnr(frames, upright) >= MIN_RGB_PSNR_DB
    assert frames[:, 2:6, 2:6, 0].min() > 200 and frames[:, 2:6, 2:6, 1].max() < 60  # red corner


def test_avi_with_b_frames_gives_frames_at_their_own_times(tmp_path) -> None:
    """AVI stores decode-order stamps: with B-frames PyAV hands decoded frames shuffled times
    (0.05, 0.2, 0.15, 0.25, 0.1, ...). They must come out in order, one frame per 1 / fps."""
    import av

    frames = smooth_frames(40, 48, 64)
    frames[:, :, :4] = np.arange(40)[:, None, None, None] * 6  # a left band counting frames
    path = tmp_path / "b_frames.avi"
    with av.open(str(path), mode="w", format="avi") as container:
        stream = container.add_stream("libx264", rate=20)
        stream.width, stream.height, stream.pix_fmt = 64, 48, "yuv420p"
        stream.options = {"crf": "10", "bframes": "3"}
        for image in frames:
            container.mux(stream.encode(av.VideoFrame.from_ndarray(image, format="rgb24")))
        container.mux(stream.encode())
    with av.open(str(path)) as container:  # the trap: shuffled stamps straight from PyAV
        raw = [f.time for f in container.decode(video=0)]
    assert np.any(np.diff(raw) < 0)
    out, stamps = media.read_video_file(path)
    np.testing.assert_allclose(stamps, np.arange(40) / 20.0, atol=1e-6)
    np.testing.assert_allclose(out[:, 20, 1, 1], np.arange(40) * 6, atol=3)  # frames in order
    assert psnr(out, frames) >= MIN_RGB_PSNR_DB


def test_probe_gives_the_declared_start_and_duration(video_file) -> None:
    info = media.probe_video_file(video_file)  # 60 frames at 30 fps
    assert info.start_s == pytest.approx(0.0, abs=1e-6)
    assert info.duration_s == pytest.approx(2.0, abs=1.5 / 30)
