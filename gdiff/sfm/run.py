"""The poses stage entry point: register every image of a scene in one frame (COLMAP or known
poses) and write the outputs; ``cameras.json`` is written last."""

from __future__ import annotations

import logging
import os
import shutil
import tempfile
import time
from pathlib import Path

from ..cameras import SETS, Camera, save_cameras
from ..errors import PosesError, SceneError
from ..splat.ply import write_points
from .colmap import _colmap_logging, _points_of, _run_colmap
from .images import _count, _image_sizes, discover_images
from .known import _run_known, _strip, load_known_cameras
from .options import PosesOptions

log = logging.getLogger("gdiff.sfm")


def run_poses(scene_dir: str | os.PathLike, out_dir: str | os.PathLike,
              options: PosesOptions | None = None,
              images: list[tuple[str, str]] | None = None) -> dict:
    """Register all images of a scene in one frame and write the poses outputs.

    Args:
        scene_dir: the scene folder (images are addressed relative to it).
        out_dir: output folder (``sparse/0/``, ``points.ply``, ``cameras.json``).
        options: :class:`PosesOptions`.
        images: ``(relative path, set)`` pairs with set in before | after | eval_before |
            eval_after, in capture order within each set; None discovers them
            (:func:`discover_images`).

    Returns:
        Summary dict: ``source`` (colmap | known), ``matcher``, ``images`` and ``registered``
        (counts per set), ``dropped`` (image names), ``num_models``, ``num_points``,
        ``mean_reprojection_error`` (pixels), ``seconds``; for COLMAP also
        ``mapper_attempts`` and ``refinement`` (see :func:`refine_model`).

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
    sizes = _image_sizes(root, names)
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
    out.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix=".poses_work_", dir=out))
    try:
        with _colmap_logging(opts.colmap_log):
            if known is not None:
                result = _run_known(root, work, images, sizes, known, opts)
            else:
                result = _run_colmap(root, work, images, sizes, opts)
        cams, rec, summary = result
        write_points(work / "points.ply", *_points_of(rec))
        model_dir = work / "sparse" / "0"
        model_dir.mkdir(parents=True, exist_ok=True)
        rec.write_binary(str(model_dir))
        _commit(work, out, cams)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    summary["seconds"] = round(time.time() - t0, 2)
    log.info("poses done: registered %s of %s, %d points, mean reprojection error %.3f px, "
             "%.1f s", summary["registered"], summary["images"], summary["num_points"],
             summary["mean_reprojection_error"], summary["seconds"])
    return summary


def _commit(work: Path, out: Path, cams: list[Camera]) -> None:
    """Move the finished outputs from ``work`` into ``out``; cameras.json last."""
    (out / "cameras.json").unlink(missing_ok=True)
    (out / "sparse").mkdir(exist_ok=True)
    target = out / "sparse" / "0"
    if target.exists():
        old = work / "old_model"
        os.replace(target, old)
    os.replace(work / "sparse" / "0", target)
    os.replace(work / "points.ply", out / "points.ply")
    save_cameras(out / "cameras.json", cams)
