"""The arm's colour region in dim frames (hand_mask v25, issue 9): ``arm_region.lift_dark``."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from egosim.pipeline.stage import ConfigError
from egosim.stages.hand_mask.arm_region import (
    ArmParams,
    hand_arm_mask,
    lift_dark,
    quartile_lightness,
)
from egosim.stages.hand_mask.capsules import CapsuleParams
from egosim.stages.hand_mask.stage import HandMaskConfig


def _hand_pointing_up() -> np.ndarray:
    """Keypoints ``(21, 2)`` of a hand whose fingers point up from a wrist at (80.5, 70.5)."""
    kp = np.full((21, 2), np.nan)
    kp[0] = [80.5, 70.5]
    for j, x in zip((5, 9, 13, 17), (74.5, 79.5, 84.5, 89.5), strict=True):
        kp[j] = [x, 45.5]
        kp[j + 1 : j + 4] = [[x, 45.5 - 6 * i] for i in (1, 2, 3)]
    kp[1:5] = [[72.5, 66.5 - 5 * i] for i in range(4)]
    return kp


def _dim_sleeve_and_shadow(gain: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(image (120, 160, 3), sleeve (H, W) bool, shadow (H, W) bool)``: a navy sleeve from
    the wrist down to the bottom border, and beside it a shadow that runs from the sleeve
    down-right to the bottom border, on a light floor; the scene's light levels times
    ``gain``, then a gamma of 1.4, as the rehearsal's dim copies (a small gain crushes the
    sleeve and the shadow within 18 Lab of each other; the shadow part returned is the part
    away from the sleeve)."""
    h, w = 120, 160
    rng = np.random.default_rng(0)
    scene = np.full((h, w, 3), (230, 225, 215), np.float64)  # light floor
    shadow_poly = np.array([[88, 76], [150, 112], [150, 120], [118, 120], [88, 100]], np.int32)
    shadow = np.zeros((h, w), np.uint8)
    cv2.fillPoly(shadow, [shadow_poly], 1)  # from the sleeve down-right to the bottom border
    scene[shadow > 0] = (95, 95, 100)
    scene[70:, 70:91] = (20, 25, 60)  # navy sleeve from the wrist to the bottom border
    scene[35:72, 68:95] = (200, 160, 140)  # the hand's skin
    scene = np.clip(scene + rng.normal(0, 3, scene.shape), 0, 255)
    image = 255.0 * (np.clip(scene * gain, 0, 255) / 255.0) ** 1.4
    sleeve = np.zeros((h, w), bool)
    sleeve[75:, 73:88] = True
    inner = cv2.erode(shadow, np.ones((5, 5), np.uint8)) > 0  # (H, W) off its edges
    inner[:, :95] = False  # the part away from the sleeve
    return np.round(image).astype(np.uint8), sleeve, inner


def test_lift_dark_lifts_a_dim_frame_to_the_floor_and_leaves_a_lit_one() -> None:
    """A dim frame's upper-quartile lightness is lifted to the floor (not past it by more than
    the bisection's step); a frame already that bright, a black one and floor 0 come back as
    they are (the same array)."""
    dim, _, _ = _dim_sleeve_and_shadow(0.25)
    assert quartile_lightness(dim) < 40.0
    lifted = lift_dark(dim, 70.0)
    assert 70.0 <= quartile_lightness(lifted) <= 74.0, quartile_lightness(lifted)
    assert np.all(lifted >= dim)  # a gamma below 1 only brightens
    lit, _, _ = _dim_sleeve_and_shadow(1.0)
    assert quartile_lightness(lit) >= 70.0
    assert lift_dark(lit, 70.0) is lit
    assert lift_dark(dim, 0.0) is dim
    black = np.zeros_like(dim)
    assert lift_dark(black, 70.0) is black


def test_dim_shadow_beside_a_sleeve_is_not_taken_for_the_arm() -> None:
    """Rehearsal copy 50013 t=28 in small: in a dim frame the shadow beside a navy sleeve lies
    within the walk's 18 Lab of the sleeve, so the sleeve's colour region runs along the shadow
    to the border and the arm is re-aimed there. Read from the lifted frame (``dark_floor``),
    the region stays on the sleeve; the same scene well lit is masked alike either way."""
    kp = _hand_pointing_up()[None]  # (1, 21, 2)
    one = np.array([True])
    image, sleeve, shadow = _dim_sleeve_and_shadow(0.25)
    masks = {
        floor: hand_arm_mask(image, kp, one, CapsuleParams(), ArmParams(dark_floor=floor)) > 0
        for floor in (0.0, 70.0)
    }
    assert masks[0.0][shadow].mean() > 0.5, f"unlifted: shadow {masks[0.0][shadow].mean():.2f}"
    assert masks[70.0][shadow].mean() < 0.05, f"lifted: shadow {masks[70.0][shadow].mean():.2f}"
    assert masks[70.0][sleeve].mean() > 0.9, f"lifted: sleeve {masks[70.0][sleeve].mean():.2f}"
    lit, _, _ = _dim_sleeve_and_shadow(1.0)
    a, b = (
        hand_arm_mask(lit, kp, one, CapsuleParams(), ArmParams(dark_floor=floor))
        for floor in (0.0, 70.0)
    )
    assert np.array_equal(a, b)


def test_dark_floor_is_range_checked() -> None:
    """``dark_floor`` out of [0, 255] is refused by both configs, quoting the value."""
    with pytest.raises(ConfigError, match="dark_floor must be in \\[0, 255\\], got -1"):
        HandMaskConfig(dark_floor=-1.0)
    with pytest.raises(ValueError, match="dark_floor must be in \\[0, 255\\], got 300"):
        ArmParams(dark_floor=300.0)


def test_quartile_lightness_ignores_a_black_border() -> None:
    """A lit picture in a black letterbox keeps its upper-quartile lightness where the median
    falls (HOT3D: median 14-52, upper quartile 60-102): the floor does not lift it."""
    image = np.zeros((100, 100, 3), np.uint8)
    image[:, 40:] = 150  # 60% lit, 40% black bars
    lab_l = cv2.cvtColor(image, cv2.COLOR_RGB2LAB)[..., 0]
    assert quartile_lightness(image) == pytest.approx(float(np.percentile(lab_l, 75)))
    assert quartile_lightness(image) > 70.0
    assert lift_dark(image, 70.0) is image
