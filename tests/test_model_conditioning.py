"""Channel layout, the one mask function (polarity and packing), samples, and the tiny VAE."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import pytest
import torch

from egosim.model.conditioning import (
    CONDITION,
    MASK,
    NOISY,
    SCENE,
    SKELETON,
    TrainingSample,
    collate,
    condition_latents,
    fold_frames,
    latent_frames,
    pack_mask,
    unfold_frames,
    unpack_mask,
    video_to_tensor,
)
from egosim.model.errors import SampleError
from egosim.model.metrics import psnr
from egosim.model.vae import PackedVAE


@pytest.fixture(autouse=True)
def _one_thread() -> Iterator[None]:
    """Tiny models run faster on one thread, above all on a shared, loaded machine."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def synthetic_video(seed: int, t: int = 9, h: int = 32, w: int = 48) -> np.ndarray:
    """Moving coloured discs and a gradient background (a stand-in for the synthetic world)."""
    rng = np.random.default_rng(seed)
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    frames = []
    centres = rng.uniform(0, 1, (3, 2)) * [w, h]
    vel = rng.uniform(-1.5, 1.5, (3, 2))
    colours = rng.uniform(0, 255, (3, 3))
    for k in range(t):
        img = np.stack([u / w * 200, v / h * 150, np.full_like(u, 60.0)], axis=-1)
        for c, dv, col in zip(centres, vel, colours, strict=True):
            cx, cy = c + k * dv
            img[(u - cx) ** 2 + (v - cy) ** 2 < 30] = col
        frames.append(img)
    return np.clip(np.stack(frames), 0, 255).astype(np.uint8)


def test_layout_is_16_4_16_16() -> None:
    assert (NOISY.start, NOISY.stop, MASK.stop, SCENE.stop, SKELETON.stop) == (0, 16, 20, 36, 52)
    assert slice(16, 52) == CONDITION


def test_mask_polarity_known_is_one() -> None:
    t, h, w = 9, 16, 16
    vis = torch.zeros(1, t, h, w)
    vis[:, :, :, :8] = 1  # left half observed
    packed = pack_mask(vis, (h // 8, w // 8))  # Wan latent resolution (factor 8)
    assert packed.shape == (1, 4, latent_frames(t), 2, 2)
    assert torch.all(packed[..., 0] == 1) and torch.all(packed[..., 1] == 0)
    # all known = DWM's identity mode: all-ones channel
    assert torch.all(pack_mask(torch.ones(1, t, h, w), (2, 2)) == 1)


def test_mask_round_trips_and_first_frame_is_repeated() -> None:
    g = torch.Generator().manual_seed(0)
    t, hl, wl = 13, 3, 4
    cells = (torch.rand(2, t, hl, wl, generator=g) > 0.5).float()
    vis = cells.repeat_interleave(8, dim=2).repeat_interleave(8, dim=3)  # constant per cell
    packed = pack_mask(vis, (hl, wl))
    assert packed.shape == (2, 4, 4, hl, wl)
    # latent frame 0 holds pixel frame 0 four times; latent frame 1 holds frames 1..4
    for k in range(4):
        assert torch.equal(packed[:, k, 0], cells[:, 0])
        assert torch.equal(packed[:, k, 1], cells[:, 1 + k])
    assert torch.equal(unpack_mask(packed, (hl * 8, wl * 8)), vis)


def test_fold_unfold_inverse() -> None:
    x = torch.randn(2, 3, 9, 4, 5)
    assert fold_frames(x).shape == (2, 12, 3, 4, 5)
    torch.testing.assert_close(unfold_frames(fold_frames(x)), x)


def test_sample_validation_lists_every_problem() -> None:
    v = np.zeros((9, 16, 16, 3), np.uint8)
    with pytest.raises(SampleError) as err:
        TrainingSample(
            target_video=v[:5],
            scene_video=v,
            visibility=np.full((9, 16, 16), 2, np.uint8),
            skeleton_video=v.astype(np.float32),
            first_frame=v[0],
            prompt="x",
        )
    msg = str(err.value)
    assert "target_video" in msg and "visibility" in msg and "skeleton_video must be uint8" in msg
    with pytest.raises(SampleError, match="1 \\+ 4k"):
        TrainingSample(
            target_video=v[:8],
            scene_video=v[:8],
            visibility=np.ones((8, 16, 16)),
            skeleton_video=v[:8],
            first_frame=v[0],
            prompt="",
        )


def test_first_frame_conditioning_and_scene_masking() -> None:
    vid = synthetic_video(0, h=16, w=16)
    vis = np.zeros((9, 16, 16), np.uint8)
    vis[:, :, :8] = 1
    s = TrainingSample(
        target_video=vid,
        scene_video=vid,
        visibility=vis,
        skeleton_video=vid,
        first_frame=vid[3],
        prompt="p",
    )
    pix = collate([s])
    assert torch.all(pix.visibility[:, 0] == 1)  # frame 0 fully known
    torch.testing.assert_close(pix.scene[:, :, 0], video_to_tensor([vid[3:4]])[:, :, 0])
    assert torch.all(pix.scene[:, :, 1:, :, 8:] == 0)  # unseen pixels are 0
    cond = condition_latents(PackedVAE(), pix)
    assert cond.shape == (1, 36, 3, 16, 16)


def test_tiny_vae_reconstructs_held_out_frames() -> None:
    vae = PackedVAE(seed=0)
    vids = np.stack([synthetic_video(seed) for seed in (101, 102, 103)])  # never seen anywhere
    x = video_to_tensor(list(vids))
    z = vae.encode(x)
    assert z.shape == (3, 16, 3, 32, 48)
    rec = ((vae.decode(z) + 1) * 127.5).round().clamp(0, 255).to(torch.uint8)
    rec = rec.permute(0, 2, 3, 4, 1).numpy()
    value = psnr(rec, vids)
    assert value >= 28.0  # lossless design: inf (uint8 round trip is exact)
    # orthogonal mix: the latent keeps the energy of the packed pixels (same scale)
    torch.testing.assert_close(z.norm(), fold_frames(x).norm(), rtol=1e-4, atol=0)
