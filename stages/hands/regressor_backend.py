"""Backend ``regressor``: a learned hand regressor (HaMeR / WiLoR style) from local weights.

For one clip:

1. **Detect**: square boxes around each hand, with its side, from the default ``mediapipe``
   backend's tracked and side-assigned 2D landmarks (``boxes="mediapipe"``; its scene check
   drops the same false hands first: the EgoDex portrait variant's curtain fold), or from the clip's
   own joint labels projected with its camera (``boxes="given"``: the regressor alone, evaluated
   on true boxes). A box is centred on the landmarks' bounding box, its side ``box_scale`` times
   the larger of its width (over the seen aspect, below) and height (HaMeR's rescale of
   keypoint boxes and ``expand_to_aspect_ratio``).
2. **Crop**: each box is resampled to an ``image_size`` square; left hands are mirrored first,
   since the network (like HaMeR's MANO head) models right hands only. ``crop_columns`` are
   then cut from each side (HaMeR's ViT sees the middle 192 of 256 columns: the seen aspect).
3. **Regress** (:class:`HandRegressor`): a ViT backbone over the crop's patches, then one of
   two heads. Head ``joints``: mean-pooled tokens, an MLP that predicts 21 joints in metres
   relative to the wrist (joint order of the clip labels, MediaPipe / OpenPose) and a
   weak-perspective camera ``(s, tx, ty)``. Head ``mano`` (:class:`ManoHead`, HaMeR's): a
   transformer decoder whose one token cross-attends to the image tokens and reads out MANO's
   16 rotations (6D), shape and the camera; the MANO layer
   (:class:`~egosim.stages.hands.mano.ManoLayer`, from the folder's ``mano.safetensors``)
   turns them into the 21 joints in MANO's frame, placed by the camera at MANO's origin
   instead of the wrist. Either way the joints are in the camera's axes (OpenCV: x right, y
   down, z forward): as in HaMeR, the crop is not rotated to face the hand.
4. **Place** (:func:`full_perspective_translation`): the weak-perspective camera says that a
   wrist-relative point ``X`` appears at the crop-normalised coordinate
   ``n = s * (X_xy + (tx, ty))``, where ``n`` runs over ``[-1, 1]`` across the box; in full-image
   pixels ``u = c_u + n_x * b / 2`` for a box of side ``b`` pixels centred at ``(c_u, c_v)``. A
   pinhole ``(fx, fy, cx, cy)`` with the wrist at camera translation ``T`` maps a point near the
   wrist (``|X| << T_z``) to ``u = fx * (X_x + T_x) / T_z + cx``. Equal pixels per metre give
   ``s * b / 2 = f / T_z``, so ``T_z = 2 f / (s b)`` (``f`` the mean of ``fx`` and ``fy``), and
   equal wrist pixels give ``T_x = T_z * (c_u + s * tx * b / 2 - cx) / fx`` (and ``T_y`` with
   ``c_v, ty, cy, fy``). With ``fx = fy`` this is HaMeR's ``cam_crop_to_full``:
   ``T_x = tx + 2 (c_u - cx) / (s b)``; here ``f, cx, cy`` are the clip's intrinsics, not a
   guessed focal at the image centre, so the depth is metric if the predicted hand size is.
   Mirroring a left hand's crop negates ``n_x``, so its joints' x and its ``tx`` are negated.
   Then to world with ``world_from_cam``.

Weights are a local folder with ``config.json`` (:class:`RegressorSpec` fields),
``model.safetensors`` (the state dict of :class:`HandRegressor`) and, for head ``mano``,
``mano.safetensors`` (MANO's arrays); pickled checkpoints are refused before anything is
unpickled. :func:`save_regressor` writes the first two. A released HaMeR checkpoint (ViTPose
ViT-H on 256 x 192 crops, the MANO head) becomes such a folder with ``egosim hands
convert-hamer`` (:mod:`egosim.stages.hands.convert_checkpoint`) and the licensed
``MANO_RIGHT.pkl`` its ``mano.safetensors`` with ``egosim hands convert-mano``
(:mod:`egosim.stages.hands.convert_mano`); neither is unpickled. WiLoR's refinement network is
not implemented. The backbone's parameter names follow timm/ViTPose (``patch_embed.proj``,
``blocks.N.attn.qkv``, ``blocks.N.mlp.fc1``) and the MANO head's HaMeR's. torch is imported by
this module; the stage imports it only when this backend is chosen.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
from pathlib import Path
from typing import Literal

import cv2
import numpy as np
import torch
from safetensors import SafetensorError
from safetensors.torch import load_file, save_file
from torch import nn

from egosim.model.checkpoint import refuse_pickle
from egosim.pipeline.geometry import project_world_points, transform_points
from egosim.pipeline.records import LEFT, NUM_HAND_JOINTS, RIGHT, Clip
from egosim.pipeline.stage import ConfigError
from egosim.stages.hands.filters import Detections
from egosim.stages.hands.given import NoHandLabelsError
from egosim.stages.hands.mano import (
    MANO_FILE,
    NUM_MANO_JOINTS,
    ManoLayer,
    load_mano_layer,
    place_mano_parameters,
    rotation_6d_to_matrix,
)
from egosim.stages.hands.mediapipe_backend import (
    MediaPipeParams,
    checked_side_landmarks,
    detect_landmarks,
)

CONFIG_FILE = "config.json"  # architecture and preprocessing of a weights folder
WEIGHTS_FILE = "model.safetensors"  # the state dict of HandRegressor
ARCHITECTURE = "egosim-hand-regressor"  # the ``architecture`` value config.json must hold
BATCH_SIZE = 32  # crops per forward pass
PICKLE_SUFFIXES = (".bin", ".pt", ".pth", ".ckpt", ".pkl")  # torch.save checkpoints, refused


class RegressorWeightsError(ConfigError):
    """A regressor weights folder is missing, incomplete or does not match its config."""


@dataclasses.dataclass(frozen=True)
class RegressorSpec:
    """Architecture and preprocessing of a :class:`HandRegressor` (``config.json``)."""

    image_size: int = 256  # square crop side in pixels
    patch_size: int = 16  # ViT patch side in pixels; divides image_size
    hidden_size: int = 768  # token width
    num_layers: int = 12  # transformer blocks
    num_heads: int = 12  # attention heads; divides hidden_size
    mlp_ratio: float = 4.0  # MLP width over hidden_size in each block
    head_size: int = 1024  # hidden width of the joint/camera head
    box_scale: float = 2.0  # crop side over the larger side of the landmarks' box
    # columns cut from each side of the crop before the backbone (HaMeR: 32 of 256, 192 wide)
    crop_columns: int = 0
    patch_padding: int = 0  # zero padding of the patch convolution (ViTPose/HaMeR: 2)
    # the head: "joints" (21 wrist-relative joints) or "mano" (HaMeR's MANO parameter decoder
    # with the MANO layer of the folder's mano.safetensors)
    head: Literal["joints", "mano"] = "joints"
    decoder_dim: int = 1024  # head "mano": token width of the transformer decoder
    decoder_depth: int = 6  # head "mano": decoder layers (self-, cross-attention, MLP)
    decoder_heads: int = 8  # head "mano": attention heads
    decoder_dim_head: int = 64  # head "mano": width of one head
    decoder_mlp: int = 1024  # head "mano": hidden width of each MLP
    num_betas: int = 10  # head "mano": MANO shape coefficients predicted
    image_mean: tuple[float, float, float] = (0.485, 0.456, 0.406)  # RGB in [0, 1] (ImageNet)
    image_std: tuple[float, float, float] = (0.229, 0.224, 0.225)  # RGB in [0, 1] (ImageNet)

    def __post_init__(self) -> None:
        problems = []
        if self.image_size <= 0 or self.patch_size <= 0 or self.image_size % self.patch_size:
            problems.append(
                f"patch_size must divide image_size, got {self.patch_size} and {self.image_size}"
            )
        if self.num_heads <= 0 or self.hidden_size % self.num_heads:
            problems.append(
                f"num_heads must divide hidden_size, got {self.num_heads} and {self.hidden_size}"
            )
        if self.num_layers < 1 or self.head_size < 1 or self.mlp_ratio <= 0:
            problems.append(
                f"num_layers, head_size, mlp_ratio must be positive, got {self.num_layers}, "
                f"{self.head_size}, {self.mlp_ratio}"
            )
        width = self.image_size - 2 * self.crop_columns
        if self.crop_columns < 0 or width < self.patch_size:
            problems.append(f"crop_columns {self.crop_columns} leaves too narrow a crop")
        if self.patch_padding < 0:
            problems.append(f"patch_padding must be >= 0, got {self.patch_padding}")
        if self.head not in ("joints", "mano"):
            problems.append(f"head must be 'joints' or 'mano', got {self.head!r}")
        decoder = (self.decoder_dim, self.decoder_depth, self.decoder_heads, self.decoder_dim_head)
        if min(*decoder, self.decoder_mlp, self.num_betas) < 1:
            problems.append("decoder sizes and num_betas must be positive")
        if not self.box_scale >= 1.0:
            problems.append(f"box_scale must be >= 1, got {self.box_scale}")
        if len(self.image_mean) != 3 or len(self.image_std) != 3 or min(self.image_std) <= 0:
            problems.append(f"image_mean/std must be 3 values (std > 0), got {self.image_std}")
        if problems:
            raise RegressorWeightsError("; ".join(problems))

    @property
    def grid(self) -> tuple[int, int]:
        """Patch rows and columns the backbone sees."""

        def cells(n: int) -> int:
            return (n + 2 * self.patch_padding - self.patch_size) // self.patch_size + 1

        return cells(self.image_size), cells(self.image_size - 2 * self.crop_columns)

    @property
    def visible_aspect(self) -> float:
        """Width over height of the part of the square crop the backbone sees."""
        return (self.image_size - 2 * self.crop_columns) / self.image_size


class Attention(nn.Module):
    """Multi-head self-attention with a fused ``qkv`` projection (timm naming)."""

    def __init__(self, dim: int, num_heads: int) -> None:
        super().__init__()
        self.num_heads = num_heads
        self.qkv = nn.Linear(dim, 3 * dim)
        self.proj = nn.Linear(dim, dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """``x (B, N, C)`` -> ``(B, N, C)``."""
        b, n, c = x.shape
        qkv = self.qkv(x).reshape(b, n, 3, self.num_heads, c // self.num_heads)  # (B, N, 3, H, D)
        q, k, v = qkv.permute(2, 0, 3, 1, 4)  # each (B, H, N, D)
        out = nn.functional.scaled_dot_product_attention(q, k, v)  # (B, H, N, D)
        return self.proj(out.transpose(1, 2).reshape(b, n, c))  # (B, N, C)


class Mlp(nn.Module):
    """Two linear layers with a GELU between (timm naming)."""

    def __init__(self, dim: int, hidden: int) -> None:
        super().__init__()
        self.fc1 = nn.Linear(dim, hidden)
        self.fc2 = nn.Linear(hidden, dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """``x (B, N, C)`` -> ``(B, N, C)``."""
        return self.fc2(nn.functional.gelu(self.fc1(x)))


class Block(nn.Module):
    """Pre-norm transformer block."""

    def __init__(self, dim: int, num_heads: int, mlp_ratio: float) -> None:
        super().__init__()
        self.norm1 = nn.LayerNorm(dim, eps=1e-6)
        self.attn = Attention(dim, num_heads)
        self.norm2 = nn.LayerNorm(dim, eps=1e-6)
        self.mlp = Mlp(dim, int(dim * mlp_ratio))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """``x (B, N, C)`` -> ``(B, N, C)``."""
        x = x + self.attn(self.norm1(x))
        return x + self.mlp(self.norm2(x))


class DecoderAttention(nn.Module):
    """Multi-head attention of HaMeR's pose transformer: self-attention (``to_qkv``) or
    cross-attention to a context (``to_q``, ``to_kv``); projections without bias."""

    def __init__(self, dim: int, heads: int, dim_head: int, context_dim: int | None) -> None:
        super().__init__()
        inner = heads * dim_head
        self.heads = heads
        if context_dim is None:
            self.to_qkv = nn.Linear(dim, 3 * inner, bias=False)
        else:
            self.to_q = nn.Linear(dim, inner, bias=False)
            self.to_kv = nn.Linear(context_dim, 2 * inner, bias=False)
        self.to_out = nn.Sequential(nn.Linear(inner, dim))

    def forward(self, x: torch.Tensor, context: torch.Tensor | None = None) -> torch.Tensor:
        """``x (B, N, dim)``, ``context (B, M, context_dim)`` -> ``(B, N, dim)``."""
        if context is None:
            q, k, v = self.to_qkv(x).chunk(3, dim=-1)  # each (B, N, inner)
        else:
            q = self.to_q(x)  # (B, N, inner)
            k, v = self.to_kv(context).chunk(2, dim=-1)  # each (B, M, inner)

        def split(t: torch.Tensor) -> torch.Tensor:  # (B, L, inner) -> (B, H, L, D)
            return t.reshape(t.shape[0], t.shape[1], self.heads, -1).transpose(1, 2)

        out = nn.functional.scaled_dot_product_attention(split(q), split(k), split(v))
        return self.to_out(out.transpose(1, 2).reshape(x.shape[0], x.shape[1], -1))


class PreNorm(nn.Module):
    """LayerNorm, then ``fn`` (HaMeR's ``PreNorm``)."""

    def __init__(self, dim: int, fn: nn.Module) -> None:
        super().__init__()
        self.norm = nn.LayerNorm(dim)
        self.fn = fn

    def forward(self, x: torch.Tensor, **kwargs: torch.Tensor) -> torch.Tensor:
        """``fn(norm(x), **kwargs)``."""
        return self.fn(self.norm(x), **kwargs)


class FeedForward(nn.Module):
    """Linear, GELU, (dropout slot), linear: HaMeR's ``FeedForward`` (``net.0``, ``net.3``)."""

    def __init__(self, dim: int, hidden: int) -> None:
        super().__init__()
        self.net = nn.Sequential(
            nn.Linear(dim, hidden), nn.GELU(), nn.Identity(), nn.Linear(hidden, dim)
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """``x (B, N, dim)`` -> ``(B, N, dim)``."""
        return self.net(x)


class TokenDecoder(nn.Module):
    """HaMeR's ``TransformerDecoder``: one token, embedded, through ``depth`` layers of
    self-attention, cross-attention to the image tokens and an MLP (pre-norm, residual)."""

    def __init__(self, spec: RegressorSpec) -> None:
        super().__init__()
        dim = spec.decoder_dim
        self.to_token_embedding = nn.Linear(1, dim)
        self.pos_embedding = nn.Parameter(torch.zeros(1, 1, dim))
        self.transformer = nn.Module()
        self.transformer.layers = nn.ModuleList(
            nn.ModuleList(
                [
                    PreNorm(
                        dim, DecoderAttention(dim, spec.decoder_heads, spec.decoder_dim_head, None)
                    ),
                    PreNorm(
                        dim,
                        DecoderAttention(
                            dim, spec.decoder_heads, spec.decoder_dim_head, spec.hidden_size
                        ),
                    ),
                    PreNorm(dim, FeedForward(dim, spec.decoder_mlp)),
                ]
            )
            for _ in range(spec.decoder_depth)
        )

    def forward(self, context: torch.Tensor) -> torch.Tensor:
        """Image tokens ``context (B, N, C)`` -> the decoded token ``(B, dim)``."""
        token = torch.zeros(context.shape[0], 1, 1, dtype=context.dtype, device=context.device)
        x = self.to_token_embedding(token) + self.pos_embedding  # (B, 1, dim)
        for self_attn, cross_attn, mlp in self.transformer.layers:
            x = self_attn(x) + x
            x = cross_attn(x, context=context) + x
            x = mlp(x) + x
        return x[:, 0]  # (B, dim)


class ManoHead(nn.Module):
    """HaMeR's ``MANOTransformerDecoderHead`` (one refinement step, zero input token): MANO
    pose as 6D rotations, shape and a weak-perspective camera, each an offset from its mean."""

    def __init__(self, spec: RegressorSpec) -> None:
        super().__init__()
        npose = 6 * NUM_MANO_JOINTS
        self.transformer = TokenDecoder(spec)
        self.decpose = nn.Linear(spec.decoder_dim, npose)
        self.decshape = nn.Linear(spec.decoder_dim, spec.num_betas)
        self.deccam = nn.Linear(spec.decoder_dim, 3)
        identity_6d = torch.tensor([1.0, 0.0, 0.0, 0.0, 1.0, 0.0])  # columns e_x, e_y
        self.register_buffer("init_hand_pose", identity_6d.repeat(NUM_MANO_JOINTS)[None])
        self.register_buffer("init_betas", torch.zeros(1, spec.num_betas))
        self.register_buffer("init_cam", torch.tensor([[0.9, 0.0, 0.0]]))  # HaMeR's mean camera
        for layer in (self.decpose, self.decshape, self.deccam):  # untrained: near the means
            nn.init.normal_(layer.weight, std=0.01)
            nn.init.zeros_(layer.bias)

    def forward(self, context: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Image tokens ``(B, N, C)`` -> ``(rotations (B, 16, 3, 3), betas (B, num_betas),
        cam (B, 3) = (s, tx, ty))``."""
        token = self.transformer(context)  # (B, dim)
        pose = self.decpose(token) + self.init_hand_pose  # (B, 96)
        betas = self.decshape(token) + self.init_betas  # (B, num_betas)
        cam = self.deccam(token) + self.init_cam  # (B, 3)
        rotations = rotation_6d_to_matrix(pose.reshape(-1, NUM_MANO_JOINTS, 6))  # (B, 16, 3, 3)
        return rotations, betas, cam


class HandRegressor(nn.Module):
    """ViT backbone plus a head: hand joints and a weak-perspective camera per crop.

    Head ``joints``: 21 wrist-relative joints. Head ``mano`` (needs ``mano``, the MANO layer):
    MANO pose and shape, whose joints (MANO's frame, placed by the camera at MANO's origin) the
    layer computes.
    """

    def __init__(self, spec: RegressorSpec, mano: ManoLayer | None = None) -> None:
        super().__init__()
        self.spec = spec
        c = spec.hidden_size
        rows, cols = spec.grid
        self.patch_embed = nn.Module()
        self.patch_embed.proj = nn.Conv2d(
            3, c, spec.patch_size, stride=spec.patch_size, padding=spec.patch_padding
        )
        self.pos_embed = nn.Parameter(torch.zeros(1, rows * cols, c))
        self.blocks = nn.ModuleList(
            Block(c, spec.num_heads, spec.mlp_ratio) for _ in range(spec.num_layers)
        )
        self.last_norm = nn.LayerNorm(c, eps=1e-6)
        nn.init.trunc_normal_(self.pos_embed, std=0.02)  # ViT's choice
        if spec.head == "mano":
            if mano is not None and mano.num_betas != spec.num_betas:
                raise RegressorWeightsError(
                    f"the MANO file has {mano.num_betas} shape coefficients, the head predicts "
                    f"{spec.num_betas}"
                )
            self.mano_head = ManoHead(spec)
            self.mano = mano  # its arrays are not in the state dict (their own file); None: no
            return  # forward (a converter only checks and saves the weights)
        self.head = nn.Sequential(nn.Linear(c, spec.head_size), nn.GELU())
        self.joints_out = nn.Linear(spec.head_size, NUM_HAND_JOINTS * 3)
        self.cam_out = nn.Linear(spec.head_size, 3)
        # Outputs are offsets from a mean hand and a mean camera, as HaMeR adds its head's output
        # to MANO's mean parameters and an initial camera (0.9, 0, 0): training sets the mean
        # hand (zeros here); the camera's scale starts at 0.9 of the box.
        self.register_buffer("mean_joints", torch.zeros(NUM_HAND_JOINTS, 3))
        self.register_buffer("mean_cam", torch.tensor([_softplus_inverse(0.9), 0.0, 0.0]))
        # Small output layers: an untrained model predicts near the means, not wild cameras.
        for layer in (self.joints_out, self.cam_out):
            nn.init.normal_(layer.weight, std=0.01)
            nn.init.zeros_(layer.bias)

    def features(self, crops: torch.Tensor) -> torch.Tensor:
        """``crops (B, 3, S, S)`` normalised -> image tokens ``(B, N, C)`` after the last norm."""
        if self.spec.crop_columns:
            crops = crops[..., self.spec.crop_columns : -self.spec.crop_columns]
        x = self.patch_embed.proj(crops)  # (B, C, rows, cols)
        x = x.flatten(2).transpose(1, 2) + self.pos_embed  # (B, N, C)
        for block in self.blocks:
            x = block(x)  # (B, N, C)
        return self.last_norm(x)

    def forward_mano(self, crops: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Head ``mano``: ``crops`` -> ``(rotations (B, 16, 3, 3), betas (B, K), cam (B, 3))``."""
        return self.mano_head(self.features(crops))

    def forward(self, crops: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``crops (B, 3, S, S)`` normalised -> ``(joints (B, 21, 3) metres, cam (B, 3) = (s,
        tx, ty))``; head ``joints``: wrist at 0 and ``s > 0``; head ``mano``: MANO's frame."""
        if self.spec.head == "mano":
            if self.mano is None:
                raise RegressorWeightsError("head 'mano' needs the MANO layer (mano.safetensors)")
            rotations, betas, cam = self.forward_mano(crops)
            _, joints = self.mano(rotations, betas)  # (B, 21, 3)
            return joints.to(cam.dtype), cam
        h = self.head(self.features(crops).mean(dim=1))  # (B, head_size)
        joints = self.joints_out(h).reshape(-1, NUM_HAND_JOINTS, 3) + self.mean_joints  # (B, 21, 3)
        joints = joints - joints[:, :1]  # (B, 21, 3) wrist at the origin
        raw = self.cam_out(h) + self.mean_cam  # (B, 3)
        scale = nn.functional.softplus(raw[:, :1])  # (B, 1) > 0: the hand is in front
        return joints, torch.cat([scale, raw[:, 1:]], dim=1)  # (B, 21, 3), (B, 3)


def _softplus_inverse(y: float) -> float:
    return math.log(math.expm1(y))


def save_regressor(model: HandRegressor, folder: str | Path) -> None:
    """Write ``model`` as a weights folder (``config.json`` + ``model.safetensors``)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    config = {"architecture": ARCHITECTURE, **dataclasses.asdict(model.spec)}
    (folder / CONFIG_FILE).write_text(json.dumps(config, indent=2) + "\n")
    state = {k: v.detach().cpu().contiguous() for k, v in model.state_dict().items()}
    save_file(state, folder / WEIGHTS_FILE)


def load_regressor(folder: str | Path, device: str = "cpu") -> HandRegressor:
    """Load a weights folder written by :func:`save_regressor` (eval mode, on ``device``).

    Raises :class:`RegressorWeightsError` when the folder or a file is missing or does not match
    the config, and :class:`~egosim.model.checkpoint.UnsafeCheckpointError` for a pickle.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise RegressorWeightsError(f"regressor_weights {str(folder)!r} is not a folder")
    if not (folder / WEIGHTS_FILE).is_file():
        pickles = sorted(p.name for p in folder.iterdir() if p.suffix in PICKLE_SUFFIXES)
        hint = (
            f"; {pickles} are pickles, which are never loaded (they can run code): a HaMeR "
            "checkpoint converts with `egosim hands convert-hamer CKPT --out FOLDER` (read as "
            "data, never unpickled)"
            if pickles
            else ""
        )
        raise RegressorWeightsError(
            f"regressor_weights {str(folder)!r} has no {WEIGHTS_FILE}{hint}"
        )
    if not (folder / CONFIG_FILE).is_file():
        raise RegressorWeightsError(f"regressor_weights {str(folder)!r} has no {CONFIG_FILE}")
    try:
        config = json.loads((folder / CONFIG_FILE).read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise RegressorWeightsError(f"{folder / CONFIG_FILE}: unreadable ({exc})") from exc
    arch = config.pop("architecture", None) if isinstance(config, dict) else None
    if arch != ARCHITECTURE:
        raise RegressorWeightsError(
            f"{folder / CONFIG_FILE}: architecture must be {ARCHITECTURE!r}, got {arch!r} "
            "(HaMeR checkpoints need converting: `egosim hands convert-hamer CKPT --out FOLDER`)"
        )
    known = {f.name for f in dataclasses.fields(RegressorSpec)}
    unknown = sorted(set(config) - known)
    if unknown:
        raise RegressorWeightsError(f"{folder / CONFIG_FILE}: unknown keys {unknown}")
    for key in ("image_mean", "image_std"):
        if key in config:
            config[key] = tuple(config[key])
    try:
        spec = RegressorSpec(**config)
    except TypeError as exc:
        raise RegressorWeightsError(f"{folder / CONFIG_FILE}: {exc}") from exc
    refuse_pickle(folder / WEIGHTS_FILE)  # before any parsing: a pickle can run code
    try:
        state = load_file(folder / WEIGHTS_FILE)
    except (SafetensorError, OSError) as exc:
        raise RegressorWeightsError(f"{folder / WEIGHTS_FILE}: not safetensors ({exc})") from exc
    mano = load_mano_layer(folder / MANO_FILE) if spec.head == "mano" else None
    model = HandRegressor(spec, mano)
    try:
        model.load_state_dict(state, strict=True)
    except RuntimeError as exc:
        raise RegressorWeightsError(
            f"{folder / WEIGHTS_FILE} does not match config: {exc}"
        ) from exc
    return model.to(device).eval()


@functools.lru_cache(maxsize=2)
def _cached_regressor(folder: str, device: str) -> HandRegressor:
    return load_regressor(folder, device)


def full_perspective_translation(
    cam: np.ndarray, box_centre: np.ndarray, box_size: np.ndarray, intrinsics: np.ndarray
) -> np.ndarray:
    """Wrist translations ``(N, 3)`` in the camera from weak-perspective ``cam (N, 3)``
    ``(s, tx, ty)`` of crops centred at ``box_centre (N, 2)`` pixels with side ``box_size (N,)``
    pixels, under ``intrinsics (4,)`` (derivation in the module docstring)."""
    fx, fy, cx, cy = np.asarray(intrinsics, dtype=np.float64)
    cam = np.asarray(cam, dtype=np.float64)
    s, tx, ty = cam[:, 0], cam[:, 1], cam[:, 2]  # each (N,)
    half = np.asarray(box_size, dtype=np.float64) / 2.0  # (N,)
    centre = np.asarray(box_centre, dtype=np.float64)  # (N, 2)
    tz = 0.5 * (fx + fy) / (s * half)  # (N,) metres
    u_root = centre[:, 0] + s * tx * half  # (N,) wrist pixel
    v_root = centre[:, 1] + s * ty * half  # (N,)
    return np.stack([tz * (u_root - cx) / fx, tz * (v_root - cy) / fy, tz], axis=-1)  # (N, 3)


def square_box(
    uv: np.ndarray, box_scale: float, aspect: float = 1.0
) -> tuple[np.ndarray, float] | None:
    """Centre ``(2,)`` and side (pixels) of the square box around ``uv (21, 2)`` landmarks;
    None when fewer than two are finite or they span no area. The landmarks' box is first
    widened to ``aspect`` (width / height of the part of the crop the network sees, as HaMeR's
    ``expand_to_aspect_ratio``), so its width fits the seen part: side = ``box_scale * max(w /
    aspect, h)``."""
    ok = np.all(np.isfinite(uv), axis=1)
    if ok.sum() < 2:
        return None
    lo, hi = uv[ok].min(axis=0), uv[ok].max(axis=0)  # (2,), (2,)
    width, height = hi - lo
    side = float(max(width / aspect, height)) * box_scale
    if not side > 0:
        return None
    return (lo + hi) / 2.0, side


def crop_hand(
    frame: np.ndarray, centre: np.ndarray, side: float, size: int, mirror: bool
) -> np.ndarray:
    """The square ``side``-pixel box at ``centre`` of ``frame (H, W, 3)`` resampled to
    ``(size, size, 3)`` (outside the frame: black), mirrored left-right if ``mirror``."""
    scale = size / side
    # Continuous pixel coordinates (centres at integer + 0.5) map as p = (u - (c - side/2)) *
    # scale; OpenCV's matrix maps pixel indices, hence the half-pixel terms.
    shift = (np.asarray(centre) - side / 2.0) * scale  # (2,)
    matrix = np.array(
        [
            [scale, 0.0, 0.5 * scale - 0.5 - shift[0]],
            [0.0, scale, 0.5 * scale - 0.5 - shift[1]],
        ]
    )  # (2, 3) crop index from frame index
    crop = cv2.warpAffine(
        frame, matrix, (size, size), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT
    )
    return crop[:, ::-1].copy() if mirror else crop


@dataclasses.dataclass(frozen=True)
class RegressorParams:
    """Knobs of the regressor backend (the stage's ``regressor_*`` fields)."""

    weights: str  # local weights folder (config.json + model.safetensors)
    device: str = "cpu"  # torch device of the network
    boxes: Literal["mediapipe", "given"] = "mediapipe"  # where hand boxes and sides come from
    mediapipe: MediaPipeParams = MediaPipeParams()  # noqa: RUF009 (frozen) boxes="mediapipe"


def hand_boxes(
    clip: Clip, boxes: str, mediapipe: MediaPipeParams
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """2D landmarks per side ``(T, 2, 21, 2)`` pixels, ``present (T, 2)`` and detector
    ``confidence (T, 2)`` from the default backend or the clip's labels. The default backend's
    are its 2D as :func:`~egosim.stages.hands.mediapipe_backend.hands_from_raw` has it, from the
    same function (:func:`~egosim.stages.hands.mediapipe_backend.checked_side_landmarks`):
    overlaps dropped, then the tracks that are part of the scene (unless
    ``mediapipe.scene_check`` is None), then sides, bridging and smoothing."""
    t = clip.num_frames
    if boxes == "mediapipe":  # the 2D landmarks only: the backend's 3D lift is not needed here
        # the default backend's own 2D chain (its scene check included): its false hands are
        # not boxed, and a filter added there is added here too
        raw = detect_landmarks(clip.frames, mediapipe)
        lm = checked_side_landmarks(raw, clip.width, mediapipe, clip.frames)[1]
        return lm.uv, lm.present.copy(), lm.confidence
    if clip.hand_joints is None:
        raise NoHandLabelsError("regressor_boxes 'given' needs the clip's hand_joints labels")
    if clip.world_from_cam is None:
        raise NoHandLabelsError("regressor_boxes 'given' needs camera poses to project labels")
    uv = np.stack(
        [
            project_world_points(clip.hand_joints[f], clip.world_from_cam[f], clip.intrinsics)[0]
            for f in range(t)
        ]
    )  # (T, 2, 21, 2)
    present = (
        np.asarray(clip.hand_valid, dtype=bool)
        if clip.hand_valid is not None
        else np.all(np.isfinite(clip.hand_joints), axis=(2, 3))
    )  # (T, 2)
    conf = (
        np.asarray(clip.hand_confidence, dtype=np.float64).mean(axis=2)
        if clip.hand_confidence is not None
        else np.ones((t, 2))
    )  # (T, 2)
    return uv, present, conf


def regress_hands(
    model: HandRegressor, crops: np.ndarray, device: str = "cpu"
) -> tuple[np.ndarray, np.ndarray]:
    """Run ``model`` on ``crops (N, S, S, 3)`` uint8 RGB: ``(joints (N, 21, 3), cam (N, 3))``."""
    joints, cams, _ = regress_hands_with_mano(model, crops, device)
    return joints, cams


def regress_hands_with_mano(
    model: HandRegressor, crops: np.ndarray, device: str = "cpu"
) -> tuple[np.ndarray, np.ndarray, tuple[np.ndarray, np.ndarray] | None]:
    """:func:`regress_hands` plus, for head ``mano``, the fit it came from: ``(rotations (N,
    16, 3, 3), betas (N, B))`` in the crop's (right-hand) model; None for head ``joints``."""
    spec = model.spec
    mean = torch.tensor(spec.image_mean, dtype=torch.float32).view(1, 3, 1, 1)
    std = torch.tensor(spec.image_std, dtype=torch.float32).view(1, 3, 1, 1)
    joints, cams, rotations, betas = [], [], [], []
    with torch.inference_mode():
        for i in range(0, len(crops), BATCH_SIZE):
            x = torch.from_numpy(crops[i : i + BATCH_SIZE]).permute(0, 3, 1, 2)  # (B, 3, S, S)
            x = ((x.float() / 255.0 - mean) / std).to(device)  # (B, 3, S, S)
            if spec.head == "mano" and model.mano is not None:
                r, b, c = model.forward_mano(x)  # (B, 16, 3, 3), (B, K), (B, 3)
                _, j = model.mano(r, b)  # (B, 21, 3): what forward returns
                rotations.append(r.double().cpu().numpy())
                betas.append(b.double().cpu().numpy())
            else:
                j, c = model(x)  # (B, 21, 3), (B, 3)
            joints.append(j.double().cpu().numpy())
            cams.append(c.double().cpu().numpy())
    mano = None
    if spec.head == "mano":
        mano = (
            (np.concatenate(rotations), np.concatenate(betas))
            if rotations
            else (np.zeros((0, 16, 3, 3)), np.zeros((0, spec.num_betas)))
        )
    if not joints:
        return np.zeros((0, NUM_HAND_JOINTS, 3)), np.zeros((0, 3)), mano
    return np.concatenate(joints), np.concatenate(cams), mano


def regressor_detections(clip: Clip, params: RegressorParams) -> Detections:
    """The stage's detections (``K = 2``, slot = side) of ``clip`` by the regressor.

    Joints are in world metres through the clip's ``world_from_cam`` (camera metres if None).
    """
    model = _cached_regressor(str(Path(params.weights).resolve()), params.device)
    size = model.spec.image_size
    t = clip.num_frames
    uv, found, det_conf = hand_boxes(clip, params.boxes, params.mediapipe)
    items, crops = [], []
    for f, s in zip(*np.nonzero(found), strict=True):
        box = square_box(uv[f, s], model.spec.box_scale, model.spec.visible_aspect)
        if box is None:
            continue
        centre, side = box
        items.append((f, s, centre, side))
        crops.append(crop_hand(clip.frames[f], centre, side, size, mirror=(s == LEFT)))
    stacked = np.stack(crops) if crops else np.zeros((0, size, size, 3), np.uint8)
    shapes, cams, fit = regress_hands_with_mano(model, stacked, params.device)  # (N, 21, 3)...
    left = np.array([s == LEFT for _, s, _, _ in items], dtype=bool)  # (N,)
    shapes[left, :, 0] *= -1.0  # a mirrored crop: mirror the hand back
    cams[left, 1] *= -1.0  # and its horizontal offset
    centres = np.array([c for _, _, c, _ in items]).reshape(-1, 2)  # (N, 2)
    box_sides = np.array([b for _, _, _, b in items], dtype=np.float64)  # (N,) pixels
    with np.errstate(divide="ignore", invalid="ignore"):  # s <= 0 (head mano): not in front
        roots = full_perspective_translation(cams, centres, box_sides, clip.intrinsics)  # (N, 3)

    joints = np.zeros((t, 2, NUM_HAND_JOINTS, 3))
    conf = np.zeros((t, 2, NUM_HAND_JOINTS))
    present = np.zeros((t, 2), dtype=bool)
    for n, (f, s, _, _) in enumerate(items):
        points_cam = shapes[n] + roots[n]  # (21, 3)
        if not (np.all(np.isfinite(points_cam)) and np.all(points_cam[:, 2] > 0)):
            continue  # a joint behind the camera: unusable
        joints[f, s] = (
            points_cam
            if clip.world_from_cam is None
            else transform_points(clip.world_from_cam[f], points_cam)
        )
        conf[f, s] = float(np.clip(det_conf[f, s], 0.0, 1.0))
        present[f, s] = True
    side = np.tile(np.array([LEFT, RIGHT]), (t, 1))  # (T, 2)
    mano = None if fit is None else _mano_per_slot(fit, items, shapes, roots, clip, present)
    return Detections(joints=joints, side=side, confidence=conf, present=present, mano=mano)


def _mano_per_slot(
    fit: tuple[np.ndarray, np.ndarray],
    items: list,
    shapes: np.ndarray,
    roots: np.ndarray,
    clip: Clip,
    present: np.ndarray,
) -> np.ndarray:
    """``(T, 2, 51 + B)`` world MANO parameters per frame and side (the layout of
    :data:`Detections.mano`) of the kept fits, NaN elsewhere (:func:`place_mano_parameters`;
    ``shapes (N, 21, 3)`` are already mirrored back for left hands, so ``shapes[:, 0]`` is the
    side's root joint)."""
    rotations, betas = fit  # (N, 16, 3, 3), (N, B)
    t = clip.num_frames
    out = np.full((t, 2, 51 + betas.shape[1]), np.nan)
    if not items:
        return out
    frames = np.array([f for f, _, _, _ in items])  # (N,)
    left = np.array([s == LEFT for _, s, _, _ in items], dtype=bool)  # (N,)
    poses = (
        np.tile(np.eye(4), (len(items), 1, 1))
        if clip.world_from_cam is None
        else np.asarray(clip.world_from_cam, dtype=np.float64)[frames]
    )  # (N, 4, 4)
    with np.errstate(invalid="ignore"):
        orient, pose, transl = place_mano_parameters(rotations, shapes[:, 0], roots, poses, left)
    for n, (f, s, _, _) in enumerate(items):
        if present[f, s]:
            out[f, s] = np.concatenate([orient[n], pose[n], transl[n], betas[n]])
    return out
