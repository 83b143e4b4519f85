"""Object instances from learned 2D masks: Grounding-DINO boxes prompted by text, SAM masks.

The ``grounded_sam`` backend of ``state_fusion`` replaces the default geometric segmentation
(RANSAC plane + DBSCAN) with per-frame object masks: Grounding-DINO (transformers
``GroundingDinoForObjectDetection``) finds boxes for the object labels in the config (a text
prompt ``"a cup. a box."``), SAM (``SamModel``) turns each box into a mask. Fusion then takes the
clip's points under each mask as one object cluster and tracks those across frames by 3D
overlap, exactly as it tracks DBSCAN clusters. Weights load from local folders only
(``local_files_only``): nothing is downloaded.

A segmenter is anything with ``masks(image) -> list of (H, W) bool``; :func:`build_segmenter`
makes the one a config names, and tests pass their own (e.g. ground-truth masks).
"""

from __future__ import annotations

from typing import Any, Protocol

import numpy as np


class SegmenterError(RuntimeError):
    """A segmentation backend cannot run: weights missing at the path, or bad labels."""


class Segmenter(Protocol):
    """Object masks of one RGB image."""

    def masks(self, image: np.ndarray) -> list[np.ndarray]:
        """``(H, W)`` bool masks, one per object found in ``image (H, W, 3)`` uint8 RGB."""
        ...


def text_prompt(labels: tuple[str, ...]) -> str:
    """Grounding-DINO's prompt for ``labels``: lower case, each ending with a period."""
    if not labels or not all(label.strip() for label in labels):
        raise SegmenterError(f"grounded_sam needs non-empty object labels, got {list(labels)}")
    return " ".join(f"{label.strip().lower().rstrip('.')}." for label in labels)


class GroundedSamSegmenter:
    """Grounding-DINO boxes for text labels, then one SAM mask per box (see module docstring)."""

    def __init__(
        self,
        labels: tuple[str, ...],
        dino_path: str = "",
        sam_path: str = "",
        box_threshold: float = 0.3,
        text_threshold: float = 0.25,
        device: str = "cpu",
        models: tuple[Any, Any, Any, Any] | None = None,
    ) -> None:
        """Load both models from local folders, or take ``models`` = (dino processor, dino
        model, SAM processor, SAM model) as given."""
        self.prompt = text_prompt(labels)
        self.box_threshold, self.text_threshold, self.device = box_threshold, text_threshold, device
        if models is None:
            models = self._load(dino_path, sam_path, device)
        self.dino_processor, self.dino, self.sam_processor, self.sam = models
        self.dino.eval()
        self.sam.eval()

    @staticmethod
    def _load(dino_path: str, sam_path: str, device: str) -> tuple[Any, Any, Any, Any]:
        from transformers import (
            AutoProcessor,
            GroundingDinoForObjectDetection,
            SamModel,
            SamProcessor,
        )

        if not dino_path or not sam_path:
            raise SegmenterError(
                "grounded_sam needs dino_model_path and sam_model_path (local folders)"
            )
        try:
            dino_proc = AutoProcessor.from_pretrained(dino_path, local_files_only=True)
            dino = GroundingDinoForObjectDetection.from_pretrained(dino_path, local_files_only=True)
            sam_proc = SamProcessor.from_pretrained(sam_path, local_files_only=True)
            sam = SamModel.from_pretrained(sam_path, local_files_only=True)
        except OSError as exc:
            raise SegmenterError(
                f"cannot load Grounding-DINO from {dino_path!r} or SAM from {sam_path!r}: {exc}"
            ) from exc
        return dino_proc, dino.to(device), sam_proc, sam.to(device)

    def boxes(self, image: np.ndarray) -> np.ndarray:
        """Grounding-DINO boxes ``(K, 4)`` ``x0, y0, x1, y1`` in pixels of ``image``."""
        import torch

        h, w = image.shape[:2]
        inputs = self.dino_processor(images=image, text=self.prompt, return_tensors="pt")
        with torch.no_grad():
            outputs = self.dino(**inputs.to(self.device))
        result = self.dino_processor.post_process_grounded_object_detection(
            outputs,
            inputs["input_ids"],
            threshold=self.box_threshold,
            text_threshold=self.text_threshold,
            target_sizes=[(h, w)],
        )[0]
        return result["boxes"].detach().cpu().numpy().reshape(-1, 4).astype(np.float64)

    def masks(self, image: np.ndarray) -> list[np.ndarray]:
        """One SAM mask per Grounding-DINO box of ``image`` (empty list when none is found)."""
        import torch

        h, w = image.shape[:2]
        boxes = self.boxes(image)
        if not len(boxes):
            return []
        inputs = self.sam_processor(image, input_boxes=[boxes.tolist()], return_tensors="pt")
        with torch.no_grad():
            outputs = self.sam(**inputs.to(self.device), multimask_output=False)
        masks = self.sam_processor.image_processor.post_process_masks(
            outputs.pred_masks.cpu(),
            inputs["original_sizes"].cpu(),
            inputs["reshaped_input_sizes"].cpu(),
        )[0]  # (K, 1, H, W) bool
        return [m for m in np.asarray(masks).reshape(-1, h, w).astype(bool)]


def build_segmenter(config: Any) -> Segmenter | None:
    """The segmenter a ``StateFusionConfig`` names (None for the geometric backend)."""
    if config.backend == "geometric":
        return None
    return GroundedSamSegmenter(
        labels=tuple(config.object_labels),
        dino_path=config.dino_model_path,
        sam_path=config.sam_model_path,
        box_threshold=config.box_threshold,
        text_threshold=config.text_threshold,
    )
