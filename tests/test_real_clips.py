"""Discovery of the real clips under a data folder (bench.real_clips), on a made-up layout."""

from __future__ import annotations

from pathlib import Path

import pytest

from bench import real_clips
from bench.real_clips import (
    DwmDynamicClip,
    dwm_dynamic_clips,
    dwm_dynamic_ids,
    dwm_fixed_videos,
    egodex_videos,
    hot3d_videos,
    table_entry,
)

DYN = "dwm_realworld/realworld_dynamic"


def _touch(root: Path, *paths: str) -> None:
    for rel in paths:
        path = root / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(b"")


@pytest.fixture
def data(tmp_path: Path) -> Path:
    """A data folder in the shared layout: clips with all, some and no twins, plus clutter."""
    _touch(
        tmp_path,
        # 00017 (listed before 00013 on purpose: the result is sorted) has every twin
        f"{DYN}/videos/00017.mp4",
        f"{DYN}/videos_hands/00017.mp4",
        f"{DYN}/videos_static/00017.mp4",
        f"{DYN}/prompts_rewrite/00017.txt",
        f"{DYN}/videos/00013.mp4",
        f"{DYN}/videos_hands/00013.mp4",
        f"{DYN}/videos_static/00013.mp4",
        # 90013: hands only; 80013: static only; 70013: no twin at all
        f"{DYN}/videos/90013.mp4",
        f"{DYN}/videos_hands/90013.mp4",
        f"{DYN}/videos/80013.mp4",
        f"{DYN}/videos_static/80013.mp4",
        f"{DYN}/videos/70013.mp4",
        # clutter: not clips
        f"{DYN}/videos/notes.txt",
        f"{DYN}/videos/00013.json",
        f"{DYN}/videos/._00013.mp4",
        f"{DYN}/videos_hands/55555.mp4",  # a twin with no clip
        f"{DYN}/videos_static/70013.txt",  # not a video twin
        "dwm_realworld/realworld_fixed/pour_coke.mp4",
        "dwm_realworld/realworld_fixed/lift_tumbler.mp4",
        "dwm_realworld/realworld_fixed/README.md",
        "egodex_sample/sample.mp4",
        "egodex_sample/other.MP4",
        "hot3d_video/ego_centric_aria.mp4",
        "hot3d_video/ego_centric_aria.vrs",
    )
    (tmp_path / DYN / "videos" / "sub.mp4").mkdir()  # a folder named like a clip
    return tmp_path


def test_dwm_dynamic_ids_are_every_video_sorted(data: Path) -> None:
    assert dwm_dynamic_ids(data) == ["00013", "00017", "70013", "80013", "90013"]


def test_dwm_dynamic_clips_name_the_twins_that_exist(data: Path) -> None:
    clips = {c.clip_id: c for c in dwm_dynamic_clips(data)}
    assert list(clips) == ["00013", "00017", "70013", "80013", "90013"]
    assert clips["00017"] == DwmDynamicClip(
        "00017",
        f"{DYN}/videos/00017.mp4",
        f"{DYN}/videos_hands/00017.mp4",
        f"{DYN}/videos_static/00017.mp4",
        f"{DYN}/prompts_rewrite/00017.txt",
    )
    assert clips["00013"].prompt == ""
    assert (clips["90013"].hands, clips["90013"].static) == (f"{DYN}/videos_hands/90013.mp4", "")
    assert (clips["80013"].hands, clips["80013"].static) == ("", f"{DYN}/videos_static/80013.mp4")
    assert (clips["70013"].hands, clips["70013"].static) == ("", "")


def test_other_layouts_list_their_videos_only(data: Path) -> None:
    assert dwm_fixed_videos(data) == [
        "dwm_realworld/realworld_fixed/lift_tumbler.mp4",
        "dwm_realworld/realworld_fixed/pour_coke.mp4",
    ]
    assert egodex_videos(data) == ["egodex_sample/other.MP4", "egodex_sample/sample.mp4"]
    assert hot3d_videos(data) == ["hot3d_video/ego_centric_aria.mp4"]


def test_a_missing_layout_lists_nothing(tmp_path: Path) -> None:
    assert dwm_dynamic_ids(tmp_path) == []
    assert dwm_dynamic_clips(tmp_path) == []
    assert dwm_fixed_videos(tmp_path / "absent") == []
    assert egodex_videos(tmp_path) == hot3d_videos(tmp_path) == []


def test_the_shared_data_lists_the_known_clips() -> None:
    data = Path(__file__).resolve().parents[2] / "shared" / "data"
    if not (data / DYN).is_dir():
        pytest.skip("no shared data folder")
    ids = dwm_dynamic_ids(data)
    assert {"00013", "00017"} <= set(ids)
    clips = {c.clip_id: c for c in dwm_dynamic_clips(data)}
    assert all(clips[i].hands and clips[i].static for i in ("00013", "00017"))


def test_table_entry_gives_the_default_and_says_so_once(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(real_clips, "_SAID", set())
    table = {"00013": (7, 8)}
    assert table_entry(table, "00013", (), "GAPS") == (7, 8)
    assert capsys.readouterr().out == ""
    assert table_entry(table, "90013", (), "GAPS") == ()
    assert table_entry(table, "90013", (), "GAPS") == ()
    out = capsys.readouterr().out
    assert out.count("GAPS has no entry for '90013'") == 1
    assert out.count("\n") == 1
