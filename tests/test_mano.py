"""MANO layer: against an independent numpy implementation and exact properties, tiny model."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

torch = pytest.importorskip("torch")

from egosim.stages.hands.mano import (  # noqa: E402
    MANO_PARENTS,
    MANO_TO_EGOSIM,
    ManoFileError,
    ManoLayer,
    axis_angle_to_matrix,
    load_mano_layer,
    rotation_6d_to_matrix,
    save_mano_arrays,
)

NUM_VERTICES = 48
NUM_BETAS = 4
# MANO's fingers as its joint chains (knuckle -> last joint); the tips in egosim's finger order.
FINGER_CHAINS = {"thumb": (13, 14, 15), "index": (1, 2, 3), "middle": (4, 5, 6)}
FINGER_CHAINS |= {"ring": (10, 11, 12), "little": (7, 8, 9)}
TIP_JOINT = [FINGER_CHAINS[f][-1] for f in ("thumb", "index", "middle", "ring", "little")]
# egosim joints per finger (wrist 0): thumb 1-4, index 5-8, middle 9-12, ring 13-16, little 17-20
EGOSIM_FINGER = {"thumb": range(1, 5), "index": range(5, 9), "middle": range(9, 13)}
EGOSIM_FINGER |= {"ring": range(13, 17), "little": range(17, 21)}


def tiny_mano(seed: int = 0, tip_posedirs: bool = True) -> dict[str, np.ndarray]:
    """A random 48-vertex MANO-like model: each vertex skinned to one joint and its parent; the
    five tip vertices to their finger's last joint only (with zero pose blend shapes unless
    ``tip_posedirs``)."""
    rng = np.random.default_rng(seed)
    v, j = NUM_VERTICES, len(MANO_PARENTS)
    owner = np.arange(v) % j  # vertex -> joint
    tips = np.array([v - j + t for t in TIP_JOINT])  # owner(v - 16 + t) == t
    weights = np.zeros((v, j))
    for i, o in enumerate(owner):
        share = rng.uniform(0.5, 1.0)
        weights[i, o] = share
        weights[i, max(MANO_PARENTS[o], 0)] += 1.0 - share
    weights[tips] = 0.0
    weights[tips, TIP_JOINT] = 1.0
    regressor = rng.uniform(0.0, 1.0, (j, v)) * (owner[None] == np.arange(j)[:, None])
    regressor /= regressor.sum(axis=1, keepdims=True)
    posedirs = rng.normal(0.0, 0.01, (v, 3, 9 * (j - 1)))
    if not tip_posedirs:
        posedirs[tips] = 0.0
    return {
        "v_template": rng.normal(0.0, 0.05, (v, 3)),
        "shapedirs": rng.normal(0.0, 0.01, (v, 3, NUM_BETAS)),
        "posedirs": posedirs,
        "J_regressor": regressor,
        "weights": weights,
        "kintree_table": np.stack([np.array([2**32 - 1, *MANO_PARENTS[1:]]), np.arange(j)]),
        "tip_vertices": tips,
        "hands_components": np.linalg.qr(rng.normal(size=(45, 45)))[0],
        "hands_mean": rng.normal(0.0, 0.1, 45),
    }


def numpy_mano(arrays: dict, pose: np.ndarray, betas: np.ndarray) -> np.ndarray:
    """Reference: the 21 joints (egosim order) of axis-angle ``pose (16, 3)``, loop by loop."""
    parents = list(arrays["kintree_table"][0].astype(np.int64))
    parents[0] = -1
    rots = [cv2.Rodrigues(p.reshape(3, 1))[0] for p in pose]
    v_shaped = arrays["v_template"] + arrays["shapedirs"] @ betas
    rest = arrays["J_regressor"] @ v_shaped
    lrotmin = np.concatenate([(r - np.eye(3)).ravel() for r in rots[1:]])
    v_posed = v_shaped + arrays["posedirs"] @ lrotmin
    world = []
    for j, parent in enumerate(parents):
        local = np.eye(4)
        local[:3, :3] = rots[j]
        local[:3, 3] = rest[j] - (rest[parent] if parent >= 0 else 0.0)
        world.append(local if parent < 0 else world[parent] @ local)
    skin = []
    for j, g in enumerate(world):
        undo = np.eye(4)
        undo[:3, 3] = -rest[j]
        skin.append(g @ undo)
    verts = np.zeros_like(v_posed)
    for i, p in enumerate(v_posed):
        m = sum(arrays["weights"][i, j] * skin[j] for j in range(len(parents)))
        verts[i] = (m @ np.append(p, 1.0))[:3]
    joints = np.concatenate([np.array([g[:3, 3] for g in world]), verts[arrays["tip_vertices"]]])
    return joints[list(MANO_TO_EGOSIM)]


def run_layer(layer: ManoLayer, pose: np.ndarray, betas: np.ndarray) -> np.ndarray:
    rot = axis_angle_to_matrix(torch.as_tensor(pose, dtype=torch.float64))[None]
    _, joints = layer(rot, torch.as_tensor(betas, dtype=torch.float64)[None])
    return joints[0].numpy()


def test_layer_matches_numpy_reference() -> None:
    arrays = tiny_mano()
    layer = ManoLayer(arrays, dtype=torch.float64)
    rng = np.random.default_rng(1)
    for _ in range(3):
        pose = rng.normal(0.0, 0.6, (16, 3))
        betas = rng.normal(0.0, 1.0, NUM_BETAS)
        np.testing.assert_allclose(
            run_layer(layer, pose, betas), numpy_mano(arrays, pose, betas), atol=1e-12
        )
    # float32 buffers (the backend's) agree to float32 precision on a ~0.1 m model.
    layer32 = ManoLayer(arrays)
    rot = axis_angle_to_matrix(torch.as_tensor(pose, dtype=torch.float32))[None]
    _, joints32 = layer32(rot, torch.as_tensor(betas, dtype=torch.float32)[None])
    np.testing.assert_allclose(joints32[0].numpy(), numpy_mano(arrays, pose, betas), atol=1e-6)


def test_zero_pose_and_shape_give_the_template_joints() -> None:
    arrays = tiny_mano()
    joints = run_layer(ManoLayer(arrays, dtype=torch.float64), np.zeros((16, 3)), np.zeros(4))
    expected = np.concatenate(
        [arrays["J_regressor"] @ arrays["v_template"], arrays["v_template"][arrays["tip_vertices"]]]
    )[list(MANO_TO_EGOSIM)]
    np.testing.assert_allclose(joints, expected, atol=1e-14)
    # egosim order: the thumb chain (joints 1-4) is MANO's 13, 14, 15 and the thumb tip vertex.
    np.testing.assert_allclose(joints[1:4], (arrays["J_regressor"] @ arrays["v_template"])[13:16])
    np.testing.assert_allclose(joints[4], arrays["v_template"][arrays["tip_vertices"][0]])


def test_a_global_rotation_rotates_every_joint_about_the_wrist() -> None:
    layer = ManoLayer(tiny_mano(), dtype=torch.float64)
    rng = np.random.default_rng(2)
    pose, betas = rng.normal(0.0, 0.4, (16, 3)), rng.normal(0.0, 1.0, NUM_BETAS)
    turn = np.array([0.3, -1.1, 0.7])
    turned = pose.copy()
    turned[0] = cv2.Rodrigues(cv2.Rodrigues(turn)[0] @ cv2.Rodrigues(pose[0])[0])[0][:, 0]
    base, after = run_layer(layer, pose, betas), run_layer(layer, turned, betas)
    r = cv2.Rodrigues(turn)[0]
    np.testing.assert_allclose(after[0], base[0], atol=1e-12)  # the wrist is the pivot
    np.testing.assert_allclose(after - after[0], (base - base[0]) @ r.T, atol=1e-12)


@pytest.mark.parametrize("finger", list(FINGER_CHAINS))
def test_a_finger_twist_moves_only_that_finger(finger: str) -> None:
    rng = np.random.default_rng(3)
    pose, betas = rng.normal(0.0, 0.3, (16, 3)), rng.normal(0.0, 1.0, NUM_BETAS)
    knuckle = FINGER_CHAINS[finger][0]
    twisted = pose.copy()
    twisted[knuckle] += np.array([0.2, 0.5, -0.4])
    moved_expected = set(EGOSIM_FINGER[finger][1:])  # the knuckle rotates about itself
    # Pose blend shapes move every vertex, so a tip is that finger's alone only without them at
    # the tips (the skeleton's 16 joints never depend on them).
    for tip_posedirs, checked in (
        (False, range(21)),
        (True, [k for k in range(21) if k == 0 or k % 4]),
    ):
        layer = ManoLayer(tiny_mano(tip_posedirs=tip_posedirs), dtype=torch.float64)
        moved = np.linalg.norm(
            run_layer(layer, twisted, betas) - run_layer(layer, pose, betas), axis=1
        )
        for k in checked:
            if k in moved_expected:
                assert moved[k] > 1e-4, (finger, k)
            else:
                assert moved[k] < 1e-13, (finger, k)


def test_rotation_helpers() -> None:
    aa = torch.tensor([[0.0, 0.0, 0.0], [0.3, -0.2, 1.4], [1e-10, 0.0, 0.0]], dtype=torch.float64)
    for v, m in zip(aa.numpy(), axis_angle_to_matrix(aa).numpy(), strict=True):
        np.testing.assert_allclose(m, cv2.Rodrigues(v.reshape(3, 1))[0], atol=1e-12)
    r = axis_angle_to_matrix(aa[1])
    six = torch.cat([r[:, 0] * 2.0, r[:, 1] + 0.5 * r[:, 0]])  # scaled, not orthogonal
    torch.testing.assert_close(rotation_6d_to_matrix(six), r)


def test_pca_pose_and_file_round_trip(tmp_path: Path) -> None:
    arrays = tiny_mano()
    save_mano_arrays(arrays, tmp_path / "mano.safetensors")
    layer = load_mano_layer(tmp_path / "mano.safetensors", torch.float64)
    coeffs = torch.tensor([[0.5, -1.0, 0.2]], dtype=torch.float64)
    expected = coeffs.numpy() @ arrays["hands_components"][:3] + arrays["hands_mean"]
    np.testing.assert_allclose(layer.hand_pose_from_pca(coeffs).numpy(), expected, atol=1e-6)
    flat = layer.hand_pose_from_pca(coeffs, flat_hand_mean=True).numpy()
    np.testing.assert_allclose(flat, expected - arrays["hands_mean"], atol=1e-6)
    rot = layer.rotations_from_axis_angle(
        torch.zeros(1, 3, dtype=torch.float64), torch.tensor(expected)
    )
    _, joints = layer(rot, torch.zeros(1, NUM_BETAS, dtype=torch.float64))
    pose = np.concatenate([np.zeros(3), expected[0]]).reshape(16, 3)
    np.testing.assert_allclose(joints[0].numpy(), numpy_mano(arrays, pose, np.zeros(4)), atol=1e-6)


def test_bad_files_are_named(tmp_path: Path) -> None:
    with pytest.raises(ManoFileError, match="convert-mano"):
        load_mano_layer(tmp_path / "absent.safetensors")
    bad = tiny_mano()
    bad["posedirs"] = bad["posedirs"][:, :, :10]
    with pytest.raises(ManoFileError, match=r"bad\.safetensors.*posedirs shape"):
        save_mano_arrays(bad, tmp_path / "bad.safetensors")
    del bad["weights"]
    with pytest.raises(ManoFileError, match="missing arrays"):
        ManoLayer(bad)
