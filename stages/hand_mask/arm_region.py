"""Hand-and-arm masks in image space: keypoint capsules, an arm seed, GrabCut, connectivity.

Nothing here knows the world frame: the forearm's direction comes from the image alone. For each
hand with 2D keypoints (MANO order, pixels, pixel centres at integer + 0.5):

- the hand is drawn as capsules (see ``capsules``); its thin skeleton is certainly hand;
- the hand's own direction is the wrist minus the middle knuckle (mean of the knuckles when
  that one is unknown); the arm's direction ``d`` is searched within ``max_turn_deg`` of it for
  the strip whose colour is most uniform and most unlike the strips beside it
  (:func:`arm_direction`); lengths along the arm are in hand lengths, at least the palm's
  average length at the hand's scale (a hand pointing into the view is short in the image,
  its arm often is not); when the hand's own direction leaves the image within
  ``out_of_view`` hand lengths, its arm is out of view and the direction is not searched;
- with two hands, a hand whose search is unsure (best score above ``other_arm_unsure``)
  prefers strips of the surer hand's arm colour, when that colour is rare in the frame
  (:func:`other_arm_colours`): alone, the smooth table between two knitted sleeves stands out
  from its sides (the arms) better than a sleeve whose sides lie on itself (EgoDex);
- a thin strip beyond the wrist along ``d`` (``seed_start``..``seed_end`` hand lengths) is
  certainly arm, extended by a walk along ``d`` while the colour holds and still stands out from
  the sides (:func:`arm_extent`); where the strip does not stand out from either side there is
  no arm to follow (it is out of view) and nothing more is added;
- pixels of the strip's colour connected to it within ``colour_region`` half-widths of the axis
  are certainly arm (in a dim frame, one whose upper-quartile lightness is under
  ``dark_floor``, the strip's colour, its walk and this region are read from the frame lifted
  by a gamma to that floor, :func:`lift_dark`: the tolerances are absolute Lab units, which a
  dim frame's shadows all fall within); when those within ``refine_half_angle_deg`` form a ray
  from the wrist, the arm is re-aimed along its main axis (:func:`region_direction`) and the
  labels redrawn, unless that axis turns more than ``refine_slack_deg`` farther from the
  hand's direction than the searched one (a shaded table or cushion in the arm's colour
  running off sideways); that region is probably arm wherever it runs (``region_probable``:
  an arm that turns more than the band allows is not ruled out);
- a tapered band along ``d`` from the wrist to the image border is probably arm;
- an arm whose ray from the wrist leaves through the top border is not drawn at all
  (``no_arm_from_top``, :func:`leaves_through_top`): in a head-worn view forearms come in from
  the bottom or the sides, and an arm drawn up is a hand the keypoints turned over;
- a fan of ``fan_half_angle_deg`` either side of ``d``, ending ``fan_width`` half-widths from the
  axis, is probably background (the forearm may bend at the wrist; the colour model moves those
  pixels to the arm when they look like it);
- everything else is background.

Over a clip (``stage.masks_from_keypoints``), a run of at most ``steady_frames`` frames whose
arm directions all swing more than ``steady_jump_deg`` away from the frames either side, which
agree within ``steady_agree_deg``, is drawn along the direction between those, with no search
and no re-aim (:func:`steady_directions`); a frame whose arm ray crosses past the other hand's
wrist (:func:`crosses_other_wrist`) counts as swung away whatever its angle, and the runs only
that finds are drawn without the probable colour region (``steady_off_side``); an off-side
run that starts or ends a track, which no pair of frames can bracket, holds the direction of
the track's frame next to it when it swung more than ``steady_jump_deg`` from it. The angle
rule cannot reach the first frame of a hand's track (no frame before it): there a strip that
stands out from both of its sides, not only on average, is searched too, and drawn when it is
another direction (``start_both_sides``).

GrabCut (OpenCV) learns the colour models from these labels and relabels the two "probably"
regions; only the pixels connected to a certain seed are kept, so a patch of skin-coloured table
away from the arm stays background. The certain seeds are returned per hand with the mask: they
are what ``propagate`` carries into other frames with confidence.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import cv2
import numpy as np

from egosim.stages.hand_mask.capsules import (
    FOREARM_LENGTH_M,
    FOREARM_RADIUS_M,
    KNUCKLES,
    SHIFT,
    WRIST,
    CapsuleParams,
    draw_hand,
    fixed_point,
    hand_scale_px,
)

MIDDLE_KNUCKLE = 9  # MANO index of the middle finger's MCP joint
PALM_LENGTH_M = 0.092  # wrist to middle knuckle, average adult, metres


@dataclass(frozen=True)
class ArmParams:
    """Where the arm is looked for, relative to the hand's own direction and size."""

    fan_half_angle_deg: float = 55.0  # probable-background fan either side of the arm's direction
    max_turn_deg: float = 90.0  # the arm's direction is searched this far from the hand's (0: off)
    turn_cost: float = 3.0  # a candidate's score grows by this fraction per radian of turn
    seed_start: float = 0.25  # certain-arm strip starts this many hand lengths past the wrist
    seed_end: float = 0.8  # ... and ends this many hand lengths past the wrist
    seed_width: float = 0.35  # strip half-width, times the forearm's half-width at the wrist
    band: float = 1.0  # probable-arm band half-width, times the average forearm half-width
    walk: bool = True  # extend the certain-arm strip along the arm while its colour holds
    walk_tolerance: float = 18.0  # Lab distance (OpenCV 8-bit units) of "the same colour"
    walk_gap: float = 1.0  # misses in a row (in forearm half-widths) that end the walk
    colour_region: float = 2.0  # pixels of the arm's colour connected to the strip and within
    # this many forearm half-widths of its axis are certainly arm (0: off)
    fan_width: float = 3.0  # the fan ends this many forearm half-widths from the axis (0: no end)
    refine_direction: bool = True  # re-aim the arm along the arm-coloured region's main axis
    refine_half_angle_deg: float = 60.0  # that region is looked for this far either side
    region_probable: bool = True  # that region is probably arm (else background off the band)
    unforeshortened: bool = True  # lengths along the arm from the hand's scale, not its image
    # length, when that is longer (a hand pointing into the view is short; its arm often not)
    out_of_view: float = 0.5  # no direction search when the hand's own direction leaves the
    # image within this many hand lengths of the wrist: its arm is out of view, and a search
    # sideways would follow the table (0: always search)
    refine_slack_deg: float = 40.0  # the region's axis may turn at most this much farther
    # from the hand's direction than the searched direction did (180: no limit)
    hand_ring: float = 0.03  # probably-background ring round the hand (GrabCut may grow the
    # hand into it), times its scale in px per metre: 3 cm at the hand's depth (0: none)
    other_arm: float = 18.0  # Lab distance within which a candidate strip's colour counts as
    # the colour of the other hand's arm (searched first, when more certain): one shirt, or bare
    # skin, on both arms (0: off)
    other_arm_floor: float = 0.1  # the score is multiplied by ((distance + 1) / (other_arm +
    # 1)) squared, at least this, when the colour is within ``other_arm``
    other_arm_unsure: float = 0.15  # ... only for a hand whose own best score (spread + 1 over
    # contrast + 1, times the turn cost) is above this: an arm found clearly on its own keeps it
    other_arm_rare: float = 0.15  # ... only when at most this fraction of the frame is within
    # ``other_arm`` of that colour: a shared colour tells the arm from a grey table or floor only
    # when little else in the view has it
    steady_frames: int = 10  # a run of at most this many frames whose arm directions all turn
    # more than ``steady_jump_deg`` from the frames either side of it, which agree within
    # ``steady_agree_deg``, is drawn along the direction between those (0: off; see
    # :func:`steady_directions`)
    steady_jump_deg: float = 45.0  # ... degrees a run's directions lie from both frames beside it
    steady_agree_deg: float = 30.0  # ... degrees within which those two frames must agree
    steady_off_side: bool = True  # a frame whose arm runs past the other hand's wrist towards
    # the other hand's side (:func:`crosses_other_wrist`) counts as swung away whatever its
    # angle, and never brackets a run (see :func:`steady_directions`); the hand's frames of a
    # run that holds such a frame, unless the angle alone finds it too, are drawn without
    # the probable colour region (the interpolated direction is a guess there, and its colour
    # region can be floor: :func:`off_side_runs`)
    start_both_sides: bool = True  # at the first frame of a hand's track, which no steady run
    # can reach (no frame before it), the arm is also searched for a strip that stands out from
    # both sides (contrast of the nearer side, not the mean: a strip of uniform floor along a
    # table's edge stands out from the table only; see :func:`arm_search`), and that direction
    # is drawn when it lies more than ``start_switch_deg`` from the plain search's
    off_side_min_tilt_deg: float = 45.0  # an arm is marked by ``steady_off_side`` only when
    # it also points at least this far from straight down towards the other hand's side
    start_switch_deg: float = 45.0  # ... degrees the both-sides direction must lie from the
    # plain search's to be drawn (another arm, not the same one a step off)
    no_arm_from_top: bool = True  # an arm whose ray from the wrist leaves the image through
    # its top border is not drawn (hand only): in a head-worn view the body is below the
    # camera and forearms come in from the bottom or the sides (:func:`leaves_through_top`)
    dark_floor: float = 70.0  # a frame whose upper-quartile lightness (OpenCV 8-bit L) is
    # below this is lifted by a gamma to it before the arm's strip colour, its walk and its
    # colour region are read (:func:`lift_dark`; the direction search reads the frame as it
    # is): ``walk_tolerance`` is in absolute Lab units, and in a dim frame every shadow lies
    # within it of a dark strip, so the region runs along the shadow and re-aims the arm
    # there (rehearsal copy 50013 t=28). Every well-lit frame of the real clips has 60 or more
    # (DWM 66-88, HOT3D 60-102, fixed cameras and EgoDex 140+); the dim copies 29-45 (0: off)

    def __post_init__(self) -> None:
        problems = []
        if not 0.0 <= self.fan_half_angle_deg <= 89.0:
            problems.append(f"fan_half_angle_deg must be in [0, 89], got {self.fan_half_angle_deg}")
        if not 0.0 <= self.seed_start < self.seed_end <= 3.0:
            problems.append(
                f"need 0 <= seed_start < seed_end <= 3, got {self.seed_start}, {self.seed_end}"
            )
        if not 0.0 < self.seed_width <= 2.0:
            problems.append(f"seed_width must be in (0, 2], got {self.seed_width}")
        if not 0.1 <= self.band <= 5.0:
            problems.append(f"band must be in [0.1, 5], got {self.band}")
        if not 1.0 <= self.walk_tolerance <= 200.0:
            problems.append(f"walk_tolerance must be in [1, 200], got {self.walk_tolerance}")
        if not 0.0 < self.refine_half_angle_deg < 90.0:
            problems.append(
                f"refine_half_angle_deg must be in (0, 90), got {self.refine_half_angle_deg}"
            )
        if not 0.0 <= self.walk_gap <= 20.0:
            problems.append(f"walk_gap must be in [0, 20], got {self.walk_gap}")
        if not 0.0 <= self.max_turn_deg <= 180.0:
            problems.append(f"max_turn_deg must be in [0, 180], got {self.max_turn_deg}")
        if not 0.0 <= self.refine_slack_deg <= 180.0:
            problems.append(f"refine_slack_deg must be in [0, 180], got {self.refine_slack_deg}")
        if not 0.0 <= self.other_arm_rare <= 1.0:
            problems.append(f"other_arm_rare must be in [0, 1], got {self.other_arm_rare}")
        if not 0 <= self.steady_frames <= 1000:
            problems.append(f"steady_frames must be in [0, 1000], got {self.steady_frames}")
        for name in ("steady_jump_deg", "steady_agree_deg", "start_switch_deg"):
            if not 0.0 <= getattr(self, name) <= 180.0:
                problems.append(f"{name} must be in [0, 180], got {getattr(self, name)}")
        if not 0.0 <= self.off_side_min_tilt_deg <= 90.0:
            problems.append(
                f"off_side_min_tilt_deg must be in [0, 90], got {self.off_side_min_tilt_deg}"
            )
        if not 0.0 <= self.dark_floor <= 255.0:
            problems.append(f"dark_floor must be in [0, 255], got {self.dark_floor}")
        if not 0.0 < self.other_arm_floor <= 1.0:
            problems.append(f"other_arm_floor must be in (0, 1], got {self.other_arm_floor}")
        for name in ("turn_cost", "out_of_view", "hand_ring", "other_arm", "other_arm_unsure"):
            if not 0.0 <= getattr(self, name) <= 100.0:
                problems.append(f"{name} must be in [0, 100], got {getattr(self, name)}")
        if problems:
            raise ValueError("; ".join(problems))


def quartile_lightness(image: np.ndarray, step: int = 4) -> float:
    """Upper-quartile (75th percentile) OpenCV 8-bit Lab lightness of ``image (H, W, 3)``
    uint8 RGB, on every ``step``-th pixel in each direction. Not the median: black letterbox
    bars and a fisheye circle's corners pull the median of a well-lit frame down (HOT3D: median
    14-52, upper quartile 60-102)."""
    small = np.ascontiguousarray(image[::step, ::step])
    return float(np.percentile(cv2.cvtColor(small, cv2.COLOR_RGB2LAB)[..., 0], 75))


def lift_dark(image: np.ndarray, floor: float) -> np.ndarray:
    """``image (H, W, 3)`` uint8 RGB, lifted by a gamma on its channels so that its
    upper-quartile lightness (:func:`quartile_lightness`) reaches ``floor``; the image itself
    when it is already that bright, ``floor`` is 0 or the image is black.

    The gamma is found by bisection on the subsampled image (the quartile is monotone in it).
    """
    if floor <= 0:
        return image
    small = np.ascontiguousarray(image[::4, ::4])
    if quartile_lightness(small, 1) >= floor or not small.any():
        return image
    levels = np.arange(256, dtype=np.float64) / 255.0  # (256,)

    def table(gamma: float) -> np.ndarray:
        return np.round(255.0 * levels**gamma).astype(np.uint8)  # (256,)

    lo, hi = 0.05, 1.0  # gamma: lo lifts far past any floor, hi is the image itself
    for _ in range(12):
        mid = 0.5 * (lo + hi)
        if quartile_lightness(cv2.LUT(small, table(mid)), 1) >= floor:
            lo = mid
        else:
            hi = mid
    return cv2.LUT(image, table(lo))


def hand_direction(keypoints: np.ndarray) -> tuple[np.ndarray, np.ndarray, float] | None:
    """``(wrist (2,), unit direction (2,), hand length px)`` of one hand ``(21, 2)``, or None.

    The direction points from the middle knuckle back through the wrist (towards the forearm).
    """
    wrist = keypoints[WRIST]
    if not np.all(np.isfinite(wrist)):
        return None
    if np.all(np.isfinite(keypoints[MIDDLE_KNUCKLE])):
        knuckle = keypoints[MIDDLE_KNUCKLE]
    else:
        known = keypoints[list(KNUCKLES)]
        known = known[np.all(np.isfinite(known), axis=1)]
        if len(known) == 0:
            return None
        knuckle = known.mean(axis=0)
    d = wrist - knuckle  # (2,)
    length = float(np.hypot(*d))
    if length < 1e-6:
        return None
    return wrist, d / length, length


def hand_length_px(keypoints: np.ndarray, radius_scale: float = 1.0) -> float:
    """Length in pixels of one hand ``(21, 2)`` as the arm search measures along the arm:
    wrist to middle knuckle, at least the palm's average length at the hand's scale (NaN
    without a wrist, a knuckle or a scale)."""
    found = hand_direction(keypoints)
    scale = hand_scale_px(keypoints)
    if found is None or not np.isfinite(scale) or scale <= 0:
        return float("nan")
    return max(found[2], PALM_LENGTH_M * scale * radius_scale)


def _sample(lab: np.ndarray, exclude: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Colours ``(N, 3)`` of ``lab (H, W, 3)`` at ``points (N, 2)`` (pixel centres).

    NaN outside the image and on ``exclude (H, W)`` (the hand's own mask).
    """
    h, w = lab.shape[:2]
    xi = np.floor(points[:, 0]).astype(int)
    yi = np.floor(points[:, 1]).astype(int)
    inside = (xi >= 0) & (xi < w) & (yi >= 0) & (yi < h)
    out = np.full((len(points), 3), np.nan, np.float32)
    out[inside] = lab[yi[inside], xi[inside]]
    inside[inside] = exclude[yi[inside], xi[inside]] == 0
    out[~inside] = np.nan
    return out


def arm_direction(*args: Any, **kwargs: Any) -> np.ndarray:
    """Unit image direction ``(2,)`` of the forearm from the wrist, chosen by colour: the
    direction of :func:`arm_search`, which takes the same arguments."""
    return arm_search(*args, **kwargs)[0]


def arm_search(
    lab: np.ndarray,
    wrist: np.ndarray,
    hand_dir: np.ndarray,
    hand_len: float,
    exclude: np.ndarray,
    max_turn_deg: float = 90.0,
    turn_cost: float = 0.15,
    radius: float | None = None,
    other: np.ndarray | None = None,
    other_tolerance: float = 18.0,
    other_floor: float = 0.1,
    nearer_side: bool = False,
) -> tuple[np.ndarray, np.ndarray | None, float]:
    """``(direction (2,), strip colour (3,) or None, score)`` of the forearm from ``wrist``.

    Candidate directions within ``max_turn_deg`` of ``hand_dir`` (every 5 degrees) are scored on
    a strip from 0.3 to 1.5 hand lengths past the wrist in ``lab (H, W, 3)``, the float32 Lab
    image (samples inside the image and outside ``exclude (H, W)``, the hand's own mask): how
    uniform the colour is along its axis (median absolute deviation in Lab) over how much it
    differs from two side strips ``2 * radius`` off the axis (``radius``: the forearm's
    half-width in pixels, default a third of ``hand_len``), times ``1 + turn_cost`` per radian
    of turn: a forearm (skin or sleeve) is one smooth colour that stands out from what lies
    beside it; a strip across a table or objects is not. With ``other (3,)``, the Lab colour of
    the other hand's arm, a strip within ``other_tolerance`` of it has its score multiplied by
    ``((distance + 1) / (other_tolerance + 1)) ** 2``, at least ``other_floor``: both arms wear
    one shirt (or bare skin), while a smooth strip of table between the two arms stands out
    from its sides (the arms) better than a knitted sleeve whose sides lie on itself. With
    ``nearer_side`` the contrast is the nearer side's instead of the mean of the two: a strip
    must stand out from both sides, as an arm does, and a uniform strip along the edge of a
    dark floor, which stands out from the table on one side only, does not (HOT3D window 1,
    t=0: that floor scored 0.12, the forearm 0.33; nearer side: the forearm wins). The
    lowest score wins (lower is better); the hand's direction is kept, with no colour and an
    infinite score, when no candidate has enough samples.
    """
    radius = hand_len / 3.0 if radius is None else radius
    steps = np.linspace(0.3, 1.5, 24) * hand_len  # (S,)
    offsets = np.array([-0.3, 0.0, 0.3]) * radius  # across the strip

    def colours_at(pts: np.ndarray) -> np.ndarray:
        """Lab colours ``(N, 3)`` at pixel-centre points ``(N, 2)`` in the image, off the hand."""
        colours = _sample(lab, exclude, pts)  # (N, 3) NaN outside or on the hand
        return colours[np.isfinite(colours[:, 0])]

    best, best_colour, best_score = hand_dir, None, np.inf
    for turn in np.arange(-max_turn_deg, max_turn_deg + 1e-6, 5.0):
        d = _rotate(hand_dir, float(turn))
        n = np.array([-d[1], d[0]])
        axis = wrist + steps[:, None, None] * d + offsets[None, :, None] * n  # (S, 3, 2)
        colours = colours_at(axis.reshape(-1, 2))  # (N, 3)
        if len(colours) < 12:
            continue
        centre = np.median(colours, axis=0)  # (3,)
        spread = float(np.median(np.abs(colours - centre).sum(axis=1)))
        contrast = []
        for off in (-2.0 * radius, 2.0 * radius):
            side = colours_at(wrist + steps[:, None] * d + off * n)  # (N', 3)
            if len(side) >= 4:
                contrast.append(float(np.linalg.norm(np.median(side, axis=0) - centre)))
        if not contrast:
            away = 0.0
        else:
            # nearer side: both sides must be in the image, or a strip along the border
            # (one side off it) would pass as standing out from both
            both = float(min(contrast)) if len(contrast) == 2 else 0.0
            away = both if nearer_side else float(np.mean(contrast))
        # +1 Lab unit of noise floor, so that a perfectly uniform strip still prefers no turn
        score = (spread + 1.0) / (away + 1.0) * (1.0 + turn_cost * abs(np.radians(turn)))
        if other is not None and other_tolerance > 0:
            gap = float(np.linalg.norm(centre - other))
            if gap <= other_tolerance:
                score *= max(other_floor, ((gap + 1.0) / (other_tolerance + 1.0)) ** 2)
        if score < best_score:
            best, best_colour, best_score = d, centre, score
    return best, best_colour, float(best_score)


def arm_extent(
    lab: np.ndarray,
    wrist: np.ndarray,
    d: np.ndarray,
    radius: float,
    start: float,
    end: float,
    exclude: np.ndarray,
    tolerance: float,
    gap: float,
) -> tuple[float, np.ndarray | None]:
    """Distance in pixels from ``wrist`` along ``d`` to which the arm's colour holds; that colour.

    ``lab (H, W, 3)`` float32 Lab image; ``radius`` the forearm's half-width in pixels; the
    reference colour is the median along the axis from ``start`` to ``end`` pixels past the wrist
    (outside ``exclude (H, W)``, the hand). Walking on from ``end`` in steps of half a radius, a
    step matches when the median colour across the axis (three samples within half a radius) is
    within ``tolerance`` of the reference and at least one side, two radii off the axis, is not
    (an arm stands out from what lies beside it; a strip of plain table does not). The walk ends
    after ``gap`` radii of misses in a row or at the image border. Returns the last match (at
    least ``end``) and the reference colour ``(3,)``, or ``(end, None)`` when the reference
    cannot be measured or does not stand out from both sides (no arm there to follow).
    """
    h, w = lab.shape[:2]
    n = np.array([-d[1], d[0]])  # (2,)
    step = max(1.0, 0.5 * radius)

    across = np.array([-0.5, 0.0, 0.5]) * radius  # (3,)
    ref_t = np.arange(start, end + 1e-6, step)  # (S,)
    ref_pts = wrist + ref_t[:, None, None] * d + across[None, :, None] * n  # (S, 3, 2)
    ref = _sample(lab, exclude, ref_pts.reshape(-1, 2))
    ref = ref[np.all(np.isfinite(ref), axis=1)]
    if len(ref) < 3:
        return end, None
    ref_colour = np.median(ref, axis=0)  # (3,)
    # The strip must stand out from what lies beside it, or it is background, not an arm.
    ref_sides = [
        _sample(lab, exclude, wrist + ref_t[:, None] * d + off * radius * n) for off in (-2.0, 2.0)
    ]  # 2 x (S, 3)
    away = [
        float(np.linalg.norm(np.nanmedian(c, axis=0) - ref_colour))
        for c in ref_sides
        if np.isfinite(c[:, 0]).sum() >= 2
    ]
    if not away or max(away) <= tolerance:
        return end, None
    reach = float(np.hypot(h, w))
    ts = np.arange(end + step, end + reach, step)  # (S,)
    centre = wrist + ts[:, None, None] * d + across[None, :, None] * n  # (S, 3, 2)
    sides = wrist + ts[:, None, None] * d + np.array([-2.0, 2.0])[None, :, None] * radius * n
    colours = _sample(lab, exclude, centre.reshape(-1, 2))  # (S * 3, 3) NaN outside
    colours = colours.reshape(len(ts), 3, 3)  # (S, 3, 3)
    some = np.any(np.isfinite(colours[..., 0]), axis=1)  # (S,)
    colour = np.full((len(ts), 3), np.nan, np.float32)
    colour[some] = np.nanmedian(colours[some], axis=1)
    side = _sample(lab, exclude, sides.reshape(-1, 2)).reshape(len(ts), 2, 3)  # (S, 2, 3)
    dist = np.linalg.norm(colour - ref_colour, axis=1)  # (S,) NaN outside
    side_dist = np.linalg.norm(side - ref_colour, axis=2)  # (S, 2)
    contrast = np.nanmax(np.where(np.isfinite(side_dist), side_dist, -1.0), axis=1) > tolerance
    in_image = np.isfinite(dist)
    match = in_image & (dist <= tolerance) & contrast  # (S,)
    last, misses = end, 0.0
    for t, ok, inside in zip(ts, match, in_image, strict=True):
        if not inside:
            break
        if ok:
            last, misses = float(t), 0.0
        else:
            misses += step
            if misses > gap * radius:
                break
    return last, ref_colour


def _exit_distance(point: np.ndarray, d: np.ndarray, width: int, height: int) -> float:
    """Distance in pixels from ``point (2,)`` along the unit ``d (2,)`` to the image border (0
    when ``point`` is outside the image)."""
    if not (0.0 <= point[0] <= width and 0.0 <= point[1] <= height):
        return 0.0
    ts = []
    for p, v, size in ((point[0], d[0], width), (point[1], d[1], height)):
        if v > 1e-9:
            ts.append((size - p) / v)
        elif v < -1e-9:
            ts.append(-p / v)
    return float(min(ts)) if ts else float("inf")


def leaves_through_top(point: np.ndarray, d: np.ndarray, width: int, height: int) -> bool:
    """Whether the ray from ``point (2,)`` along the unit ``d (2,)`` meets the image border
    on its top edge (y = 0), not a side or the bottom.

    An arm drawn that way runs up from the wrist: in a head-worn view the body lies below the
    camera, and a forearm enters from the bottom or a side. HOT3D window 1, t=56-60: the hands
    stage put the right hand on its own forearm, fingers down towards the bottom-right corner,
    so the hand's direction (and the arm searched round it) pointed up-left, and a band ran from
    the forearm over the house to the top border. Every other drawn arm of the real clips
    (HOT3D, EgoDex, DWM, pour_coke, lift_tumbler) leaves through a side or the bottom.

    A ``point`` outside the image is its own end (exit distance 0): it counts only when it lies
    above the top border (an arm pointing up from there); a wrist beside or below the image
    never counts, even when its ray crosses the image and leaves through the top.
    """
    if d[1] >= -1e-9:
        return False
    end = point + _exit_distance(point, d, width, height) * d  # (2,)
    return bool(end[1] <= 1e-6)


def arms_through_top(
    keypoints: np.ndarray, valid: np.ndarray, directions: np.ndarray, height: int, width: int
) -> np.ndarray:
    """``(T, K)`` bool: hands whose arm, drawn along ``directions (T, K, 2)`` (NaN: none) from
    the wrist of ``keypoints (T, K, 21, 2)`` (``valid (T, K)``), would leave the image through
    its top border (:func:`leaves_through_top`): such an arm is not drawn, and the hand's
    keypoints are doubtful (a hand turned over on its own forearm), so the stage lets its
    neighbours' masks of that hand be carried into the frame, as into a carried hand's.
    """
    out = np.zeros(valid.shape, bool)
    for t, k in zip(*np.nonzero(valid), strict=True):
        wrist = np.asarray(keypoints[t, k, 0], np.float64)  # (2,)
        d = np.asarray(directions[t, k], np.float64)  # (2,)
        if np.all(np.isfinite(wrist)) and np.all(np.isfinite(d)):
            out[t, k] = leaves_through_top(wrist, d, width, height)
    return out


def _turn_deg(a: np.ndarray, b: np.ndarray) -> float:
    """Degrees between unit vectors ``a (2,)`` and ``b (2,)``."""
    return float(np.degrees(np.arccos(np.clip(float(a @ b), -1.0, 1.0))))


def _rotate(v: np.ndarray, degrees: float) -> np.ndarray:
    a = np.radians(degrees)
    return np.array([np.cos(a) * v[0] - np.sin(a) * v[1], np.sin(a) * v[0] + np.cos(a) * v[1]])


def _arm_start(
    keypoints: np.ndarray, capsule: CapsuleParams, arm: ArmParams, height: int, width: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, float, bool] | None:
    """``(mask, wrist, hand direction, hand length, forearm half-width, search)`` of one hand.

    ``mask (H, W)`` uint8 is the hand's capsules; lengths are in pixels; ``search`` says whether
    the arm's direction is searched (not when the hand's direction leaves the image within
    ``out_of_view`` hand lengths). None without a scale or a direction, or without a forearm.
    """
    scale = hand_scale_px(keypoints)
    found = hand_direction(keypoints)
    if not np.isfinite(scale) or scale <= 0 or not capsule.forearm or found is None:
        return None
    mask, _ = draw_hand(
        keypoints, 0, height, width, CapsuleParams(capsule.radius_scale, forearm=False)
    )
    wrist, d, hand_len = found
    if arm.unforeshortened:
        # A hand pointing into the view is short in the image, its arm often is not: lengths
        # along the arm come from the hand's scale (its least foreshortened palm bone).
        hand_len = max(hand_len, PALM_LENGTH_M * scale * capsule.radius_scale)
    r_wrist = FOREARM_RADIUS_M[0] * scale * capsule.radius_scale
    leaves = _exit_distance(wrist, d, width, height) < arm.out_of_view * hand_len
    return mask, wrist, d, hand_len, r_wrist, arm.max_turn_deg > 0 and not leaves


def draw_arm_labels(
    labels: np.ndarray,
    keypoints: np.ndarray,
    capsule: CapsuleParams,
    arm: ArmParams,
    lab: np.ndarray | None = None,
    other: np.ndarray | None = None,
    direction: np.ndarray | None = None,
    nearer_side: bool = False,
    region_lab: np.ndarray | None = None,
) -> tuple[np.ndarray | None, bool]:
    """Paint one hand's GrabCut labels into ``labels (H, W)`` uint8 in place (see module doc).

    Returns the arm's unit image direction ``(2,)`` from the wrist that was drawn (None when the
    hand has no arm start: no scale, no direction or no forearm) and whether the arm drawn has a
    colour region (a strip that stands out from its sides, :func:`arm_extent`; False: no arm
    colour found, only the band and the thin seed strip). ``direction (2,)``, when
    given, is drawn as it is: no search and no re-aim (a direction the neighbouring frames
    agree on, see :func:`steady_directions`). With ``nearer_side`` the search is run again
    asking the strip to stand out from both sides (:func:`arm_search`), and that direction is
    drawn when it lies more than ``start_switch_deg`` from the first: another arm, not the
    same one a step off (the first search's choice within one valley is kept).
    ``region_lab (H, W, 3)``: the float32 Lab image the arm's strip colour, its walk and its
    colour region are read from (a dim frame lifted, :func:`lift_dark`); None: ``lab``.

    With ``lab (H, W, 3)``, the image in float32 Lab, the forearm's direction is searched round
    the hand's own (:func:`arm_direction`, with ``other (3,)``, the Lab colour of the other
    hand's arm, when given); without it, the hand's direction is used. Regions
    only ever move towards the foreground: a pixel already labelled more certainly hand (by
    another hand) keeps its label. Labels: ``cv2.GC_BGD`` < ``GC_PR_BGD`` < ``GC_PR_FGD`` <
    ``GC_FGD`` in certainty of being hand, painted in that order.
    """
    h, w = labels.shape
    scale = hand_scale_px(keypoints)
    if not np.isfinite(scale) or scale <= 0:
        return None, False
    mask, core = draw_hand(keypoints, 0, h, w, CapsuleParams(capsule.radius_scale, forearm=False))
    fan = np.zeros((h, w), np.uint8)
    band = np.zeros((h, w), np.uint8)
    seed = np.zeros((h, w), np.uint8)
    start = _arm_start(keypoints, capsule, arm, h, w)
    drawn = None
    region = None
    region_lab = lab if region_lab is None or lab is None else region_lab  # (H, W, 3)
    if start is not None and direction is not None:
        _, wrist, _, hand_len, _, _ = start
        drawn = np.asarray(direction, np.float64)
        fan, band, seed, region = _arm_regions(
            region_lab, mask, wrist, drawn, hand_len, scale, capsule, arm
        )
        if region is not None and arm.region_probable:
            band = band | region
    elif start is not None:
        _, wrist, d, hand_len, r_wrist, search = start
        hand_dir = d
        if lab is not None and search:
            extra = {} if other is None else {
                "other": other, "other_tolerance": arm.other_arm, "other_floor": arm.other_arm_floor
            }  # fmt: skip
            search_args = (lab, wrist, hand_dir, hand_len, mask)
            search_kw = {"max_turn_deg": arm.max_turn_deg, "turn_cost": arm.turn_cost,
                         "radius": r_wrist, **extra}  # fmt: skip
            d = arm_direction(*search_args, **search_kw)
            if nearer_side:
                both = arm_direction(*search_args, nearer_side=True, **search_kw)
                if _turn_deg(both, d) > arm.start_switch_deg:
                    d = both  # another arm, not the same one a step off: see the docstring
        fan, band, seed, region = _arm_regions(
            region_lab, mask, wrist, d, hand_len, scale, capsule, arm
        )
        if region is not None and arm.refine_direction:
            better = region_direction(region, wrist, d)
            limit = _turn_deg(d, hand_dir) + arm.refine_slack_deg
            if better is not None and _turn_deg(better, hand_dir) > limit:
                better = None  # the arm's colour runs off sideways (a shaded table or cushion)
            if better is not None:
                fan, band, seed, again = _arm_regions(
                    region_lab, mask, wrist, better, hand_len, scale, capsule, arm
                )
                region = region if again is None else again
                d = better
        if region is not None and arm.region_probable:
            band = band | region  # the arm's colour wherever it runs: GrabCut decides
        drawn = d
    coloured = region is not None
    if (
        start is not None
        and drawn is not None
        and arm.no_arm_from_top
        and leaves_through_top(start[1], drawn, w, h)
    ):
        fan, band, seed = np.zeros_like(fan), np.zeros_like(band), np.zeros_like(seed)
        coloured = False
    # A probably-background ring round the hand lets the colour model trim fat capsules.
    grow = max(1, round(arm.hand_ring * scale)) if arm.hand_ring > 0 else 0
    ring = cv2.dilate(mask, np.ones((3, 3), np.uint8), iterations=grow) if grow > 0 else mask
    for region, label in (
        (fan | ring, cv2.GC_PR_BGD),
        (band | mask, cv2.GC_PR_FGD),
        (seed | core, cv2.GC_FGD),
    ):
        _raise_labels(labels, region > 0, label)
    return drawn, coloured


def other_arm_colours(
    lab: np.ndarray, keypoints: np.ndarray, valid: np.ndarray, capsule: CapsuleParams,
    arm: ArmParams, starts: np.ndarray | None = None,
) -> list[np.ndarray | None]:  # fmt: skip
    """Per hand, the Lab colour ``(3,)`` of the other hand's arm to prefer, or None.

    Each searched hand's arm is first searched alone (:func:`arm_search`); a hand is given the
    strip colour of the other hand with the lowest (most certain) score, when its own score is
    above ``other_arm_unsure`` (no clear arm found alone), the other's score is lower than its
    own and at most ``other_arm_rare`` of the frame (sampled every 4 px) lies
    within ``other_arm`` of that colour: the surer arm tells the other which colour the arms
    are, when that colour is rare enough to mean arm. ``starts (K,)``: hands searched with
    ``nearer_side`` (see :func:`hand_labels`).
    """
    h, w = lab.shape[:2]
    alone: list[tuple[np.ndarray, float] | None] = []
    for k, (hand, ok) in enumerate(zip(keypoints, valid, strict=True)):
        start = _arm_start(np.asarray(hand, np.float64), capsule, arm, h, w) if ok else None
        if start is None or not start[5]:
            alone.append(None)
            continue
        mask, wrist, d, hand_len, r_wrist, _ = start
        best, colour, score = arm_search(lab, wrist, d, hand_len, mask, arm.max_turn_deg,
                                         arm.turn_cost, r_wrist)  # fmt: skip
        if starts is not None and starts[k]:  # as draw_arm_labels chooses
            both, both_colour, both_score = arm_search(lab, wrist, d, hand_len, mask,
                                                       arm.max_turn_deg, arm.turn_cost, r_wrist,
                                                       nearer_side=True)  # fmt: skip
            if _turn_deg(both, best) > arm.start_switch_deg:
                colour, score = both_colour, both_score
        alone.append(None if colour is None else (colour, score))
    out: list[np.ndarray | None] = []
    for k, own in enumerate(alone):
        others = [a for j, a in enumerate(alone) if j != k and a is not None]
        surest = min(others, key=lambda a: a[1]) if others else None
        if own is None or surest is None or own[1] <= arm.other_arm_unsure or surest[1] >= own[1]:
            out.append(None)
            continue
        share = np.linalg.norm(lab[2::4, 2::4] - surest[0], axis=2) <= arm.other_arm  # (H', W')
        out.append(surest[0] if float(share.mean()) <= arm.other_arm_rare else None)
    return out


def _arm_regions(
    lab: np.ndarray | None,
    mask: np.ndarray,
    wrist: np.ndarray,
    d: np.ndarray,
    hand_len: float,
    scale: float,
    capsule: CapsuleParams,
    arm: ArmParams,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
    """``(fan, band, seed, region)`` ``(H, W)`` uint8 of an arm leaving ``wrist`` along ``d``.

    ``fan``: probably background; ``band``: probably arm; ``seed``: certainly arm (the strip,
    extended by :func:`arm_extent`, plus the arm-coloured pixels near the axis connected to it);
    ``region``: the pixels of the arm's colour connected to the strip within
    ``refine_half_angle_deg`` of ``d`` (None without ``lab`` or a measurable arm colour), for
    :func:`region_direction`.
    """
    h, w = mask.shape
    seed = np.zeros((h, w), np.uint8)
    reach = float(np.hypot(h, w)) + float(np.hypot(*(wrist - [w / 2, h / 2])))
    r0 = FOREARM_RADIUS_M[0] * scale * capsule.radius_scale * arm.band
    r1 = FOREARM_RADIUS_M[1] * scale * capsule.radius_scale * arm.band
    r_end = min(r0 + (r1 - r0) * reach / max(FOREARM_LENGTH_M * scale, 1e-6), 2.0 * r1)
    n = np.array([-d[1], d[0]])  # (2,) normal
    end = wrist + reach * d

    def filled(polygon: np.ndarray) -> np.ndarray:
        """``(H, W)`` uint8, 1 inside ``polygon (N, 2)`` (pixels)."""
        out = np.zeros((h, w), np.uint8)
        cv2.fillPoly(out, [fixed_point(polygon)], 1, cv2.LINE_8, SHIFT)
        return out

    def band_of(k: float) -> np.ndarray:
        """The tapered band along ``d`` to the border, ``k`` times the forearm's half-width."""
        return filled(np.stack([wrist + k * r0 * n, end + k * r_end * n, end - k * r_end * n,
                                wrist - k * r0 * n]))  # fmt: skip

    # Fan: the wrist's neighbourhood plus every direction within the half-angle, at most
    # ``fan_width`` forearm half-widths from the axis (so a false arm stays a bounded band).
    half = arm.fan_half_angle_deg
    rays = [wrist + reach * _rotate(d, a) for a in np.linspace(-half, half, 9)]
    fan = filled(np.stack([wrist + r0 * n, *rays, wrist - r0 * n]))  # (11, 2) polygon
    if arm.fan_width > 0:
        fan &= band_of(arm.fan_width)
    band = band_of(1.0)
    a = wrist + arm.seed_start * hand_len * d
    seed_end = arm.seed_end * hand_len
    ref = None
    if lab is not None and arm.walk:
        seed_end, ref = arm_extent(lab, wrist, d, r0, arm.seed_start * hand_len, seed_end,
                                   mask, arm.walk_tolerance, arm.walk_gap)  # fmt: skip
    b = wrist + seed_end * d
    thickness = max(1, round(2 * arm.seed_width * FOREARM_RADIUS_M[0] * scale))
    cv2.line(seed, tuple(fixed_point(a)), tuple(fixed_point(b)), 1, thickness, cv2.LINE_8, SHIFT)
    if lab is None or ref is None:
        return fan, band, seed, None
    close = (np.linalg.norm(lab - ref, axis=2) <= arm.walk_tolerance) & (mask == 0)  # (H, W)
    half = arm.refine_half_angle_deg
    rays = [wrist + reach * _rotate(d, a) for a in np.linspace(-half, half, 13)]
    wide_fan = filled(np.stack([wrist, *rays]))
    region = connected_to((close & (wide_fan > 0)).astype(np.uint8) | seed, seed)
    if arm.colour_region > 0:
        # The arm's colour near its axis, connected to the strip, is certainly arm.
        wide = band_of(arm.colour_region)
        seed = seed | connected_to((close & (wide > 0)).astype(np.uint8) | seed, seed)
    return fan, band, seed, region


def region_direction(
    region: np.ndarray, wrist: np.ndarray, d: np.ndarray, max_spread: float = 0.35
) -> np.ndarray | None:
    """Unit direction ``(2,)`` from ``wrist`` along which ``region (H, W)`` mostly lies, or None.

    The principal axis of the region's pixels about the wrist (not about their centroid: an arm
    is a ray from the wrist), turned to agree with ``d``. None for a region of fewer than 20
    pixels or one that is not ray-like (second over first singular value above ``max_spread``:
    a patch of table in the arm's colour, not an arm).
    """
    ys, xs = np.nonzero(region)
    if len(ys) < 20:
        return None
    v = np.stack([xs + 0.5, ys + 0.5], axis=1) - wrist  # (N, 2)
    _, sv, vt = np.linalg.svd(v, full_matrices=False)
    if sv[1] > max_spread * sv[0]:
        return None
    axis = vt[0]
    return axis if float(axis @ d) >= 0 else -axis


_CERTAINTY = {cv2.GC_BGD: 0, cv2.GC_PR_BGD: 1, cv2.GC_PR_FGD: 2, cv2.GC_FGD: 3}
_LUT = np.array([0, 3, 1, 2], np.uint8)  # label -> certainty of being hand (GC codes 0..3)


def _raise_labels(labels: np.ndarray, where: np.ndarray, label: int) -> None:
    """Set ``labels`` to ``label`` on ``where`` where that is more certainly hand than before."""
    higher = where & (_LUT[labels] < _CERTAINTY[label])
    labels[higher] = label


def grabcut_labels(
    image: np.ndarray, labels: np.ndarray, iterations: int = 3, max_side: int = 256
) -> np.ndarray:
    """Foreground ``(H, W)`` uint8 of GrabCut on ``image (H, W, 3)`` RGB seeded by ``labels``.

    Works in the bounding box of the non-background labels (plus an eighth of its size on each
    side), downscaled so that its longer side is at most ``max_side`` pixels; the result is
    upscaled back. Certain-hand labels always stay foreground. Without any background label in
    the box, the probable-hand pixels are returned unchanged.
    """
    h, w = labels.shape
    fg_any = labels != cv2.GC_BGD
    out = (labels == cv2.GC_FGD) | (labels == cv2.GC_PR_FGD)
    if not (labels == cv2.GC_FGD).any():
        return out.astype(np.uint8)
    ys, xs = np.nonzero(fg_any)
    my, mx = max(4, (ys.max() - ys.min()) // 8), max(4, (xs.max() - xs.min()) // 8)
    y0, y1 = max(0, ys.min() - my), min(h, ys.max() + my + 1)
    x0, x1 = max(0, xs.min() - mx), min(w, xs.max() + mx + 1)
    crop = cv2.cvtColor(np.ascontiguousarray(image[y0:y1, x0:x1]), cv2.COLOR_RGB2BGR)
    lab = labels[y0:y1, x0:x1]
    factor = min(1.0, max_side / max(crop.shape[:2]))
    if factor < 1.0:
        size = (max(1, round(crop.shape[1] * factor)), max(1, round(crop.shape[0] * factor)))
        crop = cv2.resize(crop, size, interpolation=cv2.INTER_AREA)
        small = cv2.resize(lab, size, interpolation=cv2.INTER_NEAREST)
    else:
        small = lab.copy()
    if (
        not np.isin(small, (cv2.GC_BGD, cv2.GC_PR_BGD)).any()
        or not np.isin(small, (cv2.GC_FGD, cv2.GC_PR_FGD)).any()
    ):
        return out.astype(np.uint8)
    bgd_model = np.zeros((1, 65), np.float64)
    fgd_model = np.zeros((1, 65), np.float64)
    cv2.setRNGSeed(0)
    try:
        cv2.grabCut(crop, small, None, bgd_model, fgd_model, iterations, cv2.GC_INIT_WITH_MASK)
    except cv2.error:  # a degenerate colour model (e.g. one colour only): keep the labels
        return out.astype(np.uint8)
    hand = np.isin(small, (cv2.GC_FGD, cv2.GC_PR_FGD)).astype(np.uint8)  # (h', w')
    if factor < 1.0:
        hand = cv2.resize(hand, (x1 - x0, y1 - y0), interpolation=cv2.INTER_LINEAR)
    result = np.zeros((h, w), np.uint8)
    result[y0:y1, x0:x1] = hand
    result[labels == cv2.GC_FGD] = 1
    return result


def connected_to(mask: np.ndarray, seeds: np.ndarray) -> np.ndarray:
    """The parts of ``mask (H, W)`` (8-connected components) that touch ``seeds (H, W)``."""
    count, comp = cv2.connectedComponents(mask.astype(np.uint8), connectivity=8)
    if count <= 1:
        return mask.astype(np.uint8)
    keep = np.zeros(count, bool)
    keep[np.unique(comp[(seeds > 0) & (mask > 0)])] = True
    keep[0] = False
    return keep[comp].astype(np.uint8)


def hand_labels(
    image: np.ndarray,
    keypoints: np.ndarray,
    valid: np.ndarray,
    capsule: CapsuleParams,
    arm: ArmParams,
    directions: np.ndarray | None = None,
    starts: np.ndarray | None = None,
    no_region: np.ndarray | None = None,
    allow_top: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(labels (K, H, W) uint8, drawn (K, 2), coloured (K,) bool)``: each hand's GrabCut
    labels of ``image (H, W, 3)`` (``cv2.GC_*``; see :func:`draw_arm_labels`), the arm direction
    drawn (NaN: none) and whether that arm has a colour region (a strip standing out from its
    sides; False for a hand not drawn or drawn without one).

    ``keypoints (K, 21, 2)`` pixels, ``valid (K,)`` selects the hands; ``directions (K, 2)``:
    per hand a direction to draw as it is (no search, no re-aim), NaN to search; ``starts
    (K,)`` bool: hands whose track starts in this frame, searched for a strip that stands out
    from both sides (``nearer_side`` of :func:`arm_search`; ``ArmParams.start_both_sides``);
    ``no_region (K,)`` bool: hands drawn without the probable colour region (``region_probable``
    off; :func:`off_side_runs`); ``allow_top (K,)`` bool: hands whose arm ``no_arm_from_top``
    may leave undrawn (None: all; the others' arm is drawn whatever its direction).
    """
    h, w = image.shape[:2]
    own = np.full((len(keypoints), h, w), cv2.GC_BGD, np.uint8)
    drawn = np.full((len(keypoints), 2), np.nan)
    coloured = np.zeros(len(keypoints), bool)
    lab = None  # (H, W, 3) the image in Lab, converted once for every hand's arm search
    region_lab = None  # (H, W, 3) Lab of the frame lifted when dim, for the arm region (None: lab)
    if capsule.forearm and np.any(valid):
        lab = cv2.cvtColor(image, cv2.COLOR_RGB2LAB).astype(np.float32)
        lit = lift_dark(image, arm.dark_floor)  # (H, W, 3) the image itself unless dim
        if lit is not image:
            region_lab = cv2.cvtColor(lit, cv2.COLOR_RGB2LAB).astype(np.float32)
    others: list[np.ndarray | None] = [None] * len(keypoints)
    if lab is not None and arm.other_arm > 0 and int(np.sum(valid)) > 1:
        others = other_arm_colours(lab, keypoints, valid, capsule, arm, starts)
    for k, (hand, ok) in enumerate(zip(keypoints, valid, strict=True)):
        if not ok:
            continue
        fixed = None
        if directions is not None and np.all(np.isfinite(directions[k])):
            fixed = directions[k]
        nearer = bool(starts is not None and starts[k])
        arm_k = arm
        if no_region is not None and no_region[k]:
            arm_k = replace(arm, region_probable=False)
        if allow_top is not None and not allow_top[k]:
            arm_k = replace(arm_k, no_arm_from_top=False)
        points = np.asarray(hand, dtype=np.float64)  # (21, 2)
        d, coloured[k] = draw_arm_labels(own[k], points, capsule, arm_k, lab, others[k], fixed,
                                         nearer, region_lab)  # fmt: skip
        if d is not None:
            drawn[k] = d
    return own, drawn, coloured


def crosses_other_wrist(
    keypoints: np.ndarray,
    valid: np.ndarray,
    drawn: np.ndarray,
    height: int,
    width: int,
    min_tilt_deg: float = 45.0,
) -> np.ndarray:
    """``(T, K)`` bool: frames whose drawn arm runs past the other hand's wrist, to its side.

    ``keypoints (T, 2, 21, 2)`` pixels, hand 0 the left and 1 the right; ``valid (T, 2)``;
    ``drawn (T, 2, 2)`` each hand's arm direction (NaN: none). In a head-mounted view the
    forearms come into the image from below, each on its own side: with both hands in the
    frame and the left wrist left of the right one, a left arm whose ray from its wrist
    meets the image border right of the right wrist (or a right arm left of the left wrist)
    crosses to the other arm's side, which an arm does not do; a search that follows a floor
    or table edge sideways does (HOT3D window 1, t=37-45: the left arm along the table top to
    the right border). Hands in the other order (crossed, or sides swapped) are never marked,
    nor an arm tilted less than ``min_tilt_deg`` from straight down towards the other hand's
    side (two hands close together on one object, arms nearly vertical: review10c; every real
    mark measured was 59 deg or more).
    """
    tilt = np.sin(np.radians(min_tilt_deg))  # x component of a unit direction that far over
    t_count, k_count = drawn.shape[:2]
    out = np.zeros((t_count, k_count), bool)
    if k_count != 2:
        return out
    for t in range(t_count):
        wrists = np.asarray(keypoints[t, :, 0], np.float64)  # (2, 2) MANO joint 0: the wrist
        if not bool(np.all(valid[t])) or not np.all(np.isfinite(wrists)):
            continue
        if not wrists[0, 0] < wrists[1, 0]:
            continue
        for k in range(2):
            d = drawn[t, k]
            if not np.all(np.isfinite(d)):
                continue
            end = wrists[k] + _exit_distance(wrists[k], d, width, height) * d  # (2,)
            if k == 0:
                out[t, k] = bool(d[0] > tilt and end[0] > wrists[1, 0])
            else:
                out[t, k] = bool(d[0] < -tilt and end[0] < wrists[0, 0])
    return out


def off_side_runs(steady: np.ndarray, off_side: np.ndarray) -> np.ndarray:
    """``(T, K)`` bool: the frames of each replaced run (consecutive frames with a direction in
    ``steady (T, K, 2)``, NaN: kept) of a hand that hold an ``off_side (T, K)`` frame.

    Such a run was found because a frame's arm crossed to the other hand's side, not because it
    swung far by angle: the arm may have moved meanwhile, so the interpolated direction is a
    guess and its colour region may be the floor beside the arm (HOT3D window 1, t=37-44).
    """
    replaced = np.all(np.isfinite(steady), axis=2)  # (T, K)
    off = np.asarray(off_side, bool)  # (T, K)
    out = np.zeros(replaced.shape, bool)
    for k in range(replaced.shape[1]):
        for t, q in true_runs(replaced[:, k]):
            out[t:q, k] = off[t:q, k].any()
    return out


def true_runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """``[(start, end), ...]``: the runs of consecutive True frames of ``mask (T,)``, ``end``
    exclusive, in order."""
    padded = np.concatenate([[False], np.asarray(mask, bool), [False]])  # (T+2,)
    edges = np.flatnonzero(padded[1:] != padded[:-1])  # run starts and ends, alternating
    return list(zip(edges[::2].tolist(), edges[1::2].tolist(), strict=True))


def steady_directions(
    drawn: np.ndarray,
    max_frames: int,
    jump_deg: float,
    agree_deg: float,
    off_side: np.ndarray | None = None,
) -> np.ndarray:
    """Directions ``(T, K, 2)`` to draw instead (NaN: keep the frame's own) given the arm
    directions ``drawn (T, K, 2)`` of each frame's hands (NaN: none).

    An arm does not swing round and back within a few frames: for each hand, a run of at most
    ``max_frames`` consecutive frames with directions, every one of them more than
    ``jump_deg`` from the frames just before and just after the run, where those two agree
    within ``agree_deg``, takes the direction between the two (interpolated in time). The
    search's colour cue can lock on a smooth strip of floor beside a hand for several frames
    (HOT3D window 1, t=25-34: a right arm turned 90 degrees onto the floor to the left
    border); the frames either side see the arm where it is. ``off_side (T, K)`` bool: frames
    whose arm is implausible whatever its angle (:func:`crosses_other_wrist`): they count as
    swung away from both brackets and are never a bracket themselves.
    """
    t_count, k_count = drawn.shape[:2]
    out = np.full(drawn.shape, np.nan)
    if max_frames <= 0:
        return out
    has = np.all(np.isfinite(drawn), axis=2)  # (T, K)
    off = np.zeros(has.shape, bool) if off_side is None else np.asarray(off_side, bool)  # (T, K)
    drawn = drawn.copy()  # a run's replaced directions bracket the runs after it

    def angle(a: np.ndarray, b: np.ndarray) -> float:
        return _turn_deg(a / np.linalg.norm(a), b / np.linalg.norm(b))

    for k in range(k_count):
        t = 1
        while t < t_count - 1:
            p = t - 1
            fixed = False
            if has[p, k] and has[t, k] and not off[p, k]:
                for n in range(1, max_frames + 1):
                    q = t + n
                    if q >= t_count or not has[q - 1, k]:
                        break
                    run = range(t, q)
                    if not all(
                        off[r, k] or angle(drawn[r, k], drawn[p, k]) > jump_deg for r in run
                    ):  # a frame of the run agrees with the one before: no run from t
                        break
                    if not has[q, k] or off[q, k] or angle(drawn[p, k], drawn[q, k]) > agree_deg:
                        continue
                    if all(off[r, k] or angle(drawn[r, k], drawn[q, k]) > jump_deg for r in run):
                        for r in run:
                            w = (r - p) / (q - p)
                            v = (1.0 - w) * drawn[p, k] + w * drawn[q, k]
                            out[r, k] = drawn[r, k] = v / np.linalg.norm(v)
                        t, fixed = q, True
                        break
            t = t if fixed else t + 1
        if off_side is not None:
            _hold_track_ends(drawn[:, k], has[:, k], off[:, k], out[:, k], max_frames, jump_deg)
    return out


def _hold_track_ends(
    drawn: np.ndarray,
    has: np.ndarray,
    off: np.ndarray,
    out: np.ndarray,
    max_frames: int,
    jump_deg: float,
) -> None:
    """Fill ``out (T, 2)`` in place (one hand; NaN: kept) at the off-side frames that end a
    track: a run of at most ``max_frames`` off-side frames (``off (T,)``) with directions
    (``drawn (T, 2)``, ``has (T,)``), not replaced yet, with a frame of the track on one side
    only (the track starts or ends there, so no run can be bracketed), every one more than
    ``jump_deg`` from that frame's direction (a swing, not the same arm a step off), takes that
    frame's direction, held (HOT3D window 1, t=1: the left hand's last frame, its arm drawn
    along the floor to the right border, 125 degrees from the frame before). A run with track
    frames on both sides is left to the runs bracketed by agreeing frames.
    """
    t_count = len(drawn)
    for t, q in true_runs(off & has & ~np.isfinite(out[:, 0])):  # runs not replaced yet
        before = t > 0 and bool(has[t - 1])
        after = q < t_count and bool(has[q])
        if q - t <= max_frames and before != after:
            src = drawn[t - 1 if before else q]  # (2,) not off-side, or already replaced
            if all(_turn_deg(drawn[r], src) > jump_deg for r in range(t, q)):
                out[t:q] = src


def masks_from_labels(
    image: np.ndarray, own: np.ndarray, colour: bool = True, iterations: int = 3,
    max_side: int = 256,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """``(mask (H, W), per_hand (K, H, W), certain (K, H, W))`` uint8 of ``image (H, W, 3)``
    from the hands' GrabCut labels ``own (K, H, W)`` (:func:`hand_labels`); see
    :func:`hand_arm_masks`."""
    h, w = image.shape[:2]
    labels = np.full((h, w), cv2.GC_BGD, np.uint8)
    certain = (own == cv2.GC_FGD).astype(np.uint8)  # (K, H, W)
    for hand in own:
        for label in (cv2.GC_PR_BGD, cv2.GC_PR_FGD, cv2.GC_FGD):
            _raise_labels(labels, hand == label, label)
    if not colour:
        mask = np.isin(labels, (cv2.GC_FGD, cv2.GC_PR_FGD)).astype(np.uint8)
    else:
        mask = grabcut_labels(image, labels, iterations, max_side)
        mask = connected_to(mask, labels == cv2.GC_FGD)
    per_hand = np.zeros_like(certain)  # (K, H, W)
    for k, seeds in enumerate(certain):
        if seeds.any():
            per_hand[k] = connected_to(mask, seeds) & mask
    return mask, per_hand, certain


def hand_arm_masks(
    image: np.ndarray,
    keypoints: np.ndarray,
    valid: np.ndarray,
    capsule: CapsuleParams,
    arm: ArmParams,
    colour: bool = True,
    iterations: int = 3,
    max_side: int = 256,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(mask (H, W), per_hand (K, H, W), certain (K, H, W))`` uint8 of ``image (H, W, 3)``.

    ``keypoints (K, 21, 2)`` pixels, ``valid (K,)`` selects the hands. ``mask``: hand and arm
    (1); ``per_hand[k]``: the parts of ``mask`` connected to hand ``k``'s certain seeds;
    ``certain[k]``: those seeds (its skeleton core and arm strip), what later frames may carry
    with confidence (see ``propagate``). Without ``colour`` the mask is the probable-hand labels
    (capsules and the forearm band along the hand's direction).
    """
    own, _, _ = hand_labels(image, keypoints, valid, capsule, arm)
    return masks_from_labels(image, own, colour, iterations, max_side)


def hand_arm_mask(
    image: np.ndarray,
    keypoints: np.ndarray,
    valid: np.ndarray,
    capsule: CapsuleParams,
    arm: ArmParams,
    colour: bool = True,
    iterations: int = 3,
    max_side: int = 256,
) -> np.ndarray:
    """Hand-and-arm mask ``(H, W)`` uint8 of ``image (H, W, 3)`` from ``keypoints (K, 21, 2)``.

    ``valid (K,)`` selects the hands; see :func:`hand_arm_masks` (this is its ``mask``).
    """
    return hand_arm_masks(image, keypoints, valid, capsule, arm, colour, iterations, max_side)[0]
