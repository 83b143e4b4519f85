"""Inputs in the shapes researchers have them (bench/real_variants.py), on tiny generated videos:
other containers and codecs, audio, greyscale, a phone's rotation and HEVC, variable frame
timing; and the bench's verdicts."""

from __future__ import annotations

from fractions import Fraction
from pathlib import Path

import av
import numpy as np
import pytest

from bench.real_variants import (
    TIMED_OUT,
    Spec,
    Variant,
    psnr_db,
    run_variant,
    summarise,
    verdict,
    write_variant,
)
from egosim.pipeline import media
from egosim.pipeline.stage import ClipRejected
from egosim.stages.ingest.stage import IngestConfig, IngestStage
from egosim.stages.ingest.video_source import read_video_clips
from tests.conftest import smooth_frames

TINY = IngestConfig(height=32, width=48, num_frames=9, min_frames=5, fps=10.0)
SAME_PSNR_DB = 30.0  # two lossy encodes of the same pictures, ingested (measured 37.5-40.5 dB)


@pytest.fixture()
def source(tmp_path: Path) -> Path:
    """A 2 s, 20 fps, 64x96 video of moving patterns with a red corner (orientation mark)."""
    frames = smooth_frames(40, 64, 96)
    frames[:, :8, :8] = (255, 0, 0)
    path = tmp_path / "src.mp4"
    media.write_video_file(path, frames, fps=20.0, crf=10)
    return path


def _ingest(path: Path, cfg: IngestConfig = TINY) -> list[dict]:
    stage = IngestStage(cfg)
    (unit,) = stage.list_units(str(path))
    return list(stage.process_unit(unit))


def _frames(row: dict) -> np.ndarray:
    return media.decode_rgb_video(row["video"], int(row["height"]), int(row["width"]))


@pytest.mark.parametrize(
    "spec",
    [
        Spec(container="mov"),
        Spec(container="mkv"),
        Spec(container="webm"),
        Spec(container="avi"),
        Spec(container="mts"),
        Spec(audio=True),
        Spec(container="webm", audio=True),
        Spec(rotation=-90),
        Spec(rotation=90, container="mov", hevc=True, audio=True),
    ],
    ids=["mov", "mkv", "webm", "avi", "mts", "audio", "webm-opus", "rotated", "phone-hevc"],
)
def test_other_files_of_the_same_pictures_ingest_to_the_same_clips(
    tmp_path: Path, source: Path, spec: Spec
) -> None:
    plain = tmp_path / "plain.mp4"
    write_variant(source, plain, Spec())
    ext = f".{spec.container}"
    variant = tmp_path / f"variant{ext}"
    write_variant(source, variant, spec)
    if spec.rotation:
        assert media.probe_video_file(variant).rotation == spec.rotation
    if spec.audio:
        with av.open(str(variant)) as container:
            assert [s.type for s in container.streams] == ["video", "audio"]
    ref, got = _ingest(plain), _ingest(variant)
    assert [r["num_frames"] for r in got] == [r["num_frames"] for r in ref] == [9, 9]
    for a, b in zip(ref, got, strict=True):
        np.testing.assert_array_equal(a["source_frame_indices"], b["source_frame_indices"])
        np.testing.assert_allclose(a["timestamps"], b["timestamps"], atol=1e-3)
        assert psnr_db(_frames(a), _frames(b)) >= SAME_PSNR_DB


def test_greyscale_video_gives_grey_rgb_clips(tmp_path: Path, source: Path) -> None:
    path = tmp_path / "grey.mp4"
    write_variant(source, path, Spec(grey=True))
    # (libx264 codes it 4:0:0; FFmpeg's H.264 decoder hands it out as yuv420p, grey chroma)
    rows = _ingest(path)
    frames = _frames(rows[0]).astype(int)  # (T, H, W, 3)
    assert frames.shape == (9, 32, 48, 3)
    assert np.abs(frames[..., 0] - frames[..., 1]).max() <= 3  # R = G = B, up to chroma coding
    assert np.abs(frames[..., 2] - frames[..., 1]).max() <= 3
    assert frames.std() > 10  # real content


def test_variable_frame_times_pick_the_nearest_frame_in_time(tmp_path: Path) -> None:
    """Frame i is a flat grey 6 * i; its time is irregular: ingest must pick by time, not by
    index, and record the source index it took."""
    rng = np.random.default_rng(3)
    times = np.cumsum(np.r_[0.0, rng.uniform(0.02, 0.09, 39)])  # 40 frames, 11-50 fps
    frames = np.stack([np.full((32, 48, 3), 6 * i, np.uint8) for i in range(40)])
    path = tmp_path / "vfr.mp4"
    with av.open(str(path), mode="w") as container:
        stream = container.add_stream("libx264", rate=30)
        stream.width, stream.height, stream.pix_fmt = 48, 32, "yuv420p"
        stream.time_base = stream.codec_context.time_base = Fraction(1, 90000)
        stream.options = {"crf": "0"}
        for t, image in zip(times, frames, strict=True):
            frame = av.VideoFrame.from_ndarray(image, format="rgb24")
            frame.pts = round(t * 90000)
            container.mux(stream.encode(frame))
        container.mux(stream.encode())
    (row,) = _ingest(path, IngestConfig(height=32, width=48, num_frames=13, min_frames=5, fps=8))
    targets = np.arange(row["num_frames"]) / 8.0
    expected = np.abs(times[None, :] - targets[:, None]).argmin(axis=1)
    np.testing.assert_array_equal(row["source_frame_indices"], expected)
    np.testing.assert_allclose(row["timestamps"], targets)
    grey = _frames(row)[:, 16, 24, 1].astype(int)  # (T,) the picked frames' own grey levels
    np.testing.assert_allclose(grey, 6 * expected, atol=2)


def test_faster_rates_give_clips_at_the_target_rate(tmp_path: Path, source: Path) -> None:
    for fps in (24.0, 25.0, 60.0):
        path = tmp_path / f"r{fps:g}.mp4"
        write_variant(source, path, Spec(fps=fps))
        assert media.probe_video_file(path).fps == pytest.approx(fps)
        rows = _ingest(path)
        assert [r["num_frames"] for r in rows] == [9, 9]
        np.testing.assert_allclose(rows[1]["timestamps"], (9 + np.arange(9)) / 10.0, atol=1e-6)


def test_a_cut_below_the_minimum_is_a_reject_naming_it(tmp_path: Path, source: Path) -> None:
    path = tmp_path / "cut.mp4"
    write_variant(source, path, Spec(frames=6))  # 6 frames at 20 fps: 3 at 10 fps, minimum 5
    with pytest.raises(ClipRejected, match=r"cut\.mp4 is shorter than one clip.*minimum is 5"):
        list(read_video_clips(path, TINY))


def _row(code: int, workflow: str = "dataset", packed: int = 0, **kw: object) -> dict:
    base = {"exit_code": code, "workflow": workflow, "clips_packed": packed}
    return {"clips_ingested": packed, "rejects": [], "same_psnr_db": None, **base, **kw}


def test_verdicts_say_what_went_wrong() -> None:
    clips = Variant("v", "x.mp4", None, "clips")
    reject = Variant("r", "x.mp4", None, "reject", reason="shorter than one clip")
    same = Variant("s", "x.mp4", None, "clips", same_as="v")
    assert verdict(clips, _row(0, packed=1)) == "ok"
    assert verdict(clips, _row(1)) == "crash (exit 1)"
    assert verdict(clips, _row(-6)) == "crash (exit -6)"  # killed by a signal (abort)
    assert verdict(clips, _row(4)).startswith("silent nothing")
    assert verdict(clips, _row(3, rejects=["cameras: x"])) == "rejected (exit 3)"
    assert verdict(reject, _row(3, rejects=["ingest: a is shorter than one clip"])) == "ok"
    assert verdict(reject, _row(3, rejects=["ingest: cannot decode"])).startswith("reject does")
    assert verdict(reject, _row(0, packed=1)).startswith("clips where")
    assert verdict(same, _row(0, "ingest", 1, clips_ingested=1, same_psnr_db=41.0)) == "ok"
    assert verdict(same, _row(0, "ingest", 1, same_psnr_db=12.0)).startswith("frames differ")
    assert verdict(clips, _row(TIMED_OUT)) == "timed out"


def test_a_run_past_its_time_limit_is_stopped(tmp_path: Path, source: Path) -> None:
    """The CLI takes seconds to import; a 0.3 s limit stops it and says so, well before it ends."""
    code, seconds = run_variant(source, tmp_path / "run", 1, False, limit_s=0.3)
    assert code == TIMED_OUT and seconds < 5.0


def test_a_mistyped_variant_is_refused_naming_the_value() -> None:
    with pytest.raises(ValueError, match=r"expect must be 'clips' or 'reject', got 'clip'"):
        Variant("v", "x.mp4", None, "clip")
    with pytest.raises(ValueError, match=r"needs the reason fragment"):
        Variant("r", "x.mp4", None, "reject")
    with pytest.raises(ValueError, match=r"container must be mp4 or one of .*got 'mp5'"):
        Spec(container="mp5")
    with pytest.raises(ValueError, match=r"rotation must be a multiple of 90 degrees, got 45"):
        Spec(rotation=45)


def test_the_row_records_the_crop_ingest_kept(tmp_path: Path, source: Path) -> None:
    """``summarise`` reads the first clip's ``source_crop`` from the run's ingest shard: for a
    portrait video cut with ``crop=anchor`` at the bottom, the bottom band of the source."""
    from egosim.pipeline.shards import ShardWriter
    from egosim.schemas.clips import CLIPS
    from egosim.stages.common.frame_plan import plan_resize

    portrait = tmp_path / "portrait.mp4"
    write_variant(source, portrait, Spec(aspect=9 / 16, size=(64, 112)))
    cfg = IngestConfig(
        height=32, width=48, num_frames=9, min_frames=5, fps=10.0, crop="anchor",
        crop_anchor=(0.5, 1.0),
    )  # fmt: skip
    rows = _ingest(portrait, cfg)
    run = tmp_path / "run"
    (run / "ingest").mkdir(parents=True)
    with ShardWriter(run / "ingest" / "shard-00000.parquet", CLIPS, stage="test") as writer:
        for row in rows:
            writer.write_row(row)
    got = summarise(Variant("p", "x.mp4", None, "clips"), run, 0, 1.0, False, None)
    want = plan_resize(64, 112, 48, 32, (0.5, 1.0)).source_crop
    np.testing.assert_allclose(got["source_crop"], want, atol=0.05)
    assert got["source_crop"][3] == 112.0 and got["source_crop"][1] > 50  # the bottom band
