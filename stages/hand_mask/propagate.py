"""Carry hand-and-arm masks through time with optical flow, one hand at a time.

An arm that enters the view later in the clip is often already visible at the image border in
the earlier frames, where no hand keypoint is (the wrist is still below the image), and a hand
the keypoints miss for a few frames is still where the neighbouring frames put it. Going from
the last frame to the first, frame ``t + 1``'s mask is pulled back into frame ``t`` through the
dense optical flow from ``t`` to ``t + 1`` (OpenCV DIS):
``warped_t(x) = mask_{t+1}(x + flow_{t->t+1}(x))``; forwards in time the same on the reversed
clip. The masks are one hand's (:func:`propagate_hands`): a frame gets hand ``k`` carried into it
when its own mask of hand ``k`` is empty (that hand was missed), whatever the other hand's, or
when it is marked open (``open_frames``: the hand's keypoints were carried there by tracking,
see ``carry``, so its mask may lack the arm); an open frame's own mask is kept and joined.

Background that the arm covers at ``t + 1`` but not at ``t`` also maps into the arm, so the
warped mask keeps only pixels whose grey level at ``t`` is within ``photo_tolerance`` of frame
``t + 1``'s at the flow's target (the table the arm is about to cover has no flow but not the
arm's colour), and it is only a proposal. Only hand evidence travels with confidence: when the
frames' ``certain`` masks are given (the keypoint skeleton and arm strip each mask was grown
from), the certainly-arm core at ``t`` is the warped certain mask where the flow is
forward-backward consistent within ``consistency_px`` and photo-consistent, eroded; without
them, the whole consistent warped mask. A patch of background that a frame's colour model
wrongly joined to its hand is not certain there, so it reaches an earlier frame as a proposal
at most, and without a certain core next to it nothing is kept. The rest of the warped mask is
probably arm, a ring round it probably background, and GrabCut on frame ``t`` decides which of
the warped pixels stay (it never adds pixels outside the warped mask, so errors do not grow)
(see ``arm_region``). Only what connects to the certain core is kept.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from egosim.stages.hand_mask.arm_region import connected_to, grabcut_labels


@dataclass(frozen=True)
class PropagationParams:
    """How masks travel backwards in time."""

    consistency_px: float = 1.5  # forward-backward flow disagreement that marks occlusion
    erode_px: int = 2  # the certain-arm core is the consistent warped mask eroded by this
    ring_px: int = 12  # probably-background ring round the warped mask, pixels
    min_pixels: int = 30  # warped masks smaller than this are dropped (noise)
    iterations: int = 2  # GrabCut iterations per frame
    max_side: int = 256  # GrabCut works at most at this longest side
    photo_tolerance: float = 12.0  # grey levels frame t may differ from t+1 along the flow
    max_frames: int = 1000  # a mask travels at most this many frames from where it was found
    into_empty_only: bool = True  # only frames whose own mask is empty (their hands were missed)

    def __post_init__(self) -> None:
        problems = []
        if not 0.0 < self.consistency_px <= 50.0:
            problems.append(f"consistency_px must be in (0, 50], got {self.consistency_px}")
        if not 0 <= self.erode_px <= 50 or not 1 <= self.ring_px <= 200:
            problems.append(
                f"erode_px in [0, 50] and ring_px in [1, 200], got {self.erode_px}, {self.ring_px}"
            )
        if not 0.0 < self.photo_tolerance <= 255.0:
            problems.append(f"photo_tolerance must be in (0, 255], got {self.photo_tolerance}")
        if self.max_frames < 1:
            problems.append(f"max_frames must be >= 1, got {self.max_frames}")
        if self.min_pixels < 0 or self.iterations < 1 or self.max_side < 16:
            problems.append(
                f"min_pixels >= 0, iterations >= 1, max_side >= 16, got {self.min_pixels}, "
                f"{self.iterations}, {self.max_side}"
            )
        if problems:
            raise ValueError("; ".join(problems))


class FrameFlows:
    """Grey frames and dense flows (OpenCV DIS) of one clip, each computed once and kept.

    Both directions of :func:`propagate_both_ways` and every hand of :func:`propagate_hands`
    need the flows between the same neighbouring frames (one direction's ``t -> t+1`` flow is
    the other's backward flow), so they share one ``FrameFlows``; :meth:`reversed` is a view of
    the same store indexed on the reversed clip. Kept for the clip: at most two ``(H, W, 2)``
    float32 flows per neighbouring pair (about 380 MB for 61 frames at 480x832).
    """

    def __init__(self, frames: np.ndarray) -> None:
        self._frames = frames  # (T, H, W, 3) uint8 RGB, in the clip's own order
        self._reverse = False  # True: indices count from the clip's last frame
        self._grey: dict[int, np.ndarray] = {}  # clip frame index -> (H, W) uint8 grey
        self._flows: dict[tuple[int, int], np.ndarray] = {}  # (from, to) -> (H, W, 2) float32
        self._dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_FAST)

    def reversed(self) -> FrameFlows:
        """The same frames and stored flows, indexed on the reversed clip."""
        view = object.__new__(FrameFlows)
        view.__dict__.update(self.__dict__)
        view._reverse = not self._reverse
        return view

    def _index(self, t: int) -> int:
        return len(self._frames) - 1 - t if self._reverse else t

    def grey(self, t: int) -> np.ndarray:
        """Frame ``t`` in grey ``(H, W)`` uint8."""
        i = self._index(t)
        if i not in self._grey:
            self._grey[i] = cv2.cvtColor(self._frames[i], cv2.COLOR_RGB2GRAY)
        return self._grey[i]

    def flow(self, a: int, b: int) -> np.ndarray:
        """Dense flow ``(H, W, 2)`` float32 from frame ``a`` to frame ``b`` (pixels)."""
        key = (self._index(a), self._index(b))
        if key not in self._flows:
            self._flows[key] = self._dis.calc(self.grey(a), self.grey(b), None)
        return self._flows[key]


def _pull(image: np.ndarray, flow: np.ndarray, interpolation: int) -> np.ndarray:
    """``image`` sampled at ``x + flow(x)`` (OpenCV remap; outside = 0)."""
    h, w = flow.shape[:2]
    gx, gy = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    return cv2.remap(
        image, gx + flow[..., 0], gy + flow[..., 1], interpolation, borderMode=cv2.BORDER_CONSTANT
    )


def propagate_backwards(
    frames: np.ndarray,
    masks: np.ndarray,
    params: PropagationParams | None = None,
    certain: np.ndarray | None = None,
    flows: FrameFlows | None = None,
    open_frames: np.ndarray | None = None,
) -> np.ndarray:
    """Masks ``(T, H, W)`` uint8 with later masks carried back into earlier frames.

    ``frames (T, H, W, 3)`` uint8 RGB; ``masks (T, H, W)`` uint8 (1 = hand or arm), each frame's
    own mask; ``certain (T, H, W)`` uint8, optional: the part of each mask that is certainly
    hand or arm (see the module docstring; None: all of it). Frame ``T - 1`` is returned as
    given; every earlier frame gains what the (already propagated) next frame's mask shows of
    it, as long as that mask was found at most ``max_frames`` frames later. ``flows``: the
    grey frames and flows of ``frames``, shared with other calls on the same clip (None: made
    here). ``open_frames (T,)`` bool, optional: frames that receive carried masks even though
    their own is not empty (a hand whose keypoints were themselves carried there, see
    ``carry``); they are still sources for the frames beyond.
    """
    p = params or PropagationParams()
    out = masks.astype(np.uint8).copy()
    sure = out.copy() if certain is None else (certain > 0).astype(np.uint8) & out
    if len(frames) < 2:
        return out
    # Frames since the mask at each frame was found (0: its own mask is not empty).
    age = np.where(out.reshape(len(out), -1).any(axis=1), 0, p.max_frames + 1)  # (T,)
    receive = age > 0  # (T,) frames that may gain carried pixels
    if open_frames is not None:
        receive |= np.asarray(open_frames, bool)
    flows = flows or FrameFlows(frames)
    grey_of = flows.grey
    erode = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * p.erode_px + 1,) * 2)
    ring = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * p.ring_px + 1,) * 2)
    for t in range(len(frames) - 2, -1, -1):
        if out[t + 1].sum() < p.min_pixels or age[t + 1] >= p.max_frames:
            continue
        if p.into_empty_only and not receive[t]:
            continue
        fwd = flows.flow(t, t + 1)  # (H, W, 2) t -> t+1
        warped = _pull(out[t + 1], fwd, cv2.INTER_NEAREST)  # (H, W) proposal at t
        # A pixel is carried only where frame t looks like frame t+1 at the flow's target: the
        # table that the arm will cover next has zero flow but not the arm's colour.
        seen_next = _pull(grey_of(t + 1), fwd, cv2.INTER_LINEAR).astype(np.int16)  # (H, W)
        same = (np.abs(seen_next - grey_of(t).astype(np.int16)) <= p.photo_tolerance).astype(
            np.uint8
        )
        warped &= same
        new = (warped > 0) & (out[t] == 0)
        if new.sum() < p.min_pixels:
            continue
        bwd = flows.flow(t + 1, t)  # (H, W, 2) t+1 -> t
        back = _pull(bwd, fwd, cv2.INTER_LINEAR)  # (H, W, 2) bwd at x + fwd(x)
        consistent = np.hypot(*(fwd + back).transpose(2, 0, 1)) <= p.consistency_px
        carried = _pull(sure[t + 1], fwd, cv2.INTER_NEAREST) & warped & consistent.astype(np.uint8)
        core = cv2.erode(carried, erode)
        if not core.any() and not out[t].any():
            continue  # no hand evidence reaches frame t: nothing to anchor a proposal to
        labels = np.full(warped.shape, cv2.GC_BGD, np.uint8)
        labels[cv2.dilate(warped | out[t], ring) > 0] = cv2.GC_PR_BGD
        labels[warped > 0] = cv2.GC_PR_FGD
        labels[(core > 0) | (out[t] > 0)] = cv2.GC_FGD
        grown = grabcut_labels(frames[t], labels, p.iterations, p.max_side) & (warped | out[t])
        kept = connected_to(grown, labels == cv2.GC_FGD)
        sure[t] |= carried & kept
        out[t] = kept | out[t]
        age[t] = min(age[t], age[t + 1] + 1)
    return out


def propagate_both_ways(
    frames: np.ndarray,
    masks: np.ndarray,
    params: PropagationParams | None = None,
    certain: np.ndarray | None = None,
    flows: FrameFlows | None = None,
    open_frames: np.ndarray | None = None,
) -> np.ndarray:
    """Masks ``(T, H, W)`` carried backwards and forwards in time (see :func:`propagate_backwards`).

    Each direction starts from the frames' own ``masks`` (and ``certain`` parts); the result is
    their union. Both directions share ``flows`` (None: made here). ``open_frames (T,)`` bool,
    optional: frames that receive carried masks although their own is not empty, in both
    directions.
    """
    flows = flows or FrameFlows(frames)
    back = propagate_backwards(frames, masks, params, certain, flows, open_frames)
    rev = None if certain is None else certain[::-1]
    rev_open = None if open_frames is None else open_frames[::-1]
    forward = propagate_backwards(
        frames[::-1], masks[::-1], params, rev, flows.reversed(), rev_open
    )[::-1]
    return back | forward


def propagate_hands(
    frames: np.ndarray,
    masks: np.ndarray,
    per_hand: np.ndarray,
    certain: np.ndarray,
    params: PropagationParams | None = None,
    open_frames: np.ndarray | None = None,
) -> np.ndarray:
    """Masks ``(T, H, W)`` with each hand's mask carried into the frames that missed that hand.

    ``masks (T, H, W)`` every frame's own mask; ``per_hand (T, K, H, W)`` the parts of it that
    belong to hand ``k``; ``certain (T, K, H, W)`` their certain seeds (see ``arm_region``). Hand
    by hand, :func:`propagate_both_ways` carries ``per_hand[:, k]`` into the frames where it is
    empty, and into those ``open_frames (T, K)`` marks for it (optional); the result is the union
    with ``masks``. Every hand and direction shares one :class:`FrameFlows`, so each flow is
    computed once per clip.
    """
    out = masks.astype(np.uint8).copy()
    flows = FrameFlows(frames)
    for k in range(per_hand.shape[1]):
        if per_hand[:, k].any():
            opened = None if open_frames is None else open_frames[:, k]
            out |= propagate_both_ways(frames, per_hand[:, k], params, certain[:, k], flows, opened)
    return out
