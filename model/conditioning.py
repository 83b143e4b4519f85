"""The 52-channel input layout, THE mask-packing function, and the training-sample record.

Channel layout of the denoiser input (dim 1), in this order (Wan-Fun-InP's 36 + skeleton):

====================  ========  ==============================================================
slice                 channels  content
====================  ========  ==============================================================
``NOISY`` 0:16        16        noisy target latent ``x_t``
``MASK`` 16:20        4         packed visibility mask (:func:`pack_mask`)
``SCENE`` 20:36       16        VAE latent of the scene video with unseen pixels set to 0
``SKELETON`` 36:52    16        VAE latent of the hand-skeleton video (new, zero-initialised)
====================  ========  ==============================================================

Mask polarity (defined only here): the channel value is **1 where the scene pixel is known
(observed, keep it) and 0 where the model must synthesise**. This equals Wan-Fun-InP's network
input ``1 - mask_condition`` (VideoX-Fun pipelines: ``mask_condition`` is 1 on the region to
inpaint, and ``mask_latents = resize_mask(1 - mask_condition, ...)``), so an all-ones channel is
DWM's "m = 1, everything known" identity mode. EgoSim's visibility mask has the same meaning
(1 = rendered from the point cloud), so it is packed as is.

Packing (as published in VideoX-Fun for Wan-Fun-InP): the pixel mask's first frame is repeated
4 times, the frames are grouped by 4, each group becomes the 4 channels of one latent frame, and
the result is resized to latent resolution with trilinear interpolation (``align_corners=False``;
the frame axis is not resampled because it already has the latent frame count).

First-frame conditioning: the (hand-free) first frame replaces frame 0 of the scene video and
frame 0 is marked fully known, which is how Wan-Fun-InP conditions on a start image.

Training samples come in two kinds: :class:`TrainingSample` (pixels, encoded on the fly) and
:class:`LatentSample` (precomputed by the ``encode`` stage); :func:`encode_batch` is the one seam
that turns either into an :class:`EncodedBatch`.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np
import torch
from torch.nn import functional as F  # noqa: N812 (the universal torch alias)

from egosim.model.errors import SampleError
from egosim.model.presets import LATENT_CHANNELS, MASK_CHANNELS

NOISY = slice(0, LATENT_CHANNELS)  # noisy target latent
MASK = slice(NOISY.stop, NOISY.stop + MASK_CHANNELS)  # packed visibility mask
SCENE = slice(MASK.stop, MASK.stop + LATENT_CHANNELS)  # scene-video latent
SKELETON = slice(SCENE.stop, SCENE.stop + LATENT_CHANNELS)  # skeleton-video latent
CONDITION = slice(MASK.start, SKELETON.stop)  # everything but the noisy latent
TEMPORAL_GROUP = 4  # pixel frames per latent frame


def latent_frames(num_frames: int) -> int:
    """Latent frame count for ``num_frames`` pixel frames (first alone, then groups of 4)."""
    if num_frames < 1 or (num_frames - 1) % TEMPORAL_GROUP:
        raise SampleError(f"frame count must be 1 + 4k, got {num_frames}")
    return 1 + (num_frames - 1) // TEMPORAL_GROUP


def fold_frames(x: torch.Tensor) -> torch.Tensor:
    """Stack each latent frame's 4 pixel frames into channels: (B,C,T,H,W) -> (B,4C,T',H,W).

    Frame 0 is repeated 4 times (it forms latent frame 0 alone); channel index = c * 4 + k for
    pixel frame k of the group. Shared by the mask packing and the packed (tiny) VAE.
    """
    b, c, t, h, w = x.shape
    tl = latent_frames(t)
    x = torch.cat([x[:, :, :1].expand(b, c, TEMPORAL_GROUP, h, w), x[:, :, 1:]], dim=2)
    # (B, C, 4*T', H, W) -> (B, C, T', 4, H, W) -> (B, C, 4, T', H, W) -> (B, 4C, T', H, W)
    x = x.reshape(b, c, tl, TEMPORAL_GROUP, h, w).transpose(2, 3)
    return x.reshape(b, c * TEMPORAL_GROUP, tl, h, w)


def unfold_frames(x: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`fold_frames`: (B,4C,T',H,W) -> (B,C,1+4(T'-1),H,W).

    Frame 0 is the mean of its 4 copies (exact when they are equal).
    """
    b, c4, tl, h, w = x.shape
    c = c4 // TEMPORAL_GROUP
    x = x.reshape(b, c, TEMPORAL_GROUP, tl, h, w).transpose(2, 3)  # (B, C, T', 4, H, W)
    first = x[:, :, 0].mean(dim=2, keepdim=True)  # (B, C, 1, H, W)
    rest = x[:, :, 1:].reshape(b, c, (tl - 1) * TEMPORAL_GROUP, h, w)  # (B, C, 4(T'-1), H, W)
    return torch.cat([first, rest], dim=2)


def pack_mask(visibility: torch.Tensor, latent_hw: tuple[int, int]) -> torch.Tensor:
    """THE mask function: pixel visibility (B,T,H,W) in {0,1} -> mask channels (B,4,T',h,w).

    1 = known pixel (keep), 0 = synthesise; see the module docstring for the published source.
    Training and sampling both call this; nothing else builds mask channels.
    """
    if visibility.ndim != 4:
        raise SampleError(f"visibility must be (B, T, H, W), got shape {tuple(visibility.shape)}")
    packed = fold_frames(visibility.float().unsqueeze(1))  # (B, 4, T', H, W)
    tl = packed.shape[2]
    return F.interpolate(packed, size=(tl, *latent_hw), mode="trilinear", align_corners=False)


def unpack_mask(packed: torch.Tensor, pixel_hw: tuple[int, int]) -> torch.Tensor:
    """Approximate inverse of :func:`pack_mask` (nearest upsampling): (B,4,T',h,w) -> (B,T,H,W).

    Exact for masks that are constant over latent cells; used by tests and previews.
    """
    tl = packed.shape[2]
    up = F.interpolate(packed, size=(tl, *pixel_hw), mode="nearest")  # (B, 4, T', H, W)
    return unfold_frames(up)[:, 0]


@dataclass(frozen=True, kw_only=True)
class Conditions:
    """What the model is conditioned on for one clip (numpy or torch arrays, no batch axis)."""

    scene_video: np.ndarray | torch.Tensor  # (T, H, W, 3) uint8, rendered static-scene video
    visibility: np.ndarray | torch.Tensor  # (T, H, W) {0,1}: 1 = scene pixel observed
    skeleton_video: np.ndarray | torch.Tensor  # (T, H, W, 3) uint8, projected hand keypoints
    first_frame: np.ndarray | torch.Tensor  # (H, W, 3) uint8, hand-free first frame
    prompt: str  # text prompt
    text_embedding: np.ndarray | torch.Tensor | None = None  # (L, text_dim) precomputed UMT5
    image_embedding: np.ndarray | torch.Tensor | None = None  # (257, 1280) precomputed CLIP

    def __post_init__(self) -> None:
        problems = self._problems()
        if problems:
            raise SampleError(f"{type(self).__name__}: " + "; ".join(problems))

    def _problems(self) -> list[str]:
        problems = []
        scene = _shape(self.scene_video)
        if len(scene) != 4 or scene[-1] != 3:
            problems.append(f"scene_video must be (T, H, W, 3), got {scene}")
            return problems
        t, h, w, _ = scene
        for name, expected in (
            ("visibility", (t, h, w)),
            ("skeleton_video", (t, h, w, 3)),
            ("first_frame", (h, w, 3)),
        ):
            got = _shape(getattr(self, name))
            if got != expected:
                problems.append(f"{name} must be {expected}, got {got}")
        for name in ("scene_video", "skeleton_video", "first_frame"):
            if _dtype_name(getattr(self, name)) != "uint8":
                problems.append(f"{name} must be uint8, got {_dtype_name(getattr(self, name))}")
        vis = torch.as_tensor(np.asarray(self.visibility))
        if vis.numel() and not bool(((vis == 0) | (vis == 1)).all()):
            problems.append("visibility must hold only 0 and 1")
        if not isinstance(self.prompt, str):
            problems.append(f"prompt must be a str, got {type(self.prompt).__name__}")
        if (t - 1) % TEMPORAL_GROUP:
            problems.append(f"frame count must be 1 + 4k, got {t}")
        return problems

    @property
    def num_frames(self) -> int:
        """Pixel frame count T."""
        return _shape(self.scene_video)[0]

    @property
    def frame_hw(self) -> tuple[int, int]:
        """(H, W) of the frames."""
        s = _shape(self.scene_video)
        return s[1], s[2]


@dataclass(frozen=True, kw_only=True)
class TrainingSample(Conditions):
    """One training clip: the conditions plus the target video to reproduce."""

    target_video: np.ndarray | torch.Tensor  # (T, H, W, 3) uint8, real egocentric video

    def _problems(self) -> list[str]:
        problems = super()._problems()
        got, want = _shape(self.target_video), _shape(self.scene_video)
        if got != want:
            problems.append(f"target_video must have the scene_video shape {want}, got {got}")
        if _dtype_name(self.target_video) != "uint8":
            problems.append(f"target_video must be uint8, got {_dtype_name(self.target_video)}")
        return problems

    def conditions(self) -> Conditions:
        """The same clip without its target (what sampling needs)."""
        kw = {f.name: getattr(self, f.name) for f in fields(Conditions)}
        return Conditions(**kw)


def _shape(x: np.ndarray | torch.Tensor) -> tuple[int, ...]:
    return tuple(int(s) for s in x.shape)


def _dtype_name(x: np.ndarray | torch.Tensor) -> str:
    return str(x.dtype).removeprefix("torch.")


def video_to_tensor(frames: list[np.ndarray | torch.Tensor]) -> torch.Tensor:
    """Batch of uint8 videos (T,H,W,3) -> float (B,3,T,H,W) in [-1, 1]."""
    x = torch.stack([torch.as_tensor(np.asarray(f)) for f in frames])  # (B, T, H, W, 3) uint8
    return x.permute(0, 4, 1, 2, 3).float() / 127.5 - 1.0


def tensor_to_video(x: torch.Tensor) -> np.ndarray:
    """Float (B,3,T,H,W) in [-1, 1] -> uint8 (B,T,H,W,3), rounded."""
    x = ((x.detach().float().clamp(-1, 1) + 1.0) * 127.5).round().to(torch.uint8)
    return x.permute(0, 2, 3, 4, 1).cpu().numpy()


@dataclass
class PixelConditions:
    """A batch of conditions as float tensors, ready for the VAE (built by :func:`collate`)."""

    scene: torch.Tensor  # (B, 3, T, H, W) in [-1, 1], unseen pixels 0, frame 0 = first frame
    visibility: torch.Tensor  # (B, T, H, W) float {0,1}, frame 0 all ones
    skeleton: torch.Tensor  # (B, 3, T, H, W) in [-1, 1]
    prompts: list[str]  # B prompts
    text_embeddings: list[torch.Tensor | None]  # per-sample precomputed text features or None
    image_embeddings: list[torch.Tensor | None]  # per-sample precomputed image features or None


def collate(samples: list[Conditions]) -> PixelConditions:
    """Stack conditions into tensors, applying first-frame conditioning and scene masking."""
    scene = video_to_tensor([s.scene_video for s in samples])  # (B, 3, T, H, W)
    first = video_to_tensor([np.asarray(s.first_frame)[None] for s in samples])  # (B,3,1,H,W)
    vis = torch.stack([torch.as_tensor(np.asarray(s.visibility)) for s in samples]).float()
    vis[:, 0] = 1.0  # frame 0 is the given first frame: fully known
    scene = torch.cat([first, scene[:, :, 1:]], dim=2) * vis.unsqueeze(1)  # unseen pixels -> 0
    skeleton = video_to_tensor([s.skeleton_video for s in samples])

    def opt(x: np.ndarray | torch.Tensor | None) -> torch.Tensor | None:
        return None if x is None else torch.as_tensor(np.asarray(x)).float()

    return PixelConditions(
        scene=scene,
        visibility=vis,
        skeleton=skeleton,
        prompts=[s.prompt for s in samples],
        text_embeddings=[opt(s.text_embedding) for s in samples],
        image_embeddings=[opt(s.image_embedding) for s in samples],
    )


def assemble_input(noisy: torch.Tensor, condition: torch.Tensor) -> torch.Tensor:
    """Concatenate the noisy latent (B,16,T',h,w) and condition (B,36,T',h,w) -> (B,52,T',h,w)."""
    return torch.cat([noisy, condition], dim=1)


GUIDANCE_TARGETS = ("text", "skeleton", "image")  # conditions CFG / dropout may null


def condition_latents(vae: torch.nn.Module, pix: PixelConditions) -> torch.Tensor:
    """Encode a batch of conditions into the 36 condition channels (B, 36, T', h, w).

    Order: packed mask (4), scene latent (16), skeleton latent (16); see the module docstring.
    """
    device = next(iter(vae.buffers()), torch.zeros(0)).device
    scene = vae.encode(pix.scene.to(device))  # (B, 16, T', h, w)
    skeleton = vae.encode(pix.skeleton.to(device))  # (B, 16, T', h, w)
    mask = pack_mask(pix.visibility.to(device), tuple(scene.shape[-2:]))  # (B, 4, T', h, w)
    return torch.cat([mask, scene, skeleton], dim=1)


@dataclass(frozen=True, kw_only=True)
class LatentSample:
    """One training clip already in latent space: what the ``encode`` stage precomputes.

    ``x0`` and ``condition`` are exactly what :func:`encode_batch` computes from the pixel
    :class:`TrainingSample` (target latent; :func:`condition_latents`' 36 channels), so a batch
    of these skips the frozen VAE (and, with features, the text and image encoders).
    """

    x0: np.ndarray | torch.Tensor  # (16, T', h, w) clean target latent
    condition: np.ndarray | torch.Tensor  # (36, T', h, w) packed mask + scene + skeleton latents
    prompt: str  # text prompt (the hashed encoder of `tiny` reads it; features win otherwise)
    text_embedding: np.ndarray | torch.Tensor | None = None  # (L, text_dim) real UMT5 tokens
    image_embedding: np.ndarray | torch.Tensor | None = None  # (N, image_dim) CLIP features
    clip_id: str = ""  # where it came from, for error messages

    def __post_init__(self) -> None:
        problems = []
        x0, cond = _shape(self.x0), _shape(self.condition)
        if len(x0) != 4 or x0[0] != LATENT_CHANNELS:
            problems.append(f"x0 must be ({LATENT_CHANNELS}, T', h, w), got {x0}")
        want = (CONDITION.stop - CONDITION.start, *x0[1:])
        if len(cond) != 4 or cond != want:
            problems.append(f"condition must be {want} (36 channels, x0's T', h, w), got {cond}")
        for name in ("text_embedding", "image_embedding"):
            value = getattr(self, name)
            if value is not None and len(_shape(value)) != 2:
                problems.append(f"{name} must be (tokens, dim), got {_shape(value)}")
        if not isinstance(self.prompt, str):
            problems.append(f"prompt must be a str, got {type(self.prompt).__name__}")
        if problems:
            where = f" {self.clip_id!r}" if self.clip_id else ""
            raise SampleError(f"LatentSample{where}: " + "; ".join(problems))

    @property
    def latent_shape(self) -> tuple[int, int, int]:
        """(T', h, w) of the latents."""
        return _shape(self.x0)[1:]  # type: ignore[return-value]


@dataclass
class EncodedBatch:
    """A training micro-batch in latent space: what the denoiser's loss needs (built by
    :func:`encode_batch`)."""

    x0: torch.Tensor  # (B, 16, T', h, w) clean target latent
    condition: torch.Tensor  # (B, 36, T', h, w) packed mask + scene + skeleton latents
    prompts: list[str]  # B prompts
    text_embeddings: list[torch.Tensor | None]  # per-sample precomputed text features or None
    image_embeddings: list[torch.Tensor | None]  # per-sample precomputed image features or None


def _float_tensor(x: np.ndarray | torch.Tensor | None) -> torch.Tensor | None:
    return None if x is None else torch.as_tensor(x).float()


def _latent_batch(batch: list[LatentSample]) -> EncodedBatch:
    """Stack precomputed latents (float32, CPU); every sample must have the same latent shape."""
    shapes = sorted({s.latent_shape for s in batch})
    if len(shapes) > 1:
        raise SampleError(
            f"micro-batch latents differ in (T', h, w): {shapes} (clips "
            f"{[s.clip_id for s in batch]}); use batch_size 1 or one packed size"
        )
    x0 = torch.stack([_float_tensor(s.x0) for s in batch])  # (B, 16, T', h, w)
    cond = torch.stack([_float_tensor(s.condition) for s in batch])  # (B, 36, T', h, w)
    return EncodedBatch(
        x0,
        cond,
        [s.prompt for s in batch],
        [_float_tensor(s.text_embedding) for s in batch],
        [_float_tensor(s.image_embedding) for s in batch],
    )


def encode_batch(
    vae: torch.nn.Module, batch: list[TrainingSample] | list[LatentSample]
) -> EncodedBatch:
    """Turn a micro-batch into latents: pixel samples through the frozen ``vae`` (no gradients),
    precomputed :class:`LatentSample` items passed straight through (float32).

    The single place the training loop turns samples into latents. A batch must be all pixel
    samples or all latent samples (:class:`SampleError` otherwise).
    """
    latent = [isinstance(s, LatentSample) for s in batch]
    if any(latent) and not all(latent):
        kinds = [type(s).__name__ for s in batch]
        raise SampleError(f"micro-batch mixes precomputed latents and pixel samples: {kinds}")
    if batch and all(latent):
        return _latent_batch(batch)  # type: ignore[arg-type]
    pix = collate(batch)  # type: ignore[arg-type]
    device = next(iter(vae.buffers()), torch.zeros(0)).device
    with torch.no_grad():
        target = video_to_tensor([s.target_video for s in batch])  # (B, 3, T, H, W)
        x0 = vae.encode(target.to(device))  # (B, 16, T', h, w)
        cond = condition_latents(vae, pix)  # (B, 36, T', h, w)
    return EncodedBatch(x0, cond, pix.prompts, pix.text_embeddings, pix.image_embeddings)


def null_conditions(
    cond: torch.Tensor,
    context: torch.Tensor,
    image_context: torch.Tensor | None,
    targets: tuple[str, ...],
    which: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """Replace the chosen conditions by their null value (zeros) for the samples in ``which``.

    cond: (B, 36, T', h, w); context: (B, L, D); image_context: (B, N, D') or None; targets: a
    subset of :data:`GUIDANCE_TARGETS`; which: (B,) bool, default all. Used by training-time
    condition dropout and by the unconditional branch of classifier-free guidance.
    """
    unknown = [t for t in targets if t not in GUIDANCE_TARGETS]
    if unknown:
        raise SampleError(f"unknown guidance targets {unknown}; known {GUIDANCE_TARGETS}")
    b = cond.shape[0]
    which = torch.ones(b, dtype=torch.bool) if which is None else which
    keep = (~which).to(cond.device)
    if "text" in targets:
        context = context * keep.view(b, 1, 1).to(context)
    if "image" in targets and image_context is not None:
        image_context = image_context * keep.view(b, 1, 1).to(image_context)
    if "skeleton" in targets:
        cond = cond.clone()
        cond[:, SKELETON.start - CONDITION.start :] *= keep.view(b, 1, 1, 1, 1).to(cond)
    return cond, context, image_context
