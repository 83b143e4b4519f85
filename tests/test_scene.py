"""scene_cloud + scene_render: splat renderer against the synthetic world and analytic scenes."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from egosim.pipeline import media
from egosim.pipeline.clip_io import row_from_clip, write_clips
from egosim.pipeline.execute import ShardTask, run_shard_task
from egosim.pipeline.geometry import (
    intrinsics_from_fov,
    invert_se3,
    look_at,
    project_world_points,
    project_world_points_torch,
    transform_points,
    unproject_depth,
)
from egosim.pipeline.shards import ShardWriter, open_shard
from egosim.pipeline.stage import ClipRejected
from egosim.schemas.inpaint import INPAINT
from egosim.schemas.scene import SCENE_CLOUD, SCENE_RENDER
from egosim.schemas.state import STATE, scene_cloud_row_from_state
from egosim.stages.scene_cloud.stage import (
    SceneCloudError,
    SceneCloudStage,
    build_scene_cloud,
    cloud_from_row,
    fill_depth_under,
)
from egosim.stages.scene_render.splat import (
    SplatError,
    inpaint_mask_from_visible,
    render_point_cloud,
)
from egosim.stages.scene_render.stage import SceneRenderStage
from egosim.world.clip import render_clip
from egosim.world.config import WorldConfig
from tests.conftest import one_shard_task, translated, write_cameras, write_poses

H, W, T = 64, 112, 8


@pytest.fixture(scope="module")
def world_clip():
    """A tiny tabletop clip with full ground truth (the oracle)."""
    return render_clip(WorldConfig(seed=1, mode="tabletop", height=H, width=W, num_frames=T))


def psnr(a: np.ndarray, b: np.ndarray, mask: np.ndarray) -> float:
    """PSNR in dB of uint8 images over ``mask`` pixels."""
    err = (a.astype(np.float64) - b.astype(np.float64)) ** 2  # (..., 3)
    return float(10 * np.log10(255.0**2 / err[mask].mean()))


def gt_covisibility(clip, rel_tol: float = 0.02) -> np.ndarray:
    """(T, H, W) True where frame t's static surface was visible in frame 0 (from static depth).

    Each frame-t pixel is lifted with static_depth[t], reprojected into frame 0 and kept when
    it lands inside the image and agrees with static_depth[0] there within ``rel_tol``.
    """
    t_, h, w = clip.static_depth.shape
    out = np.zeros((t_, h, w), dtype=bool)
    for t in range(t_):
        depth = clip.static_depth[t]
        pts = transform_points(clip.world_from_cam[t], unproject_depth(depth, clip.intrinsics))
        uv, z = project_world_points(pts, clip.world_from_cam[0], clip.intrinsics)
        u = np.floor(np.nan_to_num(uv[..., 0], nan=-1)).astype(int)
        v = np.floor(np.nan_to_num(uv[..., 1], nan=-1)).astype(int)
        ok = (depth > 0) & (z > 0) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
        d0 = clip.static_depth[0][np.clip(v, 0, h - 1), np.clip(u, 0, w - 1)]
        out[t] = ok & (np.abs(d0 - z) < rel_tol * z)
    return out


def ideal_warp_psnr(clip, covis: np.ndarray) -> float:
    """PSNR of an ideal nearest-neighbour resampler of frame 0 (what a one-pixel splat is).

    Backward warp with the *target's* GT depth: no hole, no occlusion error, only resampling.
    """
    errs = []
    for t in range(1, clip.num_frames):
        pts = transform_points(
            clip.world_from_cam[t], unproject_depth(clip.static_depth[t], clip.intrinsics)
        )
        uv, _ = project_world_points(pts, clip.world_from_cam[0], clip.intrinsics)
        maps = (np.nan_to_num(uv, nan=-10) - 0.5).astype(np.float32)  # cv2: centres at integers
        warped = cv2.remap(clip.static_frames[0], maps[..., 0], maps[..., 1], cv2.INTER_NEAREST)
        errs.append(((warped.astype(float) - clip.static_frames[t]) ** 2)[covis[t]])
    return float(10 * np.log10(255.0**2 / np.concatenate(errs).mean()))


def render_gt(clip, radius: int = 2):
    """Cloud from the GT first frame + static depth, rendered along GT poses."""
    cloud = build_scene_cloud(
        clip.first_frame_clean, clip.static_depth[0], clip.world_from_cam[0], clip.intrinsics
    )
    result = render_point_cloud(
        cloud.points,
        cloud.colours,
        clip.world_from_cam,
        clip.intrinsics,
        clip.height,
        clip.width,
        point_size=cloud.point_size,
        max_splat_radius=radius,
        near=0.01,
    )
    return cloud, result


def test_projection_helper_matches_numpy() -> None:
    rng = np.random.default_rng(0)
    pts = rng.normal(0, 1, (500, 3))
    pose = look_at([0.3, -1.0, 0.5], [0, 0, 0])
    k = intrinsics_from_fov(832, 480, 70.0)
    uv_np, z_np = project_world_points(pts, pose, k)
    cam_from_world = torch.as_tensor(invert_se3(pose))
    u, v, _ = project_world_points_torch(torch.as_tensor(pts.T.copy()), cam_from_world, k)
    front = z_np > 0
    np.testing.assert_allclose(u.numpy()[front], uv_np[front, 0], atol=1e-6)
    np.testing.assert_allclose(v.numpy()[front], uv_np[front, 1], atol=1e-6)
    assert np.all(np.isnan(u.numpy()[~front]))


def test_first_frame_is_reproduced_exactly(world_clip) -> None:
    _, result = render_gt(world_clip, radius=0)
    vis = result.visible[0].astype(bool)
    assert vis.mean() > 0.9
    np.testing.assert_array_equal(result.rgb[0][vis], world_clip.first_frame_clean[vis])
    depth0 = world_clip.static_depth[0]
    np.testing.assert_allclose(result.depth[0][vis], depth0[vis], rtol=1e-5)


# (mode, min PSNR dB on visible pixels, min IoU with GT co-visibility), at 120x208. Tabletop is
# the issue's target. In wild clips the camera comes closer than frame 0's, so cracks are filled
# by nearest-point splats (blocky where the texture is magnified): measured 27.7 dB, 0.986 IoU;
# without the fill 30.5 dB but 0.84 IoU.
ORACLE_CASES = [("tabletop", 30.0, 0.9), ("wild", 27.0, 0.95)]


@pytest.mark.parametrize(("mode", "min_psnr", "min_iou"), ORACLE_CASES)
def test_render_matches_world_oracle(mode: str, min_psnr: float, min_iou: float) -> None:
    """PSNR on visible pixels vs the GT static video, and IoU with GT co-visibility."""
    clip = render_clip(WorldConfig(seed=1, mode=mode, height=120, width=208, num_frames=T))
    _, result = render_gt(clip)
    covis = gt_covisibility(clip)
    vis = result.visible.astype(bool)
    later = np.s_[1:]
    value = psnr(result.rgb[later], clip.static_frames[later], vis[later])
    iou = (vis & covis).sum() / (vis | covis).sum()
    assert value >= min_psnr, (value, ideal_warp_psnr(clip, covis))
    assert iou >= min_iou, iou


def _analytic_frame(pose: np.ndarray, k: np.ndarray, h: int, w: int):
    """Ray-cast a band-limited scene: floor z=0 and a raised plate z=0.1 over |x|,|y| < 0.15."""
    pix = np.stack(np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5), -1)  # (H, W, 2)
    dirs = np.stack(
        [(pix[..., 0] - k[2]) / k[0], (pix[..., 1] - k[3]) / k[1], np.ones((h, w))], -1
    )  # (H, W, 3) camera rays with unit z
    dirs_w = dirs @ pose[:3, :3].T  # (H, W, 3)
    origin = pose[:3, 3]
    depth = np.full((h, w), np.inf)
    for height, half in ((0.0, np.inf), (0.1, 0.15)):
        t = (height - origin[2]) / dirs_w[..., 2]  # (H, W) = z-depth since dirs have unit z
        hit = origin + t[..., None] * dirs_w
        ok = (t > 0) & (np.abs(hit[..., 0]) < half) & (np.abs(hit[..., 1]) < half)
        depth = np.where(ok & (t < depth), t, depth)
    hit = origin + depth[..., None] * dirs_w  # (H, W, 3)
    rgb = 128 + 60 * np.stack(
        [
            np.sin(hit[..., 0] / 0.04),
            np.cos(hit[..., 1] / 0.05),
            np.sin((hit[..., 0] + hit[..., 1]) / 0.06),
        ],
        -1,
    )
    return np.clip(rgb + 200 * hit[..., 2:3], 0, 255).astype(np.uint8), depth.astype(np.float32)


def test_band_limited_scene_psnr_above_30() -> None:
    h, w = 96, 160
    k = intrinsics_from_fov(w, h, 60.0)
    poses = np.stack(
        [
            look_at([0.03 * i - 0.05, -0.45 + 0.01 * i, 0.55 - 0.01 * i], [0, 0, 0.05])
            for i in range(6)
        ]
    )
    frames, depths = zip(*(_analytic_frame(p, k, h, w) for p in poses), strict=True)
    cloud = build_scene_cloud(frames[0], depths[0], poses[0], k)
    result = render_point_cloud(
        cloud.points, cloud.colours, poses, k, h, w, point_size=cloud.point_size, max_splat_radius=2
    )
    vis = result.visible[1:].astype(bool)
    value = psnr(result.rgb[1:], np.stack(frames[1:]), vis)
    assert value >= 30.0, value


def test_splat_radius_closes_cracks_when_zooming_in() -> None:
    k = intrinsics_from_fov(64, 48, 60.0)
    depth = np.ones((48, 64), np.float32)
    image = np.full((48, 64, 3), 100, np.uint8)
    cloud = build_scene_cloud(image, depth, np.eye(4), k)
    closer = np.eye(4)
    closer[2, 3] = 0.4  # 1.67x zoom
    args = (cloud.points, cloud.colours, closer[None], k, 48, 64)
    thin = render_point_cloud(*args, point_size=cloud.point_size, max_splat_radius=0)
    wide = render_point_cloud(*args, point_size=cloud.point_size, max_splat_radius=2)
    assert thin.visible.mean() < 0.5
    assert wide.visible.mean() == 1.0


def test_nearest_point_wins() -> None:
    k = np.array([10.0, 10.0, 2.0, 2.0])
    pts = np.array([[0.0, 0.0, 2.0], [0.0, 0.0, 1.0], [0.0, 0.0, 3.0]])
    rgb = np.array([[255, 0, 0], [0, 255, 0], [0, 0, 255]], np.uint8)
    result = render_point_cloud(pts, rgb, np.eye(4)[None], k, 4, 4)
    assert result.visible[0].sum() == 1
    assert result.visible[0, 2, 2] == 1
    assert result.rgb[0, 2, 2].tolist() == [0, 255, 0]
    assert result.depth[0, 2, 2] == pytest.approx(1.0)


def test_inpaint_mask_polarity() -> None:
    visible = np.array([[[1, 0, 1], [1, 1, 1], [0, 1, 1]]], np.uint8)
    mask = inpaint_mask_from_visible(visible)
    np.testing.assert_array_equal(mask, 1 - visible)
    assert inpaint_mask_from_visible(visible, dilate=1).sum() > mask.sum()


@pytest.mark.parametrize(
    "case",
    ["empty", "nan_pose", "non_rigid", "nan_points", "size_mismatch"],
)
def test_renderer_rejects_bad_input(case: str) -> None:
    pts = np.tile([0.0, 0.0, 1.0], (4, 1))
    rgb = np.zeros((4, 3), np.uint8)
    poses = np.tile(np.eye(4), (2, 1, 1))
    k = np.array([10.0, 10.0, 2.0, 2.0])
    if case == "empty":
        pts, rgb = np.zeros((0, 3)), np.zeros((0, 3), np.uint8)
    elif case == "nan_pose":
        poses[1, 0, 3] = np.nan
    elif case == "non_rigid":
        poses[1, 0, 0] = 2.0
    elif case == "nan_points":
        pts[0, 0] = np.nan
    else:
        rgb = rgb[:3]
    with pytest.raises(SplatError):
        render_point_cloud(pts, rgb, poses, k, 4, 4)


def test_points_behind_camera_are_skipped() -> None:
    k = np.array([10.0, 10.0, 2.0, 2.0])
    pts = np.array([[0.0, 0.0, -1.0], [0.05, 0.05, -0.5]])
    result = render_point_cloud(pts, np.full((2, 3), 9, np.uint8), np.eye(4)[None], k, 4, 4)
    assert result.visible.sum() == 0


def test_cloud_rejects_bad_depth() -> None:
    image = np.zeros((4, 5, 3), np.uint8)
    k = np.array([5.0, 5.0, 2.5, 2.0])
    with pytest.raises(SceneCloudError, match="negative"):
        build_scene_cloud(image, -np.ones((4, 5)), np.eye(4), k)
    with pytest.raises(SceneCloudError, match="empty"):
        build_scene_cloud(image, np.zeros((4, 5)), np.eye(4), k)
    with pytest.raises(SceneCloudError, match="world_from_cam"):
        build_scene_cloud(image, np.ones((4, 5)), np.full((4, 4), np.nan), k)


def test_flying_pixels_removed_planes_kept() -> None:
    k = intrinsics_from_fov(40, 30, 60.0)
    # A slanted plane (inverse depth affine in pixels) plus a step edge with a flying pixel row.
    v, u = np.mgrid[0:30, 0:40] + 0.5
    depth = 1.0 / (1.0 + 0.01 * u + 0.02 * v)
    plane = build_scene_cloud(np.zeros((30, 40, 3), np.uint8), depth, np.eye(4), k)
    assert plane.num_flying_removed == 0
    step = np.where(u < 20, 0.5, 1.5)
    step[:, 20] = 1.0  # a flying pixel column between the two sides
    cloud = build_scene_cloud(np.zeros((30, 40, 3), np.uint8), step, np.eye(4), k)
    zs = cloud.points[:, 2]
    assert not np.any(np.isclose(zs, 1.0))


def test_stages_end_to_end(world_clip, tmp_path: Path) -> None:
    clips = tmp_path / "clips.parquet"
    write_clips(clips, [world_clip])
    cloud_path = tmp_path / "scene_cloud.parquet"
    run_shard_task(
        ShardTask(
            step="scene_cloud",
            stage="scene_cloud",
            params={},
            shard_index=0,
            shard_count=1,
            output=cloud_path,
            rejects=tmp_path / "scene_cloud.rejects.parquet",
            inputs={"clips": clips},
        )
    )
    render_path = tmp_path / "scene_render.parquet"
    result = run_shard_task(
        ShardTask(
            step="scene_render",
            stage="scene_render",
            params={"max_splat_radius": 2},
            shard_index=0,
            shard_count=1,
            output=render_path,
            rejects=tmp_path / "scene_render.rejects.parquet",
            inputs={"clips": clips, "scene_cloud": cloud_path},
        )
    )
    assert result.rows == 1 and result.rejected == 0
    with open_shard(cloud_path, SCENE_CLOUD) as reader:
        cloud = cloud_from_row(next(reader.iter_rows()))
    assert len(cloud.points) > 0.8 * H * W
    with open_shard(render_path, SCENE_RENDER) as reader:
        row = next(reader.iter_rows())
    visible = media.decode_lossless_video(row["visible"])
    video = media.decode_rgb_video(row["scene_video"], H, W)
    assert visible.shape == (T, H, W) and video.shape == (T, H, W, 3)
    # every 2x2 block of the cloud's grid whose four points exist and do not tear is a quad
    assert 0.5 * (H - 1) * (W - 1) < row["surface_quads"] <= (H - 1) * (W - 1)
    covis = gt_covisibility(world_clip)
    vis = visible.astype(bool)
    assert (vis & covis).sum() / (vis | covis).sum() >= 0.9
    # Through depth quantisation and H.264 (lossy on this tiny, aliased texture) at crf 18.
    assert psnr(video[0], world_clip.first_frame_clean, vis[0]) > 22


def test_stage_rejects_clip_without_poses(world_clip, tmp_path: Path) -> None:
    world_clip = dataclasses.replace(world_clip, world_from_cam=None)
    clips = tmp_path / "clips.parquet"
    write_clips(clips, [world_clip])
    result = run_shard_task(
        ShardTask(
            step="scene_cloud",
            stage="scene_cloud",
            params={},
            shard_index=0,
            shard_count=1,
            output=tmp_path / "out.parquet",
            rejects=tmp_path / "rej.parquet",
            inputs={"clips": clips},
        )
    )
    assert result.rows == 0 and result.rejected == 1
    with open_shard(tmp_path / "rej.parquet") as reader:
        assert world_clip.clip_id in next(reader.iter_rows())["reason"]


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_cpu_and_gpu_agree(world_clip) -> None:
    cloud, cpu = render_gt(world_clip)
    gpu = render_point_cloud(
        cloud.points,
        cloud.colours,
        world_clip.world_from_cam,
        world_clip.intrinsics,
        H,
        W,
        point_size=cloud.point_size,
        max_splat_radius=2,
        near=0.01,
        device="cuda",
    )
    agree = (gpu.visible == cpu.visible).mean()
    assert agree > 0.999
    same = np.all(gpu.rgb == cpu.rgb, axis=-1).mean()
    assert same > 0.995


def _task(stage: str, tmp_path: Path, inputs: dict[str, Path], name: str) -> ShardTask:
    return one_shard_task(stage, tmp_path, inputs, name)


def test_stages_use_connected_poses_and_inpaint(world_clip, tmp_path: Path) -> None:
    clips = tmp_path / "clips.parquet"
    write_clips(clips, [world_clip])
    offset = np.array([0.3, -0.2, 0.1])
    poses = write_poses(
        tmp_path / "poses.parquet", world_clip, translated(world_clip.world_from_cam, offset)
    )
    grey = np.full((H, W, 3), 77, np.uint8)
    inpaint = tmp_path / "inpaint.parquet"
    with ShardWriter(inpaint, INPAINT, stage="test") as writer:
        writer.write_row(
            {
                "clip_id": world_clip.clip_id,
                "width": W,
                "height": H,
                "first_frame": media.encode_png(grey),
                "fill_source": media.encode_png(np.zeros((H, W), np.uint8)),
                "source_frame": media.encode_png(np.zeros((H, W), np.uint16)),
                **dict.fromkeys(("masked_fraction", "reprojected_fraction"), 0.0),
                **dict.fromkeys(("opencv_fraction", "generated_fraction"), 0.0),
                "backend": "opencv",
            }
        )
    for name, inputs in [
        ("own", {"clips": clips}),
        ("moved", {"clips": clips, "poses": poses, "inpaint": inpaint}),
    ]:
        assert run_shard_task(_task("scene_cloud", tmp_path, inputs, name)).rows == 1
    with open_shard(tmp_path / "own.parquet", SCENE_CLOUD) as reader:
        own = cloud_from_row(next(reader.iter_rows()))
    with open_shard(tmp_path / "moved.parquet", SCENE_CLOUD) as reader:
        row = next(reader.iter_rows())
        moved = cloud_from_row(row)
    assert row["image_source"] == "inpaint+static_depth"
    assert np.all(moved.colours == 77)
    np.testing.assert_allclose(moved.points, own.points + offset, atol=1e-5)
    # Rendering the moved cloud along the moved poses sees what the clip's own camera saw.
    renders = {}
    for name, inputs in [
        ("render_own", {"clips": clips, "scene_cloud": tmp_path / "own.parquet"}),
        ("render_moved", {"clips": clips, "scene_cloud": tmp_path / "moved.parquet"}),
        (
            "render_posed",
            {"clips": clips, "scene_cloud": tmp_path / "moved.parquet", "poses": poses},
        ),
    ]:
        assert run_shard_task(_task("scene_render", tmp_path, inputs, name)).rows == 1
        with open_shard(tmp_path / f"{name}.parquet", SCENE_RENDER) as reader:
            renders[name] = media.decode_lossless_video(next(reader.iter_rows())["visible"]) > 0
    same = (renders["render_posed"] == renders["render_own"]).mean()
    assert same > 0.999, same
    assert (renders["render_moved"] == renders["render_own"]).mean() < 0.9


def test_static_camera_repeats_the_first_frame(world_clip, tmp_path: Path) -> None:
    clip = dataclasses.replace(world_clip, depth=None, static_depth=None)
    clips = tmp_path / "clips.parquet"
    write_clips(clips, [clip])
    still = np.repeat(clip.world_from_cam[:1], T, axis=0)  # (T, 4, 4)
    cameras = write_cameras(tmp_path / "cameras.parquet", clip, still)  # static: no depth0
    inputs = {"clips": clips, "cameras": cameras}
    cloud_task = _task("scene_cloud", tmp_path, inputs, "cloud")
    assert run_shard_task(cloud_task).rows == 1
    with open_shard(cloud_task.output) as reader:
        assert next(reader.iter_rows())["image_source"] == "first_frame_clean+static_plane"
    render_task = _task("scene_render", tmp_path, {**inputs, "scene_cloud": cloud_task.output}, "r")
    assert run_shard_task(render_task).rows == 1
    with open_shard(render_task.output) as reader:
        row = next(reader.iter_rows())
    video = media.decode_rgb_video(row["scene_video"], H, W)
    visible = media.decode_lossless_video(row["visible"])
    assert visible.all()  # every pixel of the plane lands back on itself
    assert psnr(video[0], clip.first_frame_clean, visible[0] > 0) >= 30.0  # H.264 of frame 0
    for frame in video[1:]:  # the same frame again (up to H.264 of a still video)
        assert np.abs(frame.astype(int) - video[0]).mean() < 1.0


def test_depth_under_inpainted_pixels_continues_the_surface() -> None:
    depth = np.tile(np.linspace(1.0, 2.0, 40, dtype=np.float32), (30, 1))  # (30, 40) a slope
    filled = np.zeros((30, 40), bool)
    filled[10:20, 15:25] = True
    hand = np.where(filled, 0.4, depth)  # a hand in front of the slope
    hand[0, 0] = 0.0  # unknown stays unknown
    out = fill_depth_under(hand, filled)
    assert np.abs(out[filled] - depth[filled]).max() < 0.1
    assert np.array_equal(out[~filled], hand[~filled])


def _state_row_holding(cloud_row: dict, clip) -> dict:
    """A ``state`` row (no instances) holding ``cloud_row``'s points, fused from ``clip``."""
    n = int(cloud_row["num_points"])
    return {
        "clip_id": clip.clip_id,
        "state_clip_id": clip.clip_id,
        "previous_clip_id": None,
        "world_frame": clip.clip_id,
        "num_frames": 1,
        "num_points": n,
        "points_xyz": cloud_row["points_xyz"],
        "points_rgb": cloud_row["points_rgb"],
        "point_size": cloud_row["point_size"],
        "point_instance": np.zeros(n, "<i4").tobytes(),
        "point_source": np.zeros(n, np.uint8).tobytes(),
        **{
            name: []
            for name in (
                "instance_id",
                "instance_label",
                "instance_interactive",
                "instance_last_observed_frame",
                "instance_geometry_frame",
                "instance_interaction",
                "instance_depth_gap_m",
                "instance_centroid",
            )
        },
        "width": W,
        "height": H,
        "intrinsics": np.asarray(clip.intrinsics, np.float64).tolist(),
        "world_from_cam": clip.world_from_cam[:1].reshape(1, 16).tolist(),
        "camera_frames": [f"{clip.clip_id}:0"],
        "previous_from_clip": np.eye(4).reshape(16).tolist(),
        "sim3_scale": 1.0,
        "registration_rms_m": None,
    }


def test_scene_render_renders_a_state_as_its_scene_cloud(world_clip) -> None:
    clip_row = row_from_clip(world_clip)
    cloud_row = SceneCloudStage().process({"clips": clip_row})
    state_row = _state_row_holding(cloud_row, world_clip)
    STATE.validate_row(state_row)
    stage = SceneRenderStage()
    from_state = stage.process({"clips": clip_row, "state": state_row})
    from_cloud = stage.process(
        {"clips": clip_row, "scene_cloud": scene_cloud_row_from_state(state_row)}
    )
    assert from_state == from_cloud  # same bytes: one renderer
    # A state is no frame's depth grid: splats only, and the row says so (the cloud has quads).
    assert from_state["surface_quads"] == 0
    assert stage.process({"clips": clip_row, "scene_cloud": cloud_row})["surface_quads"] > 0
    # The state wins over a scene_cloud row given beside it.
    empty_cloud = {
        **cloud_row,
        "num_points": 1,
        "points_xyz": cloud_row["points_xyz"][:12],
        "points_rgb": cloud_row["points_rgb"][:3],
        "point_size": cloud_row["point_size"][:4],
        "point_confidence": cloud_row["point_confidence"][:1],
    }
    both = stage.process({"clips": clip_row, "state": state_row, "scene_cloud": empty_cloud})
    assert both == from_state
    with pytest.raises(ClipRejected, match=f"clip '{world_clip.clip_id}': nothing to render"):
        stage.process({"clips": clip_row})
