"""Poses stage: register every image of a scene (before, after, eval) in one frame.

Two sources of poses:

* ``colmap`` — SIFT features, matching and incremental mapping with pycolmap. All images share
  one pinhole camera when their sizes match. Matching is exhaustive for small image sets; for
  large ones a vocabulary-free pair list is used: neighbours in capture order inside each set
  (with wrap-around, for orbits) plus evenly spaced links from every image into every set, so
  the before, after and eval sets are tied together without a vocabulary tree file.
  Outlier thresholds are ``max_reproj_error`` pixels of the feature-extraction image (COLMAP's
  4 px defaults suit megapixel photos; on 320 px images false matches, e.g. on shadow edges
  that move between before and after, then survive and pull the focal length and rotations).
  Mapping is retried with further seeds and looser thresholds while images stay
  unregistered, and the kept model gets a final global refinement: bundle adjustment of all
  cameras, the shared intrinsics and points under a Cauchy loss, alternated with removal of
  observations beyond the threshold.
* ``known`` — ``cameras.json`` (gdiff layout, or the ground-truth layout with an
  ``intrinsics`` block) or a nerfstudio / instant-ngp ``transforms.json`` in the scene folder.
  The poses are kept as given and sparse points are triangulated with pycolmap from features
  matched between the images (pose-proximity pairs for large sets), so later stages always have
  a point cloud.

Outputs in ``out_dir`` (written in a temporary folder inside ``out_dir`` and moved in at the
end; ``cameras.json`` last, so its presence means the stage finished):

* ``sparse/0/`` — the COLMAP binary model (cameras, images, points3D),
* ``points.ply`` — sparse points, binary little-endian ``x y z`` float32 +
  ``red green blue`` uint8,
* ``cameras.json`` — see :mod:`gdiff.cameras` (c2w in OpenCV axes, pixel centres at +0.5,
  which is also COLMAP's convention).
"""

from __future__ import annotations

import contextlib
import logging
import os
import shutil
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import numpy as np

from .cameras import SET_TIME, SETS, Camera, cameras_from_json, cameras_from_transforms, \
    save_cameras
from .errors import PosesError, SceneError
from .io import IMAGE_EXTENSIONS, atomic_path, read_json
from .splat.ply import write_points

log = logging.getLogger("gdiff.sfm")

# Scene sub-folders searched when no image list is given, with the set they hold.
SET_FOLDERS = {"before": "before", "after": "after", "eval_before": "eval/before",
               "eval_after": "eval/after"}


@dataclass
class PosesOptions:
    """Options of the poses stage (config section ``poses``).

    Attributes:
        source: ``auto`` (known poses if the scene has cameras.json / transforms.json, else
            COLMAP), ``colmap`` or ``known``.
        matcher: ``auto`` (exhaustive up to ``exhaustive_max_images`` images, else
            ``sequential``), ``exhaustive`` or ``sequential`` (capture-order neighbours within
            each set + evenly spaced links between all images; no vocabulary tree needed).
        exhaustive_max_images: image count up to which ``auto`` matches all pairs.
        sequential_overlap: capture-order neighbours matched on each side (``sequential``).
        sequential_links: evenly spaced images of every set each image is also matched with.
        camera_model: ``PINHOLE`` (fx, fy, cx, cy) or ``SIMPLE_PINHOLE`` (one focal length).
        max_image_size: longer image side for feature extraction (larger images are
            downscaled for SIFT; poses and intrinsics stay in full-resolution pixels).
        max_num_features: SIFT features per image.
        domain_size_pooling: DSP-SIFT descriptors (pooled over several patch sizes): more
            distinctive under lighting change and on small images, fewer false matches; about
            5x slower feature extraction (matching often gets faster).
        min_num_matches: verified matches needed for an image pair to count in mapping.
        max_reproj_error: reprojection error (pixels of the feature-extraction image) above
            which an observation is an outlier: used by the mapper (triangulation, filtering;
            camera registration allows 3x, two-view RANSAC 2x) and by the final refinement.
            COLMAP's default of 4 px is meant for megapixel photos; on small images it lets
            false matches (e.g. on moving shadow edges) bias the focal length and rotations.
        refine_iterations: rounds of the final global refinement (bundle adjustment of all
            cameras, shared intrinsics and points with a Cauchy loss, then removal of
            observations beyond ``max_reproj_error``); 0 keeps the mapper's model as is.
        mapper_attempts: incremental mapping runs tried while the best model so far leaves
            images unregistered. Run k (from 0) uses seed ``seed + k`` and mapper thresholds
            ``(k + 1) * max_reproj_error``: a strict threshold keeps mapping accurate, a looser
            one can register weakly connected images (the final refinement then removes the
            outliers at ``max_reproj_error``). The model with the most registered images, then
            the lowest reprojection error, is kept.
        refine_principal_point: let bundle adjustment move the principal point (off = keep it
            at the image centre, COLMAP's default).
        max_unregistered_fraction: if a set (before, after, eval_before, eval_after) loses more
            than this fraction of its images, the stage fails listing them; otherwise they are
            dropped with a warning.
        num_threads: CPU threads for COLMAP (-1 = all).
        seed: random seed of COLMAP's RANSAC and mapper (for repeatable runs).
        colmap_log: let COLMAP write its own INFO log lines to stderr.
    """

    source: str = "auto"
    matcher: str = "auto"
    exhaustive_max_images: int = 150
    sequential_overlap: int = 8
    sequential_links: int = 6
    camera_model: str = "PINHOLE"
    max_image_size: int = 1600
    max_num_features: int = 8192
    domain_size_pooling: bool = False
    min_num_matches: int = 15
    max_reproj_error: float = 2.0
    refine_iterations: int = 3
    mapper_attempts: int = 3
    refine_principal_point: bool = False
    max_unregistered_fraction: float = 0.2
    num_threads: int = -1
    seed: int = 0
    colmap_log: bool = False

    def __post_init__(self):
        if self.source not in ("auto", "colmap", "known"):
            raise ValueError(f"source must be auto, colmap or known, not {self.source!r}")
        if self.matcher not in ("auto", "exhaustive", "sequential"):
            raise ValueError(f"matcher must be auto, exhaustive or sequential, not "
                             f"{self.matcher!r}")
        if self.camera_model not in ("PINHOLE", "SIMPLE_PINHOLE"):
            raise ValueError(f"camera_model must be PINHOLE or SIMPLE_PINHOLE (later stages "
                             f"render undistorted pinhole cameras), not {self.camera_model!r}")
        if not 0.0 <= self.max_unregistered_fraction <= 1.0:
            raise ValueError("max_unregistered_fraction must lie in [0, 1]")
        if self.sequential_overlap < 1 or self.sequential_links < 0:
            raise ValueError("sequential_overlap must be >= 1 and sequential_links >= 0")
        if not self.max_reproj_error > 0:
            raise ValueError("max_reproj_error must be > 0 (pixels)")
        if self.refine_iterations < 0 or self.mapper_attempts < 1:
            raise ValueError("refine_iterations must be >= 0 and mapper_attempts >= 1")


# --------------------------------------------------------------------------------------------
# Image lists and sets


def set_from_path(rel: str) -> str | None:
    """The image set of a scene-relative path (``before/x.png`` -> ``before``,
    ``eval/after/x.png`` -> ``eval_after``), or None if the folder is not a set folder."""
    parts = Path(rel).parts
    if len(parts) >= 2 and parts[0] in ("before", "after"):
        return parts[0]
    if len(parts) >= 3 and parts[0] == "eval" and parts[1] in ("before", "after"):
        return f"eval_{parts[1]}"
    return None


def discover_images(scene_dir: str | os.PathLike) -> list[tuple[str, str]]:
    """(relative path, set) of every image in before/, after/, eval/before/, eval/after/,
    sorted by name within each set (the capture order for sequential matching)."""
    root = Path(scene_dir)
    out = []
    for st, folder in SET_FOLDERS.items():
        d = root / folder
        if d.is_dir():
            files = sorted(p for p in d.iterdir() if p.is_file() and p.suffix in IMAGE_EXTENSIONS
                           and not p.name.startswith("."))
            out += [(p.relative_to(root).as_posix(), st) for p in files]
    if not any(s == "before" for _, s in out) or not any(s == "after" for _, s in out):
        raise SceneError(f"{root}: needs images in before/ and after/")
    return out


def _image_sizes(scene_dir: Path, names: list[str]) -> dict[str, tuple[int, int]]:
    """(width, height) per image, read from the file headers only."""
    from PIL import Image

    sizes = {}
    for n in names:
        try:
            with Image.open(scene_dir / n) as im:
                sizes[n] = im.size
        except (OSError, ValueError):
            raise SceneError(f"{scene_dir / n}: cannot be read as an image") from None
    return sizes


# --------------------------------------------------------------------------------------------
# Pair lists (vocabulary-free matching for large sets)


def sequential_pairs(groups: list[list[str]], overlap: int, links: int) -> list[tuple[str, str]]:
    """Image pairs for large sets: capture-order neighbours plus evenly spaced links.

    Args:
        groups: image names per set, each in capture order.
        overlap: each image is paired with the next ``overlap`` images of its set (cyclically,
            so the end of an orbit meets its start).
        links: each image is also paired with ``links`` evenly spaced images of every set
            (its own included), which ties the sets together and closes loops.

    Returns:
        Unordered, de-duplicated pairs ``(a, b)`` with ``a < b``; roughly
        ``N * (overlap + links * len(groups))`` of them for N images.
    """
    pairs: set[tuple[str, str]] = set()

    def add(a, b):
        if a != b:
            pairs.add((a, b) if a < b else (b, a))

    for g in groups:
        n = len(g)
        for i in range(n):
            for k in range(1, min(overlap, n - 1) + 1):
                add(g[i], g[(i + k) % n])
    if links > 0:
        for g in groups:
            for h in groups:
                if not h:
                    continue
                m = min(links, len(h))
                for j, a in enumerate(g):
                    # offset by j so different images link to different members of h
                    start = (j * len(h)) // max(len(g), 1)
                    for q in range(m):
                        add(a, h[(start + (q * len(h)) // m) % len(h)])
    return sorted(pairs)


def proximity_pairs(cameras: list[Camera], k: int) -> list[tuple[str, str]]:
    """Pairs of known cameras that likely overlap: each camera with its ``k`` nearest
    neighbours by centre distance among cameras whose viewing directions differ by < 90°."""
    centers = np.stack([c.center for c in cameras])
    dirs = np.stack([c.c2w[:3, 2] for c in cameras])
    d = np.linalg.norm(centers[:, None] - centers[None], axis=2)
    facing = dirs @ dirs.T > 0.0
    d = np.where(facing, d, np.inf)
    np.fill_diagonal(d, np.inf)
    pairs = set()
    for i, c in enumerate(cameras):
        for j in np.argsort(d[i])[:k]:
            if np.isfinite(d[i, j]):
                a, b = c.image, cameras[j].image
                pairs.add((a, b) if a < b else (b, a))
    return sorted(pairs)


# --------------------------------------------------------------------------------------------
# pycolmap steps


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
    eo.num_threads = opts.num_threads
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


def _match(db: Path, work: Path, opts: PosesOptions, pairs: list[tuple[str, str]] | None,
           pixel_scale: float = 1.0) -> None:
    """Exhaustive matching if ``pairs`` is None, else match exactly ``pairs``; two-view RANSAC
    threshold ``2 * max_reproj_error`` extraction pixels (``pixel_scale`` full-res px each)."""
    import pycolmap

    mo = pycolmap.FeatureMatchingOptions()
    mo.num_threads = opts.num_threads
    vo = pycolmap.TwoViewGeometryOptions()
    vo.ransac.random_seed = opts.seed
    vo.ransac.max_error = 2.0 * opts.max_reproj_error * pixel_scale
    if pairs is None:
        pycolmap.match_exhaustive(db, matching_options=mo, verification_options=vo,
                                  device=pycolmap.Device.cpu)
    else:
        pair_file = work / "pairs.txt"
        pair_file.write_text("".join(f"{a} {b}\n" for a, b in pairs))
        po = pycolmap.ImportedPairingOptions()
        po.match_list_path = str(pair_file)
        pycolmap.match_image_pairs(db, matching_options=mo, pairing_options=po,
                                   verification_options=vo, device=pycolmap.Device.cpu)


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
    mp.num_threads = opts.num_threads
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
    return mp


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
    bo = pycolmap.BundleAdjustmentOptions()
    bo.print_summary = False
    bo.refine_focal_length = True
    bo.refine_principal_point = bool(refine_principal_point)
    bo.ceres.loss_function_type = pycolmap.LossFunctionType.CAUCHY
    bo.ceres.loss_function_scale = 0.5 * max_error
    bo.ceres.solver_options.num_threads = num_threads
    removed = 0
    for _ in range(iterations):
        pycolmap.bundle_adjustment(rec, bo)
        removed += int(pycolmap.ObservationManager(rec).filter_all_points3D(max_error, 1.5))
    rec.update_point_3d_errors()
    after = float(rec.compute_mean_reprojection_error())
    if iterations:
        log.info("global refinement: %d rounds, %d outlier observations removed, mean "
                 "reprojection error %.3f -> %.3f px", iterations, removed, before, after)
    return {"rounds": iterations, "removed_observations": removed,
            "reprojection_before": before, "reprojection_after": after}


def _camera_of(image, rec) -> tuple[int, int, float, float, float, float]:
    """(width, height, fx, fy, cx, cy) of a pycolmap image's camera."""
    cam = rec.cameras[image.camera_id]
    p = np.asarray(cam.params, dtype=np.float64)
    if cam.model.name == "SIMPLE_PINHOLE":
        f, cx, cy = p
        fx = fy = f
    elif cam.model.name == "PINHOLE":
        fx, fy, cx, cy = p
    else:  # pragma: no cover - options restrict the model
        raise PosesError(f"camera model {cam.model.name} is not a pinhole model")
    return int(cam.width), int(cam.height), float(fx), float(fy), float(cx), float(cy)


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


# --------------------------------------------------------------------------------------------
# PLY of sparse points


# --------------------------------------------------------------------------------------------
# Known poses


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
            raise PosesError(f"{src}: image {name} is {w}x{h} but its known camera says "
                             f"{c.width}x{c.height}; give intrinsics for the images as stored")
        out[name] = Camera(c.width, c.height, c.fx, c.fy, c.cx, c.cy, c.c2w.copy(), image=name,
                           set=st, time=SET_TIME[st])
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


# --------------------------------------------------------------------------------------------
# Main entry


def _check_unregistered(images: list[tuple[str, str]], registered: set[str], max_frac: float,
                        what: str) -> list[str]:
    """Raise PosesError if a set lost more than ``max_frac`` of its images; else return the
    names of the lost images (to be dropped)."""
    lost = [(n, s) for n, s in images if n not in registered]
    bad = []
    for st in SETS:
        n_set = sum(1 for _, s in images if s == st)
        lost_set = [n for n, s in lost if s == st]
        if n_set and len(lost_set) / n_set > max_frac:
            bad.append(f"{st}: {len(lost_set)} of {n_set} ({', '.join(lost_set)})")
    if bad:
        raise PosesError(
            f"{what}: too many images could not be posed (more than "
            f"{max_frac:.0%} of a set, see poses.max_unregistered_fraction): "
            + "; ".join(bad) + ". Causes: these photos overlap too little with the others, "
            "are blurred or show untextured surfaces. Fixes: add overlapping photos between "
            "them and the rest, remove them from the scene, or give known poses "
            "(cameras.json).")
    if lost:
        log.warning("dropping %d image(s) that could not be posed: %s", len(lost),
                    ", ".join(n for n, _ in lost))
    return [n for n, _ in lost]


def _count(images, names=None) -> dict[str, int]:
    return {st: sum(1 for n, s in images if s == st and (names is None or n in names))
            for st in SETS if any(s == st for _, s in images)}


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


def _run_colmap(root: Path, work: Path, images, sizes, opts: PosesOptions):
    import pycolmap

    names = [n for n, _ in images]
    db = work / "database.db"
    single = len(set(sizes.values())) == 1
    if not single:
        log.info("images differ in size: one camera per image")
    pycolmap.set_random_seed(opts.seed)
    scale = extraction_scale(sizes, opts.max_image_size)
    _extract(db, root, names, opts, single_camera=single)
    matcher = opts.matcher
    if matcher == "auto":
        matcher = "exhaustive" if len(names) <= opts.exhaustive_max_images else "sequential"
    if matcher == "exhaustive":
        pairs = None
        log.info("matching: exhaustive (%d pairs)", len(names) * (len(names) - 1) // 2)
    else:
        groups = [[n for n, s in images if s == st] for st in SETS]
        pairs = sequential_pairs([g for g in groups if g], opts.sequential_overlap,
                                 opts.sequential_links)
        log.info("matching: sequential (%d pairs: %d capture-order neighbours + %d links per "
                 "image and set)", len(pairs), opts.sequential_overlap, opts.sequential_links)
    _match(db, work, opts, pairs, scale)
    stats = _db_stats(db, opts.min_num_matches)
    log.info("features: %.0f keypoints per image; %d image pairs with >= %d verified matches",
             stats["mean_keypoints"], stats["verified_pairs"], opts.min_num_matches)
    models, attempts = _map_best(db, root, work, opts, len(names), scale)
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
    by_name = {rec.images[i].name: rec.images[i] for i in rec.reg_image_ids()}
    dropped = _check_unregistered(images, set(by_name), opts.max_unregistered_fraction,
                                  f"COLMAP registration of {root}")
    refine = refine_model(rec, opts.max_reproj_error * scale, opts.refine_iterations,
                          opts.refine_principal_point, opts.num_threads)
    cams = []
    for n, st in images:
        if n in dropped:
            continue
        im = by_name[n]
        w, h, fx, fy, cx, cy = _camera_of(im, rec)
        cams.append(Camera(w, h, fx, fy, cx, cy, _c2w_of(im), image=n, set=st,
                           time=SET_TIME[st]))
    summary = {"source": "colmap", "matcher": matcher, "images": _count(images),
               "registered": _count(images, set(by_name)), "dropped": dropped,
               "num_models": len(models), "mapper_attempts": attempts,
               "num_points": int(rec.num_points3D()),
               "mean_reprojection_error": float(rec.compute_mean_reprojection_error()),
               "refinement": refine}
    return cams, rec, summary


def _model_key(rec) -> tuple[int, float]:
    """Ranking of candidate models: more registered images first, then lower mean
    reprojection error."""
    return rec.num_reg_images(), -float(rec.compute_mean_reprojection_error())


def _map_best(db: Path, root: Path, work: Path, opts: PosesOptions, n_images: int,
              scale: float) -> tuple[list, int]:
    """Incremental mapping, repeated with the next seed and a looser threshold (run k:
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
        recs = pycolmap.incremental_mapping(
            db, root, work / f"mapper{k}",
            options=_mapper_options(opts, n_images, scale, seed=seed, relax=k + 1.0))
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


def _run_known(root: Path, work: Path, images, sizes, known, opts: PosesOptions):
    import pycolmap

    known_cams, src = known
    log.info("known poses from %s (%d cameras)", src, len(known_cams))
    matched = _match_known(known_cams, images, src, sizes)
    dropped = _check_unregistered(images, set(matched), opts.max_unregistered_fraction,
                                  f"known poses in {src}")
    images_k = [(n, s) for n, s in images if n in matched]
    names = [n for n, _ in images_k]
    cams = [matched[n] for n in names]
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
    if len(names) <= opts.exhaustive_max_images:
        pairs, matcher = None, "exhaustive"
    else:
        pairs, matcher = proximity_pairs(cams, opts.sequential_overlap +
                                         opts.sequential_links), "proximity"
    _match(db, work, opts, pairs, extraction_scale(sizes, opts.max_image_size))
    rec = _known_reconstruction(db, matched)
    tri_dir = work / "triangulated"
    tri_dir.mkdir()
    rec = pycolmap.triangulate_points(rec, db, root, tri_dir, clear_points=True,
                                      options=_mapper_options(
                                          opts, len(names),
                                          extraction_scale(sizes, opts.max_image_size)),
                                      refine_intrinsics=False)
    if rec.num_points3D() == 0:
        raise PosesError(
            f"{src}: no sparse points could be triangulated with the known poses. Causes: the "
            "poses do not fit the images (cameras.json expects OpenCV camera-to-world "
            "matrices, x right, y down, z forward; transforms.json OpenGL ones), or the images "
            "share too few features. Fix the poses file or set poses.source: colmap.")
    summary = {"source": "known", "matcher": matcher, "images": _count(images),
               "registered": _count(images, set(names)), "dropped": dropped,
               "num_models": 1, "num_points": int(rec.num_points3D()),
               "mean_reprojection_error": float(rec.compute_mean_reprojection_error())}
    return cams, rec, summary
