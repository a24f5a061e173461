"""The poses stage entry point: register every image of a scene in one frame (COLMAP or known
poses) and write the outputs; ``cameras.json`` is written last."""

from __future__ import annotations

import logging
import os
import shutil
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from ..cameras import (PHOTO_CAMERAS, SETS, TRAIN_SETS, Camera, load_cameras,
                       save_cameras)
from ..errors import PosesError, SceneError
from ..splat.ply import write_points
from .colmap import _colmap_logging, _points_of, _run_colmap
from .images import _count, _image_sizes, discover_images
from .known import _run_known, _strip, load_known_cameras
from .options import PosesOptions
from .resample import to_one_pinhole
from .seed import depth_range, empty_cells, seed_frustum_points
from .undistort import undistort_reconstruction
from .upright import orientations, write_upright_copies

log = logging.getLogger("gdiff.sfm")

UPRIGHT = "upright"  # in the work folder: upright copies of EXIF-rotated photos (for COLMAP)


def run_poses(scene_dir: str | os.PathLike, out_dir: str | os.PathLike,
              options: PosesOptions | None = None,
              images: list[tuple[str, str]] | None = None,
              image_root: str | os.PathLike | None = None) -> dict:
    """Register all images of a scene in one frame and write the poses outputs.

    Args:
        scene_dir: the scene folder (images are addressed relative to it).
        out_dir: output folder (``sparse/0/``, ``points.ply``, ``cameras.json``).
        options: :class:`PosesOptions`.
        images: ``(relative path, set)`` pairs with set in before | after | eval_before |
            eval_after, in capture order within each set; None discovers them
            (:func:`discover_images`).
        image_root: the folder the image paths are relative to, when not ``scene_dir`` (the
            manifest's ``image_root``: frames taken from videos, see :mod:`gdiff.video`);
            ``cameras.json`` then names it in ``image_dir``.

    Returns:
        Summary dict: ``source`` (colmap | known), ``matcher``, ``images`` and ``registered``
        (counts per set), ``dropped`` (image names), ``num_models``, ``num_points`` (in the
        sparse model), ``num_points_triangulated`` and ``num_points_seeded`` (in points.ply;
        see :mod:`gdiff.sfm.seed`), ``undistorted`` (some photo had lens distortion),
        ``resampled`` (the photos' cameras differed: resampled to one common camera, see
        :mod:`gdiff.sfm.resample`), ``upright`` (photos with an EXIF orientation tag, given
        to COLMAP as upright copies, see :mod:`gdiff.sfm.upright`), ``image_dir`` (the folder
        of the photos to use, relative to ``out_dir``, or None for the scene's own),
        ``mean_reprojection_error`` (pixels), ``seconds``; for COLMAP also
        ``mapper_attempts``, ``mapped_images`` (images mapped incrementally; the others
        were registered to that model, see ``PosesOptions.map_max_images``) and
        ``refinement`` (see :func:`refine_model`).

    Raises:
        PosesError: registration failed, or a set lost too many images.
    """
    opts = options or PosesOptions()
    root = Path(scene_dir)
    out = Path(out_dir)
    t0 = time.time()
    images = [(_strip(n), s) for n, s in (images if images is not None
                                          else discover_images(root))]
    unknown_sets = sorted({s for _, s in images} - set(SETS))
    if unknown_sets:
        raise SceneError(f"image list for {root}: unknown set(s) {unknown_sets}; "
                         f"use {', '.join(SETS)}")
    names = [n for n, _ in images]
    photos = Path(image_root) if image_root is not None else root
    photo_dir = None if photos == root else os.path.relpath(photos, out)
    tags = orientations(photos, names)  # read once: PIL decodes a whole PNG to find its tag
    sizes = _image_sizes(photos, names, tags)
    counts = _count(images)
    log.info("poses for %s: %d images (%s)", root, len(images),
             ", ".join(f"{k} {v}" for k, v in counts.items()))

    known = None
    if opts.source in ("auto", "known"):
        known = load_known_cameras(root)
        if known is None and opts.source == "known":
            raise PosesError(f"{root}: poses.source is 'known' but the scene has no "
                             "cameras.json or transforms.json; add one or set "
                             "poses.source: colmap")
        if known is not None and photo_dir is not None:
            raise PosesError(f"{root}: known poses (cameras.json / transforms.json) cannot name "
                             "frames picked from a video; give photos with their poses, or "
                             "remove the poses file so that COLMAP registers the frames")
    out.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix=".poses_work_", dir=out))
    try:
        n_upright = 0
        if any(o != 1 for o in tags.values()):
            n_upright = write_upright_copies(photos, work / UPRIGHT, images, tags)
            photos = work / UPRIGHT
        with _colmap_logging(opts.colmap_log):
            if known is not None:
                result = _run_known(photos, work, images, sizes, known, opts)
            else:
                result = _run_colmap(photos, work, images, sizes, opts)
        cams, rec, summary, image_dir = result
        if image_dir is None:
            cams, image_dir = _one_pinhole(photos, work, cams, rec, opts)
        if image_dir is None and n_upright:  # the upright copies are the photos to use
            os.replace(work / UPRIGHT, work / "images")
            image_dir = "images"
        xyz, rgb = _points_of(rec)
        n_tri = len(xyz)
        # seeds come from the training photos only: an eval photo must not shape the fit
        train = [c for c in cams if c.set in TRAIN_SETS]
        n_min = opts.min_points_per_image * len(train)
        counts, cells = [], None
        if n_tri < n_min:  # too few to trust where they are: seed every photo whole
            counts = [opts.seed_points_per_image] * len(train)
        elif opts.seed_cells > 0:  # seed the parts of each photo no point covers
            cells = empty_cells(train, xyz, opts.seed_cells)
            empty = float(np.mean([c.mean() for c in cells]))
            if empty >= opts.seed_min_empty:
                counts = [int(round(opts.seed_points_per_image * c.mean())) for c in cells]
            else:
                log.info("no triangulated point projects into %.1f %% of the photos' grid cells "
                         "(< poses.seed_min_empty %.0f %%): nothing seeded", 100 * empty,
                         100 * opts.seed_min_empty)
        n_seed = int(sum(counts))
        if n_seed:
            near, far, how = depth_range(train, xyz)
            sx, sc, swept = seed_frustum_points(train, work / image_dir if image_dir else photos,
                                                counts, near, far, seed=opts.seed, cells=cells,
                                                extra=opts.seed_sweep_extra)
            log.info("seeded points: %d of %d at the depth where the photos agree (plane sweep; "
                     "%d of them from poses.seed_sweep_extra), the others at random depths",
                     int(swept.sum()), len(swept), len(swept) - n_seed)
            n_seed = len(swept)
            if cells is None:
                log.info("%d triangulated points < %d (poses.min_points_per_image %d x %d "
                         "images): seeded %d points in the camera frusta, depths %.3g to %.3g "
                         "(from the %s)", n_tri, n_min, opts.min_points_per_image, len(train),
                         n_seed, near, far, how)
            else:
                log.info("no triangulated point projects into %.1f %% of the photos' grid "
                         "cells (poses.seed_cells %d along the longer side): seeded %d points "
                         "on their rays, depths %.3g to %.3g (from the %s)",
                         100 * empty, opts.seed_cells,
                         n_seed, near, far, how)
            xyz, rgb = np.concatenate([xyz, sx]), np.concatenate([rgb, sc])
        summary.update(num_points_triangulated=n_tri, num_points_seeded=n_seed,
                       upright=n_upright, image_dir=image_dir)
        log.info("initial points: %d triangulated, %d seeded in the camera frusta", n_tri,
                 n_seed)
        write_points(work / "points.ply", xyz, rgb)
        model_dir = work / "sparse" / "0"
        model_dir.mkdir(parents=True, exist_ok=True)
        rec.write_binary(str(model_dir))
        _commit(work, out, cams, image_dir, photo_dir)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    summary["seconds"] = round(time.time() - t0, 2)
    log.info("poses done: registered %s of %s, %d points, mean reprojection error %.3f px, "
             "%.1f s", summary["registered"], summary["images"], summary["num_points"],
             summary["mean_reprojection_error"], summary["seconds"])
    return summary


def _one_pinhole(photos: Path, work: Path, cams: list[Camera], rec, opts: PosesOptions
                 ) -> tuple[list[Camera], str | None]:
    """COLMAP's cameras -> one pinhole camera: when they differ (one camera per image, photos
    of different sizes) or carry estimated distortion, the photos are resampled / undistorted
    into ``work/images`` (:func:`gdiff.sfm.resample.to_one_pinhole`) and the sparse model
    ``rec`` is converted to them in place. Returns ``(cameras, image_dir or None)``."""
    if any(c.dist is not None for c in cams):
        log.info("COLMAP estimated lens distortion (%s): undistorting the photos",
                 opts.camera_model)
    new, written = to_one_pinhole(photos, work / "images", cams, opts.resample_max_side,
                                  work / PHOTO_CAMERAS)
    if not written:
        return cams, None
    undistort_reconstruction(rec, {c.image: c for c in cams}, {c.image: c for c in new})
    return new, "images"


def _commit(work: Path, out: Path, cams: list[Camera], image_dir: str | None,
            photo_dir: str | None = None) -> None:
    """Move the finished outputs from ``work`` into ``out``; cameras.json last. ``image_dir``
    (in ``work``: undistorted photos) is moved to ``out``, and with it the photos' own cameras
    (:data:`gdiff.cameras.PHOTO_CAMERAS`, at the registered poses); otherwise ``photo_dir``
    (relative to ``out``), where set, is where cameras.json says the images are."""
    (out / "cameras.json").unlink(missing_ok=True)
    if (out / "images").exists():  # undistorted photos of an earlier run
        os.replace(out / "images", work / "old_images")
    if image_dir:
        os.replace(work / image_dir, out / image_dir)
    (out / "sparse").mkdir(exist_ok=True)
    target = out / "sparse" / "0"
    if target.exists():
        old = work / "old_model"
        os.replace(target, old)
    os.replace(work / "sparse" / "0", target)
    os.replace(work / "points.ply", out / "points.ply")
    (out / PHOTO_CAMERAS).unlink(missing_ok=True)
    if image_dir and (work / PHOTO_CAMERAS).is_file():  # the photos' own cameras, posed
        final = {c.image: c for c in cams}
        save_cameras(out / PHOTO_CAMERAS, [
            replace(c, c2w=final[c.image].c2w.copy(), set=final[c.image].set,
                    time=final[c.image].time)
            for c in load_cameras(work / PHOTO_CAMERAS) if c.image in final])
    save_cameras(out / "cameras.json", cams, image_dir=image_dir or photo_dir)
