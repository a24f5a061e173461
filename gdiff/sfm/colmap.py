"""Registration with COLMAP (pycolmap): SIFT features, matching, incremental mapping retried
with further seeds and looser thresholds, and the final robust global refinement."""

from __future__ import annotations

import contextlib
import logging
import sqlite3
from pathlib import Path
from typing import Iterator

import numpy as np

from ..cameras import SET_TIME, SETS, Camera
from ..errors import PosesError
from .images import _check_unregistered, _count
from .match import all_pairs, match_in_processes
from .options import PosesOptions
from .pairs import per_set_neighbours, retrieval_pairs, sequential_pairs, word_histograms
from .resample import shares_one_camera

log = logging.getLogger("gdiff.sfm")


@contextlib.contextmanager
def _colmap_logging(verbose: bool) -> Iterator[None]:
    import pycolmap

    old = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = old if verbose else max(old, 1)
    try:
        yield
    finally:
        pycolmap.logging.minloglevel = old


def _extract(db: Path, scene_dir: Path, names: list[str], opts: PosesOptions,
             single_camera: bool, camera_params: list[float] | None = None) -> None:
    import pycolmap

    ro = pycolmap.ImageReaderOptions()
    ro.camera_model = opts.camera_model
    if camera_params is not None:
        ro.camera_params = ",".join(f"{v:.10g}" for v in camera_params)
    eo = pycolmap.FeatureExtractionOptions()
    eo.num_threads = opts.colmap_threads()
    eo.max_image_size = opts.max_image_size
    eo.sift.max_num_features = opts.max_num_features
    eo.sift.domain_size_pooling = bool(opts.domain_size_pooling)
    mode = pycolmap.CameraMode.SINGLE if single_camera else pycolmap.CameraMode.PER_IMAGE
    pycolmap.extract_features(db, scene_dir, image_names=names, camera_mode=mode,
                              reader_options=ro, extraction_options=eo,
                              device=pycolmap.Device.cpu)


def extraction_scale(sizes: dict[str, tuple[int, int]], max_image_size: int) -> float:
    """Full-resolution pixels per feature-extraction pixel (>= 1): images whose longer side
    exceeds ``max_image_size`` are downscaled for SIFT, so keypoint noise measured in
    full-resolution pixels grows by this factor. The largest factor over ``sizes``
    (``name -> (width, height)``) is returned."""
    longest = max(max(wh) for wh in sizes.values())
    if max_image_size <= 0 or longest <= max_image_size:
        return 1.0
    return longest / float(max_image_size)


def size_groups(names: list[str], sizes: dict[str, tuple[int, int]]
                ) -> dict[tuple[int, int], list[str]]:
    """The image names grouped by ``(width, height)``, in order of appearance: COLMAP gives
    each group one camera (photos of one size are taken as one camera's; a camera per photo
    leaves each focal length to a handful of matches and fails on small photos)."""
    groups: dict[tuple[int, int], list[str]] = {}
    for n in names:
        groups.setdefault(tuple(sizes[n]), []).append(n)
    return groups


def _match(db: Path, work: Path, opts: PosesOptions, pairs: list[tuple[str, str]] | None,
           pixel_scale: float = 1.0) -> None:
    """Exhaustive matching if ``pairs`` is None, else match exactly ``pairs``; two-view RANSAC
    threshold ``2 * max_reproj_error`` extraction pixels (``pixel_scale`` full-res px each).
    With ``repeatable`` the pairs are matched in worker processes on one thread each
    (:mod:`gdiff.sfm.match`) and then verified on ``num_threads``."""
    import pycolmap

    vo = pycolmap.TwoViewGeometryOptions()
    vo.ransac.random_seed = opts.seed
    vo.ransac.max_error = 2.0 * opts.max_reproj_error * pixel_scale
    if opts.repeatable:
        match_in_processes(db, work, all_pairs(db) if pairs is None else pairs,
                           opts.num_threads, quiet=not opts.colmap_log)
        go = pycolmap.GeometricVerifierOptions()
        go.num_threads = opts.num_threads  # each pair's RANSAC is seeded: same on any thread
        pycolmap.geometric_verification(db, verifier_options=go, two_view_geometry_options=vo)
    elif pairs is None:
        pycolmap.match_exhaustive(db, matching_options=_threads(opts), verification_options=vo,
                                  device=pycolmap.Device.cpu)
    else:
        pair_file = work / "pairs.txt"
        pair_file.write_text("".join(f"{a} {b}\n" for a, b in pairs))
        po = pycolmap.ImportedPairingOptions()
        po.match_list_path = str(pair_file)
        pycolmap.match_image_pairs(db, matching_options=_threads(opts), pairing_options=po,
                                   verification_options=vo, device=pycolmap.Device.cpu)
    _sort_pairs(db)


def _threads(opts: PosesOptions):
    """COLMAP matching options on ``num_threads`` threads of this process."""
    import pycolmap

    mo = pycolmap.FeatureMatchingOptions()
    mo.num_threads = opts.num_threads
    return mo


def _sort_pairs(db: Path) -> None:
    """Rewrite the database's match tables in pair-id order. Matching threads insert pairs in
    the order they finish, and the mapper builds its correspondence graph (and so its tracks
    and points) in the tables' row order: sorted, the model does not depend on the threads."""
    with contextlib.closing(sqlite3.connect(db)) as con, con:
        for table in ("matches", "two_view_geometries"):
            con.execute(f"CREATE TEMP TABLE sorted_pairs AS SELECT * FROM {table} ORDER BY pair_id")
            con.execute(f"DELETE FROM {table}")
            con.execute(f"INSERT INTO {table} SELECT * FROM sorted_pairs ORDER BY pair_id")
            con.execute("DROP TABLE sorted_pairs")


def _read_descriptors(db: Path, names: list[str]) -> list[np.ndarray]:
    """The SIFT descriptors (M_i, 128) uint8 of the named images, from the database."""
    import pycolmap

    d = pycolmap.Database.open(str(db))
    try:
        ids = {im.name: im.image_id for im in d.read_all_images()}
        return [np.asarray(d.read_descriptors(ids[n]).data) for n in names]
    finally:
        d.close()


def _db_stats(db: Path, min_inliers: int) -> dict:
    """Images, mean keypoints per image and pairs with >= ``min_inliers`` verified matches."""
    import pycolmap

    d = pycolmap.Database.open(str(db))
    try:
        n = d.num_images()
        kp = d.num_keypoints() / max(n, 1)
        _, inliers = d.read_two_view_geometry_num_inliers()
        good = int(np.sum(np.asarray(inliers) >= min_inliers))
        return {"images": n, "mean_keypoints": kp, "verified_pairs": good}
    finally:
        d.close()


def _mapper_options(opts: PosesOptions, n_images: int, pixel_scale: float = 1.0,
                    seed: int | None = None, relax: float = 1.0):
    """COLMAP incremental-mapper options; pixel thresholds ``relax * opts.max_reproj_error``
    (extraction pixels, times ``pixel_scale`` for full-resolution pixels)."""
    import pycolmap

    mp = pycolmap.IncrementalPipelineOptions()
    mp.num_threads = opts.colmap_threads()
    mp.random_seed = opts.seed if seed is None else seed
    err = relax * opts.max_reproj_error * pixel_scale
    mp.mapper.filter_max_reproj_error = err
    mp.mapper.init_max_error = err
    mp.mapper.abs_pose_max_error = 3.0 * err
    mp.triangulation.merge_max_reproj_error = err
    mp.triangulation.complete_max_reproj_error = err
    mp.min_num_matches = opts.min_num_matches
    mp.min_model_size = max(2, min(10, n_images // 4))
    mp.multiple_models = True
    mp.extract_colors = True
    mp.ba_refine_principal_point = bool(opts.refine_principal_point)
    # global BA while the model grows by 40 % (COLMAP: 10 %), one retriangulation round per
    # BA: the final refinement (:func:`refine_model`) bundle-adjusts everything anyway, and
    # COLMAP's schedule made mapping grow faster than the image count
    mp.ba_global_frames_ratio = mp.ba_global_points_ratio = 1.4
    mp.ba_global_max_refinements = mp.ba_local_max_refinements = 1
    return mp


def bundle_options(max_error: float, num_threads: int, refine_intrinsics: bool = True,
                   refine_principal_point: bool = False):
    """pycolmap bundle-adjustment options: Cauchy loss of scale ``max_error / 2`` pixels (a few
    pixels of a false match have little pull), Ceres stopping at a relative cost decrease of
    1e-6, the focal length refined with ``refine_intrinsics`` (else every intrinsic held), the
    principal point only if asked."""
    import pycolmap

    bo = pycolmap.BundleAdjustmentOptions()
    bo.print_summary = False
    bo.refine_focal_length = bool(refine_intrinsics)
    bo.refine_principal_point = bool(refine_intrinsics and refine_principal_point)
    if not refine_intrinsics:
        bo.refine_extra_params = False
    bo.ceres.loss_function_type = pycolmap.LossFunctionType.CAUCHY
    bo.ceres.loss_function_scale = 0.5 * max_error
    bo.ceres.solver_options.num_threads = num_threads
    # stop when an iteration lowers the cost by < 1e-6 relative (Ceres' own default; COLMAP
    # sets 0, so every round ran its 100 iterations long after the cameras stopped moving)
    bo.ceres.solver_options.function_tolerance = 1e-6
    return bo


def refine_model(rec, max_error: float, iterations: int, refine_principal_point: bool = False,
                 num_threads: int = -1) -> dict:
    """Final global refinement of a reconstruction, in place.

    Each round bundle-adjusts all registered cameras, their (shared) intrinsics and all points
    with a Cauchy loss of scale ``max_error / 2`` (so residuals of a few pixels from false
    matches that survived mapping have little pull), then deletes observations whose
    reprojection error exceeds ``max_error`` or whose points have a triangulation angle
    < 1.5 deg. The focal length is refined; the principal point only if asked.

    Args:
        rec: ``pycolmap.Reconstruction`` (modified).
        max_error: outlier threshold in pixels of the images as stored.
        iterations: rounds (0 = nothing is done).

    Returns:
        ``{"rounds", "removed_observations", "reprojection_before", "reprojection_after"}``
        (mean reprojection errors in pixels).
    """
    import pycolmap

    rec.update_point_3d_errors()  # the stored errors may predate edits to the model
    before = float(rec.compute_mean_reprojection_error())
    bo = bundle_options(max_error, num_threads, True, refine_principal_point)
    removed = 0
    level = pycolmap.logging.minloglevel
    for _ in range(iterations):
        pycolmap.bundle_adjustment(rec, bo)
        pycolmap.logging.minloglevel = level  # bundle_adjustment leaves it at INFO
        removed += int(pycolmap.ObservationManager(rec).filter_all_points3D(max_error, 1.5))
    rec.update_point_3d_errors()
    after = float(rec.compute_mean_reprojection_error())
    if iterations:
        log.info("global refinement: %d rounds, %d outlier observations removed, mean "
                 "reprojection error %.3f -> %.3f px", iterations, removed, before, after)
    return {"rounds": iterations, "removed_observations": removed,
            "reprojection_before": before, "reprojection_after": after}


def _camera_of(image, rec) -> tuple[int, int, float, float, float, float, tuple | None]:
    """(width, height, fx, fy, cx, cy, dist) of a pycolmap image's camera; ``dist`` is the
    OpenCV ``(k1, k2, p1, p2)`` of the distortion models (None for pinhole models)."""
    cam = rec.cameras[image.camera_id]
    p = np.asarray(cam.params, dtype=np.float64)
    name = cam.model.name
    dist = None
    if name in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL"):
        f, cx, cy = p[:3]
        fx = fy = f
        k = list(p[3:]) + [0.0] * (2 - len(p[3:]))
        dist = (k[0], k[1], 0.0, 0.0) if name != "SIMPLE_PINHOLE" else None
    elif name in ("PINHOLE", "OPENCV"):
        fx, fy, cx, cy = p[:4]
        dist = tuple(float(v) for v in p[4:8]) if name == "OPENCV" else None
    else:  # pragma: no cover - options restrict the model
        raise PosesError(f"camera model {name} is not supported")
    return (int(cam.width), int(cam.height), float(fx), float(fy), float(cx), float(cy),
            dist)


def _c2w_of(image) -> np.ndarray:
    """Camera-to-world 4x4 (OpenCV axes) of a registered pycolmap image."""
    w2c = np.eye(4)
    w2c[:3, :4] = image.cam_from_world().matrix()
    R, t = w2c[:3, :3], w2c[:3, 3]
    c2w = np.eye(4)
    c2w[:3, :3] = R.T
    c2w[:3, 3] = -R.T @ t
    return c2w


def _points_of(rec) -> tuple[np.ndarray, np.ndarray]:
    ids = sorted(rec.points3D.keys()) if hasattr(rec.points3D, "keys") else []
    if not ids:
        return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint8)
    xyz = np.stack([rec.points3D[i].xyz for i in ids]).astype(np.float32)
    rgb = np.stack([rec.points3D[i].color for i in ids]).astype(np.uint8)
    return xyz, rgb


def _run_colmap(root: Path, work: Path, images, sizes, opts: PosesOptions):
    import pycolmap

    names = [n for n, _ in images]
    db = work / "database.db"
    groups = size_groups(names, sizes)
    if len(groups) > 1:
        log.info("images differ in size: one camera per size (%s)",
                 ", ".join(f"{w}x{h}: {len(g)} images" for (w, h), g in groups.items()))
    pycolmap.set_random_seed(opts.seed)
    scale = extraction_scale(sizes, opts.max_image_size)
    for group in groups.values():  # each extraction adds one shared camera
        _extract(db, root, group, opts, single_camera=True)
    matcher = opts.matcher
    if matcher == "auto":
        matcher = "exhaustive" if len(names) <= opts.exhaustive_limit() else "retrieval"
    sets = [g for g in ([n for n, s in images if s == st] for st in SETS) if g]
    if matcher == "exhaustive":
        pairs = None
        log.info("matching: exhaustive (%d pairs)", len(names) * (len(names) - 1) // 2)
    elif matcher == "retrieval":
        vectors = dict(zip(names, word_histograms(_read_descriptors(db, names),
                                                  seed=opts.seed)))
        pairs = retrieval_pairs(sets, vectors, opts.retrieval_neighbours,
                                opts.sequential_overlap)
        log.info("matching: retrieval (%d pairs: per image the %d most similar images by "
                 "visual words of each of the %d sets + %d capture-order neighbours)",
                 len(pairs), per_set_neighbours(opts.retrieval_neighbours, len(sets)), len(sets),
                 opts.sequential_overlap)
    else:
        pairs = sequential_pairs(sets, opts.sequential_overlap, opts.sequential_links)
        log.info("matching: sequential (%d pairs: %d capture-order neighbours + %d links per "
                 "image and set)", len(pairs), opts.sequential_overlap, opts.sequential_links)
    _match(db, work, opts, pairs, scale)
    stats = _db_stats(db, opts.min_num_matches)
    log.info("features: %.0f keypoints per image; %d image pairs with >= %d verified matches",
             stats["mean_keypoints"], stats["verified_pairs"], opts.min_num_matches)
    core = core_images(images, opts.map_max_images)
    partial = len(core) < len(names)
    if partial:
        log.info("mapping: %d of %d images spread over the sets; the other %d are registered "
                 "to that model one by one (poses.map_max_images)", len(core), len(names),
                 len(names) - len(core))
    models, attempts = _map_best(db, root, work, opts, core if partial else None, len(core),
                                 scale)
    if not models or models[0].num_reg_images() < 2:
        raise PosesError(
            f"{root}: COLMAP could not register the images ({stats['verified_pairs']} verified "
            f"image pairs, {stats['mean_keypoints']:.0f} features per image on average, "
            f"{len(names)} images). Causes: too little overlap between the photos, untextured "
            "or repetitive surfaces, blur or very small images. Fixes: take more photos with "
            "large overlap (each part of the scene seen from several nearby views), add "
            "texture, use sharper/larger images, or give known poses (cameras.json or "
            "transforms.json in the scene folder, poses.source: known).")
    rec = models[0]
    if len(models) > 1:
        in_largest = {rec.images[i].name for i in rec.reg_image_ids()}
        sizes_m = [m.num_reg_images() for m in models]
        log.warning("COLMAP made %d models of %s images; keeping the largest", len(models),
                    sizes_m)
        for k, m in enumerate(models[1:], 1):
            only = sorted({m.images[i].name for i in m.reg_image_ids()} - in_largest)
            if only:
                log.warning("model %d holds images missing from the largest: %s", k,
                            ", ".join(only))
    refine = refine_model(rec, opts.max_reproj_error * scale, opts.refine_iterations,
                          opts.refine_principal_point, opts.colmap_threads())
    if partial:  # the others, and any the mapper left out
        mapped = {rec.images[i].name for i in rec.reg_image_ids()}
        rest = [n for n in names if n not in mapped]
        failed = register_rest(db, rec, rest, opts, scale)
        log.info("registered %d of the %d images outside the mapped model%s",
                 len(rest) - len(failed), len(rest),
                 f" (not: {', '.join(failed)})" if failed else "")
    by_name = {rec.images[i].name: rec.images[i] for i in rec.reg_image_ids()}
    dropped = _check_unregistered(images, set(by_name), opts.max_unregistered_fraction,
                                  f"COLMAP registration of {root}")
    cams = []
    for n, st in images:
        if n in dropped:
            continue
        im = by_name[n]
        w, h, fx, fy, cx, cy, dist = _camera_of(im, rec)
        cams.append(Camera(w, h, fx, fy, cx, cy, _c2w_of(im), image=n, set=st,
                           time=SET_TIME[st], dist=dist))
    summary = {"source": "colmap", "matcher": matcher, "images": _count(images),
               "registered": _count(images, set(by_name)), "dropped": dropped,
               "num_models": len(models), "mapper_attempts": attempts,
               "mapped_images": len(core),
               "num_points": int(rec.num_points3D()),
               "mean_reprojection_error": float(rec.compute_mean_reprojection_error()),
               "refinement": refine, "undistorted": any(c.dist is not None for c in cams),
               "resampled": not shares_one_camera(cams)}
    return cams, rec, summary, None


def core_images(images: list[tuple[str, str]], max_images: int | None) -> list[str]:
    """The images mapped incrementally when a scene has more than ``max_images`` of them.

    Each set keeps its share of ``max_images`` (at least two images), spread evenly over its
    capture order, so every set and every part of a capture path stays in the mapped model;
    the other images are then registered to it one by one (:func:`register_rest`).

    Args:
        images: ``(name, set)`` pairs in capture order within each set.
        max_images: the most images to map (None or >= the image count: all of them).

    Returns:
        The names of the core images, in the order of ``images``.
    """
    names = [n for n, _ in images]
    if max_images is None or len(names) <= max_images:
        return names
    sets: dict[str, list[str]] = {}
    for n, st in images:
        sets.setdefault(st, []).append(n)
    keep: set[str] = set()
    for members in sets.values():
        share = max(2, round(max_images * len(members) / len(names)))
        if share >= len(members):
            keep.update(members)
            continue
        picks = np.unique(np.round(np.linspace(0, len(members) - 1, share)).astype(int))
        keep.update(members[i] for i in picks)
    return [n for n in names if n in keep]


def register_rest(db: Path, rec, names: list[str], opts: PosesOptions, scale: float) -> list[str]:
    """Register each image of ``names`` to the model ``rec`` on its own, in place: 2D-3D
    correspondences through its verified matches with the registered images, absolute pose by
    RANSAC, then refinement of that one pose (COLMAP's ``IncrementalMapper``); its matches
    with the registered images are then triangulated into new points. The model's points and
    the other cameras do not move (no bundle adjustment), so the cost per image does not grow
    with the number of images. Images that fail are tried once more after the others.

    Returns:
        The names that could not be registered.
    """
    import pycolmap

    database = pycolmap.Database.open(str(db))
    try:
        co = pycolmap.DatabaseCacheOptions()
        co.min_num_matches = opts.min_num_matches
        cache = pycolmap.DatabaseCache.create(database, co)
    finally:
        database.close()
    mapper = pycolmap.IncrementalMapper(cache)
    mapper.begin_reconstruction(rec)
    mp = _mapper_options(opts, 0, scale)
    ids = {cache.image(i).name: i for i in cache.images}
    def register(name: str) -> bool:
        if not mapper.register_next_image(mp.mapper, ids[name]):
            return False
        # its matches with registered images become points too, so the images registered
        # after it find more 2D-3D correspondences
        mapper.triangulate_image(mp.triangulation, ids[name])
        return True

    todo = [n for n in names if n in ids]
    for _ in range(2):  # a second pass only if the first registered some
        before = len(todo)
        todo = [n for n in todo if not register(n)]
        if len(todo) in (0, before):
            break
    mapper.end_reconstruction(False)
    return todo + [n for n in names if n not in ids]


def _model_key(rec) -> tuple[int, float]:
    """Ranking of candidate models: more registered images first, then lower mean
    reprojection error."""
    return rec.num_reg_images(), -float(rec.compute_mean_reprojection_error())


def _map_best(db: Path, root: Path, work: Path, opts: PosesOptions, only: list[str] | None,
              n_images: int, scale: float) -> tuple[list, int]:
    """Incremental mapping of the ``n_images`` images (only those named in ``only``, or all
    of the database), repeated with the next seed and a looser threshold (run k:
    ``seed + k``, ``(k + 1) * max_reproj_error``; up to ``opts.mapper_attempts`` runs) while
    the best model leaves images unregistered.

    Returns:
        ``(models, attempts)``: the models of the best run, largest first, and the number of
        runs made.
    """
    import pycolmap

    best: list = []
    attempts = 0
    for k in range(opts.mapper_attempts):
        seed = opts.seed + k
        pycolmap.set_random_seed(seed)
        mp = _mapper_options(opts, n_images, scale, seed=seed, relax=k + 1.0)
        if only is not None:
            mp.image_names = list(only)
        recs = pycolmap.incremental_mapping(db, root, work / f"mapper{k}", options=mp)
        attempts += 1
        models = sorted(recs.values(), key=_model_key, reverse=True)
        if models and (not best or _model_key(models[0]) > _model_key(best[0])):
            best = models
        n_best = best[0].num_reg_images() if best else 0
        if n_best == n_images:
            break
        if k + 1 < opts.mapper_attempts:
            log.info("mapping: best model so far registers %d of %d images; run %d with "
                     "seed %d and a %.1f px threshold", n_best, n_images, k + 2, seed + 1,
                     (k + 2) * opts.max_reproj_error * scale)
    return best, attempts
