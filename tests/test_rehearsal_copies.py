"""bench.rehearsal_copies: transformed twins of DWM clips whose truth still lines up."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from bench import real_clips, rehearsal_copies
from egosim.pipeline import media

T, H, W = 10, 48, 64
FIRST_HAND = 3  # the synthetic hand truth shows a hand from this frame on


def _clip(root: Path) -> None:
    """A tiny DWM clip: a gradient video, a static twin, a green left hand from FIRST_HAND."""
    dwm = root / real_clips.DWM_DYNAMIC
    ramp = np.linspace(40, 200, W, dtype=np.float32)[None, None, :, None]
    video = np.broadcast_to(
        ramp + np.arange(T, dtype=np.float32)[:, None, None, None] * 4, (T, H, W, 3)
    )
    video = video.astype(np.uint8)
    hands = np.zeros((T, H, W, 3), np.uint8)
    hands[FIRST_HAND:, 10:30, 4:24, 1] = 220  # left hand (green) at the left
    for folder, frames in (("videos", video), ("videos_static", video), ("videos_hands", hands)):
        (dwm / folder).mkdir(parents=True, exist_ok=True)
        media.write_video_file(dwm / folder / "00042.mp4", frames, 8.0, crf=0)
    (dwm / "prompts_rewrite").mkdir()
    (dwm / "prompts_rewrite" / "00042.txt").write_text("a hand\n")


def _read(root: Path, folder: str, clip_id: str) -> np.ndarray:
    return media.read_video_file(root / real_clips.DWM_DYNAMIC / folder / f"{clip_id}.mp4")[0]


def test_copies_keep_the_layout_and_their_truth_lined_up(tmp_path: Path) -> None:
    data, out = tmp_path / "data", tmp_path / "out"
    _clip(data)
    assert rehearsal_copies.main(["--data", str(data), "--out", str(out), "--crf", "0"]) == 0
    ids = real_clips.dwm_dynamic_ids(out)
    assert ids == ["40042", "50042", "60042", "70042", "80042", "90042"]
    clips = {c.clip_id: c for c in real_clips.dwm_dynamic_clips(out)}
    assert all(c.hands and c.static and c.prompt for c in clips.values())
    original = _read(data, "videos", "00042")
    hands = _read(data, "videos_hands", "00042")
    # reencode: the same pictures within a few levels
    assert np.abs(_read(out, "videos", "60042").astype(int) - original).max() <= 4
    # window: starts at the first frame with a hand, and the truth still shows it there
    window = _read(out, "videos", "70042")
    assert len(window) == T - FIRST_HAND
    assert np.abs(window[0].astype(int) - original[FIRST_HAND]).max() <= 4
    assert (_read(out, "videos_hands", "70042")[0] > 30).any()
    # reverse: last frame first
    assert np.abs(_read(out, "videos", "80042")[0].astype(int) - original[-1]).max() <= 4
    # mirror: flipped, and the left (green) hand becomes a right (red) hand on the right
    mirrored = _read(out, "videos_hands", "90042")[FIRST_HAND]
    assert mirrored[20, W - 10, 0] > 150 and mirrored[20, W - 10, 1] < 60
    assert np.abs(_read(out, "videos", "90042")[0].astype(int) - original[0, :, ::-1]).max() <= 4
    # dim: darker video and static, hand truth as it was
    assert _read(out, "videos", "50042").mean() < original.mean() - 20
    assert _read(out, "videos_static", "50042").mean() < original.mean() - 20
    dim_hands = (_read(out, "videos_hands", "50042") > 30).any(axis=-1)
    assert (dim_hands == (hands > 30).any(axis=-1)).mean() > 0.99
    # small: every twin at the same smaller size
    for folder in ("videos", "videos_hands", "videos_static"):
        assert _read(out, folder, "40042").shape[1:3] == (36, 48)


def test_first_hand_frame_counts_only_a_visible_hand() -> None:
    hands = np.zeros((4, 100, 100, 3), np.uint8)
    hands[1, 0, 0, 0] = 255  # one pixel: below MIN_HAND_FRACTION
    hands[2, :10, :10, 0] = 255
    assert rehearsal_copies.first_hand_frame(hands) == 2
    assert rehearsal_copies.first_hand_frame(np.zeros_like(hands)) == 0


def test_an_unknown_kind_is_refused(tmp_path: Path) -> None:
    with pytest.raises(SystemExit):
        rehearsal_copies.main(
            ["--data", str(tmp_path), "--out", str(tmp_path / "o"), "--kinds", "upside"]
        )
    assert rehearsal_copies.main(["--data", str(tmp_path), "--out", str(tmp_path / "o")]) == 1
