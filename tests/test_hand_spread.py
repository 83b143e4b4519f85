"""Hands v15: the landmark model's spread over turned, scaled and mirrored ROIs of a small hand,
and the 3D withheld where it is large (``roi_landmarks.landmark_spread``,
``mediapipe_backend.spread_outliers``; docs/design.md "Hands v15: small hands")."""

from __future__ import annotations

import json
from dataclasses import replace

import cv2
import numpy as np
import pytest

from egosim.stages.common.roi_landmarks import INPUT_SIZE, Roi, roi_from_landmarks
from egosim.stages.hands.mediapipe_backend import MediaPipeParams
from tests.conftest import shared_data


def test_a_turned_roi_keeps_its_centre_and_turns_its_crop() -> None:
    """A quarter turn takes an upright ROI's up direction to the image's +u (clockwise as seen,
    v pointing down); the crop's centre stays on the ROI's centre and its corners on a square of
    the scaled side."""
    roi = Roi(centre=np.array([300.0, 200.0]), side=100.0, up=np.array([0.0, -1.0]))
    turned = roi.turned(90.0, 1.25)
    np.testing.assert_allclose(turned.up, [1.0, 0.0], atol=1e-12)
    assert turned.side == pytest.approx(125.0)
    m = turned.frame_from_crop()  # (2, 3)
    centre = m[:, :2] @ np.array([INPUT_SIZE / 2, INPUT_SIZE / 2]) + m[:, 2]
    np.testing.assert_allclose(centre, roi.centre, atol=1e-9)
    top_left = m[:, 2]  # crop (0, 0): up is +u, so the crop's top-left lies right and above
    np.testing.assert_allclose(top_left, roi.centre + np.array([62.5, -62.5]), atol=1e-9)
    # turning back undoes it
    np.testing.assert_allclose(turned.turned(-90.0).up, roi.up, atol=1e-12)


def test_spread_settings_are_checked() -> None:
    with pytest.raises(ValueError, match="max_spread must be > 0, got 0"):
        MediaPipeParams(max_spread=0.0)
    with pytest.raises(ValueError, match=r"spread_max_size must be >= 0 \(of the frame height\)"):
        MediaPipeParams(spread_max_size=-1.0)


def test_the_size_gate_is_a_share_of_the_frame_height(model, monkeypatch) -> None:
    """The size under which a hand is read again is 40 px at 480 rows and scales with the frame
    (review11a: a 40 px gate in pixels tested 79% of DWM 00013's hand-frames when kept at 240
    rows): a 30 px hand is read again at 480 rows, not at 240 (where the gate is 20 px)."""
    from egosim.stages.hands.mediapipe_backend import spread_outliers

    assert MediaPipeParams().spread_max_size * 480 == 40.0
    runs = _count_model_runs(monkeypatch)
    for height, expected in ((480, 4), (240, 0), (960, 4)):
        runs.clear()
        frames, lm = _hand_on_canvas(30.0, height)
        spread_outliers(frames, lm, MediaPipeParams(), lm.present)
        assert len(runs) == expected, (height, len(runs))


@pytest.fixture
def model() -> object:
    """The landmark model on a TFLite runtime, or a skip without one."""
    pytest.importorskip("mediapipe")
    pytest.importorskip("ai_edge_litert")
    from egosim.stages.common.roi_landmarks import LandmarkModel

    return LandmarkModel(1)


def _freihand_hand() -> tuple[np.ndarray, np.ndarray]:
    """The first FreiHAND fixture image ``(224, 224, 3)`` RGB and its true 2D joints (21, 2)."""
    folder = shared_data("freihand_fixture")
    data = json.loads((folder / "test_freihand.json").read_text())
    image = data["images"][0]
    ann = next(a for a in data["annotations"] if a["image_id"] == image["id"])
    rgb = np.ascontiguousarray(cv2.imread(str(folder / image["file_name"]))[:, :, ::-1])
    return rgb, np.array(ann["keypoints"], dtype=np.float64).reshape(21, 3)[:, :2]


def test_a_mirrored_crop_is_mirrored_back(model) -> None:
    """The model on the mirrored crop of a clear real hand gives, mirrored back, the landmarks and
    the side it gives on the crop as it is (a mirror left unmapped would put the thumb where the
    pinky is: 0.68 of the hand's size off)."""
    rgb, truth = _freihand_hand()
    roi = roi_from_landmarks(truth)
    plain = model.run(rgb, roi)
    mirrored = model.run(rgb, roi, mirror=True)
    size = float(np.linalg.norm(plain.uv[9] - plain.uv[0]))
    assert plain.presence > 0.9 and mirrored.presence > 0.9
    off = np.linalg.norm(mirrored.uv - plain.uv, axis=1) / size  # (21,)
    assert np.median(off) < 0.1, off
    assert (plain.right > 0.5) == (mirrored.right > 0.5), (plain.right, mirrored.right)
    # the world landmarks come back in the same axes too (x flipped back)
    turn = np.linalg.norm(mirrored.world - plain.world, axis=1).mean()
    assert turn < 0.015, turn  # metres, hand about 0.18 m long


def test_a_clear_hand_reads_steadily(model) -> None:
    """A clear, large real hand: the answers over the turned, scaled and mirrored crops agree
    (spread 0.018 measured with the four answers, 0.023 with hands14's six; the 3D is withheld
    above 0.05)."""
    from egosim.stages.common.roi_landmarks import landmark_spread

    rgb, truth = _freihand_hand()
    assert landmark_spread(model, rgb, truth) < 0.5 * MediaPipeParams().max_spread


def _hand_on_canvas(size_px: float, height: int, hand: bool = True) -> tuple[np.ndarray, object]:
    """One frame ``(1, height, 4/3 height, 3)``, grey, with the FreiHAND fixture hand scaled to
    ``size_px`` from wrist to middle knuckle pasted in (``hand=False``: left out, a blank
    canvas), and its true landmarks as the left hand's smoothed landmarks (the right absent)."""
    from egosim.stages.hands.mediapipe_backend import SideLandmarks

    rgb, truth = _freihand_hand()
    k = size_px / float(np.linalg.norm(truth[9] - truth[0]))
    small = cv2.resize(rgb, None, fx=k, fy=k, interpolation=cv2.INTER_AREA)
    canvas = np.full((height, height * 4 // 3, 3), 128, dtype=np.uint8)
    y0, x0 = height // 2 - small.shape[0] // 2, height * 2 // 3 - small.shape[1] // 2
    if hand:
        canvas[y0 : y0 + small.shape[0], x0 : x0 + small.shape[1]] = small
    uv = np.full((1, 2, 21, 2), np.nan)  # (T, 2, 21, 2) frame pixels
    uv[0, 0] = truth * (np.array(small.shape[1::-1]) / rgb.shape[1::-1]) + [x0, y0]
    present = np.array([[True, False]])  # (T, 2)
    lm = SideLandmarks(uv, np.zeros((1, 2, 21, 3)), present * 0.9, present, present.copy())
    return canvas[None], lm


def _count_model_runs(monkeypatch) -> list[tuple[object, bool]]:
    """A list that grows by one ``(roi, mirror)`` at every run of the landmark model."""
    from egosim.stages.common.roi_landmarks import LandmarkModel

    runs: list[tuple[object, bool]] = []
    run = LandmarkModel.run

    def counted(self, frame, roi, max_gain=1.0, mirror=False):
        runs.append((roi, mirror))
        return run(self, frame, roi, max_gain, mirror)

    monkeypatch.setattr(LandmarkModel, "run", counted)
    return runs


def test_only_valid_hand_frames_are_read_again(model, monkeypatch) -> None:
    """A small hand present but not valid (its lift gave no joints) is not read again: its 3D is
    withheld anyway, and the model runs per hand-frame are the rule's cost (review11a). A valid
    one is read four times, on the ROIs hands17 kept: as it is, turned +20 degrees, scaled 1.25
    and mirrored (hands14's six had -20 degrees and 0.8 too)."""
    from egosim.stages.hands.mediapipe_backend import spread_outliers

    frames, lm = _hand_on_canvas(30.0, 480)
    runs = _count_model_runs(monkeypatch)
    out = spread_outliers(frames, lm, MediaPipeParams(), np.zeros_like(lm.present))
    assert not out.any() and len(runs) == 0
    out = spread_outliers(frames, lm, MediaPipeParams(), lm.present)
    assert not out.any() and len(runs) == 4  # read, and steady (spread 0.019 measured)
    roi = roi_from_landmarks(lm.uv[0, 0])
    expected = [(roi, False), (roi.turned(20.0), False), (roi.turned(0.0, 1.25), False)]
    expected.append((roi, True))
    for (got, mirror), (want, want_mirror) in zip(runs, expected, strict=True):
        assert mirror == want_mirror
        np.testing.assert_allclose(got.centre, want.centre, atol=1e-9)
        np.testing.assert_allclose(got.up, want.up, atol=1e-9)
        assert got.side == pytest.approx(want.side)


def test_the_gate_reads_small_hands_only_and_flags_an_unsteady_one(model, monkeypatch) -> None:
    """At 480 rows a 60 px hand is not read again and a 30 px one is (four model runs); a clear
    30 px hand reads steadily (spread 0.019 measured), its landmarks on a blank canvas do not
    (nothing there to read: 0.062 over max_spread 0.05; hands14's six answers: 0.079 over 0.06)
    and are flagged; max_spread inf or spread_max_size 0 read
    nothing (review11a finding 5: no fast test ran the gate)."""
    from egosim.stages.hands.mediapipe_backend import spread_outliers

    params = MediaPipeParams()
    runs = _count_model_runs(monkeypatch)
    frames, lm = _hand_on_canvas(60.0, 480)
    assert not spread_outliers(frames, lm, params, lm.present).any()
    assert len(runs) == 0
    frames, lm = _hand_on_canvas(30.0, 480)
    assert not spread_outliers(frames, lm, params, lm.present).any()
    assert len(runs) == 4
    blank, lm = _hand_on_canvas(30.0, 480, hand=False)
    runs.clear()
    flagged = spread_outliers(blank, lm, params, lm.present)  # (T, 2)
    assert flagged.tolist() == [[True, False]] and len(runs) == 4
    for off in (replace(params, max_spread=np.inf), replace(params, spread_max_size=0.0)):
        runs.clear()
        assert not spread_outliers(blank, lm, off, lm.present).any()
        assert len(runs) == 0


@pytest.mark.slow
def test_unsteady_small_hands_lose_their_3d_against_truth(model) -> None:
    """The tuned synthetic world's seed 1 (tabletop): its right hand behind a cylinder (frames
    32-47, 2D 39-57 px off) is lifted with its palm flipped, 104-125 degrees off. With the spread
    test (hands v15) the palm-PnP hands that keep their 3D are measured against the true joints:
    v14 28.3 degrees / 43.0 mm at 3D coverage 0.746, v15 17.5 / 32.2 at 0.664."""
    from egosim.stages.hands.mediapipe_backend import detect_landmarks, hands_from_raw
    from egosim.world.clip import render_clip
    from egosim.world.config import WorldConfig
    from tests.test_hands_mediapipe import clip_accuracy

    clip = render_clip(WorldConfig(seed=1, mode="tabletop"))
    params = MediaPipeParams()
    raw = detect_landmarks(clip.frames, params)
    figures = {}
    for name, p in (("v15", params), ("v14", replace(params, max_spread=np.inf))):
        res = hands_from_raw(
            raw, clip.width, clip.intrinsics, None, None, p, fps=clip.fps, frames=clip.frames
        )
        figures[name] = clip_accuracy(res, clip, lifted=res.lifted)
    new, old = figures["v15"], figures["v14"]
    assert new["recall"] == old["recall"]  # the 2D stays: only the 3D is withheld
    assert new["orientation_deg"] <= 20.0 and new["mpjpe_mm"] <= 36.0, new
    assert new["coverage_3d"] >= 0.6, new  # a coverage loss, bounded
    assert old["orientation_deg"] > 25.0 and old["mpjpe_mm"] > 40.0, old  # what v14 gave
