"""Optional backend: any diffusers inpainting pipeline loaded from a local path.

``AutoPipelineForInpainting.from_pretrained(path, local_files_only=True)``; diffusers (and torch)
are imported lazily. Pre-processing pads the image to a multiple of 8 (edge replication) and
gives the model a white-on-black mask of the pixels to repaint; post-processing crops back and
keeps every unmasked pixel of the original, so only masked pixels change.
"""

from __future__ import annotations

from typing import Any

import numpy as np

MULTIPLE = 8  # latent diffusion models need sizes divisible by the VAE factor


class DiffusersBackendError(RuntimeError):
    """The diffusers backend cannot run (no weights at the path, a failed call)."""


def prepare_inputs(image: np.ndarray, mask: np.ndarray) -> tuple[Any, Any, tuple[int, int]]:
    """PIL image and mask (255 = repaint) padded to multiples of 8; returns the original size."""
    from PIL import Image

    h, w = mask.shape
    pad_h, pad_w = -h % MULTIPLE, -w % MULTIPLE
    padded = np.pad(image, ((0, pad_h), (0, pad_w), (0, 0)), mode="edge")  # (H', W', 3)
    padded_mask = np.pad((mask > 0).astype(np.uint8) * 255, ((0, pad_h), (0, pad_w)), mode="edge")
    return Image.fromarray(padded), Image.fromarray(padded_mask), (h, w)


def composite_output(generated: Any, image: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Crop the model's output to ``image``'s size and keep original pixels outside ``mask``."""
    h, w = mask.shape
    out = np.asarray(generated.convert("RGB"))
    if out.shape[:2] != (h + (-h % MULTIPLE), w + (-w % MULTIPLE)):
        from PIL import Image

        size = (w + (-w % MULTIPLE), h + (-h % MULTIPLE))
        out = np.asarray(generated.convert("RGB").resize(size, Image.BICUBIC))
    out = out[:h, :w]
    return np.where(mask[..., None] > 0, out, image).astype(np.uint8)


class DiffusersInpainter:
    """Inpaint with a diffusers pipeline from a local folder (or a given pipeline object)."""

    def __init__(
        self,
        model_path: str = "",
        device: str = "cpu",
        prompt: str = "",
        steps: int = 30,
        guidance_scale: float = 7.5,
        seed: int = 0,
        pipeline: Any = None,
    ) -> None:
        """Load the pipeline from ``model_path`` unless ``pipeline`` is given."""
        if pipeline is None:
            if not model_path:
                raise DiffusersBackendError("the diffusers backend needs a local model path")
            from diffusers import AutoPipelineForInpainting

            try:
                pipeline = AutoPipelineForInpainting.from_pretrained(
                    model_path, local_files_only=True
                ).to(device)
            except (OSError, ValueError) as exc:
                raise DiffusersBackendError(
                    f"cannot load an inpainting pipeline from {model_path!r}: {exc}"
                ) from exc
        self.pipeline = pipeline
        self.device = device
        self.prompt = prompt
        self.steps = steps
        self.guidance_scale = guidance_scale
        self.seed = seed

    def inpaint(self, image: np.ndarray, mask: np.ndarray) -> np.ndarray:
        """``image (H, W, 3)`` uint8 RGB with ``mask (H, W)`` pixels repainted by the model."""
        import torch

        pil_image, pil_mask, _ = prepare_inputs(image, mask)
        generator = torch.Generator(device="cpu").manual_seed(self.seed)
        result = self.pipeline(
            prompt=self.prompt,
            image=pil_image,
            mask_image=pil_mask,
            height=pil_image.height,
            width=pil_image.width,
            num_inference_steps=self.steps,
            guidance_scale=self.guidance_scale,
            generator=generator,
        )
        return composite_output(result.images[0], image, mask)
