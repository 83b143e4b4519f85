"""The palm detector's second pass on contrast-stretched frames (``stretch_gain``).

DWM clip 00013 (real Aria footage, sleeved hands on a cushion) darkened x0.5: the palm detector
finds its left hand on no frame of the clip, so the ROI tracker has nothing to follow and the
hand is lost for the whole clip (``python -m bench.hands_real --perturb``, hands15). On the
contrast-stretched frames (the whole frame and the zoomed tiles) it finds it, on the left hand's
truth render.
"""

from __future__ import annotations

import numpy as np
import pytest

from egosim.stages.common import hand_landmarks
from egosim.stages.common.hand_landmarks import (
    HandLandmarkParams,
    detect_hand_landmarks,
    stretched_frame,
)
from egosim.stages.common.roi_landmarks import stretch_contrast
from tests.conftest import shared_data

FIRST, LAST = 32, 37  # DWM 00013 frames used (the left hand's seed is at 34)


def _clip() -> tuple[np.ndarray, np.ndarray]:
    """``(frames, left)``: DWM 00013 frames FIRST..LAST-1 ``(5, 480, 720, 3)`` and the left
    hand's truth render ``(5, 480, 720)`` bool (green in ``videos_hands``)."""
    pytest.importorskip("mediapipe")
    from egosim.pipeline.media import read_video_file

    folder = shared_data("dwm_realworld", "realworld_dynamic")
    frames, _ = read_video_file(folder / "videos" / "00013.mp4")
    render, _ = read_video_file(folder / "videos_hands" / "00013.mp4")
    r, g, b = (render[FIRST:LAST, ..., c].astype(np.int16) for c in range(3))
    left = (g > 100) & (g > r + 50) & (g > b + 50)  # (5, H, W)
    return frames[FIRST:LAST], left


def _hands(frames: np.ndarray, gain: float, probe: int = HandLandmarkParams.stretch_probe):
    """The palm detector's hands alone (no ROI tracking), with or without the stretched pass
    (``probe``: its probe's step, 0 = none)."""
    params = HandLandmarkParams(track_misses=False, stretch_gain=gain, stretch_probe=probe)
    return detect_hand_landmarks(frames, params)


def test_darkened_real_hand_is_found_on_the_stretched_frames() -> None:
    frames, left = _clip()
    dark = np.round(frames * 0.5).astype(np.uint8)  # bench.hands_real's "dark"
    assert not _hands(dark, 1.0).present.any()  # without the pass: nothing at all
    raw = _hands(dark, 4.0)
    found = [
        (f, k) for f, k in zip(*np.nonzero(raw.present), strict=True) if raw.label_right[f, k] < 0.5
    ]
    assert found, "no left hand on the stretched frames"
    for f, k in found:  # every left hand found lies on the left hand's render
        u, v = raw.uv[f, k].mean(axis=0)  # (2,) landmark centroid, pixels
        assert left[f, int(v), int(u)], (FIRST + f, u, v)


def test_well_exposed_frames_are_not_searched_again(monkeypatch) -> None:
    frames, _ = _clip()
    dark = np.round(frames * 0.5).astype(np.uint8)
    # The darkened frames stretched to their full range: well exposed (gain under 2).
    bright = np.stack([stretched_frame(f, 4.0) for f in dark])  # (5, H, W, 3)
    assert all(stretched_frame(f, 4.0) is None for f in bright)
    calls = []
    real = hand_landmarks._hands_in

    def counted(hands, image, box, swap):
        calls.append(image.shape)
        return real(hands, image, box, swap)

    monkeypatch.setattr(hand_landmarks, "_hands_in", counted)
    plain = _hands(bright, 1.0)
    n_plain = len(calls)
    # The first pass on these frames finds both sides (frame 33's left hand is labelled right),
    # so the pass would not run at all: make the right side count as missing, and count the
    # pass's entries, so that only the gain gate can keep the frames from a second search.
    monkeypatch.setattr(hand_landmarks, "_sides", lambda per_frame: {False})
    entered = _count_pass_entries(monkeypatch)
    stretched = _hands(bright, 4.0, probe=0)  # no probe: the pass's own gate is tested
    assert entered == [1]  # the pass ran ...
    assert len(calls) == 2 * n_plain  # ... and searched no frame a second time
    np.testing.assert_array_equal(stretched.present, plain.present)
    np.testing.assert_array_equal(stretched.uv, plain.uv)
    calls.clear()
    _hands(dark, 4.0)  # the dark frames are searched again (a side is missing on them)
    assert len(calls) > n_plain


def _count_pass_entries(monkeypatch) -> list[int]:
    """A list that gets one item each time ``hand_landmarks._stretched_pass`` is entered."""
    entered: list[int] = []
    real_pass = hand_landmarks._stretched_pass

    def counted_pass(*args, **kwargs):
        entered.append(1)
        return real_pass(*args, **kwargs)

    monkeypatch.setattr(hand_landmarks, "_stretched_pass", counted_pass)
    return entered


def test_a_one_hand_clip_is_probed_and_not_searched(monkeypatch) -> None:
    """DWM 00017 frames 2-7: one real hand (the left) on dim frames. The right side is
    "missing", so the stretched pass searched every frame for a hand that is not there
    (review11d: +47% detection CPU on 00017). The probe searches every second one, finds no
    right hand, and the pass does not run; the hands are those the pass gives (it adds none)."""
    pytest.importorskip("mediapipe")
    from egosim.pipeline.media import read_video_file

    folder = shared_data("dwm_realworld", "realworld_dynamic")
    frames = read_video_file(folder / "videos" / "00017.mp4")[0][2:8]  # (6, 480, 720, 3)
    assert all(stretched_frame(f, 4.0) is not None for f in frames)  # all dim
    entered = _count_pass_entries(monkeypatch)
    probed = _hands(frames, 4.0)
    assert entered == []  # the probe found nothing: no pass
    full = _hands(frames, 4.0, probe=0)
    assert entered == [1]  # without the probe the pass runs (a side is missing) ...
    np.testing.assert_array_equal(probed.present, full.present)  # ... and adds nothing
    np.testing.assert_array_equal(probed.uv, full.uv)
    assert probed.present.any() and (probed.label_right[probed.present] < 0.5).all()


def test_stretched_frame_is_stretch_contrast_on_uint8() -> None:
    rng = np.random.default_rng(1)
    # A dim frame, constant over 4x4 blocks: its every-4th-pixel sample has the same levels.
    blocks = rng.integers(20, 90, (30, 40, 3)).astype(np.uint8)
    frame = np.repeat(np.repeat(blocks, 4, axis=0), 4, axis=1)  # (120, 160, 3)
    expected = stretch_contrast(frame / 255.0, 4.0)  # float in [0, 1]
    got = stretched_frame(frame, 4.0)
    assert got is not None and got.dtype == np.uint8
    assert np.abs(got / 255.0 - expected).max() <= 1.0 / 255.0  # rounding only
    assert got.max() > 200 and got.min() < 50  # the 20..90 range spread out
    wide = rng.integers(0, 256, (120, 160, 3)).astype(np.uint8)  # full range: left alone
    assert stretched_frame(wide, 4.0) is None
