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
- ``reprojection_error_px ()``, ``num_points3d ()``, ``focal_prior ()``, ``timings (3,)``;
- ``all_points3d (Q, 3)`` every point of the model and ``all_point_ids (Q,)`` their ids;
- ``obs_frame (N,)``, ``obs_uv (N, 2)``, ``obs_point_id (N,)``: every observation of a model
  point by a registered image (frame index, pixel, point id), for PnP tracking of the frames the
  mapper missed (:mod:`egosim.stages.depth_camera.tracking`);
- ``mapper ()``: which mapper built the kept model (``incremental`` or ``global``);
- ``focal_check_factors (C,)`` and ``focal_rise (C,)``: the focal-determinacy check of the kept
  model (:func:`focal_rise`): how much its reprojection error rises when its focal is held at each
  factor times its own and the same frames and tracks are bundle-adjusted again (empty when off).

Model choice: among the models built (one per focal prior, plus the global mapper's when
``try_global``), a model whose focal gives a horizontal field of view inside
``plausible_fov_deg`` beats one outside it; then more registered images; then lower mean
reprojection error. When no model is plausible and ``prior_focal`` is set, one more model is
built with the focal fixed at the prior.

Focal check (``focal_check_factors``): the kept model is bundle-adjusted again on the same
registered frames and tracks (at most ``focal_check_points`` of its points), once with the focal
free and once per factor with the focal held at that factor times the model's own. A motion that
pins the focal (translation with depth variation) makes the held fits clearly worse; a head that
nearly only turns does not (the EgoDex sample: +1% / +0% at 0.7x / 1.4x; DWM and HOT3D +34% or
more, synthetic +65% or more). The stage reads the rises (``DepthCameraConfig.sfm_focal_min_rise``).
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
FOCAL_CHECK_TRUNCATE_PX = 4.0  # focal check: per-observation error cap (outliers, points behind)
FOCAL_CHECK_ITERATIONS = 50  # focal check: Levenberg-Marquardt iterations per bundle adjustment


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


def _map(work: Path, db: Path, opts: dict[str, Any], out: Path, refine_focal: bool = True) -> Any:
    pipeline = pycolmap.IncrementalPipelineOptions()
    pipeline.num_threads = int(opts["num_threads"])
    pipeline.extract_colors = False
    pipeline.multiple_models = True
    pipeline.min_model_size = 3
    pipeline.ba_refine_principal_point = False
    pipeline.ba_refine_focal_length = refine_focal
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


def _map_global(work: Path, db: Path, opts: dict[str, Any], out: Path) -> Any:
    """pycolmap's global mapper (GLOMAP) on the same database; None when it builds nothing."""
    options = pycolmap.GlobalPipelineOptions()
    options.num_threads = int(opts["num_threads"])
    options.random_seed = 0
    options.min_model_size = 3
    options.mapper.num_threads = int(opts["num_threads"])
    options.mapper.random_seed = 0
    options.mapper.bundle_adjustment.refine_principal_point = False
    options.mapper.global_positioning.use_gpu = False
    options.mapper.bundle_adjustment.ceres.use_gpu = False
    if out.exists():
        shutil.rmtree(out)
    out.mkdir(parents=True)
    models = pycolmap.global_mapping(db, work / "images", out, options=options)
    if not models:
        return None
    return max(models.values(), key=lambda r: r.num_reg_images())


def _plausible(rec: Any, opts: dict[str, Any]) -> bool:
    """True when the model's focal gives a horizontal FOV inside ``plausible_fov_deg``."""
    focal = float(next(iter(rec.cameras.values())).params[0])
    fov = 2.0 * np.degrees(np.arctan(0.5 * float(opts["width"]) / focal))
    low, high = opts["plausible_fov_deg"]
    return bool(low <= fov <= high)


def _describe(rec: Any, num_images: int) -> str:
    """One log line about a model: registered images, focal, reprojection error."""
    if rec is None:
        return f"no model (0/{num_images})"
    focal = float(next(iter(rec.cameras.values())).params[0])
    return (
        f"{rec.num_reg_images()}/{num_images} registered, f {focal:.1f}, "
        f"{rec.compute_mean_reprojection_error():.2f} px"
    )


def _score(rec: Any, opts: dict[str, Any]) -> tuple[bool, int, float]:
    """Sort key: plausible focal first, then more registered images, then lower error."""
    return (
        _plausible(rec, opts),
        rec.num_reg_images(),
        -rec.compute_mean_reprojection_error(),
    )


def observation_errors(rec: Any) -> np.ndarray:
    """``(N,)`` reprojection error (px) of every observation of a model point by a registered
    image (SIMPLE_PINHOLE); a point behind the camera counts as ``inf``.

    pycolmap's ``compute_mean_reprojection_error`` averages errors stored per point, which bundle
    adjustment does not update: the check needs its own figure.
    """
    cam = next(iter(rec.cameras.values()))
    f, cx, cy = (float(v) for v in np.asarray(cam.params)[:3])
    errors = []
    for image_id in rec.reg_image_ids():
        image = rec.image(image_id)
        pairs = [(p.xy, p.point3D_id) for p in image.points2D if p.has_point3D()]
        if not pairs:
            continue
        uv = np.asarray([xy for xy, _ in pairs], dtype=np.float64)  # (M, 2)
        xyz = np.asarray([rec.point3D(i).xyz for _, i in pairs], dtype=np.float64)  # (M, 3)
        cam_from_world = image.cam_from_world().matrix()  # (3, 4)
        pts_cam = xyz @ cam_from_world[:, :3].T + cam_from_world[:, 3]  # (M, 3)
        front = pts_cam[:, 2] > 1e-9
        z = np.where(front, pts_cam[:, 2], 1.0)[:, None]
        proj = f * pts_cam[:, :2] / z + np.array([cx, cy])  # (M, 2)
        errors.append(np.where(front, np.linalg.norm(proj - uv, axis=1), np.inf))
    return np.concatenate(errors) if errors else np.zeros(0)


def _adjusted_error(rec: Any, focal: float, refine_focal: bool, threads: int) -> float:
    """Mean truncated reprojection error (px) of a copy of ``rec`` bundle-adjusted with its
    focal set to ``focal`` (refined or held), poses and points free, principal point held."""
    rec = pycolmap.Reconstruction(rec)
    camera_id = next(iter(rec.cameras))
    params = np.asarray(rec.cameras[camera_id].params, dtype=np.float64).copy()
    params[0] = focal
    rec.cameras[camera_id].params = params
    options = pycolmap.BundleAdjustmentOptions()
    options.refine_focal_length = refine_focal
    options.refine_principal_point = False
    options.refine_extra_params = False
    options.print_summary = False
    options.ceres.solver_options.num_threads = threads
    options.ceres.solver_options.max_num_iterations = FOCAL_CHECK_ITERATIONS
    config = pycolmap.BundleAdjustmentConfig()
    for image_id in rec.reg_image_ids():
        config.add_image(image_id)
    config.fix_gauge(pycolmap.BundleAdjustmentGauge.TWO_CAMS_FROM_WORLD)
    pycolmap.create_default_bundle_adjuster(options, config, rec).solve()
    errors = observation_errors(rec)
    return float(np.mean(np.minimum(errors, FOCAL_CHECK_TRUNCATE_PX))) if len(errors) else 0.0


def focal_rise(
    rec: Any, factors: list[float], max_points: int, threads: int = 1, seed: int = 0
) -> np.ndarray:
    """``(C,)`` relative rise of ``rec``'s reprojection error when its focal is held at each of
    ``factors`` times its own, against the focal left free, on the same registered frames and
    tracks (at most ``max_points`` of its points, drawn with ``seed``).

    Each figure is the mean per-observation error, capped at ``FOCAL_CHECK_TRUNCATE_PX``, after a
    bundle adjustment of poses and points from the model's own. Near 0: the frames fit another
    focal as well, so the motion does not pin the focal (nor the depth that goes with it).
    """
    rec = pycolmap.Reconstruction(rec)
    ids = np.asarray(sorted(rec.point3D_ids()), dtype=np.int64)
    if len(ids) > max_points:
        keep = np.random.default_rng(seed).choice(ids, max_points, replace=False)
        for point_id in np.setdiff1d(ids, keep):
            rec.delete_point3D(int(point_id))
    focal = float(next(iter(rec.cameras.values())).params[0])
    free = _adjusted_error(rec, focal, True, threads)
    held = [_adjusted_error(rec, factor * focal, False, threads) for factor in factors]
    return np.asarray([h / max(free, 1e-9) - 1.0 for h in held], dtype=np.float64)


def _export(
    rec: Any,
    out_path: Path,
    focal_prior: float,
    timings: list[float],
    mapper: str,
    focal_check: tuple[np.ndarray, np.ndarray],
) -> None:
    index, cam_from_world = [], []
    obs_frame: list[int] = []
    obs_uv: list[Any] = []
    obs_point: list[int] = []
    frame0 = None
    for image_id in rec.reg_image_ids():
        image = rec.image(image_id)
        k = int(Path(image.name).stem)
        index.append(k)
        cam_from_world.append(np.vstack([image.cam_from_world().matrix(), [0, 0, 0, 1]]))
        if k == 0:
            frame0 = image
        for p2d in image.points2D:
            if p2d.has_point3D():
                obs_frame.append(k)
                obs_uv.append(p2d.xy)
                obs_point.append(int(p2d.point3D_id))
    point_ids = np.asarray(sorted(rec.point3D_ids()), dtype=np.int64)
    all_xyz = np.asarray([rec.point3D(int(i)).xyz for i in point_ids], dtype=np.float64)
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
        all_points3d=all_xyz.reshape(-1, 3),
        all_point_ids=point_ids,
        obs_frame=np.asarray(obs_frame, dtype=np.int64),
        obs_uv=np.asarray(obs_uv, dtype=np.float64).reshape(-1, 2),
        obs_point_id=np.asarray(obs_point, dtype=np.int64),
        mapper=np.asarray(mapper),
        focal_check_factors=np.asarray(focal_check[0], dtype=np.float64),
        focal_rise=np.asarray(focal_check[1], dtype=np.float64),
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
    best, best_prior, best_mapper = None, 0.0, "incremental"
    priors = [factor * width for factor in opts["focal_factors"]]
    if opts.get("prior_focal"):
        priors = [float(opts["prior_focal"]), *priors]

    def consider(rec: Any, prior: float, mapper: str) -> None:
        nonlocal best, best_prior, best_mapper
        if rec is not None and (best is None or _score(rec, opts) > _score(best, opts)):
            best, best_prior, best_mapper = rec, prior, mapper

    def good_enough() -> bool:
        return (
            best is not None
            and _plausible(best, opts)
            and best.num_reg_images() >= opts["good_enough_fraction"] * num_images
            and best.compute_mean_reprojection_error() <= opts["good_max_reprojection_px"]
        )

    fixed_done = False

    def map_fixed() -> None:
        """The model with the focal fixed at the clip's prior (self-calibration implausible)."""
        nonlocal fixed_done
        fixed_done = True
        _set_focal(db, float(opts["prior_focal"]))
        rec = _map(work, db, opts, work / "sparse_fixed", refine_focal=False)
        sys.stderr.write(f"sfm_worker: fixed prior focal: {_describe(rec, num_images)}\n")
        consider(rec, float(opts["prior_focal"]), "incremental-fixed-focal")

    for prior in priors:
        _set_focal(db, prior)
        rec = _map(work, db, opts, work / f"sparse_{prior:.0f}")
        sys.stderr.write(f"sfm_worker: focal prior {prior:.1f}: {_describe(rec, num_images)}\n")
        consider(rec, prior, "incremental")
        if good_enough():
            break  # a wrong focal can register every frame too, but with a larger error
        drifted = rec is not None and not _plausible(rec, opts)  # focal left the range
        if opts.get("prior_focal") and not fixed_done and drifted:
            map_fixed()
            if good_enough():
                break
    if opts.get("try_global") and not good_enough():
        _set_focal(db, priors[0])
        t_global = time.perf_counter()
        rec = _map_global(work, db, opts, work / "sparse_global")
        sys.stderr.write(
            f"sfm_worker: global mapper: {_describe(rec, num_images)} in "
            f"{time.perf_counter() - t_global:.1f} s\n"
        )
        consider(rec, priors[0], "global")
    if opts.get("prior_focal") and not fixed_done and (best is None or not _plausible(best, opts)):
        map_fixed()
    t2 = time.perf_counter()
    if best is None:
        sys.stderr.write("SfM built no model (too little texture, overlap or parallax)\n")
        return EXIT_NO_MODEL
    factors = [float(v) for v in opts.get("focal_check_factors", [])]
    rise = np.zeros(0)
    if factors:
        rise = focal_rise(best, factors, int(opts["focal_check_points"]), int(opts["num_threads"]))
        sys.stderr.write(
            "sfm_worker: focal check: error rise "
            + ", ".join(f"{r:+.1%} at {k:g}x" for k, r in zip(factors, rise, strict=True))
            + f" in {time.perf_counter() - t2:.1f} s\n"
        )
    t3 = time.perf_counter()
    _export(
        best,
        work / "result.npz",
        best_prior,
        [t1 - t0, t2 - t1, t3 - t2],
        best_mapper,
        (np.asarray(factors, dtype=np.float64), rise),
    )
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
