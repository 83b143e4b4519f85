"""bench.hand_free_real: the split of a mask's misses into background- and hand-coloured pixels,
and the region the hand-free frame replaces (the mask grown as ``inpaint`` grows it)."""

from __future__ import annotations

import numpy as np

from bench.hand_free_real import background_like_misses, filled_region
from egosim.stages.inpaint.reproject_fill import dilate
from egosim.stages.inpaint.stage import InpaintConfig, InpaintStage

SKIN = (200, 150, 120)
FLOOR = (60, 90, 160)


def test_background_like_misses_counts_only_misses_of_background_colour() -> None:
    """A truth hand of skin colour on a blue floor: the mask holds most of it and misses a
    10x4 skin strip (visible hand) and the 40x6 strip the truth draws over the floor (a render
    off the hand); only the floor strip's 240 pixels count."""
    frame = np.zeros((1, 80, 80, 3), np.uint8)
    frame[:] = FLOOR
    frame[0, 20:60, 20:50] = SKIN  # the real hand
    truth = np.zeros((1, 80, 80), bool)
    truth[0, 20:60, 20:56] = True  # the hand plus 6 columns of floor
    mask = np.zeros((1, 80, 80), bool)
    mask[0, 20:60, 20:50] = True
    mask[0, 20:30, 46:50] = False  # a missed skin strip
    missed_floor = 40 * 6
    assert int((truth & ~mask).sum()) == missed_floor + 40
    assert background_like_misses(frame, mask, truth) == missed_floor


def test_background_like_misses_zero_without_misses() -> None:
    """A mask that holds the whole truth misses nothing; a missed colour seen neither on the
    masked hand nor round it is not counted as background."""
    frame = np.full((2, 40, 40, 3), 128, np.uint8)
    truth = np.zeros((2, 40, 40), bool)
    truth[:, 10:20, 10:20] = True
    assert background_like_misses(frame, truth | False, truth) == 0
    mask = truth.copy()
    mask[:, 10:12, 10:20] = False  # missed ...
    frame[:, 10:12, 10:20] = (250, 20, 250)  # ... in a colour found nowhere else
    assert background_like_misses(frame, mask, truth) == 0


def test_filled_region_is_the_region_the_inpaint_stage_replaces() -> None:
    """The bench's grown masks are the pixels the ``inpaint`` stage fills (its own ``filled``)
    at two image sizes and with a config that grows less; a truth band 3 px round the mask is
    missed by the mask but inside the filled region at the default growth (2 + 0.008 x 160 px
    diagonal = 3 px), and not with ``dilate_fraction`` 0 (2 px)."""
    for h, w in ((96, 128), (240, 416)):
        for config in (InpaintConfig(backend="opencv"),
                       InpaintConfig(backend="opencv", dilate_fraction=0.0)):  # fmt: skip
            mask = np.zeros((1, h, w), np.uint8)
            mask[0, h // 3 : h // 2, w // 4 : w // 2] = 1
            frames = np.full((1, h, w, 3), 90, np.uint8)
            stage = InpaintStage(config).fill(frames, mask, None, np.zeros(4), None)
            np.testing.assert_array_equal(filled_region(mask, config)[0], stage.filled)
    mask = np.zeros((1, 96, 128), np.uint8)
    mask[0, 30:60, 40:80] = 1
    truth = dilate(mask, 3) > 0  # the mask plus a 3 px band
    default = filled_region(mask)
    assert InpaintConfig().grow_px(96, 128) == 3
    assert float(default[truth].mean()) == 1.0
    assert float((mask > 0)[truth].mean()) < 0.8
    narrow = filled_region(mask, InpaintConfig(dilate_fraction=0.0))
    assert float(narrow[truth].mean()) < 1.0


def _clip_files(data, cid: str, twins: tuple[str, ...], frames: int = 4) -> None:
    """A tiny DWM dynamic clip ``cid`` under ``data``: grey frames with a skin square (the hand)
    and, for each folder of ``twins``, its twin (hands: the square in green on black)."""
    from egosim.pipeline import media

    video = np.full((frames, 64, 96, 3), 90, np.uint8)
    video[:, 30:50, 40:60] = SKIN
    hands = np.zeros_like(video)
    hands[:, 30:50, 40:60] = (0, 200, 0)
    static = np.full_like(video, 90)
    root = data / "dwm_realworld" / "realworld_dynamic"
    for folder, frames_of in (
        ("videos", video),
        ("videos_hands", hands),
        ("videos_static", static),
    ):
        if folder == "videos" or folder in twins:
            (root / folder).mkdir(parents=True, exist_ok=True)
            media.write_video_file(root / folder / f"{cid}.mp4", frames_of, 8.0)


def test_dwm_truth_gives_none_for_a_missing_twin(tmp_path) -> None:
    from bench.hand_free_real import dwm_truth

    _clip_files(tmp_path, "90013", ("videos_hands",))
    truth = dwm_truth("90013", tmp_path)
    assert truth.static is None and truth.shift == (0.0, 0.0) and truth.inside.all()
    assert (
        truth.hands is not None and truth.hands[:, 40, 50].all() and not truth.hands[:, 5, 5].any()
    )
    _clip_files(tmp_path, "80013", ("videos_static",))
    truth = dwm_truth("80013", tmp_path)
    assert truth.hands is None and truth.static is not None


def test_main_measures_every_clip_found_and_says_n_a_without_truth(
    tmp_path, monkeypatch, capsys
) -> None:
    """A clip id nothing names (no 00013 / 00017 here) is measured; the figures its missing
    twins would give print as n/a instead of crashing."""
    import sys

    from bench import hand_free_real

    data = tmp_path / "data"
    _clip_files(data, "90013", ())
    _clip_files(data, "70017", ("videos_hands", "videos_static"))
    argv = ["hand_free_real", "--world", "", "--data", str(data), "--out", str(tmp_path / "o")]
    monkeypatch.setattr(sys, "argv", argv)
    assert hand_free_real.main() == 0
    lines = [x for x in capsys.readouterr().out.splitlines() if x.startswith("dwm ")]
    rows = [x for x in lines if " recall " in x]
    assert [x.split()[1] for x in rows] == ["70017", "90013"]
    assert "no videos_hands twin" in "\n".join(lines)
    assert rows[1].startswith("dwm 90013 recall n/a (3 px n/a; filled n/a")
    assert "hand n/a vs Telea n/a dB, frame n/a vs n/a" in rows[1]
    assert "recall n/a" not in rows[0]


def test_shift_stability_is_high_for_a_plain_hand_and_n_a_without_a_mask() -> None:
    """A hand and sleeve on a table, masked from its keypoints: moving them 1 px moves the mask
    by about that much (IoU near 1); a clip without a mask is not scored; 0 px is not measured."""
    from bench.hand_free_real import shift_stability
    from egosim.stages.hand_mask.stage import HandMaskConfig, masks_from_keypoints
    from tests.test_hand_mask import _hand_keypoints, _sleeve_frame

    h, w = 160, 200
    wrist, down = np.array([100.5, 60.5]), np.array([0.0, 1.0])
    frame = _sleeve_frame(h, w, wrist, down, 3)
    video = np.stack([frame, frame, frame])  # (3, H, W, 3)
    uv = np.zeros((3, 2, 21, 2))
    uv[:2, 0] = _hand_keypoints(wrist, -down, 30.0, 24.0)
    present = np.array([[True, False], [True, False], [False, False]])  # frame 2: carried
    masks = masks_from_keypoints(video, uv, present, HandMaskConfig()) > 0
    assert masks[0].sum() > 0.003 * h * w
    mean, least, worst = shift_stability(video, uv, present, masks, 1.0)
    assert 0.85 <= least <= mean + 1e-9 and mean <= 1.0, (mean, least)
    assert worst in (0, 1, 2)
    nan_mean, nan_min, frame_none = shift_stability(video, uv, present, masks, 0.0)
    assert np.isnan(nan_mean) and np.isnan(nan_min) and frame_none == -1
    none = np.zeros_like(present)
    empty = masks_from_keypoints(video, uv, none, HandMaskConfig()) > 0
    assert shift_stability(video, uv, none, empty, 1.0)[2] == -1
