"""Lens distortion: undistort a scene's photos once, in the poses stage, so every later stage
works with pinhole cameras. :func:`remap_scene` writes photos (and eval masks) remapped from
their cameras to any pinhole cameras at the same poses; undistortion uses it here, resampling
photos of different cameras to a common one in :mod:`gdiff.sfm.resample`.

Distortion is OpenCV's plumb-bob (Brown-Conrady) model with coefficients
``(k1, k2, p1, p2[, k3[, k4, k5, k6]])`` on normalised image coordinates (COLMAP's ``OPENCV``,
``RADIAL`` and ``SIMPLE_RADIAL`` models are special cases). A distorted camera of size W x H
becomes a pinhole camera of the same size whose image holds only valid pixels
(``cv2.getOptimalNewCameraMatrix`` with ``alpha = 0``: no black borders, a slightly narrower
field of view for barrel distortion; one zoom for both axes keeps the pixel aspect ratio).
gdiff puts pixel centres at +0.5 and OpenCV at integer coordinates; the conversion happens here.
"""

from __future__ import annotations

import logging
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

from ..cameras import Camera
from ..errors import SceneError
from ..io import atomic_path, imread_upright
from ..log import progress

log = logging.getLogger("gdiff.sfm")

# Eval mask folders undistorted with the eval image of the same stem.
MASK_FOLDERS = ("eval/masks", "eval/mask_before", "eval/mask_after")


def _cv_K(cam: Camera) -> np.ndarray:
    K = cam.K.copy()
    K[0, 2] -= 0.5
    K[1, 2] -= 0.5
    return K


def undistorted_camera(cam: Camera) -> Camera:
    """The pinhole camera (same size and pose, ``dist=None``) of ``cam``'s undistorted image;
    ``cam`` itself if it has no distortion."""
    if cam.dist is None:
        return cam
    K = _cv_K(cam)
    size = (cam.width, cam.height)
    newK, _ = cv2.getOptimalNewCameraMatrix(K, np.asarray(cam.dist), size, 0.0, size)
    if not np.isfinite(newK).all() or newK[0, 0] <= 0 or newK[1, 1] <= 0:
        raise SceneError(f"{cam.image}: distortion {list(cam.dist)} cannot be undistorted "
                         "(no valid pinhole view); check the coefficients' order "
                         "(k1, k2, p1, p2, k3) and the intrinsics")
    # one zoom for both axes (the larger of OpenCV's two), so the pixel aspect ratio is kept
    zoom = max(newK[0, 0] / cam.fx, newK[1, 1] / cam.fy)
    return replace(cam, fx=float(zoom * cam.fx), fy=float(zoom * cam.fy),
                   cx=float(newK[0, 2]) + 0.5,
                   cy=float(newK[1, 2]) + 0.5, dist=None, c2w=cam.c2w.copy())


def undistort_maps(cam: Camera, pinhole: Camera) -> tuple[np.ndarray, np.ndarray]:
    """``cv2.remap`` maps (float32 [H, W] each, H x W = ``pinhole``'s size) from ``cam``'s
    photo (distorted or not) to the image of ``pinhole``, a camera at the same pose: lens
    distortion removed and the intrinsics changed in one step (for a pinhole ``cam`` the
    homography ``K_pinhole @ inv(K_cam)``)."""
    dist = None if cam.dist is None else np.asarray(cam.dist)
    return cv2.initUndistortRectifyMap(_cv_K(cam), dist, None, _cv_K(pinhole),
                                       (pinhole.width, pinhole.height), cv2.CV_32FC1)


def undistort_points(xy: np.ndarray, cam: Camera, pinhole: Camera) -> np.ndarray:
    """Pixel positions [N, 2] (gdiff convention) in ``cam``'s (distorted) image -> positions
    in the image of ``pinhole`` (same pose, see :func:`undistort_maps`)."""
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 1, 2) - 0.5
    dist = None if cam.dist is None else np.asarray(cam.dist)
    out = cv2.undistortPoints(xy, _cv_K(cam), dist, P=_cv_K(pinhole))
    return out.reshape(-1, 2) + 0.5


def boxes_to_pinhole(boxes: np.ndarray, cam: Camera, pinhole: Camera, samples: int = 16
                     ) -> np.ndarray:
    """Boxes float [K, 4] ``x0, y0, x1, y1`` in pixels of ``cam``'s photo (distorted, of its
    own size) -> the boxes that hold them in the image of ``pinhole`` (same pose; the poses
    stage's undistorted or resampled photo), clipped to that image, float [K, 4]. A straight
    edge of the photo bends under undistortion: ``samples`` points along each edge are mapped
    (:func:`undistort_points`) and their bounding box taken. A box that falls wholly outside
    the pinhole image (the margin an undistortion or a common field of view crops) comes back
    empty (``x1 <= x0`` or ``y1 <= y0``)."""
    boxes = np.asarray(boxes, np.float64).reshape(-1, 4)
    if not len(boxes):
        return boxes.copy()
    s = np.linspace(0.0, 1.0, samples)
    out = np.empty_like(boxes)
    for k, (x0, y0, x1, y1) in enumerate(boxes):
        xs, ys = x0 + s * (x1 - x0), y0 + s * (y1 - y0)
        edge = np.concatenate([np.stack([xs, np.full_like(xs, y0)], 1),
                               np.stack([xs, np.full_like(xs, y1)], 1),
                               np.stack([np.full_like(ys, x0), ys], 1),
                               np.stack([np.full_like(ys, x1), ys], 1)])
        p = undistort_points(edge, cam, pinhole)
        out[k] = p[:, 0].min(), p[:, 1].min(), p[:, 0].max(), p[:, 1].max()
    out[:, [0, 2]] = out[:, [0, 2]].clip(0, pinhole.width)
    out[:, [1, 3]] = out[:, [1, 3]].clip(0, pinhole.height)
    return out


def _remap_image(img: np.ndarray, maps, nearest: bool) -> np.ndarray:
    return cv2.remap(img, maps[0], maps[1], cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_REPLICATE)


def _read(src: Path) -> np.ndarray:
    img = imread_upright(src)
    if img is None:
        raise SceneError(f"{src}: cannot be decoded as an image")
    return img


def _write(dst: Path, img: np.ndarray) -> None:
    with atomic_path(dst) as tmp:
        if not cv2.imwrite(str(tmp), img):
            raise OSError(f"could not write {dst}")


class _Maps:
    """Remap tables by (source, target) intrinsics: cameras of one lens share them."""

    def __init__(self):
        self._cache: dict[tuple, tuple] = {}

    def __call__(self, cam: Camera, target: Camera) -> tuple[np.ndarray, np.ndarray]:
        key = tuple((c.width, c.height, c.fx, c.fy, c.cx, c.cy, c.dist) for c in (cam, target))
        if key not in self._cache:
            if key[0][:6] == key[1][:6] and cam.dist is None:  # unchanged: exact copy
                gx, gy = np.meshgrid(np.arange(cam.width, dtype=np.float32),
                                     np.arange(cam.height, dtype=np.float32))
                self._cache[key] = (gx, gy)
            else:
                self._cache[key] = undistort_maps(cam, target)
        return self._cache[key]


def _shrink_first(img: np.ndarray, cam: Camera, target: Camera) -> tuple[np.ndarray, Camera]:
    """When ``target`` samples ``cam``'s photo more coarsely, area-average the photo down to
    about the target's pixel density first (``cv2.INTER_AREA``), so the remap (bilinear) does
    not alias; returns the photo and its camera (:meth:`Camera.scaled`)."""
    s = min(target.fx / cam.fx, target.fy / cam.fy)
    if s >= 0.95:
        return img, cam
    small = cam.scaled(s)
    return cv2.resize(img, (small.width, small.height), interpolation=cv2.INTER_AREA), small


def _mask_camera(mask: Path, size: tuple[int, int], cams: list[Camera]) -> Camera:
    """The eval camera whose photo has the mask's size ``(width, height)`` (``eval_after``
    first, as the evaluation prefers it)."""
    for c in sorted(cams, key=lambda c: c.set != "eval_after"):
        if (c.width, c.height) == size:
            return c
    have = ", ".join(f"{c.image} is {c.width}x{c.height}" for c in cams)
    raise SceneError(f"{mask}: mask is {size[0]}x{size[1]} but {have}; a ground-truth mask "
                     "must have the size of its eval image: resize the mask to it")


def remap_scene(scene_dir: str | Path, out_dir: str | Path, cameras: list[Camera],
                targets: list[Camera], desc: str = "resample") -> None:
    """Write every camera's photo remapped to its target camera (same pose; lens distortion
    removed and intrinsics changed, see :func:`undistort_maps`) under ``out_dir`` with the
    same scene-relative path, and the masks of the eval views (nearest-neighbour, with the
    eval camera whose photo has the mask's size).

    Args:
        scene_dir: the folder ``cam.image`` is relative to.
        out_dir: destination root (e.g. ``results/<scene>/poses/images``); a complete image
            root afterwards (unchanged photos are re-encoded too).
        cameras: the photos' cameras, ``image`` set.
        targets: the pinhole camera (``dist=None``) of each written image, same order.
        desc: progress-bar label.
    """
    root, out = Path(scene_dir), Path(out_dir)
    maps = _Maps()
    eval_cams: dict[str, list[tuple[Camera, Camera]]] = {}  # stem -> (camera, target)
    for cam, target in progress(list(zip(cameras, targets)), desc=desc, unit="image"):
        img, src = _shrink_first(_read(root / cam.image), cam, target)
        _write(out / cam.image, _remap_image(img, maps(src, target), nearest=False))
        if cam.set in ("eval_before", "eval_after"):
            eval_cams.setdefault(Path(cam.image).stem, []).append((cam, target))
    for stem, pairs in eval_cams.items():
        for folder in MASK_FOLDERS:
            for m in sorted((root / folder).glob(stem + ".*")):
                mask = _read(m)
                cam = _mask_camera(m, (mask.shape[1], mask.shape[0]), [c for c, _ in pairs])
                target = next(t for c, t in pairs if c is cam)
                _write(out / folder / m.name, _remap_image(mask, maps(cam, target), nearest=True))


def undistort_scene(scene_dir: str | Path, out_dir: str | Path, cameras: list[Camera]
                    ) -> list[Camera]:
    """Write the undistorted photo of every camera (and the eval masks of eval views) under
    ``out_dir`` with the same scene-relative paths; return the pinhole cameras.

    Args:
        scene_dir: the scene folder (``cam.image`` is relative to it).
        out_dir: destination root (e.g. ``results/<scene>/poses/images``).
        cameras: cameras with ``image`` set; those with ``dist=None`` are copied unchanged
            (re-encoded), so ``out_dir`` is a complete image root.

    Returns:
        The cameras with pinhole intrinsics of the written images, in the same order.
    """
    pinholes = [undistorted_camera(c) for c in cameras]
    remap_scene(scene_dir, out_dir, cameras, pinholes, desc="undistort")
    distorted = [(c, p) for c, p in zip(cameras, pinholes) if c.dist is not None]
    if distorted:
        c, p = distorted[0]
        log.info("undistorted %d image(s) into %s: fx %.1f -> %.1f, fy %.1f -> %.1f, "
                 "cx %.1f -> %.1f, cy %.1f -> %.1f (first distorted camera)",
                 len(distorted), out_dir, c.fx, p.fx, c.fy, p.fy, c.cx, p.cx, c.cy, p.cy)
    return pinholes


def undistort_reconstruction(rec, distorted: dict[str, Camera], pinhole: dict[str, Camera]
                             ) -> None:
    """Turn a pycolmap Reconstruction of the photos' cameras (``distorted``, keyed by image
    name; with or without distortion) into the model of the remapped photos (``pinhole``:
    undistorted, or resampled to a common camera), in place: keypoint positions of registered
    images are mapped into the new images and their cameras become ``PINHOLE`` with the
    intrinsics and size of ``pinhole`` (3D points and poses are unchanged)."""
    import pycolmap

    for iid in rec.reg_image_ids():
        im = rec.images[iid]
        c, p = distorted.get(im.name), pinhole.get(im.name)
        if c is None or p is None or (c.dist is None and _same_intrinsics(c, p)):
            continue
        pts = im.points2D
        if len(pts):
            xy = undistort_points(np.stack([q.xy for q in pts]), c, p)
            for q, v in zip(pts, xy):
                q.xy = v
        cam = rec.cameras[im.camera_id]
        cam.model = pycolmap.CameraModelId.PINHOLE
        cam.width, cam.height = p.width, p.height
        cam.params = [p.fx, p.fy, p.cx, p.cy]


def _same_intrinsics(a: Camera, b: Camera) -> bool:
    return (a.width, a.height, a.fx, a.fy, a.cx, a.cy) == (b.width, b.height, b.fx, b.fy, b.cx,
                                                           b.cy)
