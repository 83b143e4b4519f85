"""hands, backend ``regressor``: a tiny random HandRegressor saved, loaded and run on a clip."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from safetensors.torch import load_file  # noqa: E402

from egosim.model.checkpoint import UnsafeCheckpointError  # noqa: E402
from egosim.pipeline.clip_io import clip_from_row, write_clips  # noqa: E402
from egosim.pipeline.geometry import invert_se3, project_points, transform_points  # noqa: E402
from egosim.pipeline.records import RIGHT, Clip  # noqa: E402
from egosim.pipeline.shards import open_shard  # noqa: E402
from egosim.pipeline.stage import ConfigError  # noqa: E402
from egosim.stages.hands.convert_checkpoint import (  # noqa: E402
    HamerLayout,
    convert_hamer_checkpoint,
    hamer_to_regressor,
)
from egosim.stages.hands.mano import MANO_FILE, ManoLayer, save_mano_arrays  # noqa: E402
from egosim.stages.hands.regressor_backend import (  # noqa: E402
    CONFIG_FILE,
    WEIGHTS_FILE,
    HandRegressor,
    RegressorParams,
    RegressorSpec,
    RegressorWeightsError,
    crop_hand,
    full_perspective_translation,
    load_regressor,
    regressor_detections,
    save_regressor,
    square_box,
)
from egosim.stages.hands.stage import HandsConfig  # noqa: E402
from egosim.world.clip import render_clip  # noqa: E402
from egosim.world.config import WorldConfig  # noqa: E402
from tests.conftest import egodex_portrait_frames  # noqa: E402
from tests.test_hands import hands_row  # noqa: E402
from tests.test_mano import tiny_mano  # noqa: E402

TINY = RegressorSpec(
    image_size=64, patch_size=16, hidden_size=32, num_layers=2, num_heads=2, head_size=32
)


@pytest.fixture(scope="module")
def weights(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A folder holding a tiny randomly initialised regressor."""
    torch.manual_seed(0)
    folder = tmp_path_factory.mktemp("regressor")
    save_regressor(HandRegressor(TINY), folder)
    return folder


@pytest.fixture(scope="module")
def clip():
    return render_clip(WorldConfig(seed=0, height=96, width=160, num_frames=5))


def test_weak_to_full_perspective_hand_computed() -> None:
    # Box of 40 px centred at (100, 60); s = 0.5, t = (0.2, -0.4); fx = fy = 200, c = (80, 48).
    # T_z = 2 f / (s b) = 400 / 20 = 20 m; the wrist's pixel is c_box + s t b / 2 = (102, 56), so
    # T_x = 20 (102 - 80) / 200 = 2.2 (HaMeR: tx + 2 (c_u - cx) / (s b) = 0.2 + 2) and
    # T_y = 20 (56 - 48) / 200 = 0.8.
    k = np.array([200.0, 200.0, 80.0, 48.0])
    cam = np.array([[0.5, 0.2, -0.4]])
    t = full_perspective_translation(cam, np.array([[100.0, 60.0]]), np.array([40.0]), k)
    np.testing.assert_allclose(t, [[2.2, 0.8, 20.0]], atol=1e-6)
    uv, _ = project_points(t, k)
    np.testing.assert_allclose(uv, [[102.0, 56.0]], atol=1e-6)
    # A point 1 cm right of the wrist at its depth moves s * b / 2 = 10 px per metre: 0.1 px.
    uv_x, _ = project_points(t + np.array([0.01, 0.0, 0.0]), k)
    np.testing.assert_allclose(uv_x, [[102.1, 56.0]], atol=1e-6)
    # Non-square pixels: depth from the mean focal (150), each axis through its own focal.
    k2 = np.array([200.0, 100.0, 80.0, 48.0])
    t2 = full_perspective_translation(cam, np.array([[100.0, 60.0]]), np.array([40.0]), k2)
    np.testing.assert_allclose(t2, [[1.65, 1.2, 15.0]], atol=1e-6)
    np.testing.assert_allclose(project_points(t2, k2)[0], [[102.0, 56.0]], atol=1e-6)


def test_crop_puts_a_pixel_where_expected() -> None:
    frame = np.zeros((96, 160, 3), np.uint8)
    frame[50, 90] = 255  # pixel centre (90.5, 50.5)
    # A 16 px box centred at (90, 50) starts at (82, 42): the pixel's centre is at crop 8.5.
    crop = crop_hand(frame, np.array([90.0, 50.0]), 16.0, 16, mirror=False)
    assert crop.shape == (16, 16, 3)
    assert tuple(np.argwhere(crop[..., 0] == 255)[0]) == (8, 8) and crop[..., 0].sum() == 255
    mirrored = crop_hand(frame, np.array([90.0, 50.0]), 16.0, 16, mirror=True)
    assert tuple(np.argwhere(mirrored[..., 0] == 255)[0]) == (8, 7)


def test_saved_model_loads_and_predicts_the_same(weights: Path) -> None:
    torch.manual_seed(0)
    original = HandRegressor(TINY).eval()
    loaded = load_regressor(weights)
    x = torch.randn(3, 3, 64, 64)
    with torch.inference_mode():
        joints, cam = loaded(x)
        joints0, cam0 = original(x)
    assert joints.shape == (3, 21, 3) and cam.shape == (3, 3)
    torch.testing.assert_close(joints, joints0)
    torch.testing.assert_close(cam, cam0)
    assert torch.all(joints[:, 0] == 0) and torch.all(cam[:, 0] > 0)  # wrist at 0, in front


def test_detections_shapes_and_determinism(weights: Path, clip) -> None:
    params = RegressorParams(str(weights), boxes="given")
    det = regressor_detections(clip, params)
    det.check(clip.num_frames)
    assert det.joints.shape == (5, 2, 21, 3) and det.present.shape == (5, 2)
    assert det.present.any() and not (det.present & ~clip.hand_valid).any()
    assert np.isfinite(det.joints[det.present]).all()
    np.testing.assert_array_equal(det.side, np.tile([0, 1], (5, 1)))
    again = regressor_detections(clip, params)
    np.testing.assert_array_equal(det.joints, again.joints)
    np.testing.assert_array_equal(det.present, again.present)
    # In the camera every joint is in front of it.
    for f, s in zip(*np.nonzero(det.present), strict=True):
        points_cam = transform_points(invert_se3(clip.world_from_cam[f]), det.joints[f, s])
        assert (points_cam[:, 2] > 0).all()


def test_pickles_are_refused(tmp_path: Path) -> None:
    folder = tmp_path / "pickled"
    save_regressor(HandRegressor(TINY), folder)
    torch.save(HandRegressor(TINY).state_dict(), folder / WEIGHTS_FILE)  # zip-of-pickle
    with pytest.raises(UnsafeCheckpointError, match="pickle"):
        load_regressor(folder)
    (folder / WEIGHTS_FILE).rename(folder / "pytorch_model.bin")
    with pytest.raises(RegressorWeightsError, match=r"pytorch_model\.bin.*pickles"):
        load_regressor(folder)


def test_missing_or_wrong_weights_are_config_errors(tmp_path: Path, weights: Path) -> None:
    missing = tmp_path / "nowhere"
    with pytest.raises(ConfigError, match="regressor_weights must be an existing folder"):
        HandsConfig(backend="regressor", regressor_weights=str(missing))
    with pytest.raises(ConfigError, match="needs regressor_weights"):
        HandsConfig(backend="regressor")
    with pytest.raises(ConfigError, match="regressor_device"):
        HandsConfig(regressor_device="gpu")
    with pytest.raises(ConfigError, match="is not a folder"):
        load_regressor(missing)
    other = tmp_path / "other"
    other.mkdir()
    (other / WEIGHTS_FILE).write_bytes((weights / WEIGHTS_FILE).read_bytes())
    with pytest.raises(ConfigError, match=CONFIG_FILE):
        load_regressor(other)
    (other / CONFIG_FILE).write_text('{"architecture": "hamer"}')
    with pytest.raises(ConfigError, match="need converting"):
        load_regressor(other)
    wider = tmp_path / "wider"
    save_regressor(HandRegressor(TINY), wider)
    config = (wider / CONFIG_FILE).read_text().replace('"hidden_size": 32', '"hidden_size": 64')
    (wider / CONFIG_FILE).write_text(config)
    with pytest.raises(ConfigError, match="does not match config"):
        load_regressor(wider)


def test_stage_end_to_end(tmp_path: Path, weights: Path, clip) -> None:
    clips = tmp_path / "clips.parquet"
    write_clips(clips, [clip])
    params = {
        "backend": "regressor",
        "regressor_weights": str(weights),
        "regressor_boxes": "given",
        "despike": False,  # an untrained network's hands jump about
    }
    row = hands_row(tmp_path, {"clips": clips}, params)
    assert row["backend"] == "regressor"
    valid = np.asarray(row["hand_valid"])  # (T, 2)
    joints = np.asarray(row["hand_joints"], dtype=np.float64).reshape(5, 2, 21, 3)
    assert valid.any() and np.isfinite(joints[valid]).all() and np.isnan(joints[~valid]).all()
    with open_shard(clips) as reader:
        stored = clip_from_row(next(reader.iter_rows()))  # frames as the stage decodes them
    direct = regressor_detections(stored, RegressorParams(str(weights), boxes="given"))
    np.testing.assert_allclose(joints[valid], direct.joints[valid], atol=1e-5)  # float32 row


def assert_left_hands_mirror_right_hands(clip, weights: Path) -> None:
    """Mirror ``clip`` in the camera: frames flipped left-right, cx -> W - cx, hands swap sides
    and x -> -x. The network in ``weights`` sees the same right-hand crops in both, so each
    hand's joints must come out mirrored (up to the resampling of the flipped crops)."""
    t, w = clip.num_frames, clip.width
    cam_joints = np.stack(
        [
            transform_points(invert_se3(clip.world_from_cam[f]), clip.hand_joints[f])
            for f in range(t)
        ]
    )  # (T, 2, 21, 3)
    eye = np.tile(np.eye(4), (t, 1, 1))  # (T, 4, 4) the camera is the world
    fx, fy, cx, cy = clip.intrinsics
    flip = np.array([-1.0, 1.0, 1.0])
    straight = dataclasses.replace(clip, world_from_cam=eye, hand_joints=cam_joints)
    mirrored = dataclasses.replace(
        straight,
        frames=np.ascontiguousarray(clip.frames[:, :, ::-1]),
        intrinsics=np.array([fx, fy, w - cx, cy]),
        hand_joints=cam_joints[:, ::-1] * flip,
        hand_valid=clip.hand_valid[:, ::-1],
        hand_confidence=None if clip.hand_confidence is None else clip.hand_confidence[:, ::-1],
    )
    params = RegressorParams(str(weights), boxes="given")
    a = regressor_detections(straight, params)
    b = regressor_detections(mirrored, params)
    assert a.present.all()
    np.testing.assert_array_equal(a.present, b.present[:, ::-1])
    np.testing.assert_allclose(a.joints, b.joints[:, ::-1] * flip, atol=1e-4)


def test_a_left_hand_is_the_mirror_image_of_a_right_hand(weights: Path, clip) -> None:
    assert_left_hands_mirror_right_hands(clip, weights)


def test_default_boxes_come_from_mediapipe(weights: Path, clip) -> None:
    pytest.importorskip("mediapipe")
    det = regressor_detections(clip, RegressorParams(str(weights)))  # boxes="mediapipe"
    det.check(clip.num_frames)
    assert det.present.any()  # MediaPipe finds the left hand of this clip in every frame
    assert np.isfinite(det.joints[det.present]).all()


def egodex_portrait_clip() -> Clip:
    """The EgoDex portrait variant's frames (docs/design.md, "Hands: the curtain hand, scene
    cues"; ``tests.conftest.egodex_portrait_frames``, as test_hands_tracking's curtain test
    uses them) at 16 fps; a 90-degree camera, no poses."""
    from egosim.pipeline.geometry import intrinsics_from_fov

    frames = egodex_portrait_frames()  # (33, 480, 832, 3)
    return Clip(
        clip_id="egodex_portrait",
        source="video",
        source_uri="",
        fps=16.0,
        timestamps=np.arange(33) / 16.0,
        intrinsics=intrinsics_from_fov(832, 480, 90.0),
        frames=frames,
    )


def test_mediapipe_boxes_leave_out_the_scene_checks_false_hand(weights: Path, monkeypatch) -> None:
    """The regressor's boxes (``boxes="mediapipe"``) come from the default backend's tracks after
    its scene check: the EgoDex portrait variant's curtain fold, a "left hand" near (190, 210)
    on 22 frames without the check (measured), is not boxed nor regressed; the real right hand
    still is (24 frames measured with the check, as the default backend keeps it)."""
    pytest.importorskip("mediapipe")
    from egosim.stages.hands import regressor_backend
    from egosim.stages.hands.mediapipe_backend import MediaPipeParams, hand_centres, hand_size

    clip = egodex_portrait_clip()
    found = {}  # detection is the slow part: once for both runs
    detect = regressor_backend.detect_landmarks

    def detect_once(frames: np.ndarray, params: MediaPipeParams):
        if "raw" not in found:
            found["raw"] = detect(frames, params)
        return found["raw"]

    monkeypatch.setattr(regressor_backend, "detect_landmarks", detect_once)

    def on_fold(uv: np.ndarray, present: np.ndarray) -> np.ndarray:  # (T, 2) bool
        near = np.linalg.norm(hand_centres(uv) - np.array([190.0, 210.0]), axis=-1)  # (T, 2)
        return present & (near < hand_size(uv))

    unchecked = MediaPipeParams(scene_check=None)
    uv, present, _ = regressor_backend.hand_boxes(clip, "mediapipe", unchecked)
    assert on_fold(uv, present).sum() >= 15  # the false hand, boxed without the check
    det = regressor_detections(clip, RegressorParams(str(weights), mediapipe=unchecked))
    assert (det.present & on_fold(uv, present)).sum() >= 15  # and regressed

    uv, present, _ = regressor_backend.hand_boxes(clip, "mediapipe", MediaPipeParams())
    assert on_fold(uv, present).sum() == 0
    assert present[:, RIGHT].sum() >= 20
    det = regressor_detections(clip, RegressorParams(str(weights)))  # the default: checked
    det.check(clip.num_frames)
    np.testing.assert_array_equal(det.present, present)  # every box regressed, nothing else


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_cuda_matches_cpu(weights: Path, clip) -> None:
    cpu = regressor_detections(clip, RegressorParams(str(weights), boxes="given"))
    gpu = regressor_detections(clip, RegressorParams(str(weights), "cuda", boxes="given"))
    np.testing.assert_array_equal(cpu.present, gpu.present)
    np.testing.assert_allclose(gpu.joints, cpu.joints, atol=1e-3)


# ---------------------------------------------------------------------------------------------
# Head "mano": HaMeR's MANO decoder and the MANO layer; HaMeR checkpoints converted.

MANO_SPEC = RegressorSpec(
    image_size=64,
    patch_size=16,
    hidden_size=32,
    num_layers=2,
    num_heads=2,
    crop_columns=8,  # the ViT sees 64 x 48, as HaMeR's 256 x 192
    patch_padding=2,
    head="mano",
    decoder_dim=16,
    decoder_depth=2,
    decoder_heads=2,
    decoder_dim_head=8,
    decoder_mlp=24,
    num_betas=4,
)
TINY_LAYOUT = HamerLayout(num_heads=2, decoder_heads=2, image_size=64, crop_columns=8)


def mano_folder(path: Path, seed: int, constant: bool = False) -> Path:
    """A weights folder with a tiny random MANO-head regressor and tiny MANO model; with
    ``constant`` the head's output layers are zero, so every crop gives the mean pose, shape and
    camera (s = 0.9, t = 0)."""
    arrays = tiny_mano(seed)
    torch.manual_seed(seed)
    model = HandRegressor(MANO_SPEC, ManoLayer(arrays))
    if constant:
        for layer in (model.mano_head.decpose, model.mano_head.decshape, model.mano_head.deccam):
            torch.nn.init.zeros_(layer.weight)
    save_regressor(model, path)
    save_mano_arrays(arrays, path / MANO_FILE)
    return path


def test_mano_head_saves_loads_and_needs_its_mano_file(tmp_path: Path) -> None:
    folder = mano_folder(tmp_path / "w", seed=1)
    model = load_regressor(folder)
    assert not any(k.startswith("mano.") for k in model.state_dict())  # MANO: its own file
    x = torch.randn(2, 3, 64, 64)
    with torch.inference_mode():
        joints, cam = model(x)
        rotations, betas, cam2 = model.forward_mano(x)
    assert joints.shape == (2, 21, 3) and cam.shape == (2, 3) and betas.shape == (2, 4)
    torch.testing.assert_close(cam, cam2)
    eye = torch.eye(3).expand(2, 16, 3, 3)
    torch.testing.assert_close(rotations @ rotations.transpose(-1, -2), eye, atol=1e-5, rtol=0)
    # The joints are the MANO layer's for the predicted parameters.
    with torch.inference_mode():
        _, expected = ManoLayer(tiny_mano(1))(rotations, betas)
    torch.testing.assert_close(joints, expected)
    (folder / MANO_FILE).unlink()
    with pytest.raises(ConfigError, match="convert-mano"):
        load_regressor(folder)


def test_mano_head_through_the_stage_puts_the_hands_in_their_boxes(tmp_path: Path, clip) -> None:
    # A constant head: each hand is the tiny MANO template (rest pose, mean shape), with the
    # camera (0.9, 0, 0): MANO's origin at the box centre, joint X at box pixel
    # c + 0.9 X_xy b / 2 under weak perspective (x mirrored for a left hand).
    folder = mano_folder(tmp_path / "w", seed=2, constant=True)
    clips = tmp_path / "clips.parquet"
    write_clips(clips, [clip])
    params = {"backend": "regressor", "regressor_weights": str(folder), "despike": False}
    row = hands_row(tmp_path, {"clips": clips}, {**params, "regressor_boxes": "given"})
    valid = np.asarray(row["hand_valid"])  # (T, 2)
    joints = np.asarray(row["hand_joints"], dtype=np.float64).reshape(5, 2, 21, 3)
    np.testing.assert_array_equal(valid, clip.hand_valid)  # every labelled hand, every frame
    assert np.isfinite(joints[valid]).all() and np.isnan(joints[~valid]).all()

    template = ManoLayer(tiny_mano(2), dtype=torch.float64)
    rest = torch.eye(3, dtype=torch.float64).expand(1, 16, 3, 3)
    _, x_mano = template(rest, torch.zeros(1, 4, dtype=torch.float64))
    x_mano = x_mano[0].numpy()  # (21, 3) right hand, MANO frame
    k = clip.intrinsics
    for f, s in zip(*np.nonzero(valid), strict=True):
        labels_uv, _ = project_points(
            transform_points(invert_se3(clip.world_from_cam[f]), clip.hand_joints[f, s]), k
        )
        centre, side = square_box(labels_uv, MANO_SPEC.box_scale, MANO_SPEC.visible_aspect)
        hand = x_mano * (np.array([-1.0, 1.0, 1.0]) if s == 0 else 1.0)  # a left hand: mirrored
        cam_pts = transform_points(invert_se3(clip.world_from_cam[f]), joints[f, s])
        origin = cam_pts - hand  # (21, 3): MANO's origin, the same for every joint
        np.testing.assert_allclose(origin, np.broadcast_to(origin[0], origin.shape), atol=1e-5)
        origin_uv, _ = project_points(origin[:1], k)
        np.testing.assert_allclose(origin_uv[0], centre, atol=1e-3)  # px: t = 0
        uv, z = project_points(cam_pts, k)
        weak = centre + 0.9 * hand[:, :2] * side / 2.0  # (21, 2)
        # Full perspective is weak perspective scaled about the principal point by T_z / (T_z +
        # X_z) (T_z = 2 f / (s b), the origin's depth): exact; and within 1 px of it for this
        # ~0.15 m hand at the depth its box gives (up to 0.83 px here).
        tz = 2.0 * k[0] / (0.9 * side)
        np.testing.assert_allclose(origin[0, 2], tz, rtol=1e-6)
        exact = k[2:] + (weak - k[2:]) * (tz / (tz + hand[:, 2]))[:, None]
        np.testing.assert_allclose(uv, exact, atol=1e-4)
        np.testing.assert_allclose(uv, weak, atol=1.0)
        assert (np.abs(uv - centre) <= side / 2).all() and (z > 0).all()  # inside its box


def test_mano_head_left_hands_mirror_right_hands(tmp_path: Path, clip) -> None:
    assert_left_hands_mirror_right_hands(clip, mano_folder(tmp_path / "w", seed=3))


def hamer_state(rng: np.random.Generator, patches: int = 4 * 3) -> dict[str, np.ndarray]:
    """A random state dict under HaMeR's parameter names (hamer/models/backbones/vit.py,
    heads/mano_head.py, components/pose_transformer.py) at MANO_SPEC's sizes (``patches``:
    4 x 3 for its 64 x 48 view, 16 x 12 for HaMeR's 256 x 192)."""
    c, d, inner, mlp = 32, 16, 16, 24
    shapes = {
        "backbone.patch_embed.proj.weight": (c, 3, 16, 16),
        "backbone.patch_embed.proj.bias": (c,),
        "backbone.pos_embed": (1, 1 + patches, c),  # class slot + the patches
        "backbone.last_norm.weight": (c,),
        "backbone.last_norm.bias": (c,),
        "mano_head.transformer.to_token_embedding.weight": (d, 1),
        "mano_head.transformer.to_token_embedding.bias": (d,),
        "mano_head.transformer.pos_embedding": (1, 1, d),
        "mano_head.decpose.weight": (96, d),
        "mano_head.decpose.bias": (96,),
        "mano_head.decshape.weight": (4, d),
        "mano_head.decshape.bias": (4,),
        "mano_head.deccam.weight": (3, d),
        "mano_head.deccam.bias": (3,),
        "mano_head.init_hand_pose": (1, 96),
        "mano_head.init_betas": (1, 4),
        "mano_head.init_cam": (1, 3),
    }
    for i in range(2):
        b = f"backbone.blocks.{i}."
        shapes |= {
            b + "norm1.weight": (c,),
            b + "norm1.bias": (c,),
            b + "attn.qkv.weight": (3 * c, c),
            b + "attn.qkv.bias": (3 * c,),
            b + "attn.proj.weight": (c, c),
            b + "attn.proj.bias": (c,),
            b + "norm2.weight": (c,),
            b + "norm2.bias": (c,),
            b + "mlp.fc1.weight": (4 * c, c),
            b + "mlp.fc1.bias": (4 * c,),
            b + "mlp.fc2.weight": (c, 4 * c),
            b + "mlp.fc2.bias": (c,),
        }
        t = f"mano_head.transformer.transformer.layers.{i}."
        shapes |= {
            t + "0.norm.weight": (d,),
            t + "0.norm.bias": (d,),
            t + "0.fn.to_qkv.weight": (3 * inner, d),
            t + "0.fn.to_out.0.weight": (d, inner),
            t + "0.fn.to_out.0.bias": (d,),
            t + "1.norm.weight": (d,),
            t + "1.norm.bias": (d,),
            t + "1.fn.to_q.weight": (inner, d),
            t + "1.fn.to_kv.weight": (2 * inner, c),
            t + "1.fn.to_out.0.weight": (d, inner),
            t + "1.fn.to_out.0.bias": (d,),
            t + "2.norm.weight": (d,),
            t + "2.norm.bias": (d,),
            t + "2.fn.net.0.weight": (mlp, d),
            t + "2.fn.net.0.bias": (mlp,),
            t + "2.fn.net.3.weight": (d, mlp),
            t + "2.fn.net.3.bias": (d,),
        }
    return {k: rng.normal(0.0, 0.1, s).astype(np.float32) for k, s in shapes.items()}


class HyperParameters:
    """Stands in for a config object (HaMeR's yacs CfgNode) in a Lightning checkpoint."""


def write_hamer_checkpoint(path: Path, state: dict[str, np.ndarray], monkeypatch) -> None:
    """``torch.save`` of a Lightning-style checkpoint holding ``state`` (one tensor stored as a
    transposed view, one in bfloat16), MANO buffers, a discriminator and a config object whose
    module afterwards refuses to be imported."""
    import collections
    import sys
    import types

    module = types.ModuleType("fake_yacs")
    HyperParameters.__module__ = "fake_yacs"
    module.HyperParameters = HyperParameters
    monkeypatch.setitem(sys.modules, "fake_yacs", module)
    tensors = collections.OrderedDict((k, torch.from_numpy(v)) for k, v in state.items())
    proj = "backbone.blocks.0.attn.proj.weight"
    tensors[proj] = torch.from_numpy(np.ascontiguousarray(state[proj].T)).t()  # strided view
    tensors["mano_head.decshape.bias"] = tensors["mano_head.decshape.bias"].bfloat16()
    tensors["mano.v_template"] = torch.zeros(5, 3)
    tensors["discriminator.fc.weight"] = torch.zeros(2, 2)
    config = HyperParameters()
    config.__dict__["MODEL"] = {"IMAGE_SIZE": 256}
    torch.save({"state_dict": tensors, "epoch": 7, "hyper_parameters": {"cfg": config}}, path)
    monkeypatch.delitem(sys.modules, "fake_yacs")  # unpickling would now fail to import it
    monkeypatch.setattr(HyperParameters, "__module__", "fake_yacs_gone")


def test_hamer_checkpoint_converts_by_name_without_unpickling(tmp_path: Path, monkeypatch) -> None:
    rng = np.random.default_rng(0)
    state = hamer_state(rng)
    ckpt = tmp_path / "hamer.ckpt"
    write_hamer_checkpoint(ckpt, state, monkeypatch)
    with pytest.raises(Exception, match="fake_yacs"):  # torch.load would need the class
        torch.load(ckpt, weights_only=False)
    dropped = convert_hamer_checkpoint(ckpt, tmp_path / "weights", TINY_LAYOUT)
    assert dropped == ["discriminator.", "mano."]
    config = json.loads((tmp_path / "weights" / CONFIG_FILE).read_text())
    spec = RegressorSpec(
        **{
            k: tuple(v) if isinstance(v, list) else v
            for k, v in config.items()
            if k != "architecture"
        }
    )
    assert spec == dataclasses.replace(MANO_SPEC, box_scale=2.0)
    converted = load_file(tmp_path / "weights" / WEIGHTS_FILE)
    for key, value in state.items():
        if key == "backbone.pos_embed":
            expected = value[:, 1:] + value[:, :1]  # ViTPose adds its class slot to every patch
            np.testing.assert_allclose(converted["pos_embed"].numpy(), expected, atol=1e-7)
        elif key == "mano_head.decshape.bias":  # stored as bfloat16
            np.testing.assert_allclose(converted[key].numpy(), value, rtol=1e-2, atol=1e-3)
        else:
            new = key.removeprefix("backbone.")
            np.testing.assert_array_equal(converted[new].numpy(), value, err_msg=key)
    assert len(converted) == len(state)
    # With the MANO file beside it, the folder runs.
    save_mano_arrays(tiny_mano(0), tmp_path / "weights" / MANO_FILE)
    model = load_regressor(tmp_path / "weights")
    with torch.inference_mode():
        joints, cam = model(torch.randn(2, 3, 64, 64))
    assert torch.isfinite(joints).all() and torch.isfinite(cam).all()


def test_bad_checkpoints_are_named(tmp_path: Path, monkeypatch) -> None:
    rng = np.random.default_rng(1)
    state = hamer_state(rng)
    with pytest.raises(ConfigError, match=r"4 x 4 grid"):  # no column crop: a 4 x 4 grid
        hamer_to_regressor(state, dataclasses.replace(TINY_LAYOUT, crop_columns=0), "x.ckpt")
    with pytest.raises(ConfigError, match="WiLoR"):
        hamer_to_regressor({**state, "refine_net.w": np.zeros(1)}, TINY_LAYOUT, "x.ckpt")
    with pytest.raises(ConfigError, match=r"x\.ckpt: not a HaMeR checkpoint"):
        hamer_to_regressor(
            {"backbone.patch_embed.proj.weight": np.zeros((4, 3, 2, 2))}, TINY_LAYOUT, "x.ckpt"
        )
    legacy = tmp_path / "legacy.pth"
    legacy.write_bytes(b"\x80\x02}q\x00.")
    with pytest.raises(ConfigError, match=r"legacy\.pth: not a torch\.save zip"):
        convert_hamer_checkpoint(legacy, tmp_path / "out", TINY_LAYOUT)

    class Payload:
        def __reduce__(self):
            return (print, ("payload ran",))

    evil = tmp_path / "evil.ckpt"
    torch.save({"state_dict": {"backbone.x": Payload()}}, evil)
    with pytest.raises(ConfigError, match=r"evil\.ckpt: state_dict entries \['backbone\.x'\]"):
        convert_hamer_checkpoint(evil, tmp_path / "out", TINY_LAYOUT)


def test_cli_converts_hamer_checkpoints(tmp_path: Path, monkeypatch) -> None:
    from typer.testing import CliRunner

    from egosim.pipeline.cli import app

    ckpt = tmp_path / "hamer.ckpt"
    write_hamer_checkpoint(ckpt, hamer_state(np.random.default_rng(2), 16 * 12), monkeypatch)
    out = tmp_path / "weights"
    args = ["hands", "convert-hamer", str(ckpt), "--out", str(out)]
    result = CliRunner().invoke(app, [*args, "--num-heads", "2", "--decoder-heads", "2"])
    assert result.exit_code == 0, result.output
    assert "dropped discriminator., mano." in result.output
    config = json.loads((out / CONFIG_FILE).read_text())
    assert (config["image_size"], config["crop_columns"], config["head"]) == (256, 32, "mano")
    result = CliRunner().invoke(app, [*args, "--num-heads", "2", "--decoder-heads", "5"])
    assert result.exit_code == 2 and "decoder_heads" in result.output


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_mano_head_cuda_matches_cpu(tmp_path: Path, clip) -> None:
    folder = mano_folder(tmp_path / "w", seed=4)
    cpu = regressor_detections(clip, RegressorParams(str(folder), boxes="given"))
    gpu = regressor_detections(clip, RegressorParams(str(folder), "cuda", boxes="given"))
    np.testing.assert_array_equal(cpu.present, gpu.present)
    np.testing.assert_allclose(gpu.joints, cpu.joints, atol=1e-3)


def test_only_the_state_dicts_storages_are_read(tmp_path: Path) -> None:
    import zipfile

    state = hamer_state(np.random.default_rng(3))
    moment = torch.zeros(12345)  # an optimizer state: its storage is never needed
    ckpt = tmp_path / "full.ckpt"
    tensors = {k: torch.from_numpy(v) for k, v in state.items()}
    torch.save({"state_dict": tensors, "optimizer_states": [{"exp_avg": moment}]}, ckpt)
    slim = tmp_path / "slim.ckpt"
    with zipfile.ZipFile(ckpt) as src, zipfile.ZipFile(slim, "w") as dst:
        dropped = [i.filename for i in src.infolist() if i.file_size == 4 * 12345]
        assert len(dropped) == 1
        for info in src.infolist():
            if info.filename not in dropped:
                dst.writestr(info, src.read(info.filename))
    assert convert_hamer_checkpoint(slim, tmp_path / "w", TINY_LAYOUT) == []
    assert len(load_file(tmp_path / "w" / WEIGHTS_FILE)) == len(state)
    missing_weight = tmp_path / "missing.ckpt"  # a state_dict storage gone: named, not a crash
    with zipfile.ZipFile(ckpt) as src, zipfile.ZipFile(missing_weight, "w") as dst:
        for info in src.infolist():
            if not info.filename.endswith("/data/0"):
                dst.writestr(info, src.read(info.filename))
    with pytest.raises(ConfigError, match=r"missing\.ckpt: .*data/0"):
        convert_hamer_checkpoint(missing_weight, tmp_path / "w2", TINY_LAYOUT)


def reference_hamer_head(state: dict[str, np.ndarray], context: np.ndarray, heads: int):
    """HaMeR's MANOTransformerDecoderHead (zero token, one IEF step) in numpy, read from its
    code (components/pose_transformer.py, heads/mano_head.py, utils/geometry.rot6d_to_rotmat):
    ``(rotations (B, 16, 3, 3), betas, cam)``."""
    from scipy.special import erf

    def linear(x, name, bias=True):
        y = x @ state[name + ".weight"].T
        return y + state[name + ".bias"] if bias else y

    def norm(x, name):
        mu, var = x.mean(-1, keepdims=True), x.var(-1, keepdims=True)
        return (x - mu) / np.sqrt(var + 1e-5) * state[name + ".weight"] + state[name + ".bias"]

    def attend(q, k, v):  # "b n (h d) -> b h n d", softmax(q k^T / sqrt(d)) v, back
        def split(t):
            return t.reshape(t.shape[0], t.shape[1], heads, -1).transpose(0, 2, 1, 3)

        q, k, v = split(q), split(k), split(v)
        dots = q @ k.transpose(0, 1, 3, 2) / np.sqrt(q.shape[-1])
        weights = np.exp(dots - dots.max(-1, keepdims=True))
        out = weights / weights.sum(-1, keepdims=True) @ v
        return out.transpose(0, 2, 1, 3).reshape(q.shape[0], q.shape[2], -1)

    p = "mano_head.transformer."
    b = context.shape[0]
    x = linear(np.zeros((b, 1, 1)), p + "to_token_embedding") + state[p + "pos_embedding"]
    for i in range(2):
        layer = f"{p}transformer.layers.{i}."
        h = norm(x, layer + "0.norm")
        q, k, v = np.split(linear(h, layer + "0.fn.to_qkv", bias=False), 3, axis=-1)
        x = linear(attend(q, k, v), layer + "0.fn.to_out.0") + x
        h = norm(x, layer + "1.norm")
        k, v = np.split(linear(context, layer + "1.fn.to_kv", bias=False), 2, axis=-1)
        q = linear(h, layer + "1.fn.to_q", bias=False)
        x = linear(attend(q, k, v), layer + "1.fn.to_out.0") + x
        h = linear(norm(x, layer + "2.norm"), layer + "2.fn.net.0")
        h = 0.5 * h * (1.0 + erf(h / np.sqrt(2.0)))  # exact GELU
        x = linear(h, layer + "2.fn.net.3") + x
    token = x[:, 0]
    pose = linear(token, "mano_head.decpose") + state["mano_head.init_hand_pose"]
    betas = linear(token, "mano_head.decshape") + state["mano_head.init_betas"]
    cam = linear(token, "mano_head.deccam") + state["mano_head.init_cam"]
    six = pose.reshape(-1, 2, 3).transpose(0, 2, 1)  # (B * 16, 3, 2)
    a1, a2 = six[..., 0], six[..., 1]
    b1 = a1 / np.linalg.norm(a1, axis=-1, keepdims=True)
    b2 = a2 - (b1 * a2).sum(-1, keepdims=True) * b1
    b2 /= np.linalg.norm(b2, axis=-1, keepdims=True)
    rot = np.stack([b1, b2, np.cross(b1, b2)], axis=-1).reshape(b, 16, 3, 3)
    return rot, betas, cam


def test_converted_mano_head_computes_what_hamers_head_does() -> None:
    state = {k: v.astype(np.float64) for k, v in hamer_state(np.random.default_rng(6)).items()}
    model, _ = hamer_to_regressor(state, TINY_LAYOUT, "x.ckpt")
    context = np.random.default_rng(7).normal(size=(3, 12, 32))  # (B, tokens, ViT width)
    with torch.inference_mode():
        got = model.double().mano_head(torch.from_numpy(context))
    for ours, theirs in zip(got, reference_hamer_head(state, context, heads=2), strict=True):
        np.testing.assert_allclose(ours.numpy(), theirs, atol=1e-10)


def reference_vitpose(state: dict[str, np.ndarray], image: np.ndarray, heads: int) -> np.ndarray:
    """HaMeR's backbone in numpy, read from its code (hamer.py: ``backbone(x[:, :, :,
    32:-32])`` scaled to this 64-pixel crop; backbones/vit.py: patch conv padded by 2,
    ``x + pos_embed[:, 1:] + pos_embed[:, :1]``, timm blocks, ``last_norm``): tokens (B, N, C)."""
    from scipy.special import erf

    def norm(x, name):
        mu, var = x.mean(-1, keepdims=True), x.var(-1, keepdims=True)
        return (x - mu) / np.sqrt(var + 1e-6) * state[name + ".weight"] + state[name + ".bias"]

    def linear(x, name):
        return x @ state[name + ".weight"].T + state[name + ".bias"]

    x = image[:, :, :, 8:-8]  # (B, 3, 64, 48)
    x = np.pad(x, ((0, 0), (0, 0), (2, 2), (2, 2)))  # (B, 3, 68, 52)
    w = state["backbone.patch_embed.proj.weight"]  # (C, 3, 16, 16)
    rows, cols = (x.shape[2] - 16) // 16 + 1, (x.shape[3] - 16) // 16 + 1
    tokens = (
        np.stack(
            [
                np.einsum("bkij,ckij->bc", x[:, :, 16 * r : 16 * r + 16, 16 * c : 16 * c + 16], w)
                for r in range(rows)
                for c in range(cols)
            ],
            axis=1,
        )
        + state["backbone.patch_embed.proj.bias"]
    )  # (B, N, C) row-major patches
    pos = state["backbone.pos_embed"]
    x = tokens + pos[:, 1:] + pos[:, :1]
    b, n, ch = x.shape
    for i in range(2):
        p = f"backbone.blocks.{i}."
        qkv = linear(norm(x, p + "norm1"), p + "attn.qkv").reshape(b, n, 3, heads, ch // heads)
        q, k, v = qkv.transpose(2, 0, 3, 1, 4)  # each (B, H, N, D)
        dots = q @ k.transpose(0, 1, 3, 2) / np.sqrt(ch // heads)
        att = np.exp(dots - dots.max(-1, keepdims=True))
        out = (att / att.sum(-1, keepdims=True) @ v).transpose(0, 2, 1, 3).reshape(b, n, ch)
        x = x + linear(out, p + "attn.proj")
        h = linear(norm(x, p + "norm2"), p + "mlp.fc1")
        x = x + linear(0.5 * h * (1.0 + erf(h / np.sqrt(2.0))), p + "mlp.fc2")
    return norm(x, "backbone.last_norm")


def test_converted_backbone_computes_what_hamers_vit_does() -> None:
    state = {k: v.astype(np.float64) for k, v in hamer_state(np.random.default_rng(8)).items()}
    model, _ = hamer_to_regressor(state, TINY_LAYOUT, "x.ckpt")
    image = np.random.default_rng(9).normal(size=(2, 3, 64, 64))
    with torch.inference_mode():
        got = model.double().features(torch.from_numpy(image)).numpy()
    np.testing.assert_allclose(got, reference_vitpose(state, image, heads=2), atol=1e-9)


def test_stored_mano_fits_give_the_stored_joints(tmp_path: Path, clip) -> None:
    """Head ``mano`` (the tiny random model, its output layers spread so that the finger
    rotations are 50-150 degrees): the hands shard's ``mano_*`` columns put through the MANO
    layer (:func:`hand_joints_from_params`: left hands the mirrored model) give the stored world
    joints within 1e-5 m + 1e-6 relative (float32 columns; measured 3.4e-7 m), on every
    valid hand of both sides; invalid hands have NaN fits. The ``given`` backend writes nulls."""
    from egosim.schemas.hands import HANDS
    from egosim.stages.hands.mano import hand_joints_from_params

    arrays = tiny_mano(4)
    torch.manual_seed(4)
    model = HandRegressor(MANO_SPEC, ManoLayer(arrays))
    with torch.no_grad():
        model.mano_head.decpose.weight.mul_(40.0)  # std 0.4: rotations well away from I
        model.mano_head.decshape.weight.mul_(40.0)
    folder = tmp_path / "w"
    save_regressor(model, folder)
    save_mano_arrays(arrays, folder / MANO_FILE)
    clips = tmp_path / "clips.parquet"
    write_clips(clips, [clip])
    params = {"backend": "regressor", "regressor_weights": str(folder), "despike": False}
    row = hands_row(tmp_path, {"clips": clips}, {**params, "regressor_boxes": "given"})
    t = clip.num_frames
    valid = np.asarray(row["hand_valid"])  # (T, 2)
    assert valid[:, 0].any() and valid[:, 1].any()
    joints = np.asarray(row["hand_joints"], dtype=np.float64).reshape(t, 2, 21, 3)
    orient = np.asarray(row["mano_global_orient"], dtype=np.float64).reshape(t, 2, 3)
    pose = np.asarray(row["mano_hand_pose"], dtype=np.float64).reshape(t, 2, 45)
    transl = np.asarray(row["mano_transl"], dtype=np.float64).reshape(t, 2, 3)
    betas = np.asarray(row["mano_betas"], dtype=np.float64).reshape(t, 2, 4)
    for part in (orient, pose, transl, betas):
        assert np.isfinite(part[valid]).all() and np.isnan(part[~valid]).all()
    angles = np.degrees(np.linalg.norm(pose[valid].reshape(-1, 15, 3), axis=2))
    assert np.percentile(angles, 10) > 20.0  # not a test of the identity pose
    frames, sides = np.nonzero(valid)
    layer = ManoLayer(arrays, dtype=torch.float64)
    rebuilt = hand_joints_from_params(
        layer, orient[valid], pose[valid], betas[valid], transl[valid], sides == 0
    )  # (N, 21, 3)
    np.testing.assert_allclose(rebuilt, joints[frames, sides], atol=1e-5, rtol=1e-6)
    # The left hand is the mirrored model: read as a right hand, its joints are wrong.
    left = sides == 0
    wrong = hand_joints_from_params(
        layer,
        orient[valid][left],
        pose[valid][left],
        betas[valid][left],
        transl[valid][left],
        np.zeros(int(left.sum()), dtype=bool),
    )
    assert np.abs(wrong - joints[frames[left], sides[left]]).max() > 0.01
    given = hands_row(tmp_path, {"clips": clips}, {"backend": "given"}, name="given")
    assert all(given[name] is None for name in ("mano_global_orient", "mano_betas"))
    assert HANDS.row_problems(row) == []
    half = transl.copy()
    half[frames[0], sides[0]] = np.nan  # one hand-frame with a fit but no translation
    bad = {**row, "mano_transl": half.reshape(t, 6).tolist()}
    assert any("all finite or all NaN" in p for p in HANDS.row_problems(bad))
