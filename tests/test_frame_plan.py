"""Frame folders keep time order whatever their names (stages.common.frame_plan.frame_files)."""

from __future__ import annotations

from pathlib import Path

from egosim.stages.common.frame_plan import frame_files


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
