"""The real-video bench: registering a ground-truth video to the real one, and the videos it
finds under a data folder (bench/real_video)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from bench.real_video import _shift, truth_shift


@pytest.mark.parametrize("shift", [(-5.7, -5.1), (3.25, 0.0), (0.0, 7.5)])
def test_truth_shift_finds_a_principal_point_offset(shift: tuple[float, float]) -> None:
    """A truth rendered with another principal point is the real frame translated."""
    rng = np.random.default_rng(0)
    h, w = 120, 180
    texture = cv2.GaussianBlur(
        rng.uniform(0, 255, (h + 40, w + 40, 3)).astype(np.float32), (0, 0), 2
    )
    real = texture[20 : 20 + h, 20 : 20 + w]
    m = np.float32([[1, 0, -shift[0]], [0, 1, -shift[1]]])  # the truth: real moved by -shift
    truth = cv2.warpAffine(texture, m, (w + 40, h + 40), flags=cv2.INTER_LINEAR)[
        20 : 20 + h, 20 : 20 + w
    ]
    real, truth = real.astype(np.uint8), truth.astype(np.uint8)
    dx, dy = truth_shift(real, truth)
    assert (dx, dy) == pytest.approx(shift, abs=0.15)
    # shifting the truth by what truth_shift returns registers it to the real frame
    inner = (slice(12, -12), slice(12, -12))
    before = np.abs(truth.astype(float) - real)[inner].mean()
    after = np.abs(_shift(truth, dx, dy).astype(float) - real)[inner].mean()
    assert after < 0.2 * before


def test_cases_are_every_clip_found_by_layout(tmp_path: Path) -> None:
    from bench.real_video import DWM_ARIA_FOCAL_PX, HOT3D_RGB_X, cases

    dyn = "dwm_realworld/realworld_dynamic"
    for rel in (
        f"{dyn}/videos/00013.mp4",
        f"{dyn}/videos_hands/00013.mp4",
        f"{dyn}/videos_static/00013.mp4",
        f"{dyn}/videos/90013.mp4",  # a new clip with its hands truth only
        f"{dyn}/videos_hands/90013.mp4",
        "dwm_realworld/realworld_fixed/pour_coke.mp4",
        "dwm_realworld/realworld_fixed/new_fixed.mp4",
        "egodex_sample/sample.mp4",
        "hot3d_video/ego_centric_aria.mp4",
        "hot3d_video/another.mp4",
    ):
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_bytes(b"")
    found = {c.name: c for c in cases(tmp_path)}
    assert list(found) == [
        "egodex_sample",
        "dwm_00013",
        "dwm_90013",
        "new_fixed",
        "pour_coke",
        "hot3d_rgb_another",
        "hot3d_rgb",
    ]
    assert found["dwm_00013"].static_truth == f"{dyn}/videos_static/00013.mp4"
    assert found["dwm_00013"].hands_truth == f"{dyn}/videos_hands/00013.mp4"
    new = found["dwm_90013"]
    assert (new.video, new.preset, new.true_focal_px) == (
        f"{dyn}/videos/90013.mp4",
        "dwm",
        DWM_ARIA_FOCAL_PX,
    )
    assert (new.static_truth, new.hands_truth) == ("", f"{dyn}/videos_hands/90013.mp4")
    assert found["new_fixed"].preset == "dwm" and not found["new_fixed"].static_truth
    assert found["hot3d_rgb"].crop_x == found["hot3d_rgb_another"].crop_x == HOT3D_RGB_X
    assert cases(tmp_path / "absent") == ()


def test_scene_vs_truth_is_n_a_without_both_twins(tmp_path: Path) -> None:
    from bench.real_video import RealCase, scene_vs_truth

    for static, hands in (("", "hands.mp4"), ("static.mp4", "")):  # files never opened
        case = RealCase("dwm_90013", "v.mp4", "dwm", static, hands)
        assert scene_vs_truth({"height": 4}, {"video": b""}, "90013", case, tmp_path) is None


def test_run_case_passes_set_overrides_to_the_workflow(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``--set`` reaches the workflow the case runs (after the case's preset), so a stage option
    such as ``cameras.mask_hands`` can be measured on the real clips without editing files."""
    import egosim.pipeline.runner as runner
    from bench import real_video

    seen = {}

    def fake_run(workflow, out, source, n_workers):
        seen.update({s.name: s.params for s in workflow.steps})

    monkeypatch.setattr(runner, "run_workflow", fake_run)
    from egosim.stages.depth_camera.stage import DepthCameraConfig

    default = DepthCameraConfig().mask_hands
    case = real_video.RealCase("x", "clip.mp4", "dwm")
    flip = f"cameras.mask_hands={str(not default).lower()}"
    real_video.run_case(case, tmp_path, tmp_path / "run", 1, [flip])
    assert seen["ingest"]["preset"] == "dwm"
    assert seen["cameras"]["mask_hands"] is (not default)
    real_video.run_case(case, tmp_path, tmp_path / "run", 1)
    assert seen["cameras"]["mask_hands"] is default


@pytest.mark.parametrize("width", [720, 540])
def test_dwm_true_focal_keeps_the_field_of_view_of_a_resized_copy(
    tmp_path: Path, width: int
) -> None:
    from bench.real_video import DWM_ARIA_FOCAL_PX, cases, true_focal_clip_px
    from egosim.pipeline import media

    rel = "dwm_realworld/realworld_dynamic/videos/00013.mp4"
    (tmp_path / rel).parent.mkdir(parents=True)
    frames = np.zeros((3, width * 2 // 3, width, 3), np.uint8)
    media.write_video_file(tmp_path / rel, frames, 8.0)
    (case,) = cases(tmp_path)
    # ingest's dwm preset stores 720x480: the true focal there is 300 px whatever the file's size
    clip = {"width": 720, "height": 480}
    assert true_focal_clip_px(case, tmp_path, clip) == pytest.approx(DWM_ARIA_FOCAL_PX)
    # a clip stored at half that size has half the focal
    half = {"width": 360, "height": 240}
    assert true_focal_clip_px(case, tmp_path, half) == pytest.approx(DWM_ARIA_FOCAL_PX / 2)
