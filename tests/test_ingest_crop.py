"""Ingest's crop anchor (``stages/ingest/crop_anchor.py``, ``frame_plan.plan_resize``): where
the cover crop's window sits in a portrait source, the ``hands`` mode, the intrinsics and the
recorded ``source_crop`` (clips v5)."""

from __future__ import annotations

import dataclasses
import json
import logging
from pathlib import Path

import cv2
import numpy as np
import pytest

from egosim.pipeline.clip_io import clip_from_row, row_from_clip
from egosim.pipeline.geometry import intrinsics_from_fov, project_points
from egosim.pipeline.media import write_video_file
from egosim.pipeline.records import Clip
from egosim.pipeline.stage import ClipRejected, ConfigError
from egosim.stages.common.frame_plan import plan_from_crop, plan_resize
from egosim.stages.ingest import crop_anchor
from egosim.stages.ingest.frames_source import read_frame_clips
from egosim.stages.ingest.stage import IngestConfig, IngestStage
from egosim.stages.ingest.video_source import read_video_clips, standardise_clip
from tests.conftest import shared_data

# A 360x640 upright source cut into 104x60 clips (832x480 / 8): scaled to 104x185, a 60-row band.
SRC_W, SRC_H = 360, 640
CLIP = {"height": 60, "width": 104, "num_frames": 9, "min_frames": 5, "fps": 8.0}
PATCH = (120, 500, 240, 580)  # x0, y0, x1, y1 source pixels: a red "hand" in the lower third
RED = (230, 20, 20)


def _background(n: int) -> np.ndarray:
    """``(n, 640, 360, 3)`` a grey vertical ramp drifting one pixel a frame (no red in it)."""
    y = np.arange(SRC_H + n)[:, None] * 0.25 + 40
    ramp = np.repeat(np.repeat(y[..., None], 3, axis=2), SRC_W, axis=1).astype(np.uint8)
    return np.stack([ramp[i : i + SRC_H] for i in range(n)])


def _portrait_video(tmp_path: Path, n: int = 40) -> Path:
    frames = _background(n)
    x0, y0, x1, y1 = PATCH
    frames[:, y0:y1, x0:x1] = RED
    path = tmp_path / "portrait.mp4"
    write_video_file(path, frames, 30.0)
    return path


def _red_pixels(frames: np.ndarray) -> int:
    f = frames.astype(np.int16)
    return int(((f[..., 0] > 180) & (f[..., 1] < 80) & (f[..., 2] < 80)).sum())


def _without_following(frames: list[np.ndarray]) -> crop_anchor.FrameSample:
    """A sample of ``frames`` with no frame after any of them (no static-scene count)."""
    return crop_anchor.FrameSample(lambda n: [(f, None) for f in frames[:n]])


def test_crop_config_is_checked_with_the_bad_value() -> None:
    with pytest.raises(ConfigError, match=r"crop_anchor must be two fractions .* got \(0.5,\)"):
        IngestConfig(crop_anchor=(0.5,))
    with pytest.raises(ConfigError, match=r"crop_anchor .* got \(0.5, 1.5\)"):
        IngestConfig(crop_anchor=(0.5, 1.5))
    with pytest.raises(ConfigError, match="crop must be 'hands' or 'anchor', got 'top'"):
        IngestConfig(crop="top")  # type: ignore[arg-type]
    assert IngestConfig().crop_anchor == (0.5, 0.5)


def test_a_low_anchor_keeps_the_hands_of_a_portrait_video(tmp_path: Path) -> None:
    """The red patch lies in the lower third: the centre band (source rows 214-422) cuts it
    away, the bottom band keeps all of it; the intrinsics move with the crop exactly (a point
    drawn at a known projection lands where the clip's intrinsics put it) and the recorded
    crop round-trips through the clips row."""
    path = _portrait_video(tmp_path)
    centre = list(read_video_clips(path, IngestConfig(crop="anchor", **CLIP)))
    low = list(read_video_clips(path, IngestConfig(crop="anchor", crop_anchor=(0.5, 1), **CLIP)))
    assert len(centre) == len(low) == 1
    assert _red_pixels(centre[0].frames) == 0
    # The whole patch at the clip's scale (104/360): 34.7 x 23.1 px a frame, edges blended.
    per_frame = _red_pixels(low[0].frames) / low[0].num_frames
    assert 0.8 * 34.7 * 23.1 < per_frame < 1.1 * 34.7 * 23.1
    plan = plan_resize(SRC_W, SRC_H, 104, 60, (0.5, 1.0))
    np.testing.assert_allclose(low[0].source_crop, plan.source_crop)
    assert low[0].source_crop[3] == pytest.approx(SRC_H)  # the band reaches the bottom
    # Intrinsics: the patch centre as a 3D point projects into the clip where the patch is.
    k_src = intrinsics_from_fov(SRC_W, SRC_H, 70.0)
    fx, fy, cx, cy = k_src
    u, v = (PATCH[0] + PATCH[2]) / 2, (PATCH[1] + PATCH[3]) / 2  # source pixel centre (edges)
    point = np.array([(u - 0.5 - cx) / fx, (v - 0.5 - cy) / fy, 1.0]) * 2.0  # pixel-centre rule
    (uv,), _ = project_points(point[None], low[0].intrinsics)
    mask = np.all(np.abs(low[0].frames[0].astype(int) - RED) < 60, axis=-1)
    ys, xs = np.nonzero(mask)
    assert abs(uv[0] - xs.mean()) < 0.5 and abs(uv[1] - ys.mean()) < 0.5
    assert low[0].intrinsics[3] == pytest.approx(centre[0].intrinsics[3] - (125 - 62))
    # The crop is recorded in the row and read back.
    back = clip_from_row(row_from_clip(low[0]))
    np.testing.assert_array_equal(back.source_crop, low[0].source_crop)
    assert plan_from_crop(SRC_W, SRC_H, 104, 60, back.source_crop) == plan


def _red_boxes(frames: list[np.ndarray]) -> list[list[tuple[float, float, float, float]]]:
    """A stand-in detector (for ``frame_hand_boxes``): per frame, the box of its red pixels as
    fractions (none where it has no red)."""
    boxes = []
    for f in frames:
        ys, xs = np.nonzero(np.all(np.abs(f.astype(int) - RED) < 60, axis=-1))
        h, w = f.shape[:2]
        found = [(xs.min() / w, ys.min() / h, (xs.max() + 1) / w, (ys.max() + 1) / h)]
        boxes.append(found if len(xs) else [])
    return boxes


def test_hands_mode_places_the_band_over_what_the_detector_finds(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """With the detector stood in by a red-box finder, ``crop=hands`` puts the whole patch in
    the band (video file and frame folder alike), from a few sampled frames."""
    calls: list[int] = []

    def boxes(frames: list[np.ndarray]) -> list:
        calls.append(len(frames))
        assert max(frames[0].shape[:2]) <= crop_anchor.DETECT_LONG_SIDE
        return _red_boxes(frames)

    monkeypatch.setattr(crop_anchor, "frame_hand_boxes", boxes)
    path = _portrait_video(tmp_path)
    (clip,) = read_video_clips(path, IngestConfig(**CLIP))  # crop="hands" is the default
    assert calls == [crop_anchor.SAMPLE_FRAMES]
    _, y0, _, y1 = clip.source_crop
    assert y0 <= PATCH[1] and y1 >= PATCH[3]
    assert _red_pixels(clip.frames) / clip.num_frames > 0.8 * 34.7 * 23.1
    # A frame folder of the same pictures gets the same band.
    folder = tmp_path / "frames"
    folder.mkdir()
    frames = _background(20)
    frames[:, PATCH[1] : PATCH[3], PATCH[0] : PATCH[2]] = RED
    for i, f in enumerate(frames):
        cv2.imwrite(str(folder / f"{i:04d}.png"), cv2.cvtColor(f, cv2.COLOR_RGB2BGR))
    (fclip,) = read_frame_clips(folder, IngestConfig(frames_fps=15.0, **CLIP))
    np.testing.assert_allclose(fclip.source_crop, clip.source_crop)


def test_hands_mode_without_hands_or_cut_keeps_the_anchor(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """No hand found: the configured anchor (centre), said in a log line. A source whose crop
    cuts under MIN_CUT_FRACTION (16:9 into 832x480: 2.5%) is not searched at all."""
    monkeypatch.setattr(crop_anchor, "frame_hand_boxes", lambda frames: [])
    path = _portrait_video(tmp_path)
    with caplog.at_level(logging.INFO, logger=crop_anchor.__name__):
        (clip,) = read_video_clips(path, IngestConfig(**CLIP))
    np.testing.assert_allclose(clip.source_crop, plan_resize(SRC_W, SRC_H, 104, 60).source_crop)
    assert "no hand found on 8 sampled frames; crop at anchor (0.50, 0.50)" in caplog.text

    def no_read(count: int) -> list:
        raise AssertionError("sampled a source whose crop cuts under 10%")

    fail = crop_anchor.FrameSample(no_read)

    cfg = IngestConfig()
    assert crop_anchor.choose_anchor(cfg, 1920, 1080, fail, "x") == (0.5, 0.5)
    assert crop_anchor.choose_anchor(cfg, 832, 480, fail, "x") == (0.5, 0.5)
    # crop=anchor never samples either.
    anchor_cfg = IngestConfig(crop="anchor", crop_anchor=(0.5, 0.9))
    assert crop_anchor.choose_anchor(anchor_cfg, 1080, 1920, fail, "x") == (0.5, 0.9)


def test_window_placement_covers_the_most_hand() -> None:
    """Candidate anchors are k/16: offsets floor(k / 16 * slack), here multiples of 20 px."""
    assert crop_anchor.ANCHOR_STEPS == 16
    # Two hands at 100-160 and 220-280 of a 520-px axis fit together in a 200-px window at
    # offsets 80 and 100 (k = 4, 5); of those the one centred nearest the hands' (190): 80.
    assert crop_anchor.place_window(np.array([[100.0, 160.0], [220.0, 280.0]]), 200, 320) == 4 / 16
    # They cannot both fit (100-160 and 300-380): the window holds one whole; of the equal
    # covers (offsets 0-100 and 180-320) the one nearest the hands' mean centre (235): 100.
    spans = np.array([[100.0, 160.0], [300.0, 380.0]])
    anchor = crop_anchor.place_window(spans, 200, 320)
    offsets = [20 * k for k in range(17)]
    cover = [sum(max(0, min(b, o + 200) - max(a, o)) / (b - a) for a, b in spans) for o in offsets]
    assert max(cover) == 1.0 and anchor == 5 / 16
    # One hand: the window centred on it as near as the steps allow, or at the edge.
    assert crop_anchor.place_window(np.array([[250.0, 290.0]]), 100, 320) == 11 / 16  # 220
    assert crop_anchor.place_window(np.array([[500.0, 520.0]]), 100, 320) == 1.0
    # A slack that is not a multiple of 16: the offset plan_resize makes of the anchor counts.
    anchor = crop_anchor.place_window(np.array([[0.0, 30.0]]), 100, 7)
    assert anchor == 0.0


def _source_clip(frames: np.ndarray, source: str) -> Clip:
    """A SRC_W x SRC_H clip of ``frames`` at 8 fps from ``source``, as a reader hands it over."""
    return Clip(
        clip_id="c",
        source=source,
        source_uri="x",
        fps=8.0,
        timestamps=np.arange(len(frames)) / 8.0,
        intrinsics=intrinsics_from_fov(SRC_W, SRC_H, 70.0),
        frames=frames,
    )


def test_standardised_clips_record_their_crop_in_the_original_source() -> None:
    """A clip cut again (``standardise_clip`` of a clip that records a crop) maps the new crop
    through the old one into the original source's pixels."""
    frames = _background(9)
    frames[:, PATCH[1] : PATCH[3], PATCH[0] : PATCH[2]] = RED
    clip = _source_clip(frames, "mcap")
    cfg = IngestConfig(crop="anchor", crop_anchor=(0.5, 1.0), **CLIP)
    (first,) = standardise_clip(clip, cfg)
    np.testing.assert_allclose(
        first.source_crop, plan_resize(SRC_W, SRC_H, 104, 60, (0.5, 1.0)).source_crop
    )
    half = dict(CLIP, height=30, width=30)
    (second,) = standardise_clip(first, IngestConfig(crop="anchor", crop_anchor=(0.0, 0.5), **half))
    inner = plan_resize(104, 60, 30, 30, (0.0, 0.5)).source_crop  # pixels of ``first``
    x0, y0, x1, y1 = first.source_crop
    sx, sy = (x1 - x0) / 104, (y1 - y0) / 60
    expected = [x0 + inner[0] * sx, y0 + inner[1] * sy, x0 + inner[2] * sx, y0 + inner[3] * sy]
    np.testing.assert_allclose(second.source_crop, expected)


def test_real_hand_in_a_portrait_frame_is_found_and_kept(tmp_path: Path) -> None:
    """A real hand photo (FreiHAND, with its 2D keypoints) pasted into the lower third of a
    portrait video: the detector finds it and every true keypoint lies inside the band; the
    centre band would hold none of them."""
    pytest.importorskip("mediapipe")
    folder = shared_data("freihand_fixture")
    meta = json.loads((folder / "test_freihand.json").read_text())
    ann = next(a for a in meta["annotations"] if a["image_id"] == 355)
    image = cv2.cvtColor(cv2.imread(str(folder / "00000355.jpg")), cv2.COLOR_BGR2RGB)
    top, left = 416, 68  # the photo's rows 416-640 of the source
    frames = _background(40)
    frames[:, top : top + 224, left : left + 224] = image
    path = tmp_path / "hand.mp4"
    write_video_file(path, frames, 30.0)
    (clip,) = read_video_clips(path, IngestConfig(**CLIP))
    kp = np.asarray(ann["keypoints"], dtype=np.float64).reshape(-1, 3)[:, :2] + [left, top]
    _, y0, _, y1 = clip.source_crop
    assert kp[:, 1].min() >= y0 and kp[:, 1].max() <= y1, (kp[:, 1].min(), kp[:, 1].max(), y0)
    cy0, cy1 = plan_resize(SRC_W, SRC_H, 104, 60).source_crop[1::2]
    assert not ((kp[:, 1] >= cy0) & (kp[:, 1] <= cy1)).any()


@pytest.mark.parametrize("seek", [False, True])
def test_crop_samples_spread_over_the_video(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, seek: bool
) -> None:
    """8 frames spread over the source, by one decoding pass or (long videos) by seeking: frame
    i of the test video is flat grey level 5 i, so each sample names its index."""
    from egosim.pipeline.media import probe_video_file

    n = 40
    frames = np.stack([np.full((64, 48, 3), 5 * i, np.uint8) for i in range(n)])
    path = tmp_path / "ramp.mp4"
    write_video_file(path, frames, 30.0)
    if seek:
        monkeypatch.setattr(crop_anchor, "SEEK_AFTER_S", 0.5)  # 1.33 s: a "long" video

        def no_pass(*args: object) -> list:
            raise AssertionError("decoded in one pass, not by seeking")

        monkeypatch.setattr(crop_anchor, "_pass_frames", no_pass)
    sample = crop_anchor.sample_video(path, probe_video_file(path))
    got = [round(float(f.mean()) / 5) for f in sample(8)]
    # Seeking takes the first frame from half a frame before each time (k + 0.5) / 8 of the
    # duration: the same frames as the pass's indices.
    assert got == [int((k + 0.5) * n / 8) for k in range(8)]  # 2, 7, 12, ... 37
    # ... and the static-scene count's partner of each is the next source frame.
    assert [round(float(f.mean()) / 5) for f in sample.following(8)] == [i + 1 for i in got]


def test_clips_schema_checks_the_crop_and_the_principal_point_it_moves(tmp_path: Path) -> None:
    """A bottom band's principal point lies above the image: accepted when the row's
    source_crop puts it inside the source frame, refused without one; a bad crop is named."""
    from egosim.schemas import CLIPS

    path = _portrait_video(tmp_path)
    cfg = IngestConfig(crop="anchor", crop_anchor=(0.5, 1.0), **CLIP)
    (clip,) = read_video_clips(path, cfg)
    row = row_from_clip(clip)
    assert row["intrinsics"][3] < 0  # cy above the image
    assert CLIPS.row_problems(row) == []
    problems = CLIPS.row_problems({**row, "source_crop": None})
    assert any("principal point" in p and "lies outside the 104x60 image" in p for p in problems)
    bad = CLIPS.row_problems({**row, "source_crop": [0.0, 500.0, 360.0, 400.0]})
    assert any("source_crop must be x0, y0, x1, y1" in p for p in bad)
    # The Clip record checks the same (one shared rule, schemas.clips.source_crop_problems).
    from dataclasses import replace

    assert clip.problems() == []
    bad_clip = replace(clip, source_crop=np.array([0.0, 500.0, 360.0, 400.0]))
    assert any("source_crop must be x0, y0, x1, y1" in p for p in bad_clip.problems())


def test_an_odd_sized_frame_among_the_crop_samples_rejects_the_folder(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A frame folder whose odd-sized image is one of the crop search's samples is rejected
    naming that file, as when the clip's frames meet it (it was a bare ValueError from
    stacking the samples)."""

    def no_hands(frames: list[np.ndarray]) -> list:
        np.stack(frames)  # as the detector's input is stacked: one size
        return []

    monkeypatch.setattr(crop_anchor, "frame_hand_boxes", no_hands)
    n = 20
    odd = crop_anchor.sample_indices(n, crop_anchor.SAMPLE_FRAMES)[4]  # index 11: sampled
    folder = tmp_path / "frames"
    folder.mkdir()
    for i in range(n):
        h = SRC_H - 40 if i == odd else SRC_H
        cv2.imwrite(str(folder / f"{i:04d}.png"), np.full((h, SRC_W, 3), 100, np.uint8))
    cfg = IngestConfig(frames_fps=15.0, **CLIP)
    with pytest.raises(ClipRejected, match=rf"{odd:04d}\.png: size \(600, 360\) differs"):
        list(read_frame_clips(folder, cfg))


def test_without_mediapipe_the_crop_stays_at_the_anchor_with_a_warning(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """MediaPipe not installed: ``crop=hands`` keeps ``crop_anchor`` and says why (a warning),
    rather than failing the source."""
    from egosim.stages.common.hand_landmarks import MediaPipeUnavailableError

    def missing(frames: list[np.ndarray]) -> list:
        raise MediaPipeUnavailableError("hand landmarks need mediapipe")

    monkeypatch.setattr(crop_anchor, "frame_hand_boxes", missing)
    frames = [np.zeros((64, 36, 3), np.uint8)] * crop_anchor.SAMPLE_FRAMES
    cfg = IngestConfig(crop_anchor=(0.5, 0.75))
    with caplog.at_level(logging.WARNING, logger=crop_anchor.__name__):
        anchor = crop_anchor.choose_anchor(cfg, 1080, 1920, _without_following(frames), "portrait")
    assert anchor == (0.5, 0.75)
    assert "portrait: crop at anchor (0.5, 0.75), hands not looked for" in caplog.text


def test_a_failed_seek_samples_by_one_pass_instead(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A long video whose seeking fails (no frame timestamps, a broken index) still gets its 8
    spread samples, by one decoding pass."""
    from egosim.pipeline.media import MediaError, probe_video_file

    n = 40
    frames = np.stack([np.full((64, 48, 3), 5 * i, np.uint8) for i in range(n)])
    path = tmp_path / "ramp.mp4"
    write_video_file(path, frames, 30.0)
    monkeypatch.setattr(crop_anchor, "SEEK_AFTER_S", 0.5)  # 1.33 s: a "long" video

    def broken(*args: object) -> list:
        raise MediaError("cannot seek in video file: no frame timestamps")

    monkeypatch.setattr(crop_anchor, "_seek_frames", broken)
    sample = crop_anchor.sample_video(path, probe_video_file(path))(8)
    got = [round(float(f.mean()) / 5) for f in sample]
    assert got == [int((k + 0.5) * n / 8) for k in range(8)]  # 2, 7, 12, ... 37


def test_robot_clips_keep_the_configured_anchor(monkeypatch: pytest.MonkeyPatch) -> None:
    """A robot clip (a gripper opening) is not searched for human hands: with ``crop="hands"`` it
    is cut at ``crop_anchor`` even where the detector would report a hand elsewhere, while the
    same clip without the gripper follows the detector."""
    frames = _background(9)
    monkeypatch.setattr(
        crop_anchor, "frame_hand_boxes", lambda f: [[(0.3, 0.0, 0.6, 0.1)]] * len(f)
    )
    clip = _source_clip(frames, "lerobot")
    cfg = IngestConfig(crop="hands", crop_anchor=(0.5, 0.5), **CLIP)
    top = plan_resize(SRC_W, SRC_H, 104, 60, (0.5, 0.0)).source_crop
    centre = plan_resize(SRC_W, SRC_H, 104, 60, (0.5, 0.5)).source_crop
    (human,) = standardise_clip(clip, cfg)
    np.testing.assert_allclose(human.source_crop, top)  # the detector's hand is at the top
    robot = dataclasses.replace(clip, gripper_opening=np.full((9, 2), 0.04, np.float32))
    (cut,) = standardise_clip(robot, cfg)
    np.testing.assert_allclose(cut.source_crop, centre)


def _blobs(height: int, width: int, seed: int) -> np.ndarray:
    """``(height, width, 3)`` uint8 static texture SIFT finds: a random 1/8-scale grid, enlarged."""
    grid = np.random.default_rng(seed).integers(0, 256, (height // 8, width // 8), np.uint8)
    grey = cv2.resize(grid, (width, height), interpolation=cv2.INTER_CUBIC)
    return np.repeat(grey[..., None], 3, axis=2)


def _scene(textured_rows: tuple[int, int], shift: int) -> np.ndarray:
    """A 640x360 portrait frame: plain grey (a bare table) with static texture in
    ``textured_rows`` of the source, the whole picture moved ``shift`` pixels right (the
    camera turning a little from one frame to the next)."""
    frame = np.full((SRC_H, SRC_W + 8, 3), 150, np.uint8)
    y0, y1 = textured_rows
    frame[y0:y1] = _blobs(SRC_H, SRC_W + 8, seed=3)[y0:y1]
    return np.ascontiguousarray(frame[:, 8 - shift : 8 - shift + SRC_W])


def test_a_hands_band_with_too_little_scene_moves_towards_it() -> None:
    """The hands' band over a bare table (no SIFT matches there) moves to the band with the
    scene's texture that still keeps at least half of the hands; where the hands' band holds
    texture enough (STATIC_MIN_MATCHES), it stays."""
    plan = plan_resize(SRC_W, SRC_H, 832, 480)  # scaled 832x1479, a 480-row band (208 source)
    hand = (0.3, 480 / SRC_H, 0.7, 608 / SRC_H)  # source rows 480-608 in every frame
    per_frame = [[hand]] * 4
    placed = crop_anchor.hands_anchor(plan, [hand], (0.5, 0.5))
    y0, y1 = plan_resize(SRC_W, SRC_H, 832, 480, placed).source_crop[1::2]
    assert y0 <= 480 and y1 >= 608  # the hands' band holds the whole hand ...
    # ... and the texture (rows 260-420) lies above it: the band moves up as far as it may
    # while covering half of the hand (its bottom at row 544 or below).
    frames = [_scene((260, 420), 0)] * 4
    following = [_scene((260, 420), 2)] * 4
    moved, note = crop_anchor.texture_anchor(plan, frames, following, per_frame, placed)
    assert moved[1] < placed[1] and "moved from" in note, note
    m0, m1 = plan_resize(SRC_W, SRC_H, 832, 480, moved).source_crop[1::2]
    assert m0 < 420 and m1 >= 544, (m0, m1)
    kept = (min(m1, 608) - max(m0, 480)) / 128
    assert kept >= crop_anchor.HANDS_KEEP_FRACTION
    # The moved band holds more matches than the hands' band had.
    pos = crop_anchor.static_matches(frames[0], following[0], [hand])[..., 1] * SRC_H  # (M, 2)
    count = [int(((pos >= a) & (pos < b)).all(axis=1).sum()) for a, b in ((y0, y1), (m0, m1))]
    assert count[0] < crop_anchor.STATIC_MIN_MATCHES <= count[1], count
    # Texture all over: the hands' band has matches enough and stays.
    frames = [_scene((0, SRC_H), 0)] * 4
    following = [_scene((0, SRC_H), 2)] * 4
    kept_anchor, note = crop_anchor.texture_anchor(plan, frames, following, per_frame, placed)
    assert kept_anchor == placed and "moved" not in note, note
    # Bare everywhere: too few matches, but no band that keeps the hands has more; it stays.
    frames = [_scene((0, 0), 0)] * 4
    following = [_scene((0, 0), 2)] * 4
    kept_anchor, note = crop_anchor.texture_anchor(plan, frames, following, per_frame, placed)
    assert kept_anchor == placed and "no better band keeps the hands" in note, note


def test_the_scene_check_needs_the_next_frame() -> None:
    """A plain ``sample`` callable (no following frames) keeps the hands' anchor, as before
    ingest v9; with following frames the same bare-table band moves up to the texture."""
    frames = [_scene((260, 420), 0)] * 8

    def boxes(fr: list[np.ndarray]) -> list:
        return [[(0.3, 480 / SRC_H, 0.7, 608 / SRC_H)]] * len(fr)

    import unittest.mock

    with unittest.mock.patch.object(crop_anchor, "frame_hand_boxes", boxes):
        plain = crop_anchor.choose_anchor(
            IngestConfig(), SRC_W, SRC_H, _without_following(frames), "x"
        )
        both = crop_anchor.sample_frames(8, lambda i: _scene((260, 420), i % 2 * 2))
        moved = crop_anchor.choose_anchor(IngestConfig(), SRC_W, SRC_H, both, "x")
    placed = crop_anchor.hands_anchor(
        plan_resize(SRC_W, SRC_H, 832, 480), boxes(frames[:1])[0], (0.5, 0.5)
    )
    assert plain == placed
    assert moved[1] < placed[1]


def test_a_file_units_fingerprint_names_the_crop_detector(tmp_path, monkeypatch) -> None:
    """With crop="hands" the frames depend on whether MediaPipe is there (without it every band
    stays at the anchor), so a file unit's fingerprint names the detector and a run resumed
    without it ingests again; crop="anchor" does not look for hands and keeps one fingerprint."""
    video = tmp_path / "v.mp4"
    video.write_bytes(b"not read here")
    unit = f"video:{video}"
    hands = IngestStage(IngestConfig(source="video"))
    anchor = IngestStage(IngestConfig(source="video", crop="anchor"))
    monkeypatch.setattr(crop_anchor, "crop_detector", lambda: "mediapipe 0.10.21")
    found, fixed = hands.unit_fingerprint(unit), anchor.unit_fingerprint(unit)
    assert found.endswith("|crop mediapipe 0.10.21")
    monkeypatch.setattr(crop_anchor, "crop_detector", lambda: "none")
    assert hands.unit_fingerprint(unit) == found.replace("mediapipe 0.10.21", "none")
    assert anchor.unit_fingerprint(unit) == fixed
    synthetic = "synthetic:tabletop:0"
    assert hands.unit_fingerprint(synthetic) == synthetic  # never cropped by the search
