"""The ``evaluate`` stage: figures of a generated clip against its packed ground truth.

- PSNR and SSIM over the whole clip, PSNR over the hand region (the pack's hand mask), each also
  for the copy-the-scene-video baseline: the condition the model gets (the hand-free first frame,
  then the scene render, black where nothing was rendered).
- LPIPS (AlexNet) when ``lpips_weights`` names a local weights file and the package is there.
- Depth-ERR and Cam-ERR (``camera_backend``): the registered ``depth_camera`` stage with that
  backend estimates intrinsics, poses and frame-0 depth *from the generated frames*; the result
  is aligned to the pack's reference cameras at frame 0, scaled by the median depth ratio, and
  compared: Depth-ERR = AbsRel of frame-0 depth, Cam-ERR = mean per-pixel Plücker-ray distance
  (:func:`egosim.pipeline.geometry.camera_error`). ``sfm`` is the honest estimate (heavy, and it
  needs frames big enough to match features: on ``tiny``-sized clips it usually fails and the
  figures are null with the reason in ``note``). ``given`` hands the reference cameras and depth
  back, so its figures are 0 by construction: a plumbing check, not a measurement. ``none``
  skips both.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any, ClassVar, Literal

import numpy as np

from egosim.model.metrics import lpips_distance, psnr, ssim
from egosim.pipeline import media
from egosim.pipeline.clip_io import row_from_clip
from egosim.pipeline.geometry import camera_error, invert_se3
from egosim.pipeline.records import Clip, PackRecord, SimulationRecord
from egosim.pipeline.stage import ClipRejected, ClipStage, ConfigError, StageConfig, get_stage
from egosim.schemas import ShardSchema
from egosim.schemas.pack import EVALUATION, PACK, SIMULATION

CameraBackend = Literal["none", "given", "sfm", "da3"]


@dataclasses.dataclass(frozen=True)
class EvaluateConfig(StageConfig):
    """Parameters of ``evaluate``."""

    camera_backend: CameraBackend = "none"  # depth_camera backend run on generated clips
    lpips_weights: str = ""  # local LPIPS alex.pth; "" = no LPIPS

    def __post_init__(self) -> None:
        if self.camera_backend not in ("none", "given", "sfm", "da3"):
            raise ConfigError(
                f"camera_backend must be none, given, sfm or da3, got {self.camera_backend!r}"
            )


def baseline_video(videos: Mapping[str, np.ndarray]) -> np.ndarray:
    """Copy-the-scene-video baseline ``(T, H, W, 3)``: first frame, then the visible scene."""
    scene = videos["scene"] * videos["visible"][..., None]  # unseen pixels black
    return np.concatenate([videos["first_frame"][None], scene[1:]]).astype(np.uint8)


def masked_psnr(pred: np.ndarray, target: np.ndarray, mask: np.ndarray) -> float | None:
    """PSNR over pixels where ``mask (T, H, W)`` is set; None when the mask is empty."""
    sel = mask.astype(bool)
    if not sel.any():
        return None
    return psnr(pred[sel], target[sel])


def align_and_compare(
    intrinsics: np.ndarray,
    ref_poses: np.ndarray,
    ref_depth0: np.ndarray | None,
    est_poses: np.ndarray,
    est_depth0: np.ndarray | None,
    height: int,
    width: int,
) -> tuple[float | None, float]:
    """(Depth-ERR, Cam-ERR) of estimated vs reference cameras ``(T, 4, 4)`` and depth ``(H, W)``.

    The estimate's trajectory is expressed relative to its frame 0, scaled by the median
    reference/estimate depth ratio (1 without depth), and re-anchored at the reference frame 0.
    """
    scale, depth_err = 1.0, None
    if ref_depth0 is not None and est_depth0 is not None:
        valid = (ref_depth0 > 0) & (est_depth0 > 0)
        if valid.any():
            scale = float(np.median(ref_depth0[valid] / est_depth0[valid]))
            rel = np.abs(scale * est_depth0[valid] - ref_depth0[valid]) / ref_depth0[valid]
            depth_err = float(rel.mean())
    rel_poses = invert_se3(est_poses[0])[None] @ est_poses  # (T, 4, 4) est_cam0_from_cam
    rel_poses[:, :3, 3] *= scale
    aligned = ref_poses[0][None] @ rel_poses  # (T, 4, 4) world_from_cam
    return depth_err, camera_error(intrinsics, aligned, ref_poses, height, width)


class EvaluateStage(ClipStage):
    """PSNR, SSIM, hand-region PSNR, LPIPS, Depth-ERR and Cam-ERR of generated clips."""

    name = "evaluate"
    description = "PSNR, SSIM, Depth-ERR, Cam-ERR (Plücker), LPIPS; vs the copy-scene baseline"
    config_class = EvaluateConfig
    inputs: ClassVar[Mapping[str, ShardSchema]] = {"pack": PACK, "simulation": SIMULATION}
    output = EVALUATION
    backends = ("metrics",)
    config: EvaluateConfig

    def process(self, rows: Mapping[str, Mapping[str, Any]]) -> dict[str, Any]:
        """Evaluate one generated clip."""
        pack, sim = PackRecord.of(rows["pack"]), SimulationRecord.of(rows["simulation"])
        cid = pack.clip_id
        t, h, w = pack.size
        videos = pack.videos
        gen = media.decode_rgb_video(sim["video"], h, w, f"clip {cid!r} generated video")
        if gen.shape != (t, h, w, 3):
            raise ClipRejected(
                f"inputs disagree: clip {cid!r}: generated video is {gen.shape}, the pack "
                f"sample is {(t, h, w, 3)}"
            )
        target, base = videos["target"], baseline_video(videos)
        hand = videos.get("hand_mask")
        notes = []
        if hand is None:
            notes.append("no hand mask in the pack: hand-region PSNR not computed")
        row: dict[str, Any] = {
            "clip_id": cid,
            "num_frames": t,
            "psnr": psnr(gen, target),
            "psnr_hand": None if hand is None else masked_psnr(gen, target, hand),
            "ssim": ssim(gen, target),
            "psnr_baseline": psnr(base, target),
            "psnr_hand_baseline": None if hand is None else masked_psnr(base, target, hand),
            "ssim_baseline": ssim(base, target),
            "lpips": None,
            "depth_err": None,
            "cam_err": None,
            "camera_backend": self.config.camera_backend,
            "hand_fraction": 0.0 if hand is None else float(hand.mean()),
        }
        if self.config.lpips_weights:
            row["lpips"] = lpips_distance(gen, target, self.config.lpips_weights)
            if row["lpips"] is None:
                notes.append("LPIPS skipped: package or local weights missing")
        if self.config.camera_backend != "none":
            notes += self._cameras(pack, gen, row)
        row["note"] = "; ".join(notes)
        return row

    def _cameras(self, pack: PackRecord, gen: np.ndarray, out: dict[str, Any]) -> list[str]:
        """Fill depth_err / cam_err in ``out``; returns notes on what could not be computed."""
        backend = self.config.camera_backend
        ref_poses = pack.world_from_cam
        if ref_poses is None:
            return ["no reference cameras in the pack: Depth-ERR and Cam-ERR not computed"]
        t, h, w = gen.shape[:3]
        intrinsics = pack.intrinsics
        ref_depth = pack.depth0
        depth = None
        if ref_depth is not None:  # the given backend reads the source depth of frame 0
            depth = np.zeros((t, h, w), dtype=np.float32)
            depth[0] = ref_depth
        clip = Clip(
            clip_id=pack.clip_id,
            source="generated",
            source_uri="",
            fps=pack.fps,
            timestamps=np.arange(t) / pack.fps,
            intrinsics=intrinsics,
            frames=gen,
            world_from_cam=ref_poses if backend == "given" else None,
            depth=depth if backend == "given" else None,
        )
        stage = get_stage("depth_camera").from_params({"backend": backend})
        try:
            est = stage.process({"clips": row_from_clip(clip)})  # type: ignore[attr-defined]
        except Exception as exc:  # an estimator failing on a generated clip is a finding
            return [f"camera backend {backend} failed on the generated clip: {exc}"]
        est_poses = np.asarray(est["world_from_cam"], dtype=np.float64).reshape(t, 4, 4)
        est_depth = None
        if est.get("depth0") is not None:
            est_depth = media.decode_depth_video(est["depth0"], est["depth_unit_m"])[0]
        depth_err, cam_err = align_and_compare(
            intrinsics, ref_poses, ref_depth, est_poses, est_depth, h, w
        )
        out["depth_err"], out["cam_err"] = depth_err, cam_err
        return [] if depth_err is not None else ["no depth to compare: Depth-ERR not computed"]
