"""Tests of the plane sweep's two backends: depth against ground truth on a small synthetic-world
scene, the OpenCV backend against the torch one, and the OpenCV backend's pieces (running
winners, top-k, the shortcut that skips the mask, bands on threads) against their references."""

from __future__ import annotations

import dataclasses
from typing import Any

import cv2
import numpy as np
import pytest
import torch

from egosim.pipeline.geometry import invert_se3, make_se3, scale_intrinsics
from egosim.stages.common import plane_sweep as ps
from egosim.stages.common.plane_sweep import (
    PlaneSweepError,
    PlaneSweepParams,
    PlaneSweepResult,
    plane_sweep,
)
from egosim.world import WorldConfig, render_clip

SOURCES = [4, 8, 12, 16, 20]  # source frames of the 21-frame scene


@pytest.fixture(scope="module")
def scene() -> dict[str, Any]:
    """Grey frames, poses, usable masks and true depth of a 21-frame 120x208 wild clip (~5 s)."""
    clip = render_clip(WorldConfig(seed=0, mode="wild", height=120, width=208, num_frames=21))
    grey = np.stack([cv2.cvtColor(f, cv2.COLOR_RGB2GRAY) for f in clip.frames]).astype(np.float32)
    kernel = np.ones((5, 5), np.uint8)
    usable = np.stack([cv2.dilate(m.astype(np.uint8), kernel) == 0 for m in clip.hand_mask])
    near, far = np.percentile(clip.depth[0], [1, 99]) * np.array([0.7, 1.3])
    return {
        "grey": grey,  # (T, H, W) float32
        "intrinsics": clip.intrinsics,
        "cam_from_world": invert_se3(clip.world_from_cam),  # (T, 4, 4)
        "usable": usable.astype(np.float32),  # (T, H, W) 1 = off the (dilated) hands
        "depth": clip.depth[0],  # (H, W) true z-depth of frame 0
        "range": (float(near), float(far)),
    }


def _sweep(scene: dict[str, Any], params: PlaneSweepParams, scale: float = 1.0) -> PlaneSweepResult:
    """Sweep frame 0 of ``scene`` against :data:`SOURCES`, optionally at a smaller size."""
    grey, usable, k = scene["grey"], scene["usable"], scene["intrinsics"]
    if scale != 1.0:
        h, w = grey.shape[1:]
        size = (round(w * scale), round(h * scale))
        grey = np.stack([cv2.resize(g, size, interpolation=cv2.INTER_AREA) for g in grey])
        usable = np.stack([cv2.resize(u, size, interpolation=cv2.INTER_NEAREST) for u in usable])
        k = scale_intrinsics(k, size[0] / w, size[1] / h)
    cfw = scene["cam_from_world"]
    return plane_sweep(
        grey[0],
        grey[SOURCES],
        k,
        cfw[0],
        cfw[SOURCES],
        scene["range"],
        usable[0],
        usable[SOURCES],
        params=params,
    )


def _assert_same(a: PlaneSweepResult, b: PlaneSweepResult, exact: bool) -> None:
    """Two sweeps agree: exactly, or within the rounding of two implementations.

    Rounding: OpenCV's warps place samples on a 1/32 pixel grid, so a sample within 1/64 pixel of
    a hand or the image border can fall on either side of it, and a near-tie between planes or
    sources can go either way: a few pixels in a thousand may differ.
    """
    if exact:
        for field in dataclasses.fields(PlaneSweepResult):
            np.testing.assert_array_equal(getattr(a, field.name), getattr(b, field.name))
        return
    rel = np.abs(a.depth - b.depth) / b.depth
    assert np.median(rel) < 1e-5, np.median(rel)
    assert (rel > 0.01).mean() < 0.002, (rel > 0.01).mean()
    assert np.abs(a.confidence - b.confidence).mean() < 1e-3
    assert ((a.confidence >= 0.5) != (b.confidence >= 0.5)).mean() < 0.002
    assert (np.abs(a.zncc - b.zncc) > 1e-3).mean() < 0.002
    assert (a.visible == b.visible).mean() > 0.995
    assert (a.support == b.support).mean() > 0.995


# --- accuracy on the synthetic world -------------------------------------------------------------


def test_default_sweep_matches_ground_truth_depth(scene: dict[str, Any]) -> None:
    """The default (OpenCV) sweep: AbsRel on confident pixels and their share of the frame."""
    assert PlaneSweepParams().resolved_backend() == "opencv"
    result = _sweep(scene, PlaneSweepParams())
    truth = scene["depth"]
    rel = np.abs(result.depth - truth) / truth
    confident = result.confidence >= 0.5
    # measured: AbsRel 0.018 on 77% of the pixels (the torch backend gives the same figures)
    assert confident.mean() >= 0.65, confident.mean()
    assert rel[confident].mean() <= 0.03, rel[confident].mean()
    assert rel[confident].mean() < rel.mean()
    assert (result.support <= result.visible).all()
    assert not (confident & (scene["usable"][0] == 0)).any()  # nothing confident on a hand


def test_opencv_backend_agrees_with_torch_backend(scene: dict[str, Any]) -> None:
    """Same algorithm, two implementations: equal up to rounding, hand masks included."""
    params = PlaneSweepParams(num_planes=32)
    fast = _sweep(scene, dataclasses.replace(params, backend="opencv"), scale=0.5)
    reference = _sweep(scene, dataclasses.replace(params, backend="torch"), scale=0.5)
    _assert_same(fast, reference, exact=False)
    assert (fast.visible < len(SOURCES)).any()  # sources that do not see part of frame 0


def test_opencv_shortcut_is_exact_and_threads_only_round(
    scene: dict[str, Any], monkeypatch: pytest.MonkeyPatch
) -> None:
    """Skipping the mask where a band maps wholly onto valid pixels changes nothing; bands on
    threads change only the rounding of the box sums (their running sums start on other rows)."""
    params = PlaneSweepParams(num_planes=24, threads=1)
    base = _sweep(scene, params, scale=0.5)
    threaded = _sweep(scene, dataclasses.replace(params, threads=3), scale=0.5)
    monkeypatch.setattr(ps._Source, "sees_all", lambda self, corners: False)
    checked = _sweep(scene, params, scale=0.5)
    _assert_same(checked, base, exact=True)
    _assert_same(threaded, base, exact=False)


# --- pieces of the OpenCV backend ----------------------------------------------------------------


def test_running_winner_equals_winner_over_the_stack() -> None:
    """Planes fed one at a time give :func:`_winner`'s refined inverse depth, score and plane,
    ties (first maximum) and the clamped first and last planes included."""
    rng = np.random.default_rng(0)
    cost = rng.uniform(-1, 1, (9, 6, 7)).astype(np.float32)  # (D, H, W)
    cost[:, 0] = -1.0  # a row never seen: all planes tie, plane 0 wins
    cost[3, 1], cost[5, 1] = 2.0, 2.0  # a tie between two planes: the first wins
    cost[0, 2] = 3.0  # winners on the first ...
    cost[-1, 3] = 3.0  # ... and on the last plane
    inv_depths = torch.linspace(0.2, 1.0, 9).numpy()
    want_inv, want_best, want_idx = ps._winner(torch.from_numpy(cost), torch.from_numpy(inv_depths))
    running = ps._RunningWinner((6, 7))
    plane = np.zeros((6, 7), np.int32)
    for d in range(len(cost)):
        plane.fill(d)
        running.update(cost[d].copy(), plane)
    np.testing.assert_array_equal(running.idx, want_idx.numpy())
    np.testing.assert_array_equal(running.best, want_best.numpy())
    np.testing.assert_allclose(running.refined(inv_depths), want_inv.numpy(), rtol=0, atol=1e-7)


@pytest.mark.parametrize("k", [1, 2, 3, 5])
def test_top_k_mean_equals_torch_topk(k: int) -> None:
    rng = np.random.default_rng(k)
    scores = rng.uniform(-1, 1, (5, 4, 6)).astype(np.float32)  # (S, H, W)
    scores[:, 0] = -1.0  # unseen everywhere
    want = torch.from_numpy(scores).topk(k, dim=0).values.mean(0).numpy()
    top = np.empty((k, 4, 6), np.float32)
    got = ps._top_k_mean(scores, k, top, np.empty((4, 6), np.float32), np.empty((4, 6), np.float32))
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-6)


def test_plane_behind_a_source_camera_is_not_seen() -> None:
    """A source 3 m ahead of the reference, looking the same way: every plane (1 to 2.5 m) lies
    behind it (the homography's third row turns negative), so it sees nothing; the backends
    agree."""
    h, w = 24, 32
    rng = np.random.default_rng(1)
    images = rng.uniform(0, 255, (3, h, w)).astype(np.float32)
    centres = [[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.0, 0.0, 3.0]]
    cfw = invert_se3(np.stack([make_se3(np.eye(3), c) for c in centres]))
    intrinsics = np.array([30.0, 30.0, 16.0, 12.0])
    results = [
        plane_sweep(
            images[0],
            images[1:],
            intrinsics,
            cfw[0],
            cfw[1:],
            (1.0, 2.5),
            params=PlaneSweepParams(num_planes=8, window=3, backend=backend),
        )
        for backend in ("opencv", "torch")
    ]
    for result in results:
        assert result.visible.max() <= 1  # only the translated source can see anything
        assert (result.confidence == 0).all()  # min_support = 2 is never reached
    np.testing.assert_array_equal(results[0].visible, results[1].visible)


def test_params_report_every_bad_value() -> None:
    with pytest.raises(PlaneSweepError) as info:
        PlaneSweepParams(num_planes=2, window=4, top_k=0, backend="cuda", threads=-1)
    message = str(info.value)
    for part in ("num_planes", "got 2", "window", "got 4", "top_k", "'cuda'", "threads"):
        assert part in message, message
    assert PlaneSweepParams(device="cuda").resolved_backend() == "torch"
    assert PlaneSweepParams(device="cuda", backend="opencv").resolved_backend() == "opencv"
