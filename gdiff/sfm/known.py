"""Known poses: ``cameras.json`` (gdiff layout, or the ground-truth layout with an
``intrinsics`` block) or a nerfstudio / instant-ngp ``transforms.json``. Sparse points are
triangulated with pycolmap; by default the poses are refined with them first
(:mod:`gdiff.sfm.refine_known`: a robot's poses are off by a degree or two), else kept as
given."""

from __future__ import annotations

import logging
import os
from dataclasses import replace
from pathlib import Path

from ..cameras import PHOTO_CAMERAS, SET_TIME, Camera, cameras_from_json, cameras_from_transforms
from ..errors import PosesError, SceneError
from ..io import read_json
from .colmap import _extract, _match, extraction_scale
from .images import _check_unregistered, _count, set_from_path
from .options import PosesOptions
from .pairs import proximity_pairs
from .refine_known import refine_known_poses, triangulate
from .resample import shares_one_camera, to_one_pinhole

log = logging.getLogger("gdiff.sfm")


def _strip(name: str) -> str:
    name = str(name).replace("\\", "/")
    return name[2:] if name.startswith("./") else name


def read_cameras_file(path: str | os.PathLike) -> list[Camera]:
    """Cameras from a ``cameras.json`` (gdiff layout, or with the intrinsics in an
    ``intrinsics`` block and ``file`` per frame, as in the test scenes' ``gt_cameras.json``) or
    a ``transforms.json`` (nerfstudio / instant-ngp, OpenGL axes, converted to OpenCV).

    Image names are scene-relative; ``set``/``time`` come from the file or the image folder.
    """
    f = Path(path)
    data = read_json(f)
    if "transform_matrix" in str(data.get("frames", [{}])[:1]):
        cams = cameras_from_transforms(data, source=str(f))
    else:
        if isinstance(data.get("intrinsics"), dict):
            data = {**data["intrinsics"], **{k: v for k, v in data.items() if k != "intrinsics"}}
        cams = cameras_from_json(data, source=str(f))
    for c in cams:
        if c.image is None:
            raise SceneError(f"{f}: a frame has no image path ('image', 'file' or 'file_path')")
        c.image = _strip(c.image)
        if c.set is None:
            c.set = set_from_path(c.image)
        if c.time is None and c.set in SET_TIME:
            c.time = SET_TIME[c.set]
    return cams


def load_known_cameras(scene_dir: str | os.PathLike) -> tuple[list[Camera], Path] | None:
    """Known poses of a scene: ``(cameras, file)`` from its ``cameras.json`` or, failing that,
    ``transforms.json`` (see :func:`read_cameras_file`); None if it has neither."""
    root = Path(scene_dir)
    for name in ("cameras.json", "transforms.json"):
        f = root / name
        if f.is_file():
            return read_cameras_file(f), f
    return None


def _match_known(known: list[Camera], images: list[tuple[str, str]], src: Path,
                 sizes: dict[str, tuple[int, int]]) -> dict[str, Camera]:
    """Known camera per scene image (matched by path, or by path without extension)."""
    by_name = {c.image: c for c in known}
    by_stem = {str(Path(c.image).with_suffix("")): c for c in known}
    out = {}
    for name, st in images:
        c = by_name.get(name) or by_stem.get(str(Path(name).with_suffix("")))
        if c is None:
            continue
        w, h = sizes[name]
        if (c.width, c.height) != (w, h):
            raise PosesError(f"{src}: image {name} is {w}x{h} (as displayed, EXIF orientation "
                             f"applied) but its known camera says {c.width}x{c.height}; give "
                             "the intrinsics of each image as displayed")
        out[name] = Camera(c.width, c.height, c.fx, c.fy, c.cx, c.cy, c.c2w.copy(), image=name,
                           set=st, time=SET_TIME[st], dist=c.dist)
    return out


def _known_reconstruction(db: Path, cams: dict[str, Camera]):
    """A pycolmap Reconstruction holding the database's images with the known poses."""
    import pycolmap

    d = pycolmap.Database.open(str(db))
    try:
        images = d.read_all_images()
        frames = {f.frame_id: f for f in d.read_all_frames()}
        cameras = {c.camera_id: c for c in d.read_all_cameras()}
        rigs = d.read_all_rigs()
    finally:
        d.close()
    rec = pycolmap.Reconstruction()
    for im in images:
        k = cams[im.name]
        cam = cameras[im.camera_id]
        cam.params = ([k.fx, k.fy, k.cx, k.cy] if cam.model.name == "PINHOLE"
                      else [0.5 * (k.fx + k.fy), k.cx, k.cy])
    for cam in cameras.values():
        rec.add_camera(cam)
    for rig in rigs:
        rec.add_rig(rig)
    for im in images:
        f = frames[im.frame_id]
        w2c = cams[im.name].w2c
        f.rig_from_world = pycolmap.Rigid3d(pycolmap.Rotation3d(w2c[:3, :3]), w2c[:3, 3])
        rec.add_frame(f)
    for im in images:
        rec.add_image(im)
    for fid in frames:
        rec.register_frame(fid)
    return rec


def _run_known(root: Path, work: Path, images, sizes, known, opts: PosesOptions):
    """Known poses: bring the photos (in ``root``) to one pinhole camera if the cameras carry
    distortion or differ (:func:`gdiff.sfm.resample.to_one_pinhole`, into ``work/images``),
    then triangulate matched features: with ``opts.refine_known`` refining the poses with them
    (:func:`gdiff.sfm.refine_known.refine_known_poses`), else with the poses held fixed.

    Returns ``(cameras, reconstruction, summary, image_dir)``; ``image_dir`` is ``"images"``
    when undistorted or resampled photos were written, else None."""
    import pycolmap

    known_cams, src = known
    opts = replace(opts, camera_model="PINHOLE")  # known (undistorted) intrinsics are pinhole
    log.info("known poses from %s (%d cameras)", src, len(known_cams))
    matched = _match_known(known_cams, images, src, sizes)
    dropped = _check_unregistered(images, set(matched), opts.max_unregistered_fraction,
                                  f"known poses in {src}")
    images_k = [(n, s) for n, s in images if n in matched]
    names = [n for n, _ in images_k]
    cams = [matched[n] for n in names]
    image_dir = None
    lens = {"undistorted": any(c.dist is not None for c in cams),
            "resampled": not shares_one_camera(cams)}
    if lens["undistorted"]:
        log.info("%s gives lens distortion: undistorting the photos", src)
    cams, written = to_one_pinhole(root, work / "images", cams, opts.resample_max_side,
                                   work / PHOTO_CAMERAS)
    if written:
        matched = dict(zip(names, cams))
        sizes = {n: (c.width, c.height) for n, c in matched.items()}
        root, image_dir = work / "images", "images"
    intr = {(c.width, c.height, c.fx, c.fy, c.cx, c.cy) for c in cams}
    single = len(intr) == 1
    c0 = cams[0]
    params = None
    if single:
        params = ([c0.fx, c0.fy, c0.cx, c0.cy] if opts.camera_model == "PINHOLE"
                  else [0.5 * (c0.fx + c0.fy), c0.cx, c0.cy])
    db = work / "database.db"
    pycolmap.set_random_seed(opts.seed)
    _extract(db, root, names, opts, single_camera=single, camera_params=params)
    if len(names) <= opts.exhaustive_limit():
        pairs, matcher = None, "exhaustive"
    else:
        pairs, matcher = proximity_pairs(cams, opts.sequential_overlap +
                                         opts.sequential_links), "proximity"
    _match(db, work, opts, pairs, extraction_scale(sizes, opts.max_image_size))
    rec = _known_reconstruction(db, matched)
    scale = extraction_scale(sizes, opts.max_image_size)
    refined = {}
    if opts.refine_known:
        rec, matched, info = refine_known_poses(rec, db, root, work, matched, opts, scale,
                                                opts.colmap_threads())
        cams = [matched[n] for n in names]
        refined = {"refined_images": len(info["refined"]),
                   "turned_to_partner": sorted(info["paired"]),
                   "turned_in_common": info["anchored"], "kept_as_given": info["given"],
                   "refined_rotation_deg": round(info["rotation_deg"], 4),
                   "refined_centre_frac": round(info["centre_frac"], 6)}
    else:
        rec = triangulate(rec, db, root, work / "triangulated", opts, len(names), scale, 1.0,
                          clear=True)
    if rec.num_points3D() < len(names):
        log.warning(
            "%s: only %d sparse points could be triangulated with the known poses. Causes: "
            "the poses do not fit the images (cameras.json expects OpenCV camera-to-world "
            "matrices, x right, y down, z forward; transforms.json OpenGL ones) or are too "
            "inaccurate for poses.max_reproj_error, or the images share too few features. "
            "Points seeded in the camera frusta stand in for them.", src,
            rec.num_points3D())
    summary = {"source": "known", "matcher": matcher, "images": _count(images),
               "registered": _count(images, set(names)), "dropped": dropped,
               "num_models": 1, "num_points": int(rec.num_points3D()),
               "mean_reprojection_error": float(rec.compute_mean_reprojection_error()), **lens,
               **refined}
    return cams, rec, summary, image_dir
