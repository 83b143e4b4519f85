"""Metric scale from hand size (``stages/depth_camera/metric_scale.py``, issue 17).

The synthetic world has metric poses, depth and hand joints. SfM's arbitrary units are simulated
by multiplying the poses' translations and the depth by a factor ``k``: the true scale is then
``1 / k`` metres per unit. Frame 0's depth is masked under the (dilated) hands, as the SfM plane
sweep leaves it.

- Oracle: the true joints projected to pixels (2D landmarks) and the true camera-frame joints
  about their centre (metric world landmarks) replace MediaPipe; this tests the geometry and the
  contact rule.
- MediaPipe (slow): the estimator end to end on a rendered clip.
"""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest

from egosim.pipeline.geometry import (
    intrinsics_from_fov,
    invert_se3,
    look_at,
    project_points,
    transform_points,
)
from egosim.pipeline.records import Clip
from egosim.stages.common.hand_landmarks import RawLandmarks, place_in_camera
from egosim.stages.common.hand_lift import PALM_JOINTS, PALM_TEMPLATE
from egosim.stages.depth_camera.metric_scale import (
    MetricScaleInputError,
    MetricScaleParams,
    MetricScaleParamsError,
    drop_depth_outliers,
    estimate_metric_scale,
    on_main_surface,
    pooled_metric_scale,
    scale_from_landmarks,
    scale_from_samples,
    splat_depth,
    surface_depth,
)
from egosim.world.clip import render_clip
from egosim.world.config import WorldConfig

ORACLE = MetricScaleParams(proximal_ratio=1.0)  # true joints: true proximal phalanges


def sfm_units(clip: Clip, factor: float) -> tuple[np.ndarray, np.ndarray]:
    """Poses ``(T, 4, 4)`` and frame-0 depth ``(H, W)`` of ``clip`` in units of ``1/factor`` m.

    Depth is 0 (unknown) under frame 0's hands, grown by 8 px.
    """
    world_from_cam = clip.world_from_cam.copy()
    world_from_cam[:, :3, 3] *= factor
    hands = cv2.dilate(clip.hand_mask[0], np.ones((17, 17), np.uint8)) > 0  # (H, W)
    depth0 = np.where(hands, 0.0, clip.depth[0].astype(np.float64)) * factor
    return world_from_cam, depth0


def oracle_landmarks(clip: Clip) -> RawLandmarks:
    """True 2D joints and true metric joints about their centre, where the hand is visible."""
    t = clip.num_frames
    uv = np.full((t, 2, 21, 2), np.nan)
    world = np.full((t, 2, 21, 3), np.nan)
    present = np.zeros((t, 2), dtype=bool)
    for f in range(t):
        cam_from_world = invert_se3(clip.world_from_cam[f])
        for h in range(2):
            points_cam = transform_points(cam_from_world, clip.hand_joints[f, h])  # (21, 3)
            if not clip.hand_valid[f, h] or (points_cam[:, 2] <= 0).any():
                continue
            uv[f, h] = project_points(points_cam, clip.intrinsics)[0]
            world[f, h] = points_cam - points_cam.mean(axis=0)
            present[f, h] = True
    return RawLandmarks(uv=uv, world=world, label_right=np.ones((t, 2)), present=present)


@pytest.fixture(scope="module")
def small_world() -> Clip:
    """A small tabletop clip (a tuning seed: tabletop 0)."""
    return render_clip(WorldConfig(seed=0, num_frames=17, height=240, width=416))


# ----------------------------------------------------------------------------- geometry


def test_place_in_camera_recovers_a_known_hand() -> None:
    k = np.array([500.0, 500.0, 320.0, 240.0])
    rng = np.random.default_rng(0)
    shape = rng.normal(0.0, 0.03, (21, 3))
    shape -= shape.mean(axis=0)
    truth = shape + np.array([0.1, -0.05, 0.6])  # (21, 3) camera metres
    uv, _ = project_points(truth, k)
    np.testing.assert_allclose(place_in_camera(uv, shape, k), truth, atol=1e-9)


def test_splat_depth_moves_a_plane_with_the_camera() -> None:
    h, w = 40, 60
    k = intrinsics_from_fov(w, h, 60.0)
    depth0 = np.full((h, w), 2.0)
    cam0 = np.eye(4)
    same, source = splat_depth(depth0, k, cam0, cam0)
    np.testing.assert_allclose(same, depth0)
    np.testing.assert_array_equal(source, np.arange(h * w).reshape(h, w))
    back = np.eye(4)
    back[2, 3] = -0.5  # camera t is 0.5 units further from the plane: it shrinks, no holes
    further, _ = splat_depth(depth0, k, cam0, back)
    centre = further[h // 2 - 5 : h // 2 + 5, w // 2 - 5 : w // 2 + 5]
    np.testing.assert_allclose(centre, 2.5)
    assert (further == 0).any()  # the border of view t sees past frame 0's field of view
    forward = np.eye(4)
    forward[2, 3] = 0.5  # nearer: the plane magnifies, splatting leaves single-pixel holes
    nearer, _ = splat_depth(depth0, k, cam0, forward)
    np.testing.assert_allclose(nearer[nearer > 0], 1.5)
    params = MetricScaleParams()
    uv = np.array([[w / 2 + 0.3, h / 2 + 0.7], [5.5, 7.5]])
    np.testing.assert_allclose(surface_depth(nearer, uv, params), 1.5)


def flat_hand_over_table(
    h: int, w: int, poses: np.ndarray, scale: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, RawLandmarks, np.ndarray, np.ndarray]:
    """A flat hand (the average palm, 10 cm across) with its joint centres 1 cm above the table
    z = 0, seen by ``poses (T, 4, 4)`` (metric, world from camera) through a 70 degree
    ``h x w`` camera. Returns (intrinsics, hand joints (21, 3) in world metres, frame 0's
    z-depth of the table (H, W) in metres, landmarks of frames 1.. as the detector gives them:
    pixels and joints about their centroid, camera frame; the poses in units of ``scale``
    metres, frames (T, H, W, 3) whose pixels all differ from frame 0's from frame 1 on: the
    hand is in front of the table wherever it is)."""
    k = intrinsics_from_fov(w, h, 70.0)
    rng = np.random.default_rng(1)
    hand = np.zeros((21, 3))
    hand[:, :2] = rng.uniform(-0.05, 0.05, (21, 2))  # flat, 10 cm across, world metres
    hand[list(PALM_JOINTS), :2] = PALM_TEMPLATE[:, :2] - [0.05, 0.0]  # the average palm
    hand[:, 2] = 0.01  # joint centres 1 cm above the table z = 0
    rays = np.concatenate(
        [(np.mgrid[0:h, 0:w][::-1].transpose(1, 2, 0) + 0.5 - k[2:]) / k[:2], np.ones((h, w, 1))],
        axis=-1,
    )  # (H, W, 3) camera rays with z = 1
    depth0_m = -poses[0, 2, 3] / (rays @ poses[0, :3, :3].T)[..., 2]  # (H, W) z-depth to z = 0
    t = len(poses)
    uv = np.full((t, 2, 21, 2), np.nan)
    world = np.full((t, 2, 21, 3), np.nan)
    present = np.zeros((t, 2), dtype=bool)
    for f in range(1, t):
        points_cam = transform_points(invert_se3(poses[f]), hand)  # (21, 3)
        uv[f, 0] = project_points(points_cam, k)[0]
        world[f, 0] = points_cam - points_cam.mean(axis=0)
        present[f, 0] = True
    units = poses.copy()
    units[:, :3, 3] /= scale
    frames = np.zeros((t, h, w, 3), np.uint8)
    frames[1:] = 200
    return k, hand, depth0_m, RawLandmarks(uv, world, np.ones((t, 2)), present), units, frames


@pytest.mark.parametrize("lift", ["palm_pnp", "translation"])
def test_hand_resting_on_a_plane_gives_the_scale(lift: str) -> None:
    """Hand-built: a flat hand 1 cm above a table (joint centres), seen from eight poses; its
    palm is the average palm the palm-PnP lift assumes."""
    h, w = 120, 160
    scale = 0.25  # metres per unit
    metric_poses = np.stack(
        [look_at([-0.35 + 0.02 * i, 0.01 * i, 0.4], [0.0, 0.0, 0.0]) for i in range(8)]
    )  # (T, 4, 4) metric
    k, _, depth0_m, lm, units, frames = flat_hand_over_table(h, w, metric_poses, scale)
    t = len(metric_poses)
    est = scale_from_landmarks(
        lm,
        frames,
        k,
        units,
        depth0_m / scale,
        None,
        MetricScaleParams(contact_offset_m=0.01, lift=lift, proximal_ratio=1.0),
    )
    assert est.scale is not None, est.reason
    # Contact offset 1 cm = the joints' height: the estimate is exact up to the ray's obliquity.
    assert est.scale == pytest.approx(scale, rel=0.02)
    assert est.num_samples == t - 1
    assert est.source == "hand_size"


# ----------------------------------------------------------------------------- rules


def test_too_few_detections_give_no_scale_with_a_reason(small_world: Clip) -> None:
    world_from_cam, depth0 = sfm_units(small_world, 2.9)
    lm = oracle_landmarks(small_world)
    lm.present[2:] = False  # at most 2 frames x 2 hands
    est = scale_from_landmarks(
        lm, small_world.frames, small_world.intrinsics, world_from_cam, depth0, None
    )
    assert est.scale is None and est.spread is None
    assert est.num_samples < MetricScaleParams().min_detections
    assert "strict window" in est.reason and "wide window" in est.reason
    assert "usable hand detections" in est.reason
    none = scale_from_landmarks(
        lm, small_world.frames, small_world.intrinsics, world_from_cam, None, None
    )
    assert none.scale is None and "depth" in none.reason


def test_inputs_that_disagree_are_named(small_world: Clip) -> None:
    world_from_cam, depth0 = sfm_units(small_world, 2.9)
    with pytest.raises(MetricScaleInputError) as err:
        scale_from_landmarks(
            oracle_landmarks(small_world),
            small_world.frames,
            small_world.intrinsics,
            world_from_cam[:-1],
            depth0[:-1],
            None,
        )
    assert "world_from_cam" in str(err.value) and "depth0" in str(err.value)


def samples_of(estimates: list[float], offset: float) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per-detection samples whose estimate (joint quantile of (z_m + offset) / z_s) is given:
    five joints each, surface depth 2 units."""
    return [(np.full(5, 2.0 * e - offset), np.full(5, 2.0)) for e in estimates]


def test_a_tail_of_misfit_detections_is_left_out() -> None:
    """Hand-built estimates: 20 contact detections near 1.0 and 10 hovering lower; 6 misfits
    (20% of the clip, more than the 0.9 quantile leaves out) sit at 1.4-2.8, as a MediaPipe
    track off any hand did on tabletop 1."""
    params = MetricScaleParams()
    rng = np.random.default_rng(4)
    contact = list(1.0 + rng.uniform(-0.02, 0.02, 20))
    hover = list(rng.uniform(0.7, 0.95, 10))
    tail = [1.4, 1.5, 1.7, 1.9, 2.3, 2.8]
    plain = dataclasses.replace(params, outlier_mads=None)  # v11: every estimate kept
    with_tail = samples_of(contact + hover + tail, params.contact_offset_m)
    assert scale_from_samples(with_tail, plain).scale > 1.35
    est = scale_from_samples(with_tail, params)
    assert est.scale == pytest.approx(1.0, abs=0.02)
    assert est.num_samples == 36  # usable detections, the left-out ones included
    clean = scale_from_samples(samples_of(contact + hover, params.contact_offset_m), params)
    assert est.scale == pytest.approx(clean.scale, abs=1e-9)
    assert est.spread == pytest.approx(clean.spread, abs=1e-9)


def test_a_wide_spread_of_hovering_hands_is_not_cut() -> None:
    """Hand-built estimates spread as on a real clip where the hands mostly reach (DWM 00013:
    0.43-1.14 and one at 1.67): the MAD is wide, so the rule is the plain contact quantile."""
    params = MetricScaleParams()
    estimates = [*np.linspace(0.43, 1.01, 21), 1.14, 1.67]
    samples = samples_of(estimates, params.contact_offset_m)
    plain = scale_from_samples(samples, dataclasses.replace(params, outlier_mads=None))
    assert scale_from_samples(samples, params).scale == pytest.approx(plain.scale, abs=1e-12)
    assert plain.scale == pytest.approx(np.quantile(estimates, 0.9), abs=1e-9)


def test_estimates_without_spread_are_not_cut() -> None:
    """Over half the estimates equal (a MAD of 0): no tail can be measured, so none is cut (a
    cut at the median would drop every estimate above it)."""
    params = MetricScaleParams()
    estimates = [1.0] * 12 + [1.05, 1.1, 1.2]
    samples = samples_of(estimates, params.contact_offset_m)
    plain = scale_from_samples(samples, dataclasses.replace(params, outlier_mads=None))
    assert scale_from_samples(samples, params).scale == pytest.approx(plain.scale, abs=1e-12)
    assert plain.scale > 1.01


def test_params_name_every_bad_field() -> None:
    with pytest.raises(MetricScaleParamsError) as err:
        MetricScaleParams(
            joint_quantile=1.5,
            min_detections=0,
            joints=(3, 25),
            proximal_ratio=0.0,
            wide_outlier_rel=0.0,
            wide_joint_rel=float("nan"),
        )
    message = str(err.value)
    for name in (
        "joint_quantile",
        "min_detections",
        "joints",
        "proximal_ratio",
        "wide_outlier_rel",
        "wide_joint_rel",
    ):
        assert name in message


# ----------------------------------------------------------------------------- synthetic world


@pytest.mark.parametrize("factor", [0.37, 2.9])
def test_oracle_landmarks_recover_the_scale(small_world: Clip, factor: float) -> None:
    world_from_cam, depth0 = sfm_units(small_world, factor)
    est = scale_from_landmarks(
        oracle_landmarks(small_world),
        small_world.frames,
        small_world.intrinsics,
        world_from_cam,
        depth0,
        None,
        ORACLE,
    )
    assert est.scale is not None, est.reason
    assert est.scale * factor == pytest.approx(1.0, abs=0.05)
    assert 0.0 <= est.spread < 0.1


@pytest.mark.parametrize("factor", [0.37, 2.9])
def test_oracle_scale_survives_misfit_detections(small_world: Clip, factor: float) -> None:
    """A third detection on every third frame: a hand's true landmarks shrunk to 0.6 of their
    size (so the lift puts it 1/0.6 as far) and moved 80 px, over a patch of colour frame 0
    does not show (a detection on something that moved). 5 of 28 detections: more than the
    0.9 quantile leaves out, so v11's rule came out +46% (measured); the outlier cut drops them."""
    world_from_cam, depth0 = sfm_units(small_world, factor)
    lm = oracle_landmarks(small_world)
    t = small_world.num_frames
    uv = np.concatenate([lm.uv, np.full((t, 1, 21, 2), np.nan)], axis=1)  # (T, 3, 21, 2)
    world = np.concatenate([lm.world, np.full((t, 1, 21, 3), np.nan)], axis=1)  # (T, 3, 21, 3)
    present = np.concatenate([lm.present, np.zeros((t, 1), dtype=bool)], axis=1)  # (T, 3)
    frames = small_world.frames.copy()
    for f in range(0, t, 3):
        hand = lm.uv[f, 0]  # (21, 2)
        centre = hand.mean(axis=0)
        uv[f, 2] = centre + 0.6 * (hand - centre) + np.array([-80.0, 0.0])
        lo = np.maximum(np.floor(uv[f, 2].min(axis=0)).astype(int) - 2, 0)
        hi = np.ceil(uv[f, 2].max(axis=0)).astype(int) + 3
        frames[f, lo[1] : hi[1], lo[0] : hi[0]] = (255, 0, 255)
        world[f, 2], present[f, 2] = lm.world[f, 0], True
    misfit = RawLandmarks(uv=uv, world=world, label_right=np.ones((t, 3)), present=present)
    args = (misfit, frames, small_world.intrinsics, world_from_cam, depth0, None)
    plain = scale_from_landmarks(*args, dataclasses.replace(ORACLE, outlier_mads=None))
    assert plain.scale * factor > 1.3  # the misfits reach past the 0.9 quantile
    est = scale_from_landmarks(*args, ORACLE)
    assert est.scale is not None, est.reason
    assert est.num_samples == plain.num_samples == 28
    assert est.scale * factor == pytest.approx(1.0, abs=0.05)


@pytest.mark.parametrize("factor", [0.37, 2.9])
def test_wide_window_recovers_the_scale_from_sparse_depth(small_world: Clip, factor: float) -> None:
    """A low-texture scene: confident depth on 5% of pixels, scattered.

    The strict 3 px window finds too few known depths under the joints; the wide-window fallback
    still gets the scale and says so.
    """
    world_from_cam, depth0 = sfm_units(small_world, factor)
    rng = np.random.default_rng(3)
    sparse = np.where(rng.random(depth0.shape) < 0.05, depth0, 0.0)  # (H, W)
    args = (
        oracle_landmarks(small_world),
        small_world.frames,
        small_world.intrinsics,
        world_from_cam,
        sparse,
        None,
    )
    strict = scale_from_landmarks(*args, MetricScaleParams(wide_window_px=0, proximal_ratio=1.0))
    assert strict.scale is None and "usable hand detections" in strict.reason
    est = scale_from_landmarks(*args, ORACLE)
    assert est.scale is not None, est.reason
    assert est.source == "hand_size_wide"
    assert est.scale * factor == pytest.approx(1.0, abs=0.05)
    assert 0.0 <= est.spread < 0.1
    # The fallback does not replace a strict estimate that succeeds.
    full = scale_from_landmarks(*args[:4], depth0, None, ORACLE)
    assert full.source == "hand_size"


def test_wide_window_skips_windows_across_a_depth_edge() -> None:
    """Wide windows: the median of known depths, none where the quartiles straddle an edge."""
    depth = np.zeros((60, 60))
    depth[::3, :40:3] = 2.0  # sparse known depths on one plane, left of column 40
    depth[::3, 40::3] = 4.0  # a farther surface from column 40 on
    params = MetricScaleParams(wide_window_px=10, wide_min_window_pixels=10)
    uv = np.array([[15.5, 30.5], [38.5, 30.5], [52.5, 30.5]])
    out = surface_depth(depth, uv, params, wide=True)
    np.testing.assert_allclose(out[[0, 2]], [2.0, 4.0])
    assert np.isnan(out[1])  # the window holds both surfaces: no sample
    # Strict window at the same pixels: 2 px finds no known depth off the grid.
    strict = surface_depth(depth, uv + 1.0, MetricScaleParams(window_px=0))
    assert np.isnan(strict).all()


def test_isolated_depth_outliers_are_dropped() -> None:
    """A short line of confident depths at 0.55 x the plane around it (the plane sweep matching a
    drawer's edge at the wrong plane, DWM 00017) is left out; the sparse plane and a large nearer
    box (a real object: the majority of its own neighbourhood) are kept."""
    depth = np.zeros((150, 200))
    depth[::4, ::4] = 30.0  # a plain surface with confident depth on a sparse grid
    depth[80:82, 60:100] = 16.5  # the outlier line
    depth[10:60, 120:190] = 12.0  # a box nearer than the plane, dense
    out = drop_depth_outliers(depth, 25, 0.2)
    assert (out[80:82, 60:100] == 0).all()
    plane = depth == 30.0  # (H, W)
    plane[:, 75:] = False  # left of the box's neighbourhood
    assert (out[plane] == 30.0).all()
    assert (out[10:60, 120:190] == 12.0).all()  # the whole box
    # The price: sparse plane depths beside the dense box, a minority of their neighbourhood,
    # go too (fewer samples there, not wrong ones).
    assert 0 < ((out == 0) & (depth == 30.0)).sum() < 0.3 * (depth == 30.0).sum()
    assert np.isnan(depth).sum() == 0 and (drop_depth_outliers(depth * np.nan, 25, 0.2) == 0).all()


def test_joints_off_the_main_surface_are_left_out() -> None:
    """Wide window, per detection: joints whose surface depth is more than wide_joint_rel off
    the median of the detection's surface depths lie over another surface."""
    z_s = np.array([20.0, 20.4, 19.8, 21.0, 15.0, 14.9, np.nan, 20.2])
    ok = np.isfinite(z_s)
    np.testing.assert_array_equal(
        on_main_surface(z_s, ok, 0.15), [True, True, True, True, False, False, False, True]
    )


def plane_with_an_outlier_line(
    near: float | None,
) -> tuple[RawLandmarks, np.ndarray, np.ndarray, np.ndarray, np.ndarray, float]:
    """A flat hand 1 cm above a plain table seen from 12 poses (as the hand-resting test); the
    table's frame-0 depth is known on a 5 px grid except within 12 px of the hand's footprint
    (a plain surface), and a 2 px line across the footprint holds depths at ``near`` x the
    table's (None: no line). Returns (landmarks, frames, intrinsics, poses in units, depth0 in
    units, scale)."""
    h, w = 240, 320
    scale = 0.25  # metres per unit
    poses = np.stack(
        [look_at([-0.35 + 0.012 * i, 0.006 * i, 0.4], [0.0, 0.0, 0.0]) for i in range(12)]
    )  # (T, 4, 4) metric
    k, hand, depth_m, lm, units, frames = flat_hand_over_table(h, w, poses, scale)
    foot = project_points(transform_points(invert_se3(poses[0]), hand), k)[0]  # (21, 2)
    lo, hi = np.floor(foot.min(axis=0)).astype(int), np.ceil(foot.max(axis=0)).astype(int)
    known = np.zeros((h, w), dtype=bool)
    known[::5, ::5] = True
    known[lo[1] - 12 : hi[1] + 12, lo[0] - 12 : hi[0] + 12] = False
    depth = np.where(known, depth_m, 0.0)  # (H, W) metres
    if near is not None:
        mid = (lo[1] + hi[1]) // 2
        depth[mid : mid + 2, lo[0] : hi[0]] = near * depth_m[mid : mid + 2, lo[0] : hi[0]]
    return lm, frames, k, units, depth / scale, scale


def test_wide_window_is_not_taken_by_a_line_of_outliers() -> None:
    """The defect of depth_camera v17 on DWM 00017 (issues 9, 17): on a plain surface a few
    confident depths at 0.55 x the surface's were all the wide window held under the hand, and
    the scale came out 1.9x. The outliers are left out before the splat (v18); without the
    line the two agree."""
    params = MetricScaleParams(contact_offset_m=0.01, proximal_ratio=1.0)
    lm, frames, k, units, depth0, scale = plane_with_an_outlier_line(0.55)
    v17 = dataclasses.replace(params, wide_outlier_rel=None, wide_joint_rel=None)
    before = scale_from_landmarks(lm, frames, k, units, depth0, None, v17)
    assert before.source == "hand_size_wide" and before.scale / scale > 1.5  # the defect
    est = scale_from_landmarks(lm, frames, k, units, depth0, None, params)
    assert est.source == "hand_size_wide" and est.num_samples >= 10
    assert est.scale == pytest.approx(scale, rel=0.06)
    # No outliers: the same figure.
    clean = scale_from_landmarks(*plane_with_an_outlier_line(None)[:5], None, params)
    assert est.scale == pytest.approx(clean.scale, rel=0.03)


def test_depth_camera_puts_sfm_units_in_metres(
    small_world: Clip, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The stage's wiring: an SfM-unit estimate comes back in metres, poses and depth alike."""
    from egosim.stages.depth_camera import metric_scale
    from egosim.stages.depth_camera.stage import CameraEstimate, with_hand_size_scale

    monkeypatch.setattr(
        metric_scale, "detect_hand_landmarks", lambda frames, params: oracle_landmarks(small_world)
    )
    factor = 2.9
    world_from_cam, depth0 = sfm_units(small_world, factor)
    t = small_world.num_frames
    est = CameraEstimate(
        intrinsics=small_world.intrinsics,
        world_from_cam=world_from_cam,
        registered=np.ones(t, dtype=bool),
        static=False,
        depth0=depth0.astype(np.float32),
        confidence0=np.ones_like(depth0, dtype=np.float32),
        backend="sfm",
        scale_source="none",
    )
    metric = with_hand_size_scale(est, small_world.frames)
    assert metric.scale_source == "hand_size"
    assert metric.metric_scale * factor == pytest.approx(1.0, abs=0.05)
    true_t = small_world.world_from_cam[:, :3, 3]  # (T, 3) metres
    assert np.abs(metric.world_from_cam[:, :3, 3] - true_t).max() < 0.05 * np.abs(true_t).max()
    np.testing.assert_allclose(metric.world_from_cam[:, :3, :3], world_from_cam[:, :3, :3])
    known = depth0 > 0
    ratio = metric.depth0[known] / small_world.depth[0][known]
    assert np.median(ratio) == pytest.approx(1.0, abs=0.05)
    # No depth (static or rotation-only): nothing to scale, returned as it was.
    flat = dataclasses.replace(est, depth0=None, confidence0=None)
    assert with_hand_size_scale(flat, small_world.frames) is flat


@pytest.mark.slow
@pytest.mark.xfail(
    strict=True,
    reason="known, issue 17: since depth_camera v7 (palm lift) MediaPipe's 2D palm on the world's "
    "drawn hands is 0.74 of the true one, so this clip's scale comes out +19% (+46% with "
    "depth_camera v11's refined palm lift, +15% since v12 leaves out a misfit track; oracle "
    "landmarks: within 10%, tested above); strict, so it fails loudly once the bias is gone",
)
def test_mediapipe_recovers_the_scale_on_a_world_clip() -> None:
    pytest.importorskip("mediapipe")
    clip = render_clip(WorldConfig(seed=1, mode="tabletop"))
    factor = 2.9
    world_from_cam, depth0 = sfm_units(clip, factor)
    est = estimate_metric_scale(clip.frames, clip.intrinsics, world_from_cam, depth0, None)
    assert est.scale is not None, est.reason
    assert est.scale * factor == pytest.approx(1.0, abs=0.10)


def world_scale_errors(config: WorldConfig, factors: tuple[float, ...] = (0.37, 2.9)) -> list[str]:
    """Table rows: relative scale error of the oracle and the MediaPipe paths on one world clip."""
    from egosim.stages.common.hand_landmarks import detect_hand_landmarks, drop_overlapping

    clip = render_clip(config)
    found = drop_overlapping(detect_hand_landmarks(clip.frames), 0.5)  # as estimate_metric_scale
    paths = {"oracle": (oracle_landmarks(clip), ORACLE), "mediapipe": (found, MetricScaleParams())}
    rows = []
    for path, (landmarks, params) in paths.items():
        for factor in factors:
            world_from_cam, depth0 = sfm_units(clip, factor)
            est = scale_from_landmarks(
                landmarks, clip.frames, clip.intrinsics, world_from_cam, depth0, None, params
            )
            err = f"{est.scale * factor - 1:+.3f}" if est.scale is not None else est.reason
            spread = f"{est.spread:.3f}" if est.spread is not None else "-"
            rows.append(
                f"{config.mode:8s} seed {config.seed}  {path:9s} x{factor:<5} "
                f"detections {int(landmarks.present.sum()):3d} used {est.num_samples:3d} "
                f"error {err} spread {spread} ({est.source})"
            )
    return rows


if __name__ == "__main__":
    # Scale errors on full-size world clips (61 frames, 480x832): tuned on tabletop seeds 0-1.
    #   .venv/bin/python tests/test_metric_scale.py tabletop:0 tabletop:1 wild:0 alt:tabletop:0 ...
    import sys

    # Held-out world: prefix the variant, e.g. alt:tabletop:0 (WorldConfig.variant).
    for spec in sys.argv[1:] or ["tabletop:0", "tabletop:1"]:
        *variant, mode, seed = spec.split(":")
        name = variant[0] if variant else "default"
        config = WorldConfig(seed=int(seed), mode=mode, variant=name)
        for line in world_scale_errors(config):
            print(config.variant, line, flush=True)


@pytest.mark.parametrize("factor", [0.37, 2.9])
def test_pooled_scale_of_two_segments_recovers_the_scale(small_world: Clip, factor: float) -> None:
    """The source track's scale (depth_camera v9): two segments of one reconstruction, each with
    its own first-frame depth, pooled into one scale."""
    world_from_cam, _ = sfm_units(small_world, factor)
    marks = oracle_landmarks(small_world)
    segments, landmarks = [], []
    for start, end in ((0, 9), (8, 17)):
        hands = cv2.dilate(small_world.hand_mask[start], np.ones((17, 17), np.uint8)) > 0
        depth = np.where(hands, 0.0, small_world.depth[start].astype(np.float64)) * factor
        segments.append((small_world.frames[start:end], world_from_cam[start:end], depth, None))
        landmarks.append(
            RawLandmarks(
                uv=marks.uv[start:end],
                world=marks.world[start:end],
                label_right=marks.label_right[start:end],
                present=marks.present[start:end],
            )
        )
    est = pooled_metric_scale(segments, small_world.intrinsics, ORACLE, landmarks=landmarks)
    assert est.scale is not None, est.reason
    # The goal (10%); measured +6.4% (oracle landmarks with the palm lift: -6% to +7%).
    assert est.scale * factor == pytest.approx(1.0, abs=0.10)
    one = pooled_metric_scale(segments[:1], small_world.intrinsics, ORACLE, landmarks[:1])
    assert est.num_samples > one.num_samples  # both segments gave detections
