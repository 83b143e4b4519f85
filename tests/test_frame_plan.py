"""Frame folders keep time order whatever their names (stages.common.frame_plan.frame_files);
the crop window's anchor and the recorded crop (plan_resize, plan_from_crop)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from egosim.stages.common.frame_plan import CropError, frame_files, plan_from_crop, plan_resize


def _touch(folder: Path, names: list[str]) -> None:
    for name in names:
        (folder / name).write_bytes(b"")


def test_unpadded_numbers_sort_as_numbers(tmp_path: Path):
    """ffmpeg's ``%d.jpg`` writes 1.jpg .. 12.jpg: a plain sort gave 1, 10, 11, 12, 2, ..."""
    _touch(tmp_path, [f"{k}.jpg" for k in range(1, 13)] + ["notes.txt"])
    assert [p.name for p in frame_files(tmp_path)] == [f"{k}.jpg" for k in range(1, 13)]


def test_prefixed_and_padded_names_keep_their_order(tmp_path: Path):
    names = [f"frame_{k:010d}.JPG" for k in (80, 85, 90, 100, 105)]  # EPIC-KITCHENS style
    _touch(tmp_path, list(reversed(names)))
    assert [p.name for p in frame_files(tmp_path)] == names
    mixed = tmp_path / "mixed"
    mixed.mkdir()
    _touch(mixed, ["img9.png", "img10.png", "img9b.png", "IMG11.png"])
    assert [p.name for p in frame_files(mixed)] == [
        "img9.png",
        "img9b.png",
        "img10.png",
        "IMG11.png",
    ]


def test_digit_like_characters_in_names_do_not_break_the_listing(tmp_path: Path):
    """``str.isdigit`` is true of ``²`` but ``int`` refuses it; such a name is text, not a crash."""
    _touch(tmp_path, ["2.jpg", "1²2.jpg", "10.jpg", "1.jpg"])
    assert [p.name for p in frame_files(tmp_path)] == ["1.jpg", "1²2.jpg", "2.jpg", "10.jpg"]


def test_the_default_anchor_is_the_centre_crop() -> None:
    """(0.5, 0.5) gives ``(scaled - size) // 2`` on both axes for any sizes: the outputs of
    every source without an anchor are those of the centre crop."""
    rng = np.random.default_rng(0)
    for _ in range(500):
        sw, sh = (int(v) for v in rng.integers(32, 4000, 2))
        w, h = (int(v) for v in rng.integers(16, 1000, 2))
        plan = plan_resize(sw, sh, w, h)
        assert plan.crop_x == (plan.scaled_width - w) // 2
        assert plan.crop_y == (plan.scaled_height - h) // 2
    low = plan_resize(1080, 1920, 832, 480, (0.5, 1.0))
    assert (low.crop_x, low.crop_y) == (0, low.scaled_height - 480)
    assert plan_resize(1080, 1920, 832, 480, (0.0, 0.0)).crop_y == 0
    with pytest.raises(CropError, match=r"two fractions in \[0, 1\], got \(0.5, 1.2\)"):
        plan_resize(1080, 1920, 832, 480, (0.5, 1.2))


def test_recorded_crop_rebuilds_the_plan() -> None:
    for src, dst, anchor in [
        ((1080, 1920), (832, 480), (0.5, 0.83)),
        ((426, 610), (832, 480), (0.5, 1.0)),
        ((1440, 1080), (832, 480), (0.5, 0.2)),
        ((1920, 1080), (832, 480), (0.0, 0.5)),
        ((640, 480), (640, 480), (0.5, 0.5)),
    ]:
        plan = plan_resize(*src, *dst, anchor)
        again = plan_from_crop(*src, *dst, plan.source_crop)
        assert again == plan
    assert plan_from_crop(1080, 1920, 832, 480, None) == plan_resize(1080, 1920, 832, 480)
    x0, _, x1, y1 = plan_resize(1080, 1920, 832, 480, (0.5, 1.0)).source_crop
    assert (x0, x1, y1) == (0.0, 1080.0, pytest.approx(1920.0))
    with pytest.raises(CropError, match="is not a 832x480 window"):
        plan_from_crop(1080, 1920, 832, 480, (0, 0, 1080, 1000))  # not 480 rows tall
    with pytest.raises(CropError, match="is not a 832x480 window"):
        plan_from_crop(720, 1280, 832, 480, (0, 0, 1080, 623.1))  # another source size
