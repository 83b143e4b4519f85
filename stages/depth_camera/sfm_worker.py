"""Subprocess entry point that runs pycolmap incremental SfM on a folder of frames.

Run as ``python -m egosim.stages.depth_camera.sfm_worker WORKDIR``. ``WORKDIR`` holds
``images/NNNN.png`` (frames), optionally ``masks/NNNN.png.png`` (255 = use, 0 = ignore features)
and ``options.json`` (see :class:`egosim.stages.depth_camera.sfm.SfmOptions`). The worker writes
``result.npz`` (uncompressed) with the best model found, or exits non-zero with the reason on
stderr. pycolmap aborts the whole process on internal failures, which is why it runs here and
not in the stage's process (see HAZARDS.md).

Result arrays:

- ``image_index (R,)`` frame index of each registered image;
- ``cam_from_world (R, 4, 4)`` world-to-camera of each registered image;
- ``camera_params (3,)`` SIMPLE_PINHOLE ``f, cx, cy`` (single shared camera);
- ``points3d (P, 3)`` and ``points_frame0_uv (P, 2)``: the model's points seen in frame 0 and
  where frame 0 observes them (empty when frame 0 is not registered);
- ``reprojection_error_px ()``, ``num_points3d ()``, ``focal_prior ()``, ``timings (3,)``.
"""

# numpy before pycolmap: pycolmap bundles a zlib that breaks later deflate calls if it loads first.
import numpy as np  # isort: skip
import zlib  # noqa: F401  isort: skip

import json
import shutil
import sys
import time
from pathlib import Path
from typing import Any

import pycolmap  # isort: skip

EXIT_NO_MODEL = 3  # no model could be built (too little texture or parallax)


def _reader_options(opts: dict[str, Any], focal_factor: float, mask_dir: Path | None) -> Any:
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "SIMPLE_PINHOLE"
    reader.default_focal_length_factor = float(focal_factor)
    if mask_dir is not None:
        reader.mask_path = str(mask_dir)
    return reader


def _extract_and_match(work: Path, opts: dict[str, Any], focal_factor: float, db: Path) -> None:
    mask_dir = work / "masks" if (work / "masks").is_dir() else None
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.max_image_size = int(opts["max_image_size"])
    extraction.num_threads = int(opts["num_threads"])
    extraction.sift.max_num_features = int(opts["max_num_features"])
    pycolmap.extract_features(
        db,
        work / "images",
        camera_mode=pycolmap.CameraMode.SINGLE,
        reader_options=_reader_options(opts, focal_factor, mask_dir),
        extraction_options=extraction,
        device=pycolmap.Device.cpu,
    )
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = int(opts["num_threads"])
    pairing = pycolmap.SequentialPairingOptions()
    pairing.overlap = int(opts["sequential_overlap"])
    pairing.quadratic_overlap = bool(opts["quadratic_overlap"])
    pairing.loop_detection = False  # needs a vocabulary tree download: aborts offline
    pycolmap.match_sequential(
        db, matching_options=matching, pairing_options=pairing, device=pycolmap.Device.cpu
    )


def _set_focal(db_path: Path, focal: float) -> None:
    """Overwrite the prior focal length of every camera in the database."""
    db = pycolmap.Database.open(db_path)
    try:
        for camera in db.read_all_cameras():
            params = np.asarray(camera.params, dtype=np.float64).copy()
            params[0] = focal
            camera.params = params
            camera.has_prior_focal_length = False
            db.update_camera(camera)
    finally:
        db.close()


def _map(work: Path, db: Path, opts: dict[str, Any], out: Path) -> Any:
    pipeline = pycolmap.IncrementalPipelineOptions()
    pipeline.num_threads = int(opts["num_threads"])
    pipeline.extract_colors = False
    pipeline.multiple_models = True
    pipeline.min_model_size = 3
    pipeline.ba_refine_principal_point = False
    pipeline.ba_refine_focal_length = True
    pipeline.max_runtime_seconds = int(opts["max_mapping_seconds"])
    pipeline.random_seed = 0
    pipeline.mapper.init_min_tri_angle = float(opts["init_min_tri_angle"])
    pipeline.mapper.random_seed = 0
    pipeline.triangulation.random_seed = 0
    if out.exists():
        shutil.rmtree(out)
    out.mkdir(parents=True)
    models = pycolmap.incremental_mapping(db, work / "images", out, options=pipeline)
    if not models:
        return None
    return max(models.values(), key=lambda r: r.num_reg_images())


def _score(rec: Any) -> tuple[int, float]:
    """Sort key: more registered images first, then lower reprojection error."""
    return (rec.num_reg_images(), -rec.compute_mean_reprojection_error())


def _export(rec: Any, out_path: Path, focal_prior: float, timings: list[float]) -> None:
    index, cam_from_world = [], []
    frame0 = None
    for image_id in rec.reg_image_ids():
        image = rec.image(image_id)
        k = int(Path(image.name).stem)
        index.append(k)
        cam_from_world.append(np.vstack([image.cam_from_world().matrix(), [0, 0, 0, 1]]))
        if k == 0:
            frame0 = image
    cameras = list(rec.cameras.values())
    points, uvs = [], []
    if frame0 is not None:
        for p2d in frame0.points2D:
            if p2d.has_point3D():
                points.append(rec.point3D(p2d.point3D_id).xyz)
                uvs.append(p2d.xy)
    np.savez(
        out_path,
        image_index=np.asarray(index, dtype=np.int64),
        cam_from_world=np.asarray(cam_from_world, dtype=np.float64).reshape(-1, 4, 4),
        camera_params=np.asarray(cameras[0].params, dtype=np.float64),
        points3d=np.asarray(points, dtype=np.float64).reshape(-1, 3),
        points_frame0_uv=np.asarray(uvs, dtype=np.float64).reshape(-1, 2),
        reprojection_error_px=np.float64(rec.compute_mean_reprojection_error()),
        num_points3d=np.int64(rec.num_points3D()),
        focal_prior=np.float64(focal_prior),
        timings=np.asarray(timings, dtype=np.float64),
    )


def main(argv: list[str]) -> int:
    """Run SfM in ``argv[0]``; returns the process exit code."""
    pycolmap.logging.logtostderr = True
    pycolmap.logging.minloglevel = 2  # errors only
    work = Path(argv[0])
    opts = json.loads((work / "options.json").read_text())
    num_images = len(list((work / "images").glob("*.png")))
    width = float(opts["width"])
    db = work / "database.db"
    t0 = time.perf_counter()
    _extract_and_match(work, opts, opts["focal_factors"][0], db)
    t1 = time.perf_counter()
    sys.stderr.write(f"sfm_worker: features and matches in {t1 - t0:.1f} s\n")
    best, best_prior = None, 0.0
    for factor in opts["focal_factors"]:
        _set_focal(db, factor * width)
        rec = _map(work, db, opts, work / f"sparse_{factor:g}")
        sys.stderr.write(
            f"sfm_worker: focal factor {factor:g}: "
            f"{0 if rec is None else rec.num_reg_images()}/{num_images} registered\n"
        )
        if rec is not None and (best is None or _score(rec) > _score(best)):
            best, best_prior = rec, factor * width
        if (
            best is not None
            and best.num_reg_images() >= opts["good_enough_fraction"] * num_images
            and best.compute_mean_reprojection_error() <= opts["good_max_reprojection_px"]
        ):
            break  # a wrong focal can register every frame too, but with a larger error
    t2 = time.perf_counter()
    if best is None:
        sys.stderr.write("SfM built no model (too little texture, overlap or parallax)\n")
        return EXIT_NO_MODEL
    _export(best, work / "result.npz", best_prior, [t1 - t0, t2 - t1, 0.0])
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
