"""state_fusion's learned-mask backend (``grounded_sam``): Grounding-DINO + SAM from local folders.

The plumbing is checked twice: tiny randomly initialised Grounding-DINO and SAM models saved to
a folder and loaded back by the backend (shapes, boxes inside the image, determinism, refusals),
and fusion driven by ground-truth object masks in place of DBSCAN, measured like the geometric
backend (the moved object within 1 cm of the truth; geometric: 4.7 mm on the same clip).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from bench.bench_state_fusion import SMALL, measure_state_update
from egosim.pipeline.records import Clip
from egosim.pipeline.stage import ConfigError
from egosim.stages.state_fusion.config import StateFusionConfig
from egosim.stages.state_fusion.segmenters import (
    GroundedSamSegmenter,
    SegmenterError,
    text_prompt,
)
from egosim.world import WorldConfig, render_clip

VOCAB = ["[PAD]", "[UNK]", "[CLS]", "[SEP]", "[MASK]", ".", "a", "cup", "box", "bowl"]


def tiny_grounded_sam(folder: Path) -> tuple[Path, Path]:
    """Random tiny Grounding-DINO (+ a BERT word-piece tokenizer) and SAM saved as transformers
    folders under ``folder``; returns their paths."""
    import torch
    from transformers import (
        BertTokenizerFast,
        GroundingDinoConfig,
        GroundingDinoForObjectDetection,
        GroundingDinoProcessor,
        SamConfig,
        SamModel,
        SamProcessor,
    )
    from transformers.models.grounding_dino.image_processing_pil_grounding_dino import (
        GroundingDinoImageProcessorPil,
    )
    from transformers.models.sam.image_processing_pil_sam import SamImageProcessorPil

    torch.manual_seed(0)
    (folder / "vocab.txt").write_text("\n".join(VOCAB))
    dino_cfg = GroundingDinoConfig(
        backbone_config={
            "model_type": "swin", "embed_dim": 8, "depths": [1, 1, 1, 1],
            "num_heads": [1, 1, 1, 1], "window_size": 4, "image_size": 64,
            "out_features": ["stage2", "stage3", "stage4"],
        },
        text_config={
            "model_type": "bert", "hidden_size": 32, "num_hidden_layers": 1,
            "num_attention_heads": 2, "intermediate_size": 32, "vocab_size": len(VOCAB),
            "max_position_embeddings": 64,
        },
        d_model=32, encoder_layers=1, decoder_layers=2, encoder_ffn_dim=16, decoder_ffn_dim=16,
        encoder_attention_heads=2, decoder_attention_heads=2, num_queries=8, max_text_len=32,
        encoder_n_points=2, decoder_n_points=2,
    )  # fmt: skip
    dino = folder / "dino"
    GroundingDinoForObjectDetection(dino_cfg).save_pretrained(dino)
    GroundingDinoProcessor(
        image_processor=GroundingDinoImageProcessorPil(
            size={"shortest_edge": 64, "longest_edge": 96}
        ),
        tokenizer=BertTokenizerFast(vocab_file=str(folder / "vocab.txt")),
    ).save_pretrained(dino)
    sam_cfg = SamConfig(
        vision_config={
            "hidden_size": 16, "num_hidden_layers": 1, "num_attention_heads": 2,
            "image_size": 64, "patch_size": 16, "output_channels": 8, "num_pos_feats": 4,
            "mlp_dim": 16, "global_attn_indexes": [0], "window_size": 0,
        },
        prompt_encoder_config={
            "hidden_size": 8, "image_size": 64, "patch_size": 16, "mask_input_channels": 4
        },
        mask_decoder_config={
            "hidden_size": 8, "mlp_dim": 16, "num_hidden_layers": 1, "num_attention_heads": 2,
            "iou_head_hidden_dim": 8,
        },
    )  # fmt: skip
    sam = folder / "sam"
    SamModel(sam_cfg).save_pretrained(sam)
    SamProcessor(
        SamImageProcessorPil(size={"longest_edge": 64}, pad_size={"height": 64, "width": 64})
    ).save_pretrained(sam)
    return dino, sam


def test_grounded_sam_loads_local_folders_and_segments(tmp_path: Path) -> None:
    dino, sam = tiny_grounded_sam(tmp_path)
    seg = GroundedSamSegmenter(("Cup", "box."), str(dino), str(sam), 0.0, 0.0)
    assert seg.prompt == "cup. box."
    image = (np.random.default_rng(1).random((60, 90, 3)) * 255).astype(np.uint8)
    boxes = seg.boxes(image)
    assert boxes.shape == (8, 4)  # every query passes threshold 0
    assert (boxes[:, :2] >= -1e-3).all() and (boxes[:, 2] <= 90 + 1e-3).all()
    assert (boxes[:, 3] <= 60 + 1e-3).all() and (boxes[:, 2:] >= boxes[:, :2]).all()
    masks = seg.masks(image)
    assert len(masks) == 8 and all(m.shape == (60, 90) and m.dtype == bool for m in masks)
    again = seg.masks(image)
    assert all(np.array_equal(a, b) for a, b in zip(masks, again, strict=True))
    strict = GroundedSamSegmenter(("cup",), str(dino), str(sam), box_threshold=1.01)
    assert strict.masks(image) == []  # no box: no mask, no SAM call


def test_grounded_sam_refuses_missing_weights_and_labels(tmp_path: Path) -> None:
    with pytest.raises(SegmenterError, match="missing"):
        GroundedSamSegmenter(("cup",), str(tmp_path / "missing"), str(tmp_path / "missing"))
    with pytest.raises(SegmenterError, match="non-empty object labels"):
        text_prompt(("cup", " "))
    with pytest.raises(ConfigError, match="grounded_sam' needs object_labels"):
        StateFusionConfig(backend="grounded_sam", object_labels=("cup",))


class TruthSegmenter:
    """The world's object masks (hands excluded) of whichever clip frame it is given (the
    nearest frame: fusion sees the frames after the clip's H.264 round trip)."""

    def __init__(self, clip: Clip) -> None:
        self.frames = clip.frames.astype(np.int16)
        self.object_mask = clip.object_mask

    def masks(self, image: np.ndarray) -> list[np.ndarray]:
        k = int(np.argmin(np.abs(self.frames - image.astype(np.int16)).mean(axis=(1, 2, 3))))
        ids = [i for i in np.unique(self.object_mask[k]) if i > 0]
        return [self.object_mask[k] == i for i in ids]


def test_fusion_from_given_object_masks_places_the_moved_object() -> None:
    config = WorldConfig(seed=0, **SMALL)
    figures = measure_state_update(
        config, look_back=False, segmenter=TruthSegmenter(render_clip(config))
    )
    (obj,) = figures["objects"]
    assert obj["interactive"] and obj["error"] < 0.01, obj  # measured 4.7 mm
    assert obj["baseline_error"] > 0.8 * obj["shift"]
    assert figures["hand_fraction"] <= 0.01
