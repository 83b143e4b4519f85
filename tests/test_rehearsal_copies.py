"""bench.rehearsal_copies: transformed twins of DWM clips whose truth still lines up."""

from __future__ import annotations

import json
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
    # the index names each copy's source frames
    assert real_clips.rehearsal_source(out / real_clips.DWM_DYNAMIC, "70042") == (
        "00042",
        tuple(range(FIRST_HAND, T)),
    )
    assert real_clips.rehearsal_source(out / real_clips.DWM_DYNAMIC, "80042")[1] == tuple(
        range(T - 1, -1, -1)
    )
    assert real_clips.rehearsal_source(out / real_clips.DWM_DYNAMIC, "00042") is None
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


def test_a_second_run_keeps_the_first_runs_index_entries(tmp_path: Path) -> None:
    data, out = tmp_path / "data", tmp_path / "out"
    _clip(data)
    assert rehearsal_copies.main(["--data", str(data), "--out", str(out), "--kinds", "mirror"]) == 0
    assert (
        rehearsal_copies.main(["--data", str(data), "--out", str(out), "--kinds", "reverse"]) == 0
    )
    root = out / real_clips.DWM_DYNAMIC
    assert real_clips.rehearsal_source(root, "90042") == ("00042", tuple(range(T)))
    assert real_clips.rehearsal_source(root, "80042") is not None


def test_a_broken_rehearsal_index_is_a_clear_error(tmp_path: Path) -> None:
    (tmp_path / real_clips.REHEARSAL_INDEX).write_text('{"70042": {"source": "00042"}}')
    with pytest.raises(ValueError, match="70042"):
        real_clips.rehearsal_source(tmp_path, "70042")
    assert real_clips.rehearsal_source(tmp_path, "60042") is None
    (tmp_path / real_clips.REHEARSAL_INDEX).write_text("not json")
    with pytest.raises(ValueError, match=r"rehearsal\.json"):
        real_clips.rehearsal_source(tmp_path, "70042")


def test_render_gaps_of_a_copy_are_its_sources_at_the_copys_frames(tmp_path: Path) -> None:
    from bench.hands_real import RENDER_GAPS, render_gaps

    root = tmp_path / real_clips.DWM_DYNAMIC
    (root / "videos").mkdir(parents=True)
    index = {
        "70013": {"source": "00013", "frames": list(range(8, 49))},  # window from frame 8
        "80013": {"source": "00013", "frames": list(range(48, -1, -1))},  # reversed
    }
    (root / real_clips.REHEARSAL_INDEX).write_text(json.dumps(index))
    gaps = RENDER_GAPS["00013"]  # (7, 8, 21, 22, 35)
    assert render_gaps(root / "videos" / "70013.mp4") == tuple(f - 8 for f in gaps if f >= 8)
    assert render_gaps(root / "videos" / "80013.mp4") == tuple(sorted(48 - f for f in gaps))
    assert render_gaps(root / "videos" / "00013.mp4") == gaps
    assert render_gaps(root / "videos" / "12345.mp4") == ()
