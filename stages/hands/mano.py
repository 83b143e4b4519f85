"""The MANO hand model (Romero et al. 2017) as a torch layer, from a safetensors file of arrays.

MANO maps shape coefficients ``betas (B,)`` and 16 joint rotations (the wrist's global
orientation, then 15 finger joints, each relative to its parent) to a 778-vertex mesh and its
joints:

1. **Shape blend shapes**: ``v_shaped = v_template + shapedirs . betas`` (``shapedirs (V, 3,
   B)``).
2. **Joint regressor**: rest joints ``J = J_regressor @ v_shaped`` (``J_regressor (16, V)``).
3. **Pose blend shapes**: ``v_posed = v_shaped + posedirs . vec(R_1 - I, ..., R_15 - I)``
   (``posedirs (V, 3, 135)``; the matrices flattened row-major, the wrist's rotation left out,
   as MANO's ``lrotmin``).
4. **Linear blend skinning**: along the kinematic tree (``parents``, root first) each joint's
   world transform is ``G_j = G_parent(j) [R_j | J_j - J_parent(j)]`` (``G_0 = [R_0 | J_0]``);
   the posed joint is ``G_j``'s translation; vertex ``v`` moves by ``sum_j weights[v, j] G_j
   [I | -J_j]``.

The 21 output joints are MANO's 16 posed joints plus 5 fingertip vertices (thumb, index,
middle, ring, little: vertices 744, 320, 443, 554, 671 of the official mesh, the ones HaMeR and
WiLoR use), reordered to egosim's 21-joint MANO order (wrist; then thumb, index, middle, ring
and little chains, knuckle to tip: ``docs/design.md``, Conventions). MANO's own order is wrist,
index 1-3, middle 1-3, little 1-3, ring 1-3, thumb 1-3.

The arrays come from a safetensors file written by
:func:`egosim.stages.hands.convert_mano.convert_mano_pickle` from the licence-gated official
``MANO_RIGHT.pkl`` (never unpickled) or by :func:`save_mano_arrays`: required ``v_template (V,
3)``, ``shapedirs (V, 3, B)``, ``posedirs (V, 3, 9 (J - 1))``, ``J_regressor (J, V)``, ``weights
(V, J)`` and ``parents (J,)`` (or the official ``kintree_table (2, J)``, whose first row is the
parents); optional ``tip_vertices (5,)`` (default: the official mesh's), ``hands_components (K,
45)`` and ``hands_mean (45,)`` for MANO's PCA hand pose. Units are the file's (metres for MANO).
Only right hands are modelled here, as HaMeR does: a left hand is a mirrored right hand.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np
import torch
from safetensors import SafetensorError
from safetensors.numpy import load_file, save_file
from torch import nn

from egosim.model.checkpoint import refuse_pickle
from egosim.pipeline.stage import ConfigError

MANO_FILE = "mano.safetensors"  # the converted model's name in a regressor weights folder
NUM_MANO_JOINTS = 16  # wrist + 15 finger joints
FINGERTIP_VERTICES = (744, 320, 443, 554, 671)  # thumb, index, middle, ring, little (official)
# egosim joint k is MANO joint MANO_TO_EGOSIM[k] (16..20: the fingertip vertices above)
MANO_TO_EGOSIM = (0, 13, 14, 15, 16, 1, 2, 3, 17, 4, 5, 6, 18, 10, 11, 12, 19, 7, 8, 9, 20)
MANO_PARENTS = (-1, 0, 1, 2, 0, 4, 5, 0, 7, 8, 0, 10, 11, 0, 13, 14)  # the official tree
REQUIRED_ARRAYS = ("v_template", "shapedirs", "posedirs", "J_regressor", "weights")


class ManoFileError(ConfigError):
    """A MANO arrays file is missing, unreadable or inconsistent; the message names it."""


def parents_from_arrays(arrays: Mapping[str, np.ndarray]) -> np.ndarray:
    """The ``(J,)`` parent indices (root: -1) from ``parents`` or MANO's ``kintree_table``."""
    if "parents" in arrays:
        parents = np.asarray(arrays["parents"]).astype(np.int64).reshape(-1)
    elif "kintree_table" in arrays:
        table = np.asarray(arrays["kintree_table"]).astype(np.int64)
        if table.ndim != 2 or table.shape[0] != 2:
            raise ManoFileError(f"kintree_table must be (2, J), got {table.shape}")
        parents = table[0].copy()  # the official file stores the root's parent as 2**32 - 1
    else:
        raise ManoFileError("needs 'parents' or 'kintree_table'")
    parents[0] = -1
    return parents


def check_mano_arrays(arrays: Mapping[str, np.ndarray]) -> list[str]:
    """Problems (empty when consistent) with a MANO arrays mapping (layout: module docstring)."""
    missing = [k for k in REQUIRED_ARRAYS if k not in arrays]
    if missing:
        return [f"missing arrays {missing}"]
    try:
        parents = parents_from_arrays(arrays)
    except ManoFileError as exc:
        return [str(exc)]
    v, j = np.shape(arrays["v_template"])[0], len(parents)
    problems = []
    shapes = {
        "v_template": (v, 3),
        "J_regressor": (j, v),
        "weights": (v, j),
        "posedirs": (v, 3, 9 * (j - 1)),
    }
    for key, shape in shapes.items():
        if np.shape(arrays[key]) != shape:
            problems.append(f"{key} shape {np.shape(arrays[key])} != {shape}")
    sd = np.shape(arrays["shapedirs"])
    if len(sd) != 3 or sd[:2] != (v, 3):
        problems.append(f"shapedirs shape {sd} != ({v}, 3, B)")
    if any(not 0 <= p < i for i, p in enumerate(parents) if i > 0):
        problems.append(f"parents must list each joint after its parent, got {parents.tolist()}")
    tips = np.asarray(arrays.get("tip_vertices", FINGERTIP_VERTICES))
    if tips.shape != (5,) or tips.min() < 0 or tips.max() >= v:
        problems.append(f"tip_vertices must be 5 vertex indices below {v}, got {tips.tolist()}")
    if j != NUM_MANO_JOINTS:
        problems.append(f"MANO has {NUM_MANO_JOINTS} joints, the file has {j}")
    if "hands_components" in arrays and np.shape(arrays["hands_components"])[1:] != (45,):
        problems.append(f"hands_components shape {np.shape(arrays['hands_components'])}")
    if "hands_mean" in arrays and np.shape(arrays["hands_mean"]) != (45,):
        problems.append(f"hands_mean shape {np.shape(arrays['hands_mean'])} != (45,)")
    for key, value in arrays.items():
        if np.issubdtype(np.asarray(value).dtype, np.floating) and not np.isfinite(value).all():
            problems.append(f"{key} has non-finite values")
    return problems


def save_mano_arrays(arrays: Mapping[str, np.ndarray], path: str | Path) -> None:
    """Write MANO ``arrays`` (checked) as a safetensors file: floats as float64, ints int64."""
    problems = check_mano_arrays(arrays)
    if problems:
        raise ManoFileError(f"{path}: " + "; ".join(problems))
    out = {}
    for key, value in arrays.items():
        value = np.asarray(value)
        kind = np.float64 if np.issubdtype(value.dtype, np.floating) else np.int64
        out[key] = np.ascontiguousarray(value.astype(kind))
    save_file(out, str(path))


def load_mano_arrays(path: str | Path) -> dict[str, np.ndarray]:
    """Read and check a MANO safetensors file; :class:`ManoFileError` names what is wrong."""
    path = Path(path)
    if not path.is_file():
        raise ManoFileError(
            f"{path}: no MANO file (convert the licensed MANO_RIGHT.pkl with "
            "`egosim hands convert-mano MANO_RIGHT.pkl --out DIR`)"
        )
    refuse_pickle(path)  # the official .pkl itself is never loaded
    try:
        arrays = load_file(str(path))
    except (SafetensorError, OSError) as exc:
        raise ManoFileError(f"{path}: not safetensors ({exc})") from exc
    problems = check_mano_arrays(arrays)
    if problems:
        raise ManoFileError(f"{path}: " + "; ".join(problems))
    return arrays


def axis_angle_to_matrix(axis_angle: torch.Tensor) -> torch.Tensor:
    """Rodrigues: rotation vectors ``w (..., 3)`` (radians) -> matrices ``(..., 3, 3)``,
    ``I + sin(t)/t [w]x + (1 - cos t)/t^2 [w]x^2`` with ``t = |w|`` (series below 1e-4 rad)."""
    angle = torch.linalg.vector_norm(axis_angle, dim=-1)[..., None, None]  # (..., 1, 1)
    small = angle < 1e-4
    safe = torch.where(small, torch.ones_like(angle), angle)
    sq = angle * angle
    a = torch.where(small, 1.0 - sq / 6.0, torch.sin(safe) / safe)  # sin(t) / t
    b = torch.where(small, 0.5 - sq / 24.0, (1.0 - torch.cos(safe)) / (safe * safe))
    x, y, z = axis_angle.unbind(-1)
    zero = torch.zeros_like(x)
    k = torch.stack([zero, -z, y, z, zero, -x, -y, x, zero], dim=-1)  # (..., 9)
    k = k.reshape(*axis_angle.shape[:-1], 3, 3)  # (..., 3, 3) cross-product matrix of w
    eye = torch.eye(3, dtype=axis_angle.dtype, device=axis_angle.device)
    return eye + a * k + b * (k @ k)  # (..., 3, 3)


def rotation_6d_to_matrix(x: torch.Tensor) -> torch.Tensor:
    """HaMeR's 6D rotations ``(..., 6)`` -> matrices ``(..., 3, 3)``: Gram-Schmidt on the two
    3-vectors ``x[..., :3]`` and ``x[..., 3:]``, which become the first two columns."""
    a1, a2 = x[..., :3], x[..., 3:]
    b1 = nn.functional.normalize(a1, dim=-1)
    b2 = nn.functional.normalize(a2 - (b1 * a2).sum(-1, keepdim=True) * b1, dim=-1)
    b3 = torch.linalg.cross(b1, b2, dim=-1)
    return torch.stack([b1, b2, b3], dim=-1)  # columns b1, b2, b3


class ManoLayer(nn.Module):
    """MANO (right hand): ``(rotations (N, 16, 3, 3), betas (N, B))`` -> vertices and the 21
    joints in egosim's order (formulas in the module docstring); buffers in ``dtype``."""

    def __init__(
        self, arrays: Mapping[str, np.ndarray], dtype: torch.dtype = torch.float32
    ) -> None:
        super().__init__()
        problems = check_mano_arrays(arrays)
        if problems:
            raise ManoFileError("; ".join(problems))

        def buffer(key: str, value: np.ndarray) -> None:
            tensor = torch.as_tensor(np.asarray(value, dtype=np.float64)).to(dtype)
            self.register_buffer(key, tensor, persistent=False)  # saved in its own file

        for key in REQUIRED_ARRAYS:
            buffer(key, arrays[key])
        self.num_betas = int(self.shapedirs.shape[2])
        self.parents = tuple(int(p) for p in parents_from_arrays(arrays))
        tips = np.asarray(arrays.get("tip_vertices", FINGERTIP_VERTICES), dtype=np.int64)
        self.register_buffer("tip_vertices", torch.as_tensor(tips), persistent=False)
        self.has_pca = "hands_components" in arrays
        if self.has_pca:
            buffer("hands_components", arrays["hands_components"])
        buffer("hands_mean", arrays.get("hands_mean", np.zeros(45)))

    def hand_pose_from_pca(
        self, coeffs: torch.Tensor, flat_hand_mean: bool = False
    ) -> torch.Tensor:
        """The 15 finger rotation vectors ``(N, 45)`` from PCA ``coeffs (N, K)`` (MANO's
        ``hands_components``), plus ``hands_mean`` unless ``flat_hand_mean``."""
        if not self.has_pca:
            raise ManoFileError("this MANO file has no hands_components (PCA hand pose)")
        pose = coeffs @ self.hands_components[: coeffs.shape[-1]]  # (N, 45)
        return pose if flat_hand_mean else pose + self.hands_mean

    def rotations_from_axis_angle(
        self, global_orient: torch.Tensor, hand_pose: torch.Tensor
    ) -> torch.Tensor:
        """``(N, 16, 3, 3)`` from the wrist's ``global_orient (N, 3)`` and ``hand_pose (N, 45)``
        rotation vectors (relative to the flat hand; add ``hands_mean`` for MANO's mean pose)."""
        pose = torch.cat([global_orient, hand_pose], dim=-1).reshape(-1, NUM_MANO_JOINTS, 3)
        return axis_angle_to_matrix(pose)

    def forward(
        self, rotations: torch.Tensor, betas: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """``rotations (N, 16, 3, 3)``, ``betas (N, B)`` -> ``(vertices (N, V, 3), joints (N,
        21, 3))`` in the model's frame (the root joint's rest position is not moved)."""
        n = rotations.shape[0]
        dtype = self.v_template.dtype
        rotations, betas = rotations.to(dtype), betas.to(dtype)
        v_shaped = self.v_template + torch.einsum("vcb,nb->nvc", self.shapedirs, betas)
        rest = torch.einsum("jv,nvc->njc", self.J_regressor, v_shaped)  # (N, 16, 3)
        eye = torch.eye(3, dtype=dtype, device=rotations.device)
        pose_feature = (rotations[:, 1:] - eye).reshape(n, -1)  # (N, 135)
        v_posed = v_shaped + torch.einsum("vcp,np->nvc", self.posedirs, pose_feature)
        world = self._chain(rotations, rest)  # (N, 16, 4, 4)
        posed_joints = world[:, :, :3, 3]  # (N, 16, 3)
        # Skinning transforms: each joint's world transform after undoing its rest position.
        skin = world.clone()
        skin[:, :, :3, 3] = posed_joints - (world[:, :, :3, :3] @ rest[..., None])[..., 0]
        blend = torch.einsum("vj,njab->nvab", self.weights, skin)  # (N, V, 4, 4)
        vertices = (blend[..., :3, :3] @ v_posed[..., None])[..., 0] + blend[..., :3, 3]
        tips = vertices[:, self.tip_vertices]  # (N, 5, 3)
        joints = torch.cat([posed_joints, tips], dim=1)[:, list(MANO_TO_EGOSIM)]  # (N, 21, 3)
        return vertices, joints

    def _chain(self, rotations: torch.Tensor, rest: torch.Tensor) -> torch.Tensor:
        """World transforms ``(N, J, 4, 4)`` of the joints along the kinematic tree."""
        n = rotations.shape[0]
        world = []
        for j, parent in enumerate(self.parents):
            local = torch.zeros(n, 4, 4, dtype=rotations.dtype, device=rotations.device)
            local[:, :3, :3] = rotations[:, j]
            local[:, :3, 3] = rest[:, j] - (rest[:, parent] if parent >= 0 else 0.0)
            local[:, 3, 3] = 1.0
            world.append(local if parent < 0 else world[parent] @ local)
        return torch.stack(world, dim=1)


def load_mano_layer(path: str | Path, dtype: torch.dtype = torch.float32) -> ManoLayer:
    """A :class:`ManoLayer` (buffers in ``dtype``) from a MANO safetensors file."""
    return ManoLayer(load_mano_arrays(path), dtype)


MIRROR_X = np.diag([-1.0, 1.0, 1.0])  # (3, 3) a left hand is a right hand mirrored across x
FLIP_AXIS_ANGLE = np.array([1.0, -1.0, -1.0])  # M R(w) M = R(w * FLIP_AXIS_ANGLE), M = MIRROR_X


def place_mano_parameters(
    rotations_cam: np.ndarray,
    root_cam: np.ndarray,
    translation_cam: np.ndarray,
    world_from_cam: np.ndarray,
    left: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A regressed MANO fit as world parameters ``(global_orient (N, 3), hand_pose (N, 45),
    transl (N, 3))`` (rotation vectors, radians; metres) for :func:`hand_joints_from_params`.

    The network fits the right-hand model to a crop, mirrored for a left hand, in the camera's
    axes: camera joints ``J_c = M_s MANO(R, betas) + T`` with ``M_s`` = :data:`MIRROR_X` for a left
    hand, else I; ``rotations_cam (N, 16, 3, 3)`` are ``R``, ``root_cam (N, 3)`` is ``M_s J0``
    (MANO's root joint, which no rotation moves) and ``translation_cam (N, 3)`` is ``T``. With
    ``MANO(R0, ...) = R0 (MANO(I, ...) - J0) + J0`` and ``world_from_cam (N, 4, 4) = [Rwc | twc]``
    the world joints are ``M_s MANO(R0', R1..15', betas) + transl`` for ``R0' = M_s Rwc M_s R0``,
    ``Rj' = Rj``, ``transl = Rwc (M_s J0 + T) + twc - M_s J0``; a left hand's parameters are then
    stored in the mirrored (left) model's convention, each rotation ``M_s R M_s`` (HaMeR's
    ``(x, -y, -z)`` flip of a rotation vector)."""
    from scipy.spatial.transform import Rotation

    rot = np.asarray(rotations_cam, dtype=np.float64)  # (N, 16, 3, 3)
    n = rot.shape[0]
    mirror = np.where(np.asarray(left, dtype=bool)[:, None, None], MIRROR_X, np.eye(3))  # (N,3,3)
    r_wc = np.asarray(world_from_cam, dtype=np.float64)[:, :3, :3]  # (N, 3, 3)
    t_wc = np.asarray(world_from_cam, dtype=np.float64)[:, :3, 3]  # (N, 3)
    world = rot.copy()  # (N, 16, 3, 3) in the stored (side's own) convention
    world[:, 0] = r_wc @ mirror @ rot[:, 0] @ mirror  # = M_s R0' M_s
    world[:, 1:] = mirror[:, None] @ rot[:, 1:] @ mirror[:, None]
    vectors = Rotation.from_matrix(world.reshape(-1, 3, 3)).as_rotvec().reshape(n, 16, 3)
    root = np.asarray(root_cam, dtype=np.float64)  # (N, 3)
    transl = (r_wc @ (root + np.asarray(translation_cam, np.float64))[..., None])[..., 0]
    transl = transl + t_wc - root  # (N, 3)
    return vectors[:, 0], vectors[:, 1:].reshape(n, 45), transl


def hand_joints_from_params(
    layer: ManoLayer,
    global_orient: np.ndarray,
    hand_pose: np.ndarray,
    betas: np.ndarray,
    transl: np.ndarray,
    left: np.ndarray,
) -> np.ndarray:
    """The 21 joints ``(N, 21, 3)`` (egosim order) of MANO parameters as the ``hands`` shard
    stores them: ``global_orient (N, 3)`` and ``hand_pose (N, 45)`` rotation vectors, ``betas
    (N, B)``, ``transl (N, 3)``, ``left (N,)``. A right hand is ``MANO(...) + transl``; a left
    hand is the mirrored model, ``MIRROR_X MANO(flip(global_orient), flip(hand_pose), betas) +
    transl`` with ``flip`` = :data:`FLIP_AXIS_ANGLE` per rotation vector."""
    left = np.asarray(left, dtype=bool)  # (N,)
    flip = np.where(left[:, None], FLIP_AXIS_ANGLE, 1.0)  # (N, 3)
    orient = np.asarray(global_orient, np.float64) * flip  # (N, 3)
    pose = np.asarray(hand_pose, np.float64).reshape(-1, 15, 3) * flip[:, None]  # (N, 15, 3)
    dtype = layer.v_template.dtype
    rotations = layer.rotations_from_axis_angle(
        torch.as_tensor(orient, dtype=dtype), torch.as_tensor(pose.reshape(-1, 45), dtype=dtype)
    )  # (N, 16, 3, 3)
    with torch.no_grad():
        _, joints = layer(rotations, torch.as_tensor(np.asarray(betas, np.float64), dtype=dtype))
    joints = joints.double().cpu().numpy()  # (N, 21, 3)
    joints[left, :, 0] *= -1.0
    return joints + np.asarray(transl, np.float64)[:, None]
