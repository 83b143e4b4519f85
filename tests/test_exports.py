"""``egosim export``: each format read back the way its tool's loader reads it.

A hand-built ``pack`` shard (known frames, masks, first frame, prompt) in a run folder is
exported; the outputs are parsed as the tools do (VideoX-Fun: ``json.load`` and paths joined to
``data_root``; EgoSim: ``csv.DictReader`` and the mask next to the ego prior; DWM: the dataset
file's relative paths and ``<sequence>/<subdir>/<stem>``), every MP4 is decoded with PyAV and
checked for frame count, size, rate and pixel values against the pack within the codec's
tolerance; masks are recovered exactly by thresholding at 128.
"""

from __future__ import annotations

import csv
import json
from fractions import Fraction
from pathlib import Path

import av
import numpy as np
import pytest
from typer.testing import CliRunner

from egosim.pipeline import media
from egosim.pipeline.cli import EXIT_USER_ERROR, app
from egosim.pipeline.export.dwm import DwmConfig, export_dwm, frame_indices
from egosim.pipeline.export.egosim_csv import COLUMNS, export_egosim_csv
from egosim.pipeline.export.run_index import ExportError
from egosim.pipeline.export.videox_fun import VideoXFunConfig, export_videox_fun
from egosim.pipeline.shards import ShardWriter
from egosim.pipeline.stage import ConfigError
from egosim.schemas.captions import CAPTIONS
from egosim.schemas.pack import PACK
from tests.conftest import smooth_frames

T, H, W, FPS = 9, 24, 40, 4.0  # the packed samples: 9 frames of 24x40 at 4 fps
MIN_PSNR_DB = 35.0  # H.264 CRF 18 of the smooth test pattern: measured 41-45 dB
LEVEL_TOL = 4.0  # mean colour of a flat frame after H.264 and resizing, 0-255 levels


def _blocks(rng: np.random.Generator, t: int) -> np.ndarray:
    """A ``(t, H, W)`` {0, 1} mask of 8x8 blocks (codec-friendly edges)."""
    coarse = rng.random((t, H // 8, W // 8)) > 0.5
    return np.repeat(np.repeat(coarse, 8, axis=1), 8, axis=2).astype(np.uint8)


def _flat_frames(offset: int) -> np.ndarray:
    """``(T, H, W, 3)``: frame i is one flat colour, so a frame's index shows in its mean."""
    levels = np.array([[30 + 22 * i + offset, 200 - 15 * i, 90 + offset] for i in range(T)])
    return np.broadcast_to(levels[:, None, None, :], (T, H, W, 3)).astype(np.uint8).copy()


def _sample(clip_id: str, seed: int) -> dict:
    rng = np.random.default_rng(seed)
    return {
        "clip_id": clip_id,
        "target": smooth_frames(T, H, W, seed),
        "scene": smooth_frames(T, H, W, seed + 10),
        "skeleton": smooth_frames(T, H, W, seed + 20),
        "visible": _blocks(rng, T),
        "hand_mask": _blocks(rng, T),
        "first_frame": smooth_frames(1, H, W, seed + 30)[0],
        "prompt": f"the right hand moves the box, clip {clip_id}",
    }


def _pack_row(s: dict) -> dict:
    return {
        "clip_id": s["clip_id"],
        "num_frames": T,
        "width": W,
        "height": H,
        "fps": FPS,
        "frame_indices": list(range(T)),
        "intrinsics": [30.0, 30.0, W / 2, H / 2],
        "world_from_cam": None,
        "target_video": media.encode_rgb_video(s["target"], FPS),
        "scene_video": media.encode_rgb_video(s["scene"], FPS),
        "visible": media.encode_mask_video(s["visible"]),
        "skeleton_video": media.encode_rgb_video(s["skeleton"], FPS),
        "first_frame": media.encode_png(s["first_frame"]),
        "first_frame_source": "inpaint",
        "hand_mask": media.encode_mask_video(s["hand_mask"]),
        "depth0": None,
        "depth_unit_m": None,
        "prompt": s["prompt"],
        "visible_fraction": 0.5,
        "registered_fraction": 1.0,
        "hand_valid_fraction": 1.0,
    }


@pytest.fixture(scope="module")
def packed(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict[str, dict]]:
    """A run folder whose ``pack`` step holds two samples; returns it and the samples."""
    run = tmp_path_factory.mktemp("exports") / "run"
    samples = {s["clip_id"]: s for s in (_sample("clip-a", 0), _sample("clip-b", 1))}
    samples["clip-b"]["target"] = _flat_frames(0)  # frame index readable after resampling
    samples["clip-b"]["scene"] = _flat_frames(10)
    with ShardWriter(run / "pack" / "shard-00000.parquet", PACK, stage="test") as writer:
        for s in samples.values():
            writer.write_row(_pack_row(s))
    return run, samples


@pytest.fixture(scope="module")
def one_clip(packed, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A run folder whose pack step holds clip-b only (for the full-size DWM export)."""
    run = tmp_path_factory.mktemp("exports") / "run1"
    with ShardWriter(run / "pack" / "shard-00000.parquet", PACK, stage="test") as writer:
        writer.write_row(_pack_row(packed[1]["clip-b"]))
    return run


def _decode(path: Path) -> tuple[np.ndarray, Fraction]:
    """Every frame of an MP4 as RGB ``(T, H, W, 3)``, and the stream's average rate."""
    with av.open(str(path)) as container:
        stream = container.streams.video[0]
        frames = np.stack([f.to_ndarray(format="rgb24") for f in container.decode(stream)])
        return frames, stream.average_rate


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
    return float("inf") if mse == 0 else 10 * np.log10(255.0**2 / mse)


def _check_video(path: Path, want: np.ndarray, fps: float) -> None:
    frames, rate = _decode(path)
    assert frames.shape == want.shape, path
    assert float(rate) == pytest.approx(fps), path
    assert _psnr(frames, want) >= MIN_PSNR_DB, path


def _check_mask(path: Path, want: np.ndarray, fps: float) -> None:
    frames, rate = _decode(path)
    assert frames.shape == (*want.shape, 3) and float(rate) == pytest.approx(fps), path
    np.testing.assert_array_equal(frames.mean(axis=-1) >= 128, want > 0, err_msg=str(path))


def test_videox_fun_metadata_and_videos_read_back(packed, tmp_path: Path) -> None:
    run, samples = packed
    result = export_videox_fun(run, tmp_path / "vx")
    assert result.written == ["clip-a", "clip-b"] and not result.skipped
    data_root = tmp_path / "vx"
    with open(data_root / "metadata.json") as f:  # as ImageVideoControlDataset does
        entries = json.load(f)
    assert [e["clip_id"] for e in entries] == ["clip-a", "clip-b"]
    for entry in entries:
        s = samples[entry["clip_id"]]
        assert entry["type"] == "video" and entry["text"] == s["prompt"]
        assert (entry["num_frames"], entry["height"], entry["width"], entry["fps"]) == (
            T,
            H,
            W,
            FPS,
        )
        _check_video(data_root / entry["file_path"], s["target"], FPS)
        _check_video(data_root / entry["control_file_path"], s["scene"], FPS)
        _check_video(data_root / entry["skeleton_file_path"], s["skeleton"], FPS)
        _check_mask(data_root / entry["mask_file_path"], 1 - s["visible"], FPS)  # 1 = inpaint
        _check_mask(data_root / entry["hand_mask_file_path"], s["hand_mask"], FPS)
        first = media.decode_png((data_root / entry["first_frame_file_path"]).read_bytes())
        np.testing.assert_array_equal(first, s["first_frame"])
    again = export_videox_fun(run, tmp_path / "abs", VideoXFunConfig(absolute_paths=True))
    with open(again.index) as f:
        entry = json.load(f)[0]
    assert Path(entry["file_path"]).is_absolute() and Path(entry["file_path"]).is_file()


def test_egosim_csv_columns_and_clip_folders_read_back(packed, tmp_path: Path) -> None:
    run, samples = packed
    result = export_egosim_csv(run, tmp_path / "es")
    root = tmp_path / "es"
    with open(root / "metadata.csv", newline="", encoding="utf-8") as f:
        reader = csv.DictReader(f)
        assert tuple(reader.fieldnames) == COLUMNS
        rows = list(reader)
    assert [r["video_id"] for r in rows] == result.written == ["clip-a", "clip-b"]
    for row in rows:
        s = samples[row["video_id"]]
        assert row["prompt"] == s["prompt"]
        _check_video(root / row["video"], s["target"], FPS)
        ego_prior = root / row["ego_prior_video"]
        _check_video(ego_prior, s["scene"], FPS)
        _check_mask(ego_prior.parent / "pc_mask_video.mp4", s["visible"], FPS)  # EgoSim's lookup
        _check_video(root / row["hand_keypoint_video"], s["skeleton"], FPS)
        first = media.decode_png((root / row["first_frame"]).read_bytes())
        np.testing.assert_array_equal(first, s["first_frame"])
        assert (ego_prior.parent / "caption.txt").read_text().strip() == s["prompt"]


def test_dwm_frame_times_follow_the_sample_and_hold_rule() -> None:
    assert frame_indices(61, 16.0, 8.0) == list(range(0, 61, 2))[:30]  # 61 frames = 3.81 s
    assert frame_indices(9, 4.0, 8.0) == [0, 0, 1, 1, 2, 2, 3, 3, 4, 4, 5, 5, 6, 6, 7, 7, 8, 8]
    assert frame_indices(49, 8.0, 8.0) == list(range(49))
    assert DwmConfig().fps == 8.0 and DwmConfig().num_frames == 49
    assert (DwmConfig().height, DwmConfig().width) == (480, 720)


def _dwm_sample(root: Path, line: str) -> dict[str, Path]:
    """DWM's resolve_sample_paths: ``<sequence>/videos/<stem>.mp4`` -> its siblings."""
    video = root / line
    sequence, stem = video.parent.parent, video.stem
    return {
        "video": video,
        "static": sequence / "videos_static" / f"{stem}.mp4",
        "hands": sequence / "videos_hands" / f"{stem}.mp4",
        "prompt": sequence / "prompts_rewrite" / f"{stem}.txt",
        "metadata": sequence / "metadata" / f"{stem}.json",
    }


def test_dwm_layout_rate_length_and_size_as_dwm_reads_it(packed, tmp_path: Path) -> None:
    run, samples = packed
    result = export_dwm(run, tmp_path / "dwm")  # DWM's defaults: 49 frames, 8 fps, 720x480
    root = tmp_path / "dwm"
    lines = (root / "dataset_files" / "egosim.txt").read_text().splitlines()
    assert (
        lines
        == ["egosim/videos/clip-a.mp4", "egosim/videos/clip-b.mp4"]
        == [f"egosim/videos/{c}.mp4" for c in result.written]
    )
    paths = _dwm_sample(root, lines[1])
    for key in ("video", "static", "hands"):
        frames, rate = _decode(paths[key])
        assert frames.shape == (49, 480, 720, 3) and float(rate) == pytest.approx(8.0), key
    assert paths["prompt"].read_text().strip() == samples["clip-b"]["prompt"]
    meta = json.loads(paths["metadata"].read_text())
    # 9 frames at 4 fps = 2.25 s = 18 frames at 8 fps; 31 more repeat the last (DWM's clone).
    assert meta["source_indices"] == [i // 2 for i in range(18)] + [8] * 31
    assert meta["padded_frames"] == 31 and meta["resize"] == "pad"
    # Pad: 40x24 scaled by 18 to 720x432, centred with 24 black rows above and below.
    assert meta["box"] == [0, 24, 720, 432] and meta["scale"] == pytest.approx(18.0)
    frames, _ = _decode(paths["video"])
    want = _flat_frames(0)[meta["source_indices"], 0, 0].astype(np.float64)  # (49, 3)
    content = frames[:, 28:452].reshape(49, -1, 3).mean(axis=1)  # inside the box, off its edge
    np.testing.assert_allclose(content, want, atol=LEVEL_TOL)
    bars = np.concatenate([frames[:, :20], frames[:, 460:]], axis=1)
    assert bars.max() <= LEVEL_TOL  # black


def test_dwm_crop_and_reject_options(packed, tmp_path: Path) -> None:
    run, _ = packed
    config = DwmConfig(num_frames=13, height=48, width=48, resize="crop", group="g")
    result = export_dwm(run, tmp_path / "crop", config)
    paths = _dwm_sample(tmp_path / "crop", "g/videos/clip-b.mp4")
    frames, rate = _decode(paths["static"])
    assert frames.shape == (13, 48, 48, 3) and float(rate) == pytest.approx(8.0)
    meta = json.loads(paths["metadata"].read_text())
    assert meta["box"] == [16, 0, 48, 48] and meta["padded_frames"] == 0  # 80x48, centre crop
    want = _flat_frames(10)[meta["source_indices"], 0, 0].astype(np.float64)
    np.testing.assert_allclose(frames.reshape(13, -1, 3).mean(axis=1), want, atol=LEVEL_TOL)
    assert result.written == ["clip-a", "clip-b"]
    strict = export_dwm(run, tmp_path / "strict", DwmConfig(num_frames=19, short="reject"))
    assert strict.written == [] and set(strict.skipped) == {"clip-a", "clip-b"}
    assert "18 frames at 8 fps, fewer than num_frames 19" in strict.skipped["clip-a"]
    assert (tmp_path / "strict" / "dataset_files" / "egosim.txt").read_text() == ""


def test_bad_options_inputs_and_existing_outputs_are_refused(packed, tmp_path: Path) -> None:
    run, _ = packed
    with pytest.raises(ConfigError, match=r"resize must be 'pad' or 'crop', got 'fit'"):
        DwmConfig(resize="fit")
    with pytest.raises(ConfigError, match="group"):
        DwmConfig(group="../up")
    with pytest.raises(ConfigError, match=r"crf must be in 0\.\.51, got 60"):
        VideoXFunConfig(crf=60)
    other = tmp_path / "other"  # a run without a pack step
    with ShardWriter(other / "captions" / "shard-00000.parquet", CAPTIONS, stage="test") as w:
        w.write_row({"clip_id": "clip-a", "text": "a prompt", "origin": "template"})
    with pytest.raises(ExportError, match=r"other: no step wrote pack shards \(steps: "):
        export_videox_fun(other, tmp_path / "none")
    with pytest.raises(ExportError, match="no step folders with shard"):
        export_videox_fun(run.parent, tmp_path / "none")  # a folder holding a run, not a run
    export_egosim_csv(run, tmp_path / "twice")
    with pytest.raises(ExportError, match="already holds an export"):
        export_egosim_csv(run, tmp_path / "twice")


def test_cli_export_commands(packed, tmp_path: Path) -> None:
    run, _ = packed
    runner = CliRunner()
    for kind, index in (
        ("videox-fun", "metadata.json"),
        ("egosim-csv", "metadata.csv"),
        ("dwm", "dataset_files/egosim.txt"),
    ):
        out = tmp_path / kind
        args = ["export", kind, str(run), "--out", str(out)]
        if kind == "dwm":
            args += ["--set", "num_frames=5", "--set", "height=32", "--set", "width=48"]
        result = runner.invoke(app, args)
        assert result.exit_code == 0, result.output
        assert (out / index).is_file() and "2 clip(s)" in result.output
    bad = runner.invoke(
        app, ["export", "dwm", str(run), "--out", str(tmp_path / "x"), "--set", "fps=0"]
    )
    assert bad.exit_code == EXIT_USER_ERROR and "fps must be > 0, got 0.0" in bad.output
