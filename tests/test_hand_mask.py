"""Tests of the hand_mask stage: capsules, colour refinement, SAM prompts, stage and shards."""

from __future__ import annotations

import dataclasses
import json
from functools import cache
from pathlib import Path

import cv2
import numpy as np
import pytest

from egosim.pipeline import media
from egosim.pipeline.clip_io import clip_from_row, row_from_clip, write_clips
from egosim.pipeline.execute import ShardTask, run_shard_task
from egosim.pipeline.records import Clip
from egosim.pipeline.shards import ShardReader, ShardWriter
from egosim.pipeline.stage import ClipRejected, ConfigError
from egosim.schemas.hand_mask import HAND_MASK
from egosim.schemas.hands import HANDS, MANO_COLUMNS
from egosim.stages.hand_mask.capsules import CapsuleParams, draw_hand, hand_scale_px
from egosim.stages.hand_mask.sam import build_prompts, mask_box
from egosim.stages.hand_mask.stage import HandMaskConfig, HandMaskStage
from egosim.world import WorldConfig, render_clip
from tests.conftest import shared_data, translated, write_poses

SEEDS = (0, 1, 2, 3)


@cache
def world_clip(seed: int) -> Clip:
    """A tiny synthetic clip (cached across the tests of this module)."""
    return render_clip(WorldConfig(seed=seed, height=96, width=160, num_frames=12))


def iou(a: np.ndarray, b: np.ndarray) -> float:
    """Intersection over union of two boolean masks (1.0 when both are empty)."""
    union = np.logical_or(a, b).sum()
    return 1.0 if union == 0 else float(np.logical_and(a, b).sum() / union)


def mean_iou(masks: np.ndarray, truth: np.ndarray) -> float:
    """Mean per-frame IoU of two ``(T, H, W)`` mask stacks."""
    return float(np.mean([iou(m > 0, g > 0) for m, g in zip(masks, truth, strict=True)]))


def test_mean_iou_on_synthetic_world() -> None:
    stage = HandMaskStage()
    per_seed = {seed: mean_iou(stage.masks_for_clip(world_clip(seed)), world_clip(seed).hand_mask)
                for seed in SEEDS}  # fmt: skip
    mean = float(np.mean(list(per_seed.values())))
    # Image-space arms (no world axis), at 96x160 x 12 frames. Measured (hand_mask v10): seed 0
    # 0.910, 1 0.794, 2 0.874, 3 0.911 (mean 0.872; v9: 0.770); tuned on this world. Tolerance
    # 0.8 (issue 9's goal; was 0.65 before v10).
    assert mean >= 0.8, f"mean IoU {mean:.3f} per seed {per_seed}"


def test_colour_model_beats_capsules_alone() -> None:
    clip = world_clip(0)
    plain = HandMaskStage(HandMaskConfig(colour_refine=False)).masks_for_clip(clip)
    refined = HandMaskStage().masks_for_clip(clip)
    iou_plain, iou_refined = mean_iou(plain, clip.hand_mask), mean_iou(refined, clip.hand_mask)
    assert iou_refined > iou_plain, f"colour {iou_refined:.3f} vs capsules {iou_plain:.3f}"


def _rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    """4x4 rotation about ``axis (3,)`` by ``angle`` radians (Rodrigues)."""
    axis = axis / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    out = np.eye(4)
    out[:3, :3] = np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k
    return out


def test_masks_do_not_depend_on_the_world_frame() -> None:
    """Rotating and moving the whole world (joints and cameras alike) leaves the masks alone."""
    clip = render_clip(WorldConfig(seed=1, height=64, width=112, num_frames=4))
    moved_from_world = _rotation(np.array([0.3, -1.0, 0.7]), 2.1)  # (4, 4)
    moved_from_world[:3, 3] = [1.5, -0.4, 3.0]
    joints = clip.hand_joints.astype(np.float64) @ moved_from_world[:3, :3].T
    joints += moved_from_world[:3, 3]  # (T, 2, 21, 3)
    moved = dataclasses.replace(
        clip,
        hand_joints=joints.astype(np.float32),
        world_from_cam=moved_from_world @ clip.world_from_cam,
    )
    stage = HandMaskStage()
    original, rotated = stage.masks_for_clip(clip), stage.masks_for_clip(moved)
    assert original.sum() > 0
    # float32 joints round differently after the move: allow a few boundary pixels per frame.
    assert np.sum(original != rotated) <= 0.01 * original.sum(), "masks changed with the frame"


def test_arm_found_beyond_the_wrist() -> None:
    """A sleeve-coloured bar from the wrist to the border is masked; the table beside it is not."""
    from egosim.stages.hand_mask.arm_region import ArmParams, hand_arm_mask

    h, w = 120, 160
    image = np.full((h, w, 3), (40, 120, 40), np.uint8)  # green table
    rng = np.random.default_rng(0)
    image = np.clip(image + rng.normal(0, 6, image.shape), 0, 255).astype(np.uint8)
    kp = np.full((21, 2), np.nan)
    kp[0] = [80.5, 70.5]  # wrist; fingers point up, so the arm runs down
    for j, x in zip((5, 9, 13, 17), (74.5, 79.5, 84.5, 89.5), strict=True):
        kp[j] = [x, 45.5]
        kp[j + 1 : j + 4] = [[x, 45.5 - 6 * i] for i in (1, 2, 3)]
    kp[1:5] = [[72.5, 66.5 - 5 * i] for i in range(4)]
    image[70:, 70:91] = (150, 40, 160)  # purple sleeve from the wrist to the bottom border
    mask = hand_arm_mask(image, kp[None], np.array([True]), CapsuleParams(), ArmParams())
    sleeve = np.zeros((h, w), bool)
    sleeve[75:, 72:89] = True
    assert mask[sleeve].mean() > 0.9, f"sleeve covered {mask[sleeve].mean():.2f}"
    table = np.ones((h, w), bool)
    table[:, 55:106] = False
    assert mask[table].mean() < 0.01, f"table masked {mask[table].mean():.3f}"


def test_arm_walk_follows_a_bar_and_stops_at_its_end() -> None:
    """The colour walk reaches a sleeve's end; on plain table it finds no arm to follow."""
    from egosim.stages.hand_mask.arm_region import arm_extent

    h, w = 100, 200
    image = np.full((h, w, 3), (40, 120, 40), np.uint8)
    image[45:56, 20:150] = (150, 40, 160)  # a purple bar from x = 20 to 150, 11 px high
    lab = cv2.cvtColor(image, cv2.COLOR_RGB2LAB).astype(np.float32)
    none = np.zeros((h, w), np.uint8)
    wrist, d = np.array([20.5, 50.5]), np.array([1.0, 0.0])
    extent, ref = arm_extent(lab, wrist, d, 5.0, 5.0, 20.0, none, 18.0, 1.0)
    assert ref is not None and 125.0 <= extent <= 130.0, extent  # the bar ends 129.5 px on
    plain = cv2.cvtColor(np.full((h, w, 3), (40, 120, 40), np.uint8), cv2.COLOR_RGB2LAB)
    extent, ref = arm_extent(plain.astype(np.float32), wrist, d, 5.0, 5.0, 20.0, none, 18.0, 1.0)
    assert ref is None and extent == 20.0


def test_arm_direction_turn_cost(monkeypatch: pytest.MonkeyPatch) -> None:
    """A sleeve 40 degrees off the hand's direction is followed at a low turn cost, not at a
    high one, and ``ArmParams.turn_cost`` is what the arm search uses (hand_mask v9: the
    forearm's half-width used to be passed in its place)."""
    from egosim.stages.hand_mask.arm_region import ArmParams, arm_direction, draw_arm_labels

    h, w = 160, 200
    rng = np.random.default_rng(1)
    image = np.clip(rng.normal(120, 40, (h, w, 3)), 0, 255).astype(np.uint8)  # busy table
    wrist = np.array([100.5, 40.5])
    turned = np.array([np.sin(np.radians(40.0)), np.cos(np.radians(40.0))])  # 40 deg off "down"
    end = wrist + 200 * turned
    cv2.line(image, (100, 40), (round(end[0]), round(end[1])), (150, 40, 160), 15)  # sleeve
    lab = cv2.cvtColor(image, cv2.COLOR_RGB2LAB).astype(np.float32)
    none = np.zeros((h, w), np.uint8)
    down = np.array([0.0, 1.0])
    cheap = arm_direction(lab, wrist, down, 30.0, none, 90.0, 0.3, 7.0)
    dear = arm_direction(lab, wrist, down, 30.0, none, 90.0, 1e4, 7.0)
    # candidates every 5 degrees, and the turn cost may keep it one step short
    assert np.degrees(np.arccos(np.clip(cheap @ turned, -1, 1))) <= 7.5, cheap
    assert np.allclose(dear, down), dear
    # The stage's labels call the search with ArmParams' turn cost and the forearm's
    # half-width as the side-strip radius.
    import egosim.stages.hand_mask.arm_region as arm_region

    seen = {}

    def recording(*args, **kwargs):
        seen.update(kwargs, args=args)
        return arm_direction(*args, **kwargs)

    kp = np.full((21, 2), np.nan)
    kp[0] = wrist
    for j, x in zip((5, 9, 13, 17), (92.5, 98.5, 104.5, 110.5), strict=True):
        kp[j] = [x, 15.5]  # knuckles above the wrist: the hand points up, its arm "down"
    monkeypatch.setattr(arm_region, "arm_direction", recording)
    labels = np.full((h, w), cv2.GC_BGD, np.uint8)
    draw_arm_labels(labels, kp, CapsuleParams(), ArmParams(turn_cost=0.7), lab)
    scale = hand_scale_px(kp)
    assert seen["turn_cost"] == 0.7
    assert seen["radius"] == pytest.approx(0.027 * scale)  # FOREARM_RADIUS_M[0] at the wrist


def _hand_keypoints(wrist: np.ndarray, up: np.ndarray, length: float, span: float) -> np.ndarray:
    """Keypoints ``(21, 2)`` of a flat hand: knuckles ``length`` px from ``wrist`` along the unit
    ``up`` (wrist to knuckles), ``span`` px apart across it, fingers on along ``up``."""
    across = np.array([-up[1], up[0]])
    kp = np.full((21, 2), np.nan)
    kp[0] = wrist
    for j, offset in zip((5, 9, 13, 17), (-1.5, -0.5, 0.5, 1.5), strict=True):
        base = wrist + length * up + offset * span / 3.0 * across
        kp[j : j + 4] = [base + i * 6.0 * up for i in range(4)]
    kp[1:5] = [wrist - 0.6 * span * across + i * 5.0 * up for i in range(4)]
    return kp


def _sleeve_frame(h: int, w: int, wrist: np.ndarray, d: np.ndarray, seed: int) -> np.ndarray:
    """A busy table ``(H, W, 3)`` with a purple sleeve 17 px wide from ``wrist`` along ``d``."""
    rng = np.random.default_rng(seed)
    image = np.clip(rng.normal(120, 40, (h, w, 3)), 0, 255).astype(np.uint8)
    image = cv2.GaussianBlur(image, (5, 5), 0)
    end = wrist + 400 * d
    cv2.line(image, tuple(int(v) for v in wrist), tuple(int(v) for v in end), (150, 40, 160), 17)
    return image


def _sleeve_pixels(h: int, w: int, wrist: np.ndarray, d: np.ndarray) -> np.ndarray:
    """The sleeve's core ``(H, W)`` bool from 25 px past the wrist on, 9 px wide."""
    core = np.zeros((h, w), np.uint8)
    a, b = wrist + 25 * d, wrist + 400 * d
    cv2.line(core, tuple(int(v) for v in a), tuple(int(v) for v in b), 1, 9)
    return core > 0


def test_arm_of_a_foreshortened_hand_is_found() -> None:
    """A hand pointing into the view (knuckles 4 px from the wrist in the image, a normal
    knuckle span) still gets its sleeve: lengths along the arm come from the hand's scale
    (hand_mask v10), not its projected length, which put the whole arm strip inside the hand."""
    from egosim.stages.hand_mask.arm_region import ArmParams, hand_arm_mask

    h, w = 160, 200
    wrist, down = np.array([100.5, 40.5]), np.array([0.0, 1.0])
    image = _sleeve_frame(h, w, wrist, down, 2)
    kp = _hand_keypoints(wrist, -down, 4.0, 16.0)  # (21, 2) foreshortened: 4 px wrist-knuckle
    sleeve = _sleeve_pixels(h, w, wrist, down)
    found = hand_arm_mask(image, kp[None], np.array([True]), CapsuleParams(), ArmParams()) > 0
    assert found[sleeve].mean() > 0.9, f"sleeve covered {found[sleeve].mean():.2f}"
    off = np.ones((h, w), bool)
    off[:, 70:131] = False
    assert found[off].mean() < 0.01, f"table masked {found[off].mean():.3f}"
    short = ArmParams(unforeshortened=False)
    old = hand_arm_mask(image, kp[None], np.array([True]), CapsuleParams(), short) > 0
    assert old[sleeve].mean() < 0.5, "the projected length alone should miss this arm"


def test_no_sideways_arm_for_a_hand_at_the_border() -> None:
    """A hand entering from the bottom border (its arm below the image): no arm band is drawn
    sideways along the table, though a sleeve-coloured bar runs there (hand_mask v10); a hand
    in the middle of the image still finds that bar 60 degrees off its own direction."""
    from egosim.stages.hand_mask.arm_region import ArmParams, hand_arm_mask

    h, w = 160, 240
    side = np.array([np.cos(np.radians(200.0)), np.sin(np.radians(200.0))])  # left, a bit up
    kp_low = _hand_keypoints(np.array([120.5, 154.5]), np.array([0.0, -1.0]), 30.0, 20.0)
    image = _sleeve_frame(h, w, np.array([120.5, 154.5]), side, 4)
    bar = _sleeve_pixels(h, w, np.array([120.5, 154.5]), side)
    found = hand_arm_mask(image, kp_low[None], np.array([True]), CapsuleParams(), ArmParams()) > 0
    assert found[bar].mean() < 0.1, f"sideways band covered {found[bar].mean():.2f} of the bar"
    always = ArmParams(out_of_view=0.0)
    old = hand_arm_mask(image, kp_low[None], np.array([True]), CapsuleParams(), always) > 0
    assert old[bar].mean() > 0.5, "without the rule the search follows the bar"
    wrist = np.array([120.5, 60.5])
    kp_mid = _hand_keypoints(wrist, np.array([0.0, -1.0]), 30.0, 20.0)  # arm 60 deg off down
    down = np.array([np.cos(np.radians(150.0)), np.sin(np.radians(150.0))])
    image = _sleeve_frame(h, w, wrist, down, 5)
    bar = _sleeve_pixels(h, w, wrist, down)
    found = hand_arm_mask(image, kp_mid[None], np.array([True]), CapsuleParams(), ArmParams()) > 0
    assert found[bar].mean() > 0.9, f"mid-image arm covered {found[bar].mean():.2f}"


def test_region_direction_of_a_ray_and_of_a_blob() -> None:
    """A ray from the wrist gives its direction (to 2 degrees); a round patch gives none."""
    from egosim.stages.hand_mask.arm_region import region_direction

    region = np.zeros((200, 200), np.uint8)
    wrist = np.array([20.5, 20.5])
    cv2.line(region, (20, 20), (160, 100), 1, 9)  # 29.7 degrees below the x axis
    got = region_direction(region, wrist, np.array([1.0, 0.0]))
    assert got is not None
    angle = np.degrees(np.arctan2(got[1], got[0]))
    assert abs(angle - np.degrees(np.arctan2(80, 140))) < 2.0, angle
    blob = np.zeros((200, 200), np.uint8)
    cv2.circle(blob, (40, 40), 50, 1, -1)  # a patch of table round the wrist
    assert region_direction(blob, wrist, np.array([1.0, 0.0])) is None


@pytest.mark.slow
def test_mean_iou_on_held_out_world() -> None:
    """The 'alt' world (sleeves, upper arms, other hands and cameras) was not tuned on."""
    stage = HandMaskStage()
    per_case = {}
    for mode, seed in (("tabletop", 1), ("wild", 2)):
        clip = render_clip(
            WorldConfig(seed=seed, mode=mode, height=96, width=160, num_frames=8, variant="alt")
        )
        per_case[(mode, seed)] = mean_iou(stage.masks_for_clip(clip), clip.hand_mask)
    mean = float(np.mean(list(per_case.values())))
    # Measured at 96x160 x 8 frames (hand_mask v10): tabletop 1 0.498, wild 2 0.848 (mean
    # 0.673; v9: 0.374): the alt arms' sleeves and upper arms are found only in part at this
    # size. Tolerance 0.55 (was 0.3 before v10; issue 9's goal: 0.8).
    assert mean >= 0.55, f"held-out mean IoU {mean:.3f} per case {per_case}"


def test_backward_propagation_masks_an_arm_before_its_keypoints() -> None:
    """An arm sliding up from the border: frame 0 gets it from frame 1's mask through flow."""
    from egosim.stages.hand_mask.propagate import propagate_backwards

    rng = np.random.default_rng(1)
    table = np.clip(rng.normal(120, 40, (96, 128, 3)), 0, 255).astype(np.uint8)
    table = cv2.GaussianBlur(table, (5, 5), 0)
    frames, masks = [], []
    for top in (80, 72):  # the arm's top edge moves up by 8 px
        f = table.copy()
        f[top:, 50:70] = (200, 150, 120)
        m = np.zeros((96, 128), np.uint8)
        frames.append(f)
        masks.append(m)
    masks[1][72:, 50:70] = 1  # only the later frame knows the arm
    out = propagate_backwards(np.stack(frames), np.stack(masks))
    arm0 = np.zeros((96, 128), bool)
    arm0[82:, 52:68] = True
    assert out[0][arm0].mean() > 0.8, f"frame 0 arm covered {out[0][arm0].mean():.2f}"
    assert out[0][:70].sum() == 0, "propagation leaked above the arm"
    np.testing.assert_array_equal(out[1], masks[1])


def test_hand_scale_from_palm() -> None:
    kp = np.full((21, 2), np.nan)
    kp[0] = [50, 50]
    kp[9] = [50 + 0.092 * 1000, 50]  # 1000 px per metre along the middle metacarpal
    assert hand_scale_px(kp) == pytest.approx(1000.0)
    assert np.isnan(hand_scale_px(np.full((21, 2), np.nan)))


def test_no_hands_gives_empty_masks() -> None:
    clip = world_clip(0)
    clip = Clip(**{**clip.__dict__, "hand_valid": np.zeros((clip.num_frames, 2), bool)})
    masks = HandMaskStage().masks_for_clip(clip)
    assert masks.shape == clip.hand_mask.shape and masks.sum() == 0


def test_clip_without_joints_is_rejected() -> None:
    clip = world_clip(0)
    row = row_from_clip(Clip(**{**clip.__dict__, "hand_joints": None, "hand_valid": None}))
    with pytest.raises(ClipRejected, match=clip.clip_id):
        HandMaskStage().process({"clips": row})


def test_process_reads_its_records_as_the_decoded_clip() -> None:
    """``process`` (records: frames, labels, camera and robot arm mask read through accessors)
    gives exactly the masks of ``masks_for_clip`` on the fully decoded clip, with the robot arm
    added; a hands row of another length is rejected naming the clip."""
    clip = render_clip(WorldConfig(seed=0, height=64, width=112, num_frames=5))
    arm = np.zeros(clip.hand_mask.shape, np.uint8)
    arm[:, 40:, :12] = 1  # a robot arm entering from the lower left
    clip = dataclasses.replace(clip, embodiment_mask=arm)
    stage = HandMaskStage(HandMaskConfig(propagate_frames=2))
    row = row_from_clip(clip)
    out = stage.process({"clips": row})
    masks = media.decode_lossless_video(out["hand_mask"])
    expected = np.maximum(stage.masks_for_clip(clip_from_row(row)), arm)  # frames as stored
    np.testing.assert_array_equal(masks, expected)
    assert out["num_frames"] == 5 and (out["height"], out["width"]) == (64, 112)
    assert expected.sum() > arm.sum()  # the hands are there too
    hands = {
        "clip_id": clip.clip_id,
        "num_frames": 4,
        "hand_joints": clip.hand_joints[:4].reshape(4, -1).tolist(),
        "hand_valid": clip.hand_valid[:4].tolist(),
        "hand_confidence": clip.hand_confidence[:4].reshape(4, -1).tolist(),
    }
    with pytest.raises(ClipRejected) as info:
        stage.process({"clips": row, "hands": hands})
    assert str(info.value) == f"clip {clip.clip_id!r}: hands cover 4 frames, not 5"


def test_config_rejects_bad_values() -> None:
    with pytest.raises(ConfigError, match="radius_scale"):
        HandMaskConfig(radius_scale=0.0)
    with pytest.raises(ConfigError, match="sam_model_path"):
        HandMaskConfig(backend="sam")
    with pytest.raises(ConfigError, match="fan_half_angle_deg"):
        HandMaskConfig(fan_half_angle_deg=120.0)


def test_arm_params_reject_bad_values_all_at_once() -> None:
    """A negative turn cost would reward turning, a negative ring or out-of-view length would
    silently mean 0: every bad field is named in one message, with its value."""
    from egosim.stages.hand_mask.arm_region import ArmParams

    with pytest.raises(ValueError) as info:
        ArmParams(turn_cost=-1.0, out_of_view=-0.5, hand_ring=-0.03, max_turn_deg=200.0)
    message = str(info.value)
    for text in ("turn_cost", "got -1.0", "out_of_view", "got -0.5", "hand_ring", "got -0.03",
                 "max_turn_deg", "got 200.0"):  # fmt: skip
        assert text in message, message
    ArmParams(turn_cost=0.0, out_of_view=0.0, hand_ring=0.0, max_turn_deg=0.0)  # all off: valid


def test_stage_through_shard_task(tmp_path: Path) -> None:
    clips = tmp_path / "clips.parquet"
    write_clips(clips, [world_clip(0)])
    task = ShardTask(
        step="hand_mask",
        stage="hand_mask",
        params={},
        shard_index=0,
        shard_count=1,
        output=tmp_path / "hand_mask.parquet",
        rejects=tmp_path / "rejects.parquet",
        inputs={"clips": clips},
    )
    result = run_shard_task(task)
    assert result.rows == 1 and result.rejected == 0
    with ShardReader(task.output, HAND_MASK) as reader:
        row = next(reader.iter_rows())
    HAND_MASK.validate_row(row)
    masks = media.decode_lossless_video(row["hand_mask"])
    assert masks.shape == (12, 96, 160) and set(np.unique(masks)) <= {0, 1}
    assert np.allclose(row["coverage"], masks.reshape(12, -1).mean(1))


def test_sam_prompts_from_keypoints() -> None:
    kp = np.zeros((2, 21, 2))
    kp[0] = np.linspace([10, 10], [30, 40], 21)
    kp[1] = np.linspace([100, 10], [120, 40], 21)
    kp[1, [4, 8]] = [500, 500]  # two tips outside a 160x96 image
    boxes = np.array([[5, 5, 35, 45], [95, 5, 125, 45]], dtype=float)
    points, labels, out_boxes = build_prompts(kp, np.array([True, True]), boxes, 96, 160)
    assert len(points) == 2 and len(points[0]) == len(points[1]) == 10
    assert labels == [[1] * 10, [1] * 10]
    assert points[0][0] == [9.5, 9.5]  # pixel-centre to OpenCV coordinates
    assert out_boxes[1] == [95.0, 5.0, 125.0, 45.0]
    assert build_prompts(kp, np.array([False, False]), boxes, 96, 160) == ([], [], [])
    mask = np.zeros((96, 160), np.uint8)
    mask[10:20, 30:50] = 1
    assert mask_box(mask).tolist() == [30, 10, 49, 19]


def test_sam_backend_loads_from_local_path(tmp_path: Path) -> None:
    pytest.importorskip("transformers")
    from egosim.stages.hand_mask.sam import SamBackendError, SamSegmenter

    with pytest.raises(SamBackendError):
        SamSegmenter(str(tmp_path / "missing"))


def test_capsules_cover_real_hands() -> None:
    folder = shared_data("freihand_fixture")
    data = json.loads((folder / "test_freihand.json").read_text())
    files = {im["id"]: im["file_name"] for im in data["images"]}
    coverages = []
    for ann in data["annotations"]:
        image = cv2.imread(str(folder / files[ann["image_id"]]))
        kp = np.asarray(ann["keypoints"], dtype=np.float64).reshape(21, 3)[:, :2] + 0.5
        h, w = image.shape[:2]
        mask, _ = draw_hand(kp, 0, h, w, CapsuleParams(forearm=False))
        # Skin pixels near the keypoints (YCrCb skin box) should lie inside the mask.
        ycrcb = cv2.cvtColor(image, cv2.COLOR_BGR2YCrCb)
        skin = cv2.inRange(ycrcb, (0, 135, 85), (255, 180, 135)) > 0
        near = np.zeros((h, w), np.uint8)
        for x, y in kp:
            cv2.circle(near, (int(x), int(y)), 6, 1, -1)
        sample = skin & (near > 0)
        if sample.sum() > 20:
            coverages.append(float(mask[sample].mean()))
    assert coverages, "no skin pixels found near any keypoint"
    assert np.mean(coverages) >= 0.8, f"skin-near-keypoint coverage {np.round(coverages, 2)}"


def test_stage_uses_connected_hands_and_poses(tmp_path: Path) -> None:
    clip = render_clip(WorldConfig(seed=0, height=64, width=112, num_frames=6))
    t = clip.num_frames
    clips = tmp_path / "clips.parquet"
    write_clips(clips, [clip])
    # A hands row that kept only the left hand, and cleaned poses moved by 3 cm.
    joints = clip.hand_joints.copy()
    joints[:, 1] = np.nan
    valid = np.zeros((t, 2), bool)
    valid[:, 0] = True
    hands_row = {
        "clip_id": clip.clip_id,
        "num_frames": t,
        "backend": "given",
        "hand_joints": joints.reshape(t, -1).tolist(),
        "hand_valid": valid.tolist(),
        "hand_confidence": valid.repeat(21, axis=1).astype(np.float32).tolist(),  # (T, 42)
        "hand_lifted": valid.tolist(),
        "num_duplicates_removed": 0,
        "num_outliers_removed": 0,
        **dict.fromkeys(MANO_COLUMNS),  # no MANO fit: the joints are given
    }
    hands = tmp_path / "hands.parquet"
    with ShardWriter(hands, HANDS, stage="test") as writer:
        writer.write_row(hands_row)
    moved = translated(clip.world_from_cam, np.array([0.03, 0.0, 0.0]))
    poses = write_poses(tmp_path / "poses.parquet", clip, moved)
    params = {"colour_refine": False}
    task = ShardTask(
        step="hand_mask",
        stage="hand_mask",
        params=params,
        shard_index=0,
        shard_count=1,
        output=tmp_path / "hand_mask.parquet",
        rejects=tmp_path / "rejects.parquet",
        inputs={"clips": clips, "hands": hands, "poses": poses},
    )
    assert run_shard_task(task).rows == 1
    with ShardReader(task.output, HAND_MASK) as reader:
        masks = media.decode_lossless_video(next(reader.iter_rows())["hand_mask"])
    stage = HandMaskStage(HandMaskConfig(colour_refine=False))
    left_only = dataclasses.replace(clip, hand_joints=joints, hand_valid=valid)
    expected = stage.masks_for_clip(dataclasses.replace(left_only, world_from_cam=moved))
    np.testing.assert_array_equal(masks, expected)
    assert 0 < masks.sum() < stage.masks_for_clip(clip).sum()  # one hand fewer
    assert not np.array_equal(masks, stage.masks_for_clip(left_only))  # the camera moved


def _static_table(h: int = 96, w: int = 128) -> np.ndarray:
    """A pale, lightly textured table (what a pale hand's colour model confuses)."""
    rng = np.random.default_rng(3)
    table = np.clip(rng.normal(205, 12, (h, w, 3)), 0, 255).astype(np.uint8)
    return cv2.GaussianBlur(table, (5, 5), 0)


def test_background_patch_is_not_carried_back_without_hand_evidence() -> None:
    """pour_coke's failure: frame 1's mask holds a table patch beside the hand that just
    entered; the patch looks the same in frame 0 (static background), so plain flow carried it
    back. Only the certain hand seeds travel with confidence: frame 0 (no hand) stays empty."""
    from egosim.stages.hand_mask.propagate import propagate_backwards

    table = _static_table()
    frames = np.stack([table, table.copy()])  # (2, H, W, 3)
    frames[1, 30:96, 100:128] = (220, 170, 140)  # a hand entering from the right border
    masks = np.zeros((2, 96, 128), np.uint8)
    masks[1, 30:96, 100:128] = 1  # the hand ...
    masks[1, 40:60, 60:100] = 1  # ... and a patch of table the colour model joined to it
    certain = np.zeros_like(masks)
    certain[1, 40:90, 108:124] = 1  # the keypoint skeleton: on the hand only
    out = propagate_backwards(frames, masks, certain=certain)
    assert out[0].sum() == 0, f"{out[0].sum()} px carried into a frame without a hand"
    np.testing.assert_array_equal(out[1], masks[1])
    # Without the certain seeds the whole warped mask is trusted: the patch comes back, which
    # is the failure this guards against (the test would catch it).
    old = propagate_backwards(frames, masks)
    assert old[0, 40:60, 60:100].mean() > 0.5


def test_missed_hand_is_carried_while_the_other_is_found() -> None:
    """A frame that missed one hand but found the other gets the missed one from its neighbour
    (dwm_00013's right hand); before, only frames with no mask at all were filled."""
    from egosim.stages.hand_mask.propagate import propagate_hands

    table = _static_table()
    frames = np.stack([table.copy(), table.copy()])
    for f, shift in zip(frames, (0, 3), strict=True):
        f[50:96, 10:30] = (200, 140, 110)  # hand 0, still
        f[40 + shift : 96, 90:112] = (60, 40, 90)  # hand 1 in a dark sleeve, moving down 3 px
    per_hand = np.zeros((2, 2, 96, 128), np.uint8)
    per_hand[:, 0, 50:96, 10:30] = 1  # hand 0 found in both frames
    per_hand[1, 1, 43:96, 90:112] = 1  # hand 1 found in frame 1 only
    certain = np.zeros_like(per_hand)
    certain[:, 0, 60:90, 15:25] = 1
    certain[1, 1, 55:90, 96:106] = 1
    masks = per_hand.max(axis=1)  # (2, H, W)
    out = propagate_hands(frames, masks, per_hand, certain)
    sleeve0 = np.zeros((96, 128), bool)
    sleeve0[42:96, 92:110] = True  # hand 1 in frame 0, 2 px inside its edges
    assert out[0][sleeve0].mean() > 0.9, f"missed hand covered {out[0][sleeve0].mean():.2f}"
    outside = np.ones((96, 128), bool)
    outside[36:, 86:116] = False
    outside[46:, 6:34] = False
    assert out[0][outside].sum() == 0, "carried mask leaked onto the table"
    np.testing.assert_array_equal(out[1], masks[1])


def _drawn_hand(wrist: tuple[float, float]) -> np.ndarray:
    """21 keypoints ``(21, 2)`` of an open hand pointing up, wrist at ``wrist`` (pixels)."""
    kp = np.zeros((21, 2))
    kp[0] = (0.0, 0.0)
    for j, (dx, angle) in enumerate(((-14.0, -150.0), (-7, -100), (0, -90), (7, -80), (13, -70))):
        base = 1 + 4 * j
        start = np.array([dx * 0.5, -10.0]) if j == 0 else np.array([dx, -30.0])
        step = 10.0 * np.array([np.cos(np.radians(angle)), np.sin(np.radians(angle))])
        for i in range(4):
            kp[base + i] = start + i * step
    return kp + np.asarray(wrist)


def _moving_hand_frames(shifts: list[tuple[int, int]], gone_from: int = 99) -> np.ndarray:
    """Frames ``(T, 96, 128, 3)``: a textured hand patch moving over a textured static table by
    ``shifts`` (dx, dy per frame, cumulative); from frame ``gone_from`` on, no hand."""
    rng = np.random.default_rng(5)
    table = cv2.GaussianBlur(
        np.clip(rng.normal(120, 35, (96, 128, 3)), 0, 255).astype(np.uint8), (5, 5), 0
    )
    skin = cv2.GaussianBlur(
        np.clip(rng.normal((200, 150, 120), 25, (96, 128, 3)), 0, 255).astype(np.uint8),
        (5, 5),
        0,
    )
    region = draw_hand(_drawn_hand((40.5, 80.5)), 0, 96, 128, CapsuleParams(forearm=False))[0]
    frames, x, y = [], 0, 0
    for t, (dx, dy) in enumerate(shifts):
        x, y = x + dx, y + dy
        f = table.copy()
        if t < gone_from:
            moved = np.float32([[1, 0, x], [0, 1, y]])
            m = cv2.warpAffine(region, moved, (128, 96), flags=cv2.INTER_NEAREST) > 0
            s = cv2.warpAffine(skin, moved, (128, 96))
            f[m] = s[m]
        frames.append(f)
    return np.stack(frames)


def test_missed_hand_keypoints_are_carried_by_tracking() -> None:
    """A hand found in frame 0 only, moving 6 px right and 3 px down per frame: its keypoints
    are carried into frames 1-3 within a pixel (dwm_00013 t=33: a fast hand the dense-flow
    propagation lost); a hand found in the last frame is carried backwards the same way."""
    from egosim.stages.hand_mask.carry import carry_keypoints

    frames = _moving_hand_frames([(0, 0), (6, 3), (6, 3), (6, 3)])
    truth = np.stack([_drawn_hand((40.5 + 6 * t, 80.5 + 3 * t)) for t in range(4)])  # (4, 21, 2)
    kp = np.full((4, 2, 21, 2), np.nan)
    kp[0, 0] = truth[0]
    kp[3, 1] = truth[3]  # hand 1: the same hand, found in the last frame only
    valid = np.zeros((4, 2), bool)
    valid[0, 0] = valid[3, 1] = True
    out, ok, carried = carry_keypoints(frames, kp, valid)
    assert ok.all() and carried[1:, 0].all() and carried[:3, 1].all()
    assert not carried[0, 0] and not carried[3, 1]
    err_fwd = np.abs(out[1:, 0] - truth[1:]).max()
    err_back = np.abs(out[:3, 1] - truth[:3]).max()
    assert err_fwd < 1.0 and err_back < 1.0, f"carried off by {err_fwd:.2f} / {err_back:.2f} px"
    np.testing.assert_array_equal(out[0, 0], truth[0])


def test_hand_that_leaves_is_not_carried() -> None:
    """The hand vanishes after frame 1 (left the view, covered): the table where it was does
    not move with it, so the track stops there and no ghost hand is carried into frames 2-3;
    the frame limit also holds."""
    from egosim.stages.hand_mask.carry import CarryParams, carry_keypoints

    frames = _moving_hand_frames([(0, 0), (6, 3), (6, 3), (6, 3)], gone_from=2)
    kp = np.full((4, 1, 21, 2), np.nan)
    kp[0, 0] = _drawn_hand((40.5, 80.5))
    valid = np.zeros((4, 1), bool)
    valid[0, 0] = True
    _, ok, carried = carry_keypoints(frames, kp, valid)
    assert carried[1, 0], "the hand still in view in frame 1 was not carried"
    assert not ok[2:, 0].any(), "a hand was carried into frames without one"
    moving = _moving_hand_frames([(0, 0), (6, 3), (6, 3), (6, 3)])
    _, ok, _ = carry_keypoints(moving, kp, valid, CarryParams(max_frames=2))
    assert ok[:3, 0].all() and not ok[3, 0], "carried past max_frames"


def test_arm_not_reaimed_along_a_sideways_shade(monkeypatch: pytest.MonkeyPatch) -> None:
    """DWM 00013 t=25: the direction search, fooled by the shaded cushion, turned the arm 20
    degrees off the hand's direction, and the arm-coloured region (mostly the shade) then
    re-aimed it 47 degrees farther, nearly sideways: the certain arm seed lay on the cushion.
    The re-aiming is refused when it turns more than ``refine_slack_deg`` past the search
    (hand_mask v11), so the seed stays off the shade; without the limit it does not."""
    import egosim.stages.hand_mask.arm_region as arm_region

    h, w = 160, 240
    wrist = np.array([60.5, 128.5])
    image = _sleeve_frame(h, w, wrist, np.array([0.0, 1.0]), 7)  # the arm: down, 30 px in view
    shade = np.array([np.cos(np.radians(5.0)), np.sin(np.radians(5.0))])  # nearly sideways
    start = wrist + 12 * shade
    cv2.line(image, tuple(int(v) for v in start), tuple(int(v) for v in wrist + 400 * shade),
             (150, 40, 160), 25)  # fmt: skip
    kp = _hand_keypoints(wrist, np.array([0.0, -1.0]), 30.0, 20.0)  # fingers up: arm down
    fooled = np.array([np.cos(np.radians(60.0)), np.sin(np.radians(60.0))])  # 30 deg off down
    monkeypatch.setattr(arm_region, "arm_direction", lambda *args, **kwargs: fooled)
    far_shade = np.zeros((h, w), bool)
    far_shade[110:150, 130:] = True  # the shade more than 70 px from the wrist
    certain = {}
    for slack in (40.0, 180.0):
        params = arm_region.ArmParams(refine_slack_deg=slack)
        _, _, seeds = arm_region.hand_arm_masks(
            image, kp[None], np.array([True]), CapsuleParams(), params
        )
        certain[slack] = int(seeds[0][far_shade].sum())
    assert certain[40.0] == 0, f"{certain[40.0]} certain arm px on the far shade"
    assert certain[180.0] > 200, f"without the limit the seed should follow the shade: {certain}"


def test_carried_hand_frame_still_receives_its_neighbours_mask() -> None:
    """A frame whose hand was carried there by tracking has a mask of its own, often without
    the arm (EgoDex t=11, 41-42); marked open, it still receives the neighbour's mask (the arm)
    by propagation, joined to its own; not marked, it keeps its own only."""
    from egosim.stages.hand_mask.propagate import propagate_hands

    table = _static_table()
    frames = np.stack([table.copy(), table.copy()])
    for f in frames:
        f[30:96, 90:112] = (60, 40, 90)  # a still arm in a dark sleeve, from the bottom border
    per_hand = np.zeros((2, 1, 96, 128), np.uint8)
    per_hand[1, 0, 30:96, 90:112] = 1  # frame 1: hand and arm
    per_hand[0, 0, 30:50, 90:112] = 1  # frame 0 (carried hand): the hand only
    certain = np.zeros_like(per_hand)
    certain[1, 0, 40:90, 96:106] = 1
    certain[0, 0, 35:45, 96:106] = 1
    masks = per_hand.max(axis=1)  # (2, H, W)
    arm0 = np.zeros((96, 128), bool)
    arm0[55:94, 92:110] = True  # the arm in frame 0, inside its edges
    opened = np.array([[True], [False]])
    out = propagate_hands(frames, masks, per_hand, certain, open_frames=opened)
    assert out[0][arm0].mean() > 0.9, f"arm covered {out[0][arm0].mean():.2f}"
    assert out[0][30:50, 90:112].all(), "the frame's own mask was lost"
    outside = np.ones((96, 128), bool)
    outside[24:, 84:118] = False
    assert out[0][outside].sum() == 0, "carried mask leaked onto the table"
    closed = propagate_hands(frames, masks, per_hand, certain)
    assert closed[0][arm0].mean() < 0.1, "a frame with its own mask received without opening"


def test_carry_skips_steps_the_nearer_side_already_made(monkeypatch: pytest.MonkeyPatch) -> None:
    """A hand found in frames 0 and 3 of a moving clip: frame 1 takes frame 0's carry, frame 2
    frame 3's, each within a pixel; the backward track from frame 3 stops at frame 1, which the
    forward one reached nearer, so three tracking steps are made, not four."""
    import egosim.stages.hand_mask.carry as carry

    frames = _moving_hand_frames([(0, 0), (6, 3), (6, 3), (6, 3)])
    truth = np.stack([_drawn_hand((40.5 + 6 * t, 80.5 + 3 * t)) for t in range(4)])  # (4, 21, 2)
    kp = np.full((4, 1, 21, 2), np.nan)
    kp[[0, 3], 0] = truth[[0, 3]]
    valid = np.zeros((4, 1), bool)
    valid[[0, 3], 0] = True
    steps: list[int] = []
    step = carry.carry_step

    def counted(
        grey_a: np.ndarray, grey_b: np.ndarray, keypoints: np.ndarray, p: carry.CarryParams
    ) -> np.ndarray | None:
        steps.append(1)
        return step(grey_a, grey_b, keypoints, p)

    monkeypatch.setattr(carry, "carry_step", counted)
    out, ok, carried = carry.carry_keypoints(frames, kp, valid)
    assert ok.all() and carried[1:3, 0].all() and not carried[[0, 3], 0].any()
    err = np.abs(out[1:3, 0] - truth[1:3]).max()
    assert err < 1.0, f"carried off by {err:.2f} px"
    assert len(steps) == 3, f"{len(steps)} tracking steps"


def test_found_hand_without_a_wrist_is_not_replaced_by_a_carried_one() -> None:
    """A hand found in frame 1 whose wrist is unknown (NaN: below the joint confidence, behind
    the camera) is kept as found, not overwritten by the hand carried from frame 0, and the
    track does not pass through it into frame 2."""
    from egosim.stages.hand_mask.carry import carry_keypoints

    frames = _moving_hand_frames([(0, 0), (6, 3), (6, 3), (6, 3)])
    truth = np.stack([_drawn_hand((40.5 + 6 * t, 80.5 + 3 * t)) for t in range(4)])  # (4, 21, 2)
    kp = np.full((4, 1, 21, 2), np.nan)
    kp[:2, 0] = truth[:2]
    kp[1, 0, 0] = np.nan  # frame 1: found, wrist unknown
    valid = np.zeros((4, 1), bool)
    valid[:2, 0] = True
    out, ok, carried = carry_keypoints(frames, kp, valid)
    np.testing.assert_array_equal(out[1, 0], kp[1, 0])
    assert not carried.any() and not ok[2:, 0].any()


def test_stage_masks_a_missed_hand_where_carry_puts_it() -> None:
    """The ``keypoints`` backend end to end: a hand found in frame 0 only, moving 6 px right and
    3 px down per frame, is masked in frames 1-3 where it is (IoU > 0.9 against its capsules at
    the true keypoints) with ``carry_frames`` on, and not at all with it off."""
    from egosim.stages.hand_mask.stage import masks_from_keypoints

    frames = _moving_hand_frames([(0, 0), (6, 3), (6, 3), (6, 3)])
    truth = np.stack([_drawn_hand((40.5 + 6 * t, 80.5 + 3 * t)) for t in range(4)])  # (4, 21, 2)
    kp = np.full((4, 2, 21, 2), np.nan)
    kp[0, 0] = truth[0]
    valid = np.zeros((4, 2), bool)
    valid[0, 0] = True
    plain = {"forearm": False, "colour_refine": False}
    masks = masks_from_keypoints(frames, kp, valid, HandMaskConfig(**plain))  # (4, H, W)
    for t in range(1, 4):
        want = draw_hand(truth[t], -1, 96, 128, CapsuleParams(forearm=False))[0] > 0
        got = masks[t] > 0
        score = (want & got).sum() / (want | got).sum()
        assert score > 0.9, f"frame {t}: IoU {score:.2f} with the moved hand"
    off = masks_from_keypoints(frames, kp, valid, HandMaskConfig(carry_frames=0, **plain))
    assert not off[1:].any()


def _two_sleeves() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(lab (200, 200, 3), wrist, sleeve direction, sleeve Lab, table Lab)``: a plain table, a
    knitted sleeve (Lab noise 12) 44 px wide leaving the wrist 35 degrees off "down", and the
    other arm's sleeve (the same knit) filling the lower left, so that a smooth strip of table
    runs between the two arms (EgoDex t=24, hand_mask v16)."""
    rng = np.random.default_rng(0)
    h = w = 200
    table = np.array([128.0, 143.0, 173.0], np.float32)
    knit = np.array([100.0, 165.0, 168.0], np.float32)
    lab = np.tile(table, (h, w, 1))
    yy, xx = np.mgrid[0:h, 0:w] + 0.5
    wrist = np.array([100.0, 60.0])
    other = (xx < 86) & (yy > 70)
    lab[other] = knit + rng.normal(0, 12, (int(other.sum()), 3)).astype(np.float32)
    d = np.array([np.sin(np.radians(35.0)), np.cos(np.radians(35.0))])  # (2,) the sleeve
    rel = np.stack([xx - wrist[0], yy - wrist[1]], -1)  # (H, W, 2)
    sleeve = (rel @ d > 0) & (np.abs(rel @ np.array([-d[1], d[0]])) < 22)
    lab[sleeve] = knit + rng.normal(0, 12, (int(sleeve.sum()), 3)).astype(np.float32)
    return lab, wrist, d, knit, table


def test_arm_search_other_arm_colour() -> None:
    """Alone, the search takes the smooth table between two knitted sleeves (it stands out from
    its sides, the arms; the sleeve's sides lie on itself); given the other arm's colour it
    follows the sleeve (within 30 degrees, its colour within 10 Lab units of the knit's); a
    colour far from every strip changes nothing."""
    from egosim.stages.hand_mask.arm_region import arm_search

    lab, wrist, sleeve, knit, table = _two_sleeves()
    none = np.zeros(lab.shape[:2], np.uint8)
    down = np.array([0.0, 1.0])
    alone, colour, score = arm_search(lab, wrist, down, 30.0, none, 90.0, 3.0, 7.0)
    assert np.linalg.norm(colour - table) < 3.0, colour  # the gap between the arms
    assert np.isfinite(score)
    told, colour, _ = arm_search(lab, wrist, down, 30.0, none, 90.0, 3.0, 7.0, knit)
    assert np.degrees(np.arccos(np.clip(told @ sleeve, -1, 1))) <= 30.0, told
    assert np.linalg.norm(colour - knit) < 10.0, colour
    far, _, far_score = arm_search(lab, wrist, down, 30.0, none, 90.0, 3.0, 7.0, table + 60)
    assert np.allclose(far, alone) and far_score == score


def test_other_arm_colours_from_the_surer_hand() -> None:
    """Only the less certain of two hands is given the other's arm colour (that arm's strip
    colour), and only while its own score is above ``other_arm_unsure`` and that colour is rare
    in the frame; a hand alone, or an invalid other hand, gives none."""
    from egosim.stages.hand_mask.arm_region import ArmParams, arm_search, other_arm_colours

    h, w = 160, 240
    image = np.full((h, w, 3), (200, 200, 200), np.uint8)  # a plain grey table
    cv2.line(image, (60, 60), (60, 159), (150, 40, 160), 20)  # hand 0's arm: straight down
    cv2.line(image, (180, 60), (239, 159), (150, 40, 160), 20)  # hand 1's: turned, sideways
    lab = cv2.cvtColor(image, cv2.COLOR_RGB2LAB).astype(np.float32)
    kps = []
    for x in (60.5, 180.5):
        kp = np.full((21, 2), np.nan)
        kp[0] = [x, 60.5]
        for j, dx in zip((5, 9, 13, 17), (-9.0, -3.0, 3.0, 9.0), strict=True):
            kp[j] = [x + dx, 30.5]  # knuckles above the wrist: the arm is searched "down"
        kps.append(kp)
    kps = np.stack(kps)  # (2, 21, 2)
    capsule, arm = CapsuleParams(), ArmParams(other_arm_unsure=0.0)
    scores = []
    for kp in kps:
        scale = hand_scale_px(kp)
        mask, _ = draw_hand(kp, 0, h, w, CapsuleParams(forearm=False))
        hand_len = max(30.0, 0.092 * scale)
        scores.append(arm_search(lab, kp[0], np.array([0.0, 1.0]), hand_len, mask, 90.0, 3.0,
                                 0.027 * scale))  # fmt: skip
    assert scores[0][2] < scores[1][2]  # the straight arm is the surer one
    given = other_arm_colours(lab, kps, np.array([True, True]), capsule, arm)
    assert given[0] is None
    assert given[1] is not None and np.allclose(given[1], scores[0][1])
    assert other_arm_colours(lab, kps, np.array([False, True]), capsule, arm) == [None, None]
    # the arms' purple covers 12% of the frame: too common for a limit of 5%
    common = dataclasses.replace(arm, other_arm_rare=0.05)
    assert other_arm_colours(lab, kps, np.array([True, True]), capsule, common) == [None, None]
    # hand 1's arm, found clearly enough on its own, keeps its own choice
    sure = dataclasses.replace(arm, other_arm_unsure=scores[1][2] * 1.01)
    assert other_arm_colours(lab, kps, np.array([True, True]), capsule, sure) == [None, None]


def test_carry_stops_where_the_background_the_hand_left_tracks(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """HOT3D w001 t=2 (hand_mask v17): a hand leaves the view fast; its own pixels fail the
    backward check, the dark floor it uncovered inside its capsules tracks and the similarity
    fit keeps the keypoints on the floor. The carried skeleton's colour then jumps from skin
    to floor, so the track stops (v16 carried a ghost hand for 8 frames and masked the table
    and floor round it); a carry whose skeleton stays on the hand goes on."""
    import egosim.stages.hand_mask.carry as carry

    frames = _moving_hand_frames([(0, 0), (0, 0), (0, 0)], gone_from=1)
    frames = frames // 3  # dark floor
    frames[0] = _moving_hand_frames([(0, 0)])[0]  # the hand (skin) on its table in frame 0
    kp = np.full((3, 1, 21, 2), np.nan)
    kp[0, 0] = _drawn_hand((40.5, 80.5))
    valid = np.zeros((3, 1), bool)
    valid[0, 0] = True
    # The fit to the uncovered floor: the keypoints stay where they were.
    monkeypatch.setattr(carry, "carry_step", lambda a, b, keypoints, p: keypoints.copy())
    _, ok, carried = carry.carry_keypoints(frames, kp, valid)
    assert not carried.any() and not ok[1:].any(), "a ghost hand was carried onto the floor"
    _, ok, _ = carry.carry_keypoints(frames, kp, valid, carry.CarryParams(colour_tolerance=0))
    assert ok.all(), "with the colour check off the ghost is carried (v16)"
    still = _moving_hand_frames([(0, 0), (0, 0), (0, 0)])  # the hand stays: carried
    _, ok, carried = carry.carry_keypoints(still, kp, valid)
    assert carried[1:, 0].all()


def test_letterbox_bar_is_never_hand() -> None:
    """HOT3D's 480 x 832 frames end in a black bar (32 rows of 0): a hand whose arm runs down
    into it was masked there (v16: the arm's seed strip is certain hand, and GrabCut joins the
    black bar to a dark floor); v17 masks nothing in the bar, and ``padding`` finds bars of
    whole rows or columns from the edges only (not a black object inside the picture)."""
    from egosim.stages.hand_mask.stage import masks_from_keypoints, padding

    frames = _moving_hand_frames([(0, 0), (0, 0)])
    frames[:, 86:] = 0  # a 10-row bar at the bottom
    frames[:, 40:50, 100:110] = 0  # a black object inside the picture
    bar = padding(frames[0])
    assert bar[86:].all() and not bar[:86].any()
    kp = np.tile(_drawn_hand((40.5, 80.5)), (2, 1, 1, 1))  # (2, 1, 21, 2)
    valid = np.ones((2, 1), bool)
    masks = masks_from_keypoints(frames, kp, valid, HandMaskConfig())
    assert masks[:, :86].any() and not masks[:, 86:].any()
    side = np.zeros((8, 10, 3), np.uint8)
    side[:, :2] = 0
    side[:, 2:] = 90
    assert padding(side)[:, :2].all() and not padding(side)[:, 2:].any()


def _swing_clip(swing: tuple[int, ...], t_count: int = 7) -> tuple[np.ndarray, ...]:
    """``(frames (T, H, W, 3), keypoints (T, 2, 21, 2), valid (T, 2), sleeve (H, W), bar (H, W))``:
    one hand whose purple sleeve runs straight down from its wrist over a busy table; in the
    ``swing`` frames the sleeve is knitted (dark stripes across it) and a smooth teal bar runs
    from the wrist 70 degrees to the side, which the colour search then prefers."""
    h, w = 160, 240
    wrist, down = np.array([120.5, 50.5]), np.array([0.0, 1.0])
    side = np.array([np.cos(np.radians(20.0)), np.sin(np.radians(20.0))])
    frames = []
    for t in range(t_count):
        rng = np.random.default_rng(10 + t)
        image = np.clip(rng.normal(120, 40, (h, w, 3)), 0, 255).astype(np.uint8)
        image = cv2.GaussianBlur(image, (5, 5), 0)
        end = wrist + 400 * down
        cv2.line(
            image, tuple(int(v) for v in wrist), tuple(int(v) for v in end), (150, 40, 160), 17
        )
        if t in swing:
            for y in range(int(wrist[1]) + 4, h, 6):
                cv2.line(image, (112, y), (129, y), (60, 20, 70), 2)
            bar_end = wrist + 400 * side
            cv2.line(image, tuple(int(v) for v in wrist), tuple(int(v) for v in bar_end),
                     (40, 150, 150), 17)  # fmt: skip
        frames.append(image)
    kp = _hand_keypoints(wrist, -down, 30.0, 20.0)  # (21, 2)
    keypoints = np.full((t_count, 2, 21, 2), np.nan)
    keypoints[:, 0] = kp
    valid = np.zeros((t_count, 2), bool)
    valid[:, 0] = True
    sleeve, bar = _sleeve_pixels(h, w, wrist, down), _sleeve_pixels(h, w, wrist, side)
    return np.stack(frames), keypoints, valid, sleeve, bar & ~sleeve


def test_arm_that_swings_away_for_a_few_frames_is_drawn_between_its_neighbours(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Frames 2-4 of 7: a knitted sleeve and a smooth bar 70 degrees off, which the per-frame
    search takes (HOT3D window 1's floor, t=25-34). The frames either side find the sleeve,
    so those three are drawn along it (hand_mask v18): sleeve masked, bar not; without the
    rule (``steady_frames`` 0) they mask the bar and miss the sleeve."""
    import egosim.stages.hand_mask.stage as stage

    frames, keypoints, valid, sleeve, bar = _swing_clip((2, 3, 4))
    masks = stage.masks_from_keypoints(frames, keypoints, valid, HandMaskConfig()) > 0
    for t in range(7):
        assert masks[t][sleeve].mean() > 0.9, f"t={t} sleeve {masks[t][sleeve].mean():.2f}"
        assert masks[t][bar].mean() < 0.05, f"t={t} bar {masks[t][bar].mean():.2f}"
    off = dataclasses.replace(stage.ArmParams(), steady_frames=0)
    monkeypatch.setattr(stage, "ArmParams", lambda **kw: dataclasses.replace(off, **kw))
    old = stage.masks_from_keypoints(frames, keypoints, valid, HandMaskConfig()) > 0
    assert all(old[t][bar].mean() > 0.5 and old[t][sleeve].mean() < 0.3 for t in (2, 3, 4))


def test_steady_directions_keeps_turns_that_stay_or_runs_too_long() -> None:
    """Only a short run between agreeing neighbours is replaced: an arm that turns and stays
    turned (no agreeing frame after), one that turns by 10 degrees a frame, a run longer than
    ``max_frames`` and a run whose neighbours disagree are kept; frames without a hand are
    never given a direction."""
    from egosim.stages.hand_mask.arm_region import steady_directions

    def series(degrees: list[float]) -> np.ndarray:
        rad = np.radians(np.asarray(degrees, float))
        return np.stack([np.cos(rad), np.sin(rad)], axis=-1)[:, None]  # (T, 1, 2)

    kept = {
        "turned for good": [90, 90, 170, 170, 170, 170],
        "gradual": [90, 100, 110, 120, 130, 140, 150],
        "too long": [90] + [170] * 4 + [90],
        "neighbours disagree": [90, 170, 170, 140],
        "no hand": [90, np.nan, 90],
    }
    for name, degrees in kept.items():
        out = steady_directions(series(degrees), 3, 45.0, 30.0)
        assert not np.isfinite(out).any(), name
    out = steady_directions(series([90, 80, 170, 175, 100, 95]), 3, 45.0, 30.0)  # (T, 1, 2)
    got = np.degrees(np.arctan2(out[:, 0, 1], out[:, 0, 0]))
    assert np.isnan(got[[0, 1, 4, 5]]).all()
    np.testing.assert_allclose(got[2:4], [86.7, 93.3], atol=0.1)  # 80 -> 100, by time


def _floor_edge_frame() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(frame (H, W, 3), keypoints (21, 2), arm (H, W), floor (H, W))``, after HOT3D window
    1's frame 0: a hand whose own direction (wrist minus middle knuckle) is 44 degrees (image,
    y down) lies on the edge of a white table, 20 degrees below the horizontal through its
    wrist; below the edge a near-black, uniform floor; the skin forearm runs from the wrist at
    110 degrees over the floor. A floor strip along the table's edge stands out from the table
    on one side and not from the floor on the other: by the mean contrast of its two sides
    (and a smaller turn) it beats the forearm, which stands out from both (v18: 44 degrees,
    score 0.03; nearer side: the forearm, 0.32)."""
    h, w = 160, 240
    rng = np.random.default_rng(3)
    wrist = np.array([100.5, 60.5])
    table = np.clip(rng.normal((235, 232, 225), 6, (h, w, 3)), 0, 255)
    floor = np.clip(rng.normal(12, 1.5, (h, w, 3)), 0, 255)
    yy, xx = np.mgrid[0:h, 0:w] + 0.5
    edge = np.radians(20.0)
    below = (yy - wrist[1]) * np.cos(edge) - (xx - wrist[0]) * np.sin(edge) > 0  # (H, W)
    image = np.where(below[..., None], floor, table).astype(np.uint8)
    d = np.array([np.cos(np.radians(110.0)), np.sin(np.radians(110.0))])
    skin = np.zeros((h, w), np.uint8)
    cv2.line(skin, tuple(int(v) for v in wrist), tuple(int(v) for v in wrist + 400 * d), 1, 19)
    texture = np.clip(rng.normal((200, 150, 130), 8, (h, w, 3)), 0, 255).astype(np.uint8)
    image[skin > 0] = texture[skin > 0]
    up = -np.array([np.cos(np.radians(50.0)), np.sin(np.radians(50.0))])  # wrist to knuckles
    kp = _hand_keypoints(wrist, up, 30.0, 20.0)  # (21, 2)
    arm = _sleeve_pixels(h, w, wrist, d)
    near = cv2.dilate(skin, np.ones((3, 3), np.uint8), iterations=12) > 0  # the arm and its rim
    return image, kp, arm, below & ~near


def test_first_frame_arm_must_stand_out_from_both_sides(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """HOT3D window 1's frame 0 (hand_mask v19): the search took a uniform strip of dark floor
    that stands out on one side only over the forearm, and no steady run can correct a track's
    first frame. There the strip's contrast is the nearer side's: the forearm is masked and
    the floor is not; without the rule (``start_both_sides`` False) the floor is masked and the
    forearm missed."""
    import egosim.stages.hand_mask.stage as stage
    from egosim.stages.hand_mask import arm_region

    image, kp, arm, floor = _floor_edge_frame()
    start = arm_region._arm_start(kp, CapsuleParams(), arm_region.ArmParams(), *image.shape[:2])
    assert start is not None
    mask, wrist, d, hand_len, radius, _ = start
    lab = cv2.cvtColor(image, cv2.COLOR_RGB2LAB).astype(np.float32)
    angles = {}
    for nearer in (False, True):
        best, _, _ = arm_region.arm_search(lab, wrist, d, hand_len, mask, 90.0, 3.0, radius,
                                           nearer_side=nearer)  # fmt: skip
        angles[nearer] = float(np.degrees(np.arctan2(best[1], best[0])))
    assert abs(angles[True] - 110.0) <= 15.0, angles  # the forearm
    assert abs(angles[False] - 110.0) > 30.0, angles  # a floor strip

    frames = np.stack([image, image])  # (2, H, W, 3): the hand's track starts at t=0
    keypoints = np.full((2, 2, 21, 2), np.nan)
    keypoints[:, 0] = kp
    valid = np.array([[True, False], [True, False]])
    masks = stage.masks_from_keypoints(frames, keypoints, valid, HandMaskConfig()) > 0
    assert masks[0][arm].mean() > 0.9, f"forearm {masks[0][arm].mean():.2f}"
    assert masks[0][floor].mean() < 0.02, f"floor {masks[0][floor].mean():.3f}"
    off = dataclasses.replace(stage.ArmParams(), start_both_sides=False)
    monkeypatch.setattr(stage, "ArmParams", lambda **kw: dataclasses.replace(off, **kw))
    old = stage.masks_from_keypoints(frames, keypoints, valid, HandMaskConfig()) > 0
    assert old[0][floor].mean() > 0.3 and old[0][arm].mean() < 0.5, (
        f"without the rule: floor {old[0][floor].mean():.2f}, forearm {old[0][arm].mean():.2f}"
    )


def test_track_starts_are_the_first_frames_of_each_hand(monkeypatch: pytest.MonkeyPatch) -> None:
    """The search asks a strip to stand out from both sides exactly in the frames where a
    hand's track starts: frame 0, and a frame after one that missed that hand."""
    import egosim.stages.hand_mask.stage as stage

    seen: dict[int, list[bool]] = {}

    def recording(
        image: np.ndarray, keypoints: np.ndarray, valid: np.ndarray, capsule: CapsuleParams,
        arm: object, directions: np.ndarray | None = None, starts: np.ndarray | None = None,
        no_region: np.ndarray | None = None, allow_top: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
        assert starts is not None
        seen[len(seen)] = [bool(v) for v in starts]
        h, w = image.shape[:2]
        k = len(keypoints)
        return np.zeros((k, h, w), np.uint8), np.full((k, 2), np.nan), np.ones(k, bool)

    monkeypatch.setattr(stage, "hand_labels", recording)
    valid = np.array([[True, False], [True, True], [False, True], [True, True], [True, False]])
    frames = np.zeros((5, 16, 16, 3), np.uint8)
    keypoints = np.full((5, 2, 21, 2), np.nan)
    stage.masks_from_keypoints(frames, keypoints, valid, HandMaskConfig(carry_frames=0))
    assert [seen[t] for t in range(5)] == [
        [True, False], [False, True], [False, False], [True, False], [False, False]
    ]  # fmt: skip


def test_crosses_other_wrist_marks_arms_on_the_other_hands_side() -> None:
    """A left arm whose ray meets the border right of the right wrist (or a right arm left of
    the left wrist) is marked; arms going down on their own side, a frame with one hand and
    hands in the other order are not."""
    from egosim.stages.hand_mask.arm_region import crosses_other_wrist

    def unit(deg: float) -> np.ndarray:
        return np.array([np.cos(np.radians(deg)), np.sin(np.radians(deg))])

    keypoints = np.full((6, 2, 21, 2), np.nan)
    keypoints[:, 0, 0] = [60.0, 50.0]  # left wrist
    keypoints[:, 1, 0] = [140.0, 50.0]  # right wrist
    keypoints[5, 0, 0], keypoints[5, 1, 0] = [140.0, 50.0], [60.0, 50.0]  # swapped sides
    valid = np.ones((6, 2), bool)
    valid[4, 1] = False
    left = [0.0, 90.0, 30.0, 60.0, 0.0, 0.0]  # degrees, image y down
    right = [100.0, 180.0, 100.0, 150.0, 180.0, 180.0]
    drawn = np.stack([np.stack([unit(a), unit(b)]) for a, b in zip(left, right, strict=True)])
    got = crosses_other_wrist(keypoints, valid, drawn, 100, 200)  # (6, 2)
    # 30 deg: meets the bottom at x = 60 + 50 / tan 30 = 146.6 > 140; 60 deg: x = 88.9;
    # 150 deg: the right arm meets the bottom at x = 140 - 86.6 = 53.4 < 60
    want = [[True, False], [False, True], [True, False], [False, True], [False, False],
            [False, False]]  # fmt: skip
    assert got.tolist() == want


def test_crosses_other_wrist_spares_nearly_vertical_arms_of_hands_close_together() -> None:
    """Two hands close together on one object (wrists 5 px apart), each arm 8 degrees off
    straight down towards the other: the rays meet the bottom border past the other wrist (by
    2 px), but an arm that steep is not following a table edge sideways; not marked (review10c:
    both were). Tilted 50 degrees (past ``off_side_min_tilt_deg``, 45) they are."""
    from egosim.stages.hand_mask.arm_region import crosses_other_wrist

    keypoints = np.full((2, 2, 21, 2), np.nan)
    keypoints[:, 0, 0] = [95.0, 50.0]  # left wrist
    keypoints[:, 1, 0] = [100.0, 50.0]  # right wrist
    valid = np.ones((2, 2), bool)
    drawn = np.zeros((2, 2, 2))
    for t, tilt in enumerate((8.0, 50.0)):  # degrees from straight down, towards the other
        s, c = np.sin(np.radians(tilt)), np.cos(np.radians(tilt))
        drawn[t] = [[s, c], [-s, c]]
    got = crosses_other_wrist(keypoints, valid, drawn, 100, 200)  # (2, 2)
    assert got.tolist() == [[False, False], [True, True]]


def test_steady_directions_replaces_a_run_through_an_off_side_frame() -> None:
    """A run whose last frame turned back only 30-40 degrees (not a swing by angle) is still
    drawn between its agreeing neighbours when that frame's arm is on the other hand's side
    (HOT3D window 1, t=37-45); without the mark nothing is replaced."""
    from egosim.stages.hand_mask.arm_region import steady_directions

    rad = np.radians([90.0, 90.0, 20.0, 50.0, 80.0, 85.0])
    drawn = np.stack([np.cos(rad), np.sin(rad)], axis=-1)[:, None]  # (T, 1, 2)
    assert not np.isfinite(steady_directions(drawn, 10, 45.0, 30.0)).any()
    off = np.zeros((6, 1), bool)
    off[3] = True
    out = steady_directions(drawn, 10, 45.0, 30.0, off)  # (T, 1, 2)
    got = np.degrees(np.arctan2(out[:, 0, 1], out[:, 0, 0]))
    assert np.isnan(got[[0, 1, 4, 5]]).all()
    np.testing.assert_allclose(got[2:4], [86.7, 83.3], atol=0.1)  # 90 -> 80, by time
    off[1] = True  # an off-side frame never brackets a run: it joins it
    out = steady_directions(drawn, 10, 45.0, 30.0, off)
    got = np.degrees(np.arctan2(out[:, 0, 1], out[:, 0, 0]))
    np.testing.assert_allclose(got[1:4], [87.5, 85.0, 82.5], atol=0.1)  # between t=0 and t=4


def test_off_side_runs_are_the_replaced_runs_holding_an_off_side_frame() -> None:
    """Of each hand's replaced runs (consecutive frames with a steady direction), exactly those
    holding an off-side frame are marked, all their frames; other runs, other hands and kept
    frames are not."""
    from egosim.stages.hand_mask.arm_region import off_side_runs

    steady = np.full((9, 2, 2), np.nan)
    steady[1:4, 0] = [0.0, 1.0]  # run A of hand 0: t=1-3, holds the off-side t=2
    steady[5:7, 0] = [0.0, 1.0]  # run B of hand 0: t=5-6, no off-side frame
    steady[5:8, 1] = [1.0, 0.0]  # run C of hand 1: t=5-7, holds the off-side t=7
    off = np.zeros((9, 2), bool)
    off[[2, 8], 0] = True  # t=8 is off-side but kept (not in a run)
    off[7, 1] = True
    got = off_side_runs(steady, off)
    want = np.zeros((9, 2), bool)
    want[1:4, 0] = True
    want[5:8, 1] = True
    assert got.tolist() == want.tolist()


def test_guessed_direction_drawn_without_its_colour_region() -> None:
    """A direction drawn as given (a steady run's interpolation) into a near-black floor next
    to a white table: with the colour region probable, floor connected to that strip is
    labelled arm more than 30 px from the drawn axis; with ``no_region`` (a run through an
    off-side frame, hand_mask v20) only the band along the axis is."""
    from egosim.stages.hand_mask.arm_region import ArmParams, hand_labels

    image, kp, _, floor = _floor_edge_frame()
    h, w = image.shape[:2]
    d = np.array([[np.cos(np.radians(35.0)), np.sin(np.radians(35.0))]])  # (1, 2) onto the floor
    yy, xx = np.mgrid[0:h, 0:w] + 0.5
    axis_px = np.abs((xx - kp[0, 0]) * d[0, 1] - (yy - kp[0, 1]) * d[0, 0])  # (H, W)
    far = floor & (axis_px > 30.0)  # floor well off the band
    counts = []
    for no_region in (None, np.array([True])):
        own, drawn, _ = hand_labels(
            image, kp[None], np.array([True]), CapsuleParams(), ArmParams(), d, None, no_region
        )
        np.testing.assert_allclose(drawn, d)  # drawn as given either way
        counts.append(int(np.isin(own[0][far], (cv2.GC_FGD, cv2.GC_PR_FGD)).sum()))
    assert counts[0] > 1000 and counts[1] < 50, counts


def test_only_runs_the_off_side_mark_adds_lose_their_colour_region(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """hand_mask v20 in the stage: the left arm at t=2 turns 40 degrees (not a swing by angle)
    but its ray crosses past the right wrist, so t=2 is drawn between its neighbours and
    without the probable colour region; the right arm's swing at t=2 (60 degrees, also
    off-side) is a run v18 finds by angle alone and keeps its colour region (HOT3D window 3,
    t=5-9). With ``steady_off_side`` off neither is marked and only the right arm's run is
    redrawn."""
    import egosim.stages.hand_mask.stage as stage

    def unit(deg: float) -> list[float]:
        return [float(np.cos(np.radians(deg))), float(np.sin(np.radians(deg)))]

    left = [70.0, 70.0, 30.0, 70.0, 70.0]  # t=2 meets the bottom at x = 146.6 > 140
    right = [100.0, 100.0, 160.0, 100.0, 100.0]  # t=2 meets the bottom at x = 2.6 < 60
    seen: list[tuple[int, list[float], list[bool]]] = []
    calls = {"n": 0}

    def recording(
        image: np.ndarray, keypoints: np.ndarray, valid: np.ndarray, capsule: CapsuleParams,
        arm: object, directions: np.ndarray | None = None, starts: np.ndarray | None = None,
        no_region: np.ndarray | None = None, allow_top: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
        h, w = image.shape[:2]
        t = int(image[0, 0, 0])  # the frame's index, written into its first pixel
        calls["n"] += 1
        if directions is not None:
            assert no_region is not None
            got = np.degrees(np.arctan2(directions[:, 1], directions[:, 0]))
            seen.append((t, [float(v) for v in got], [bool(v) for v in no_region]))
        drawn = np.array([unit(left[t]), unit(right[t])])  # (2, 2)
        return np.zeros((len(keypoints), h, w), np.uint8), drawn, np.ones(2, bool)

    monkeypatch.setattr(stage, "hand_labels", recording)
    frames = np.zeros((5, 100, 200, 3), np.uint8)
    frames[:, 0, 0, 0] = np.arange(5)
    keypoints = np.full((5, 2, 21, 2), np.nan)
    keypoints[:, 0, 0] = [60.0, 50.0]  # left wrist
    keypoints[:, 1, 0] = [140.0, 50.0]  # right wrist
    valid = np.ones((5, 2), bool)
    config = HandMaskConfig(carry_frames=0)
    stage.masks_from_keypoints(frames, keypoints, valid, config)
    assert len(seen) == 1 and seen[0][0] == 2
    np.testing.assert_allclose(seen[0][1], [70.0, 100.0], atol=1e-6)  # both drawn between
    assert seen[0][2] == [True, False]  # only the left run is the mark's own
    off = dataclasses.replace(stage.ArmParams(), steady_off_side=False)
    monkeypatch.setattr(stage, "ArmParams", lambda **kw: dataclasses.replace(off, **kw))
    seen.clear()
    stage.masks_from_keypoints(frames, keypoints, valid, config)
    assert len(seen) == 1 and seen[0][2] == [False, False]
    assert np.isnan(seen[0][1][0]) and abs(seen[0][1][1] - 100.0) < 1e-6


def test_both_sides_search_wants_both_sides_in_the_image() -> None:
    """``arm_search(nearer_side=True)``: a strip along the image's top border has only one side
    in the image; it must not pass as standing out from both (review10b: it took a table strip
    along the border, 180 deg, over the navy sleeve running straight down from the wrist)."""
    from egosim.stages.hand_mask import arm_region as ar

    h, w = 160, 240
    rng = np.random.default_rng(0)
    lab = np.zeros((h, w, 3), np.float32)
    lab[..., 0] = 80  # white table
    lab[..., 1:] = 128
    yy, xx = np.mgrid[0:h, 0:w] + 0.5
    lab[(xx < 100) & (yy >= 40), 0] = 36  # dark floor, left of the arm
    lab[(xx >= 110) & (xx < 130) & (yy >= 40), 0] = 30  # navy sleeve, straight down
    lab += rng.normal(0, 1.0, lab.shape).astype(np.float32)
    wrist, hand_dir = np.array([120.0, 30.0]), np.array([0.0, 1.0])
    exclude = np.zeros((h, w), np.uint8)
    for nearer in (False, True):
        d, _, _ = ar.arm_search(
            lab, wrist, hand_dir, 60.0, exclude, 90.0, 3.0, 20.0, nearer_side=nearer
        )
        assert abs(np.degrees(np.arctan2(d[1], d[0])) - 90.0) <= 10.0, (nearer, d)  # the sleeve


def test_leaves_through_top_against_hand_computed_exits() -> None:
    """Rays from (100, 50) in a 200 x 100 image (y down): straight up meets the top; up-left
    at 45 degrees meets the top at x = 50; 20 degrees above the horizontal to the right meets
    the right border at y = 50 - 100 tan 20 = 13.6 (a side, not the top); down never does."""
    from egosim.stages.hand_mask.arm_region import leaves_through_top

    def unit(deg: float) -> np.ndarray:
        return np.array([np.cos(np.radians(deg)), np.sin(np.radians(deg))])

    p = np.array([100.0, 50.0])
    got = [leaves_through_top(p, unit(a), 200, 100) for a in (-90.0, -135.0, -20.0, 90.0, 0.0)]
    assert got == [True, True, False, False, False]
    # from (20, 50), 30 degrees up to the left meets the left border at y = 50 - 20 tan 30
    assert not leaves_through_top(np.array([20.0, 50.0]), unit(-150.0), 200, 100)
    # from (20, 5), the same ray meets the top at x = 20 - 5 / tan 30 = 11.3
    assert leaves_through_top(np.array([20.0, 5.0]), unit(-150.0), 200, 100)
    # a wrist outside the image is its own end (review11b finding 3, as the docstring says):
    # left of the image, its ray up-right crosses the image to the top at x = 90, not counted;
    # above the top border, an arm pointing up counts
    assert not leaves_through_top(np.array([-10.0, 100.0]), unit(-45.0), 200, 100)
    assert leaves_through_top(np.array([50.0, -5.0]), unit(-90.0), 200, 100)


def test_no_arm_drawn_up_to_the_top_border() -> None:
    """HOT3D window 1, t=56-60 (hand_mask v22): the hands stage put a hand on its own forearm,
    fingers down towards the bottom border, so the hand's direction (wrist minus knuckles)
    points up and the search found a uniform bar (the house's roof) running from the wrist up
    to the top border: it was masked as arm. A forearm does not enter a head-worn view from
    the top: nothing of the bar more than 10 px from the hand is masked; without the rule
    (``no_arm_from_top`` False) most of it is."""
    from egosim.stages.hand_mask.arm_region import ArmParams, hand_arm_mask

    h, w = 160, 240
    wrist = np.array([150.5, 100.5])
    up_left = np.array([np.cos(np.radians(-133.0)), np.sin(np.radians(-133.0))])
    image = _sleeve_frame(h, w, wrist, up_left, 6)
    kp = _hand_keypoints(wrist, -up_left, 30.0, 20.0)  # (21, 2) fingers down-right
    hand, _ = draw_hand(kp, 0, h, w, CapsuleParams(forearm=False))
    near = cv2.dilate(hand, np.ones((3, 3), np.uint8), iterations=10) > 0  # the hand and 10 px
    bar = _sleeve_pixels(h, w, wrist, up_left) & ~near  # (H, W) the bar off the hand
    assert bar.sum() > 500
    found = hand_arm_mask(image, kp[None], np.array([True]), CapsuleParams(), ArmParams()) > 0
    assert found[bar].mean() < 0.02, f"bar covered {found[bar].mean():.2f}"
    assert found[~near].mean() < 0.005, f"masked off the hand {found[~near].mean():.4f}"
    assert found[hand > 0].mean() > 0.8, "the hand itself is still masked"
    old = ArmParams(no_arm_from_top=False)
    before = hand_arm_mask(image, kp[None], np.array([True]), CapsuleParams(), old) > 0
    assert before[bar].mean() > 0.5, f"without the rule the bar is arm: {before[bar].mean():.2f}"


def test_steady_directions_holds_off_side_frames_at_a_track_end() -> None:
    """HOT3D window 1, t=1 (hand_mask v22): the left hand's last frame has its arm on the
    other hand's side (along the floor to the right border); no frame after it can bracket a
    run, so it kept that arm. An off-side run that ends (or starts) a track takes the direction
    of the track's frame next to it, held, when it swung more than ``jump_deg`` from it; a run
    longer than ``max_frames``, one inside a track whose neighbours disagree, one within
    ``jump_deg`` of its neighbour and frames that are not off-side are kept."""
    from egosim.stages.hand_mask.arm_region import steady_directions

    def rows(degrees: list[float]) -> np.ndarray:
        rad = np.radians(np.asarray(degrees, float))
        return np.stack([np.cos(rad), np.sin(rad)], axis=-1)  # (T, 2)

    nan = float("nan")
    drawn = np.full((8, 4, 2), np.nan)  # (T, K, 2)
    drawn[:, 0] = rows([110, 110, 0, nan, nan, nan, nan, nan])  # ends at t=2, off-side there
    drawn[:, 1] = rows([nan, nan, nan, nan, 0, -10, 95, 100])  # starts at t=4, off at t=4-5
    drawn[:, 2] = rows([90, 90, 20, 20, 20, nan, nan, nan])  # three off frames, max_frames 2
    drawn[:, 3] = rows([90, 0, 170, 170, nan, 60, 30, nan])  # t=1 off inside the track; t=6
    # off at the track's end but only 30 degrees from t=5: the same arm a step off, kept
    off = np.zeros((8, 4), bool)
    off[2, 0] = off[4, 1] = off[5, 1] = off[1, 3] = off[6, 3] = True
    off[2:5, 2] = True
    assert not np.isfinite(steady_directions(drawn, 2, 45.0, 30.0)).any()
    out = steady_directions(drawn, 2, 45.0, 30.0, off)  # (T, K, 2)
    got = np.degrees(np.arctan2(out[..., 1], out[..., 0]))  # (T, K)
    np.testing.assert_allclose(got[2, 0], 110.0, atol=1e-6)  # held from t=1
    np.testing.assert_allclose(got[4:6, 1], [95.0, 95.0], atol=1e-6)  # held from t=6
    assert np.isnan(got[:2, 0]).all() and np.isnan(got[6:, 1]).all()
    assert np.isnan(got[:, 2]).all(), "a run longer than max_frames is kept"
    assert np.isnan(got[:, 3]).all(), "inside a track or within jump_deg nothing is held"


def _turned_over_scene() -> tuple[np.ndarray, ...]:
    """A still 4-frame clip (160 x 240): a real hand at frames 0-1, fingers up-left, its forearm
    down-right to the border and a uniform blue bar past its fingertips to the top border; at
    frames 2-3 the keypoints put the hand on its own forearm, turned over (fingers down), so its
    arm would run up-left to the top border. ``(frames, keypoints, valid, true_kp, false_kp,
    hand (H, W) the real hand's capsules, beyond (H, W) the band's path past the hand)``."""
    h, w = 160, 240
    rng = np.random.default_rng(7)
    image = cv2.GaussianBlur(np.clip(rng.normal(90, 35, (h, w, 3)), 0, 255).astype(np.uint8),
                             (5, 5), 0)  # fmt: skip
    down_right = np.array([1.0, 1.0]) / np.sqrt(2.0)
    wrist = np.array([100.5, 50.5])
    true_kp = _hand_keypoints(wrist, -down_right, 25.0, 18.0)  # (21, 2) fingers up-left
    hand, _ = draw_hand(true_kp, 0, h, w, CapsuleParams(forearm=False))  # (H, W)
    skin = (205, 150, 125)
    cv2.line(image, tuple(int(v) for v in wrist), tuple(int(v) for v in wrist + 300 * down_right),
             skin, 18)  # fmt: skip
    roof = wrist - 45 * down_right  # a uniform blue bar past the fingertips to the top border
    cv2.line(image, tuple(int(v) for v in roof), tuple(int(v) for v in roof - 300 * down_right),
             (60, 110, 200), 18)  # fmt: skip
    image[hand > 0] = skin
    image = np.clip(image + rng.normal(0, 3, image.shape), 0, 255).astype(np.uint8)
    false_wrist = wrist + 45 * down_right  # on the forearm
    false_kp = _hand_keypoints(false_wrist, down_right, 25.0, 18.0)  # turned over, fingers down
    frames = np.stack([image] * 4)  # (4, H, W, 3) a still camera
    keypoints = np.full((4, 2, 21, 2), np.nan)
    keypoints[:2, 0] = true_kp
    keypoints[2:, 0] = false_kp
    valid = np.array([[True, False]] * 4)
    # the ray up-left from the false wrist, beyond the real hand's fingertips to the top border
    yy, xx = np.mgrid[0:h, 0:w] + 0.5
    along = (xx - wrist[0]) * -down_right[0] + (yy - wrist[1]) * -down_right[1]  # (H, W)
    across = np.abs((xx - wrist[0]) * down_right[1] - (yy - wrist[1]) * down_right[0])
    near = cv2.dilate(hand, np.ones((3, 3), np.uint8), iterations=10) > 0
    beyond = (along > 0) & (across < 8) & ~near  # (H, W) the band's path past the hand
    assert beyond.sum() > 100
    return frames, keypoints, valid, true_kp, false_kp, hand, beyond


def test_hand_turned_over_on_its_forearm_gets_its_neighbours_mask() -> None:
    """HOT3D window 1, t=56-60 flagged (hand_mask v22): the keypoints of frames 2-3 put the hand on
    its own forearm, turned over (fingers down the forearm to the border), so its arm would run
    up-left from that wrist through the real hand and a uniform bar (the house's roof) to the
    top border. That arm is not drawn,
    and the frames receive the hand's mask from frames 0-1 (which found it) by propagation, as
    a carried hand's: the real hand is masked and nothing up to the top border is. v21 masked
    the band to the top border; without the propagation the real hand is missed."""
    import egosim.stages.hand_mask.stage as stage

    frames, keypoints, valid, _, _, hand, beyond = _turned_over_scene()
    masks = stage.masks_from_keypoints(frames, keypoints, valid, HandMaskConfig()) > 0
    for t in (2, 3):
        assert masks[t][hand > 0].mean() > 0.8, f"t={t} real hand {masks[t][hand > 0].mean():.2f}"
        assert masks[t][beyond].mean() < 0.05, f"t={t} band {masks[t][beyond].mean():.2f}"
    off = HandMaskConfig(no_arm_from_top=False)
    before = stage.masks_from_keypoints(frames, keypoints, valid, off) > 0
    assert before[2][beyond].mean() > 0.5, f"v21's band {before[2][beyond].mean():.2f}"


def _rule_off_masks(frames: np.ndarray, kp: np.ndarray, valid: np.ndarray, cfg: HandMaskConfig):
    """v21's masks: ``masks_from_keypoints`` with ``no_arm_from_top`` False."""
    import egosim.stages.hand_mask.stage as stage

    return stage.masks_from_keypoints(
        frames, kp, valid, dataclasses.replace(cfg, no_arm_from_top=False)
    )


def test_short_top_runs_wants_a_short_run_next_to_a_source() -> None:
    """review11b finding 1: only runs of at most ``max_run`` top-exit frames of a hand with a
    valid frame of that hand next to them, not top-exit, are opened."""
    from egosim.stages.hand_mask.stage import short_top_runs

    top = np.zeros((10, 3), bool)
    valid = np.ones((10, 3), bool)
    top[3:5, 0] = True  # two frames, sources both sides: opened
    top[0:10, 1] = True  # the whole track: no source
    top[1:5, 2] = True  # four frames, longer than max_run 3
    top[7:9, 2] = True  # two frames whose neighbours are not valid
    valid[6, 2] = valid[9, 2] = False
    out = short_top_runs(top, valid, 3)
    expected = np.zeros_like(top)
    expected[3:5, 0] = True
    np.testing.assert_array_equal(out, expected)
    assert short_top_runs(top, valid, 4)[1:5, 2].all()


def test_long_or_sourceless_top_runs_draw_their_arm() -> None:
    """review11b finding 1 (hand_mask v23 also): v22 opened every frame whose arm would run up
    to the top border, with no limit, so a false hand on a curtain (EgoDex portrait_09, 17
    frames) or a view turned over (HOT3D window 1 turned 180 degrees) spread background through
    the whole run. A run longer than ``carry_frames``, or one with no frame of the same hand
    next to it that is not in the run, is the view's geometry: its arm is drawn as v21 drew it
    (masks equal to the rule off), and the band up to the top border is masked again."""
    import egosim.stages.hand_mask.stage as stage

    frames, keypoints, valid, _, false_kp, _, beyond = _turned_over_scene()
    cases = []
    cfg = HandMaskConfig(carry_frames=1)  # frames 2-3: a run of 2 > 1
    cases.append((keypoints, cfg))
    sourceless = keypoints.copy()
    sourceless[:, 0] = false_kp  # turned over in every frame: no source next to the run
    cases.append((sourceless, HandMaskConfig()))
    for kp, c in cases:
        masks = stage.masks_from_keypoints(frames, kp, valid, c) > 0
        before = _rule_off_masks(frames, kp, valid, c) > 0
        np.testing.assert_array_equal(masks, before)
        assert masks[2][beyond].mean() > 0.5, f"the arm drawn {masks[2][beyond].mean():.2f}"


def test_arm_from_the_top_kept_when_the_rule_is_off_or_the_camera_static(monkeypatch) -> None:
    """review11b finding 2: a still camera facing a person across a table sees the forearm (a
    sleeve) run from the wrist straight up to the top border. v22 drew no arm there (sleeve
    masked 0.00) and nothing could turn the rule off. ``HandMaskConfig.no_arm_from_top`` False
    masks the sleeve (1.00 in review11b's across.py), and the stage does not apply the rule to
    a clip whose ``cameras`` row says the camera is static."""
    import egosim.stages.hand_mask.stage as stage

    h, w = 160, 240
    d = np.array([0.0, -1.0])  # the arm straight up from the wrist
    wrist = np.array([120.5, 90.5])
    image = _sleeve_frame(h, w, wrist, d, 3)
    kp = _hand_keypoints(wrist, -d, 30.0, 20.0)  # (21, 2) fingers down at the camera
    hand, _ = draw_hand(kp, 0, h, w, CapsuleParams(forearm=False))
    image[hand > 0] = (205, 150, 125)
    near = cv2.dilate(hand, np.ones((3, 3), np.uint8), iterations=10) > 0
    sleeve = _sleeve_pixels(h, w, wrist, d) & ~near  # (H, W)
    assert sleeve.sum() > 300
    frames = np.stack([image] * 4)  # (4, H, W, 3)
    keypoints = np.full((4, 2, 21, 2), np.nan)
    keypoints[:, 1] = kp
    # t=0: the arm hangs down from the wrist, fingers up; t=1-3 are a short run with a source
    # (t=0), where the rule applies
    frames[0] = _sleeve_frame(h, w, wrist, -d, 3)
    keypoints[0, 1] = _hand_keypoints(wrist, d, 30.0, 20.0)
    frames[0][draw_hand(keypoints[0, 1], 0, h, w, CapsuleParams(forearm=False))[0] > 0] = (
        205, 150, 125,
    )  # fmt: skip
    valid = np.array([[False, True]] * 4)
    on = stage.masks_from_keypoints(frames, keypoints, valid, HandMaskConfig()) > 0
    off_cfg = HandMaskConfig(no_arm_from_top=False)
    off = stage.masks_from_keypoints(frames, keypoints, valid, off_cfg) > 0
    assert on[1:, sleeve].mean() < 0.05, f"head-worn rule: sleeve {on[1:, sleeve].mean():.2f}"
    assert off[1:, sleeve].mean() > 0.9, f"rule off: sleeve {off[1:, sleeve].mean():.2f}"
    assert off[1:, hand > 0].mean() > 0.8

    # A static camera's clip (its cameras row) is masked with the rule off.
    from egosim.stages.common.cameras import camera_is_static

    assert camera_is_static({"cameras": {"static_camera": True, "camera_model": "static"}})
    assert not camera_is_static({"cameras": {"static_camera": False, "camera_model": "full"}})
    assert not camera_is_static({"clips": {}})
    seen: list[HandMaskConfig] = []

    def spy(f: np.ndarray, k: np.ndarray, v: np.ndarray, cfg: HandMaskConfig) -> np.ndarray:
        seen.append(cfg)
        return np.zeros(f.shape[:3], np.uint8)

    monkeypatch.setattr(stage, "masks_from_keypoints", spy)
    clip = render_clip(WorldConfig(seed=3, height=48, width=64, num_frames=2))
    for static in (False, True):
        HandMaskStage().masks_for_clip(clip, static_camera=static)
    assert [c.no_arm_from_top for c in seen] == [True, False]


def test_true_runs_gives_each_run_of_true_frames() -> None:
    from egosim.stages.hand_mask.arm_region import true_runs

    assert true_runs(np.array([0, 1, 1, 0, 1], bool)) == [(1, 3), (4, 5)]
    assert true_runs(np.array([1, 1, 1], bool)) == [(0, 3)]
    assert true_runs(np.zeros(4, bool)) == []
    assert true_runs(np.zeros(0, bool)) == []


def test_weak_arm_runs_open_short_runs_reached_while_the_hand_barely_moves() -> None:
    """hand_mask v24: frames whose arm found no colour region are opened to their neighbours'
    masks only in runs of at most ``max_run`` frames next to a frame of the hand that found one
    and shows at least its hand's area of arm (and at most ``max_ratio`` times the arm of the
    frame beyond it), as far as the wrist moves at most ``max_move`` hand lengths per frame from
    there and the frame's own arm is under ``max_share`` of it."""
    from egosim.stages.hand_mask.arm_region import hand_length_px
    from egosim.stages.hand_mask.stage import weak_arm_runs

    up = np.array([0.0, -1.0])  # knuckles above the wrist: the arm below
    hand = _hand_keypoints(np.array([60.5, 50.5]), up, 30.0, 20.0)  # (21, 2)
    size = hand_length_px(hand)
    assert 25.0 < size < 60.0, size
    keypoints = np.repeat(hand[None, None], 12, axis=0).repeat(4, axis=1)  # (12, 4, 21, 2)
    keypoints[9:, 0] += [0.0, 0.8 * size]  # hand 0 jumps 0.8 hand lengths at t=9
    keypoints[10:, 0] += [0.1 * size, 0.0]  # ... then barely moves
    weak = np.zeros((12, 4), bool)
    valid = np.ones((12, 4), bool)
    arm_px = np.full((12, 4), 5000)  # every found frame shows an arm
    hand_px = np.full((12, 4), 1000)
    weak[3:5, 0] = True  # two frames between found arms: opened
    arm_px[3:5, 0] = [100, 2600]  # ... t=4's own arm holds from t=5 (over half of it), not t=3's
    weak[8:12, 0] = True  # to the track's end from t=7; the hand jumps at t=9: only t=8
    arm_px[8:12, 0] = 0
    weak[:, 1] = True  # the whole track: no frame found its arm, nothing to carry
    weak[2:7, 2] = True  # five frames, longer than max_run 4
    arm_px[2:7, 2] = 0
    weak[4:6, 3] = True  # next to found frames whose arm is out of view (a hand entering)
    arm_px[:, 3] = 500
    out = weak_arm_runs(weak, valid, keypoints, arm_px, hand_px, 4, 0.5, 0.5)
    expected = np.zeros_like(weak)
    expected[3, 0] = True  # reached from t=2; from t=5, t=4 holds and the walk stops there
    expected[8, 0] = True
    np.testing.assert_array_equal(out, expected)
    assert weak_arm_runs(weak, valid, keypoints, arm_px, hand_px, 5, 0.5, 0.5)[2:7, 2].all()
    jump = weak_arm_runs(weak, valid, keypoints, arm_px, hand_px, 4, 1.0, 0.5)
    assert jump[8:12, 0].all()  # the jump allowed
    assert weak_arm_runs(weak, valid, keypoints, arm_px, hand_px, 4, 0.5, 0.6)[3:5, 0].all()
    gone = valid.copy()
    gone[2, 0] = gone[5, 0] = False  # the neighbours missed the hand: no source
    assert not weak_arm_runs(weak, gone, keypoints, arm_px, hand_px, 4, 0.5, 0.5)[3:5, 0].any()
    outlier = arm_px.copy()
    outlier[1, 0] = 3000  # the source t=2 shows 1.67x the arm of t=1 beyond it: an outlier
    got = weak_arm_runs(weak, valid, keypoints, outlier, hand_px, 4, 0.5, 0.5, 1.3)
    assert not got[3, 0] and got[8, 0]
    assert weak_arm_runs(weak, valid, keypoints, outlier, hand_px, 4, 0.5, 0.5, 2.0)[3, 0]


def test_frames_whose_arm_found_no_colour_receive_their_neighbours_mask(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """hand_mask v24 in the stage: a still hand whose arm search finds a colour region at t=0-1
    and t=4, and whose mask then holds a 22 px wide arm to the bottom border, but at t=2-3 no
    region and no arm (DWM 00013 t=31-32: a navy sleeve on a dark floor, found or not by a 1 px
    shift of the keypoints), has t=2-3 opened to propagation, joined to their own mask (v23
    opened none); with ``weak_arm_frames`` 0 none is, nor when t=2-3 keep their arm."""
    import egosim.stages.hand_mask.stage as stage

    found = [True, True, False, False, True]
    keep = {"arm": False}

    def fake_labels(
        image: np.ndarray, keypoints: np.ndarray, valid: np.ndarray, capsule: CapsuleParams,
        arm: object, directions: np.ndarray | None = None, starts: np.ndarray | None = None,
        no_region: np.ndarray | None = None, allow_top: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
        h, w = image.shape[:2]
        t = int(image[0, 0, 0])  # the frame's index, written into its first pixel
        own = np.zeros((1, h, w), np.uint8)
        own[0, 0, 0] = t  # the frame's index again, for fake_masks
        return own, np.array([[0.0, 1.0]]), np.array([found[t]])  # straight down

    def fake_masks(image: np.ndarray, own: np.ndarray, *args: object) -> tuple:
        t = int(own[0, 0, 0])
        h, w = image.shape[:2]
        per_hand = stage.draw_hand(hand, 0, h, w, CapsuleParams(forearm=False))[0][None]
        if found[t] or keep["arm"]:
            per_hand[0, 50:, 50:72] = 1  # the arm, from the wrist down to the border
        return per_hand[0].copy(), per_hand, per_hand.copy()

    opened: list[np.ndarray] = []

    def spy(frames: np.ndarray, masks: np.ndarray, per_hand: np.ndarray, certain: np.ndarray,
            params: object, open_frames: np.ndarray) -> np.ndarray:  # fmt: skip
        opened.append(open_frames.copy())
        return masks

    monkeypatch.setattr(stage, "hand_labels", fake_labels)
    monkeypatch.setattr(stage, "masks_from_labels", fake_masks)
    monkeypatch.setattr(stage, "propagate_hands", spy)
    frames = np.zeros((5, 200, 120, 3), np.uint8)
    frames[:, 0, 0, 0] = np.arange(5)
    hand = _hand_keypoints(np.array([60.5, 50.5]), np.array([0.0, -1.0]), 30.0, 20.0)
    keypoints = np.repeat(hand[None, None], 5, axis=0)  # (5, 1, 21, 2) a still hand
    valid = np.ones((5, 1), bool)
    config = HandMaskConfig(carry_frames=0, grow_margin_m=0.0)
    stage.masks_from_keypoints(frames, keypoints, valid, config)
    stage.masks_from_keypoints(
        frames, keypoints, valid, dataclasses.replace(config, weak_arm_frames=0)
    )
    keep["arm"] = True
    stage.masks_from_keypoints(frames, keypoints, valid, config)
    assert opened[0][:, 0].tolist() == [False, False, True, True, False]
    assert not opened[1].any()
    assert not opened[2].any()
