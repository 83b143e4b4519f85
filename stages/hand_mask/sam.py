"""Optional SAM-family backend through transformers (``SamModel`` / ``SamProcessor``).

Weights load from a local folder only (``local_files_only``); transformers is imported lazily so
that the default backend needs nothing beyond OpenCV. Prompts come from the hand keypoints: for
each valid hand, a few positive points (wrist, knuckles, finger tips) and the bounding box of its
capsule mask, so the model segments hand and arm rather than one finger.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

PROMPT_JOINTS = (0, 5, 9, 13, 17, 4, 8, 12, 16, 20)  # wrist, knuckles, finger tips


class SamBackendError(RuntimeError):
    """The SAM backend cannot run (transformers missing, no weights at the path)."""


def build_prompts(
    keypoints: np.ndarray, valid: np.ndarray, boxes: np.ndarray, height: int, width: int
) -> tuple[list[list[list[float]]], list[list[int]], list[list[float]]]:
    """SAM prompts for one image from ``keypoints (K, 21, 2)``, ``valid (K,)``, ``boxes (K, 4)``.

    Returns ``(points, labels, boxes)`` with one entry per valid hand: ``points[k]`` holds the
    in-image prompt joints as ``[x, y]`` (OpenCV pixel coordinates: centre of pixel 0 is 0.0),
    padded to the same count by repeating the last point (SAM needs equal counts per prompt),
    ``labels[k]`` ones (positive), ``boxes[k]`` ``[x0, y0, x1, y1]``. Hands with no in-image
    prompt joint are skipped.
    """
    points: list[list[list[float]]] = []
    out_boxes: list[list[float]] = []
    for hand, ok, box in zip(keypoints, valid, boxes, strict=True):
        if not ok:
            continue
        chosen = hand[list(PROMPT_JOINTS)] - 0.5  # (P, 2) pixel-centre to OpenCV coordinates
        inside = (
            np.all(np.isfinite(chosen), axis=1)
            & (chosen[:, 0] >= 0)
            & (chosen[:, 0] <= width - 1)
            & (chosen[:, 1] >= 0)
            & (chosen[:, 1] <= height - 1)
        )
        if not inside.any():
            continue
        points.append(chosen[inside].tolist())
        out_boxes.append([float(v) for v in box])
    if not points:
        return [], [], []
    count = max(len(p) for p in points)
    points = [p + [p[-1]] * (count - len(p)) for p in points]
    labels = [[1] * count for _ in points]
    return points, labels, out_boxes


def mask_box(mask: np.ndarray) -> np.ndarray:
    """Bounding box ``[x0, y0, x1, y1]`` of a ``(H, W)`` mask; zeros when it is empty."""
    ys, xs = np.nonzero(mask)
    if len(xs) == 0:
        return np.zeros(4)
    return np.array([xs.min(), ys.min(), xs.max(), ys.max()], dtype=np.float64)


class SamSegmenter:
    """Segment hands with a SAM model from a local path, prompted by keypoints."""

    def __init__(
        self, model_path: str = "", device: str = "cpu", model: Any = None, processor: Any = None
    ) -> None:
        """Load ``SamModel``/``SamProcessor`` from ``model_path`` (or use the given objects)."""
        if model is None or processor is None:
            try:
                from transformers import SamModel, SamProcessor
            except ImportError as exc:
                raise SamBackendError(
                    "the 'sam' hand_mask backend needs transformers (pip install transformers)"
                ) from exc
            if not model_path:
                raise SamBackendError("the 'sam' backend needs sam_model_path (a local folder)")
            if not Path(model_path).is_dir():  # transformers would read it as a hub repo id
                raise SamBackendError(f"sam_model_path {model_path!r} is not a local folder")
            try:
                processor = SamProcessor.from_pretrained(model_path, local_files_only=True)
                model = SamModel.from_pretrained(model_path, local_files_only=True).to(device)
            except OSError as exc:
                raise SamBackendError(
                    f"cannot load SAM weights from {model_path!r}: {exc}"
                ) from exc
            model.eval()
        self.model = model
        self.processor = processor
        self.device = device

    def segment(
        self, image: np.ndarray, keypoints: np.ndarray, valid: np.ndarray, boxes: np.ndarray
    ) -> np.ndarray:
        """Union of SAM masks ``(H, W)`` uint8 over the hands of ``image (H, W, 3)`` RGB."""
        import torch

        height, width = image.shape[:2]
        points, labels, hand_boxes = build_prompts(keypoints, valid, boxes, height, width)
        if not points:
            return np.zeros((height, width), np.uint8)
        inputs = self.processor(
            image,
            input_points=[points],
            input_labels=[labels],
            input_boxes=[hand_boxes],
            return_tensors="pt",
        ).to(self.device)
        with torch.no_grad():
            outputs = self.model(**inputs, multimask_output=False)
        masks = self.processor.image_processor.post_process_masks(
            outputs.pred_masks.cpu(),
            inputs["original_sizes"].cpu(),
            inputs["reshaped_input_sizes"].cpu(),
        )[0]  # (K, 1, H, W) bool
        return np.asarray(masks).reshape(-1, height, width).any(axis=0).astype(np.uint8)
