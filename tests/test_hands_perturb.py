"""``bench.hands_real.perturb_clip``: the DWM clips made darker, blurred, smaller, slower or
JPEG-coded, with their truth (hand renders, render gaps) still aligned frame by frame."""

from __future__ import annotations

import numpy as np
import pytest

from bench.hands_real import PERTURB_KEYS, PERTURBATIONS, perturb_clip


def _clip(t: int = 6) -> tuple[np.ndarray, np.ndarray]:
    """``(frames, render)`` ``(t, 480, 720, 3)`` (DWM's size): random frames; pixel (0, 0) of
    frame f and of render f are both f + 10."""
    rng = np.random.default_rng(0)
    frames = rng.integers(0, 256, (t, 480, 720, 3), dtype=np.uint8)
    frames[:, 0, 0] = np.arange(t)[:, None] + 10  # a frame's own mark
    render = np.zeros((t, 480, 720, 3), np.uint8)
    render[:, 0, 0] = np.arange(t)[:, None] + 10
    return frames, render


def test_every_perturbation_keeps_the_truth_aligned() -> None:
    frames, render = _clip()
    for name in PERTURBATIONS:
        out, truth, gaps, fps = perturb_clip(frames, render, (1, 2, 4), name)
        assert out.shape[1:] == frames.shape[1:] and out.dtype == np.uint8, name
        assert len(out) == len(truth), name
        if name == "4fps":
            np.testing.assert_array_equal(out, frames[::2])  # frames 0, 2, 4
            np.testing.assert_array_equal(truth[:, 0, 0, 0], [10, 12, 14])  # their own renders
            assert gaps == (1, 2) and fps == 4.0  # gap frames 2 and 4 are now 1 and 2
        elif name == "mirror":
            np.testing.assert_array_equal(out, frames[:, :, ::-1])
            np.testing.assert_array_equal(truth[:, 0, -1, 1], np.arange(6) + 10)  # G <- R
            assert gaps == (1, 2, 4) and fps == 8.0
        else:
            np.testing.assert_array_equal(truth, render)
            assert gaps == (1, 2, 4) and fps == 8.0
            assert not np.array_equal(out, frames), name  # it did something


def test_darkening_values() -> None:
    frames = np.array([0, 1, 3, 128, 255], np.uint8).reshape(1, 1, 5, 1).repeat(3, axis=3)
    dark = perturb_clip(frames, frames, (), "dark")[0][0, 0, :, 0]
    np.testing.assert_array_equal(dark, [0, 0, 2, 64, 128])  # x 0.5, rounded half to even
    gamma = perturb_clip(frames, frames, (), "gamma")[0][0, 0, :, 0]
    # 255 (x / 255) ** 1.8: 128 -> 74.5 -> 74; 255 stays, 0 stays
    np.testing.assert_array_equal(gamma, [0, 0, 0, 74, 255])


def test_360p_loses_fine_detail_and_keeps_smooth_shading() -> None:
    h, w = 480, 720
    ramp = np.repeat(np.linspace(0, 255, w)[None, :, None], h, axis=0)  # (H, W, 1)
    smooth = np.repeat(ramp, 3, axis=2).astype(np.uint8)[None]
    out = perturb_clip(smooth, smooth, (), "360p")[0]
    assert np.abs(out.astype(int) - smooth).max() <= 2  # a ramp survives 360p
    checker = ((np.indices((h, w)).sum(axis=0) % 2) * 255).astype(np.uint8)  # 1 px checks
    fine = np.repeat(checker[..., None], 3, axis=2)[None]
    out = perturb_clip(fine, fine, (), "360p")[0]
    assert out.std() < 0.2 * fine.std()  # mostly grey: the checks are gone


def test_blur_is_horizontal() -> None:
    frame = np.zeros((1, 40, 60, 3), np.uint8)
    frame[0, 20, 30] = 255
    out = perturb_clip(frame, frame, (), "blur")[0][0, ..., 0]
    rows, cols = np.nonzero(out)
    assert set(rows) == {20} and cols.min() == 23 and cols.max() == 37  # 15 px line


def test_mirror_makes_the_left_hand_a_right_hand() -> None:
    """Mirrored, a green (left) hand rendered on the image's left is a red (right) hand on its
    right, where the flipped frame shows it; the frames' colours are kept."""
    frames = np.zeros((1, 4, 10, 3), np.uint8)
    frames[0, 1, 2] = (200, 150, 100)  # a skin pixel at u = 2
    render = np.zeros((1, 4, 10, 3), np.uint8)
    render[0, 1, 2] = (0, 255, 0)  # the left hand's green at u = 2
    out, truth, _, _ = perturb_clip(frames, render, (), "mirror")
    np.testing.assert_array_equal(out[0, 1, 7], (200, 150, 100))  # now at u = 7
    np.testing.assert_array_equal(truth[0, 1, 7], (255, 0, 0))  # red: a right hand
    assert not truth[0, 1, 2].any()


def test_unknown_perturbation_is_named() -> None:
    frames, render = _clip()
    with pytest.raises(ValueError, match="unknown perturbation 'fog'"):
        perturb_clip(frames, render, (), "fog")


def test_the_perturbation_table_shows_each_sides_3d_coverage() -> None:
    """The share of shown hand-frames found with their 3D kept is in the table, so a perturbed
    clip's loss to the withheld-3D rules (turn test, spread test) can be read there (review11a)."""
    assert {"left_coverage_3d", "right_coverage_3d"} <= set(PERTURB_KEYS)
    assert {"left_recall", "right_recall"} <= set(PERTURB_KEYS)


def test_the_dwm_clips_with_hand_renders_are_found_in_the_data_folder(tmp_path, capsys) -> None:
    """``bench.hands_real`` measures every DWM dynamic clip the data folder holds with its hand
    renders (found by ``bench.real_clips``, not a list of ids); one without renders is named and
    left out, and a clip missing from ``RENDER_GAPS`` gets no gap frames, with a printed note."""
    from bench.hands_real import RENDER_GAPS, truth_clips
    from bench.real_clips import table_entry

    dyn = tmp_path / "dwm_realworld" / "realworld_dynamic"
    (dyn / "videos").mkdir(parents=True)
    (dyn / "videos_hands").mkdir()
    for clip in ("00013", "00099", "00100"):
        (dyn / "videos" / f"{clip}.mp4").write_bytes(b"")
    for clip in ("00013", "00099"):
        (dyn / "videos_hands" / f"{clip}.mp4").write_bytes(b"")
    found = truth_clips(tmp_path)
    assert [(v.name, r.parent.name) for v, r in found] == [
        ("00013.mp4", "videos_hands"),
        ("00099.mp4", "videos_hands"),
    ]
    assert "00100 has no hand renders" in capsys.readouterr().out
    assert table_entry(RENDER_GAPS, "00099", (), "RENDER_GAPS") == ()
    assert "RENDER_GAPS has no entry for '00099'" in capsys.readouterr().out


def test_real_part_skips_a_data_folder_without_interhand(tmp_path, capsys) -> None:
    """A kept-aside data folder may hold only DWM clips: the InterHand part says it is skipped
    instead of crashing (FileNotFoundError before)."""
    from bench.hands_real import main

    main(["--skip-synthetic", "--data", str(tmp_path)])
    assert "InterHand: no fixture" in capsys.readouterr().out
