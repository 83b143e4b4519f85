"""Precomputed latents vs encoding on the fly: training step time of the tiny-wan preset on CPU.

Both runs train the same preset on the same clips in the same process (one core, one torch
thread): once from a latents shard written by the ``encode`` stage (frozen encoders never run),
once from the pack with the frozen parts run inside every step (the Wan VAE on the target and
both condition videos in ``encode_batch``, UMT5 on the prompt and CLIP on the first frame when
the sample is fetched, as training would without ``encode``). Step time is the training loop's
own ``step_seconds`` (data fetch + encode + forward + backward + AdamW), first step left out.
"""

from __future__ import annotations

import json
import os
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

from egosim.model.conditioning import TrainingSample
from egosim.model.encoders import FrozenEncoders, write_tiny_wan_folder
from egosim.model.train import TrainConfig, train
from egosim.pipeline import media
from egosim.pipeline.shards import ShardWriter
from egosim.schemas.latents import LATENTS
from egosim.schemas.pack import PACK
from egosim.stages.common.latents_dataset import open_training_data
from egosim.stages.common.pack_dataset import PackDataset
from egosim.stages.encode.stage import EncodeConfig, EncodeStage
from egosim.world import WorldConfig, render_clip

SIZES = ((9, 64, 64), (17, 128, 224))  # (T, H, W): tiny-wan's default, a larger CPU size
STEPS = 4  # optimizer steps per run (the first is left out of the mean)


def _pack_rows(n: int, t: int, h: int, w: int) -> list[dict]:
    """Pack rows of synthetic-world clips (target, static scene, hand mask as skeleton)."""
    rows = []
    for seed in range(n):
        clip = render_clip(WorldConfig(seed=seed, height=h, width=w, num_frames=t))
        skeleton = np.repeat(clip.hand_mask[..., None], 3, axis=-1) * np.uint8(255)
        visible = (clip.static_depth > 0).astype(np.uint8)
        rows.append(
            {
                "clip_id": f"bench-{seed}",
                "num_frames": t,
                "width": w,
                "height": h,
                "fps": 16.0,
                "frame_indices": list(range(t)),
                "intrinsics": [float(v) for v in clip.intrinsics],
                "world_from_cam": None,
                "target_video": media.encode_rgb_video(clip.frames, 16.0),
                "scene_video": media.encode_rgb_video(clip.static_frames, 16.0),
                "visible": media.encode_mask_video(visible),
                "skeleton_video": media.encode_rgb_video(skeleton, 16.0),
                "first_frame": media.encode_png(clip.first_frame_clean),
                "first_frame_source": "first_frame_clean",
                "hand_mask": None,
                "depth0": None,
                "depth_unit_m": None,
                "prompt": f"the right hand picks up object {seed}",
                "visible_fraction": float(visible[1:].mean()),
                "registered_fraction": 1.0,
                "hand_valid_fraction": 1.0,
            }
        )
    return rows


class OnTheFly(Sequence):
    """Pack samples whose text and image features are computed when fetched (no cache)."""

    def __init__(self, pack: PackDataset, encoders: FrozenEncoders) -> None:
        self.pack, self.encoders = pack, encoders

    def __len__(self) -> int:
        return len(self.pack)

    def __getitem__(self, i: int) -> TrainingSample:  # type: ignore[override]
        s = self.pack[i]
        text = self.encoders.text([s.prompt])[0]
        image = self.encoders.image([np.asarray(s.first_frame)])[0]
        fields = ("target_video", "scene_video", "visibility", "skeleton_video", "first_frame")
        return TrainingSample(
            **{f: getattr(s, f) for f in fields},
            prompt=s.prompt,
            text_embedding=text,
            image_embedding=image,
        )


def _step_seconds(run_dir: Path) -> float:
    with (run_dir / "metrics.jsonl").open() as log:
        times = [json.loads(line)["step_seconds"] for line in log if line.strip()]
    return float(np.mean(times[1:]))


def bench_latents_vs_on_the_fly() -> list[dict]:
    """tiny-wan training step time from a latents shard vs encoding on the fly (same run)."""
    previous = os.sched_getaffinity(0) if hasattr(os, "sched_getaffinity") else None
    if previous is not None:
        os.sched_setaffinity(0, {min(previous)})
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    figures = []
    try:
        with tempfile.TemporaryDirectory() as tmp_name:
            tmp = Path(tmp_name)
            folder = write_tiny_wan_folder(tmp / "weights")
            stage = EncodeStage(EncodeConfig(preset="tiny-wan", weights_dir=str(folder)))
            encoders = stage.encoders  # loaded once, here: the per-clip timing leaves it out
            for t, h, w in SIZES:
                label = f"{t}x{h}x{w}"
                rows = _pack_rows(2, t, h, w)
                pack_path = tmp / label / "pack" / "shard-00000.parquet"
                with ShardWriter(pack_path, PACK, stage="pack") as writer:
                    for row in rows:
                        writer.write_row(row)
                t0 = time.perf_counter()
                latents_path = tmp / label / "encode" / "shard-00000.parquet"
                with ShardWriter(latents_path, LATENTS, stage="encode") as writer:
                    for row in rows:
                        writer.write_row(stage.process({"pack": row}))
                encode_s = (time.perf_counter() - t0) / len(rows)
                config = TrainConfig(
                    preset="tiny-wan",
                    steps=STEPS,
                    weights_dir=str(folder),
                    preview_steps=0,
                    checkpoint_every=0,
                    cond_dropout=0.0,
                )
                pre = tmp / label / "train_latents"
                fly = tmp / label / "train_fly"
                train(config, open_training_data(tmp / label), pre)
                train(config, OnTheFly(PackDataset(pack_path), encoders), fly)
                s_pre, s_fly = _step_seconds(pre), _step_seconds(fly)
                figures += [
                    {
                        "name": f"tiny-wan step from latents {label}",
                        "value": s_pre,
                        "unit": "s/step",
                        "baseline": "encoding on the fly (VAE+UMT5+CLIP)",
                        "baseline_value": s_fly,
                    },
                    {
                        "name": f"encode stage per clip {label}",
                        "value": encode_s,
                        "unit": "s/clip",
                        "baseline": "-",
                        "baseline_value": None,
                    },
                ]
    finally:
        torch.set_num_threads(threads)
        if previous is not None:
            os.sched_setaffinity(0, previous)
    return figures
