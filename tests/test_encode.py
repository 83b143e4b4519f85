"""The ``encode`` stage, the ``latents`` schema and the frozen encoders (tiny random models).

Ground truths: diffusers' own Wan pipeline methods (``_get_t5_prompt_embeds``,
``encode_image``) on the same tiny models, and ``encode_batch``, which training calls on the fly.
"""

from __future__ import annotations

import types
from pathlib import Path

import numpy as np
import pytest
import torch

from egosim.model.conditioning import encode_batch
from egosim.model.encoders import (
    EncoderFolders,
    build_tiny_tokenizer,
    clean_prompt,
    load_encoders,
    write_tiny_wan_folder,
)
from egosim.model.errors import WeightsMismatchError
from egosim.model.vae import PackedVAE
from egosim.pipeline import media
from egosim.pipeline.check import check_paths
from egosim.pipeline.runner import IN_PROCESS, run_workflow
from egosim.pipeline.shards import ShardReader, ShardWriter, find_shards
from egosim.pipeline.stage import ConfigError
from egosim.pipeline.workflow import load_workflow
from egosim.schemas.latents import LATENTS, decode_tensor
from egosim.schemas.pack import PACK
from egosim.stages.common.latents_dataset import LatentsDataset
from egosim.stages.common.pack_dataset import PackDataset
from egosim.stages.encode.stage import EncodeConfig, EncodeStage, tensor_bytes
from tests.conftest import smooth_frames

REPO = Path(__file__).resolve().parents[1]
T, H, W = 9, 32, 48  # small clip; multiples of 16 so tiny-wan (VAE x8, patch 2) takes it
PROMPTS = ("the right hand picks up the blue box", "the left hand opens the lid")


def pack_row(clip_id: str, t: int = T, h: int = H, w: int = W, seed: int = 0) -> dict:
    """A valid pack row of smooth synthetic videos and a visibility mask with holes."""
    rng = np.random.default_rng(seed)
    target = smooth_frames(t, h, w, seed)
    scene = smooth_frames(t, h, w, seed + 1)
    skeleton = np.zeros((t, h, w, 3), np.uint8)
    skeleton[:, h // 4 : h // 2, w // 3 : w // 2] = (255, 40, 40)  # a "hand" blob
    visible = (rng.random((t, h, w)) > 0.2).astype(np.uint8)
    return {
        "clip_id": clip_id,
        "num_frames": t,
        "width": w,
        "height": h,
        "fps": 16.0,
        "frame_indices": list(range(t)),
        "intrinsics": [float(w), float(w), w / 2, h / 2],
        "world_from_cam": None,
        "target_video": media.encode_rgb_video(target, 16.0),
        "scene_video": media.encode_rgb_video(scene, 16.0),
        "visible": media.encode_mask_video(visible),
        "skeleton_video": media.encode_rgb_video(skeleton, 16.0),
        "first_frame": media.encode_png(scene[0]),
        "first_frame_source": "inpaint",
        "hand_mask": None,
        "depth0": None,
        "depth_unit_m": None,
        "prompt": PROMPTS[seed % len(PROMPTS)],
        "visible_fraction": float(visible[1:].mean()),
        "registered_fraction": 1.0,
        "hand_valid_fraction": 1.0,
    }


def write_pack(path: Path, rows: list[dict]) -> Path:
    """Write pack rows as a pack shard."""
    with ShardWriter(path, PACK, stage="pack") as writer:
        for row in rows:
            writer.write_row(row)
    return path


@pytest.fixture(scope="module")
def wan_folder(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Tiny random Wan-architecture weights in the diffusers layout (tiny-wan widths)."""
    return write_tiny_wan_folder(tmp_path_factory.mktemp("wan") / "weights")


@pytest.fixture(scope="module")
def pack_shard(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Two clips in one pack shard."""
    tmp = tmp_path_factory.mktemp("pack")
    return write_pack(tmp / "shard-00000.parquet", [pack_row("c0", seed=0), pack_row("c1", seed=1)])


def _encode_run(out: Path, pack: Path, **params: str) -> Path:
    wf = load_workflow(
        REPO / "workflows" / "encode.yaml", [f"encode.{k}={v}" for k, v in params.items()]
    )
    run_workflow(wf, out, scheduler=IN_PROCESS, inputs={"pack": [pack]})
    return out


# --- config and schema ---------------------------------------------------------------------------


def test_config_lists_every_bad_value() -> None:
    with pytest.raises(ConfigError) as err:
        EncodeConfig(preset="nope", encoder_dtype="int8", storage_dtype="float64", device="tpu")
    msg = str(err.value)
    for part in ("'nope'", "'int8'", "'float64'", "'tpu'"):
        assert part in msg
    with pytest.raises(ConfigError, match="needs weights_dir"):
        EncodeConfig(preset="tiny-wan")
    assert EncodeStage.gpu and EncodeStage.output is LATENTS


@pytest.mark.parametrize("dtype", ["float32", "bfloat16", "float16"])
def test_tensor_bytes_round_trip_equals_the_torch_cast(dtype: str) -> None:
    x = torch.randn(3, 5, 7, generator=torch.Generator().manual_seed(0)) * 10
    back = decode_tensor(tensor_bytes(x, dtype), (3, 5, 7), dtype)
    assert back.dtype == np.float32 and back.flags.writeable
    cast = x.to(getattr(torch, dtype)).float().numpy()
    np.testing.assert_array_equal(back, cast)  # exact: decoding loses nothing
    if dtype == "float32":
        np.testing.assert_array_equal(back, x.numpy())
    else:  # rounding to nearest: half an ulp (bf16 8 bits, fp16 11 bits of mantissa)
        bits = 8 if dtype == "bfloat16" else 11
        assert np.all(np.abs(back - x.numpy()) <= np.abs(x.numpy()) * 2.0**-bits + 1e-7)
    with pytest.raises(ValueError, match="needs"):
        decode_tensor(tensor_bytes(x, dtype), (3, 5, 8), dtype)


def _latents_row(**overrides) -> dict:
    tl, lh, lw = 3, 4, 6
    x0 = torch.randn(16, tl, lh, lw)
    row = {
        "clip_id": "c0",
        "num_frames": 9,
        "height": 32,
        "width": 48,
        "fps": 16.0,
        "preset": "tiny-wan",
        "latent_frames": tl,
        "latent_height": lh,
        "latent_width": lw,
        "dtype": "float32",
        "x0": tensor_bytes(x0, "float32"),
        "condition": tensor_bytes(torch.randn(36, tl, lh, lw), "float32"),
        "prompt": "p",
        "text_max_tokens": 512,
        "text_features": tensor_bytes(torch.randn(5, 32), "float32"),
        "text_length": 5,
        "text_dim": 32,
        "image_features": None,
        "image_tokens": None,
        "image_dim": None,
    }
    return {**row, **overrides}


def test_latents_validator_reports_every_problem() -> None:
    assert LATENTS.row_problems(_latents_row()) == []
    nan = torch.zeros(36, 3, 4, 6)
    nan[0, 0, 0, 0] = float("nan")
    bad = _latents_row(
        x0=b"\0" * 12,
        condition=tensor_bytes(nan, "float32"),
        text_dim=None,
        image_tokens=257,
    )
    problems = LATENTS.row_problems(bad)
    text = "; ".join(problems)
    assert "x0:" in text and "condition has non-finite" in text
    assert "text_features, text_length and text_dim" in text
    assert "image_features, image_tokens and image_dim" in text
    assert LATENTS.row_problems(_latents_row(latent_frames=4))  # 1 + (9 - 1) / 4 = 3
    assert LATENTS.row_problems(_latents_row(height=33))
    assert LATENTS.row_problems(_latents_row(dtype="float64"))


# --- the frozen encoders against diffusers' Wan pipelines ----------------------------------------


def test_prompt_cleaning_follows_wan() -> None:
    assert clean_prompt("  the &amp;amp; hand\n\tmoves  ") == "the & hand moves"
    tok = build_tiny_tokenizer()
    ids = tok(["ab"], padding="max_length", max_length=8, return_tensors="pt")
    assert ids.input_ids[0].tolist() == [3, 4, 1, 0, 0, 0, 0, 0]  # chars, EOS 1, pad 0


def test_text_and_image_features_equal_diffusers_wan_pipeline(
    wan_folder: Path, monkeypatch
) -> None:
    import diffusers.pipelines.wan.pipeline_wan_i2v as wan_i2v
    from diffusers import FlowMatchEulerDiscreteScheduler, WanImageToVideoPipeline
    from PIL import Image

    if not wan_i2v.is_ftfy_available():  # diffusers calls ftfy.fix_text unconditionally
        monkeypatch.setattr(wan_i2v, "ftfy", types.SimpleNamespace(fix_text=str), raising=False)
    enc = load_encoders("tiny-wan", EncoderFolders.from_root(wan_folder))
    pipe = WanImageToVideoPipeline(
        tokenizer=enc.text.tokenizer,
        text_encoder=enc.text.model,
        image_encoder=enc.image.model,
        image_processor=enc.image.processor,
        transformer=None,
        vae=enc.vae.vae,
        scheduler=FlowMatchEulerDiscreteScheduler(),
    )
    prompts = [PROMPTS[0], "  two &amp; spaces  "]
    cpu = torch.device("cpu")
    ref = pipe._get_t5_prompt_embeds(prompts, max_sequence_length=512, device=cpu)
    ours = enc.text(prompts)
    for i, feats in enumerate(ours):
        assert feats.shape == (len(clean_prompt(prompts[i])) + 1, 32)  # chars + EOS
        assert feats.dtype == torch.float32
        torch.testing.assert_close(feats, ref[i, : len(feats)], rtol=0, atol=0)
        assert not ref[i, len(feats) :].any()  # Wan's padding rows are zeros: not stored
    image = smooth_frames(1, 48, 80)[0]
    ref_img = pipe.encode_image(Image.fromarray(image), device=cpu)
    ours_img = enc.image([image])
    assert ours_img.shape == (1, 257, 32)  # CLS + 16 x 16 patches, as ViT-H/14
    torch.testing.assert_close(ours_img, ref_img, rtol=0, atol=0)


def test_encoders_refuse_missing_folders_and_wrong_widths(wan_folder: Path, tmp_path) -> None:
    with pytest.raises(WeightsMismatchError, match="no text_encoder"):
        load_encoders("tiny-wan", EncoderFolders.from_root(wan_folder, text_encoder=tmp_path / "x"))
    # The 1.3B preset takes 4096-wide text features: the tiny UMT5 (32) is refused by name.
    with pytest.raises(WeightsMismatchError, match="d_model is 32"):
        from egosim.model.encoders import load_text_features
        from egosim.model.presets import get_preset

        folders = EncoderFolders.from_root(wan_folder)
        load_text_features(
            get_preset("wan2.1-fun-1.3b-inp"), folders, torch.device("cpu"), torch.float32
        )


# --- the stage ------------------------------------------------------------------------------------


def test_tiny_encode_equals_on_the_fly_and_round_trips(pack_shard: Path, tmp_path: Path) -> None:
    out = _encode_run(tmp_path / "run", pack_shard, preset="tiny")
    (shard,) = find_shards([out], "encode")
    assert check_paths([shard]) == (1, [])
    latents, pack = LatentsDataset(out), PackDataset(pack_shard)
    assert latents.clip_ids == pack.clip_ids == ["c0", "c1"]
    assert latents.sizes == pack.sizes == [(T, H, W)] * 2
    assert latents.latent_sizes == [(3, H, W)] * 2  # tiny's packed VAE: spatial factor 1
    for i in range(2):
        stored = latents[i]
        fly = encode_batch(PackedVAE(), [pack[i]])
        assert stored.x0.dtype == torch.float32
        torch.testing.assert_close(stored.x0, fly.x0[0], rtol=0, atol=0)  # float32: bit-exact
        torch.testing.assert_close(stored.condition, fly.condition[0], rtol=0, atol=0)
        assert stored.text_embedding is None and stored.image_embedding is None
        assert stored.prompt == pack[i].prompt


def test_wan_encode_stores_features_bf16_within_rounding(
    pack_shard: Path, wan_folder: Path, tmp_path: Path
) -> None:
    out32 = _encode_run(
        tmp_path / "f32", pack_shard, preset="tiny-wan", weights_dir=str(wan_folder)
    )
    out16 = _encode_run(
        tmp_path / "bf16",
        pack_shard,
        preset="tiny-wan",
        weights_dir=str(wan_folder),
        storage_dtype="bfloat16",
    )
    enc = load_encoders("tiny-wan", EncoderFolders.from_root(wan_folder))
    pack = PackDataset(pack_shard)
    # One clip per call, as the stage encodes (CPU convolutions round differently per batch).
    direct = [enc.encode([pack[i]], [pack.clip_ids[i]])[0] for i in range(2)]
    for out, exact in ((out32, True), (out16, False)):
        ds = LatentsDataset(out)
        assert check_paths(find_shards([out], "encode"))[1] == []
        assert ds.latent_sizes == [(3, H // 8, W // 8)] * 2
        for i in range(2):
            got, want = ds[i], direct[i]
            assert got.text_embedding.shape == (len(PROMPTS[i]) + 1, 32)
            assert got.image_embedding.shape == (257, 32)
            pairs = [
                (got.x0, want.x0),
                (got.condition, want.condition),
                (got.text_embedding, want.text_embedding),
                (got.image_embedding, want.image_embedding),
            ]
            for a, b in pairs:
                if exact:
                    torch.testing.assert_close(a, b, rtol=0, atol=0)
                else:  # bf16 storage: nearest rounding, relative error <= 2^-8
                    assert torch.all((a - b).abs() <= b.abs() * 2.0**-8 + 1e-30)
    with ShardReader(find_shards([out16], "encode")[0], LATENTS) as reader:
        row = next(reader.iter_rows())
    assert row["dtype"] == "bfloat16" and len(row["x0"]) == 16 * 3 * 4 * 6 * 2


def test_encoding_is_deterministic(pack_shard: Path, wan_folder: Path) -> None:
    pack = PackDataset(pack_shard)
    a = load_encoders("tiny-wan", EncoderFolders.from_root(wan_folder)).encode([pack[1]], ["c1"])
    b = load_encoders("tiny-wan", EncoderFolders.from_root(wan_folder)).encode([pack[1]], ["c1"])
    for name in ("x0", "condition", "text_embedding", "image_embedding"):
        assert torch.equal(getattr(a[0], name), getattr(b[0], name)), name


def test_sizes_the_preset_cannot_take_are_rejected(wan_folder: Path, tmp_path: Path) -> None:
    pack = write_pack(tmp_path / "p.parquet", [pack_row("odd", h=40, w=48), pack_row("ok")])
    out = _encode_run(tmp_path / "run", pack, preset="tiny-wan", weights_dir=str(wan_folder))
    assert LatentsDataset(out).clip_ids == ["ok"]
    with ShardReader(out / "rejects.parquet") as reader:
        (reject,) = list(reader.iter_rows())
    assert reject["clip_id"] == "odd" and "40x48 is not a multiple of 16" in reject["reason"]
