"""Lens distortion: undistort a scene's photos once, in the poses stage, so every later stage
works with pinhole cameras.

Distortion is OpenCV's plumb-bob (Brown-Conrady) model with coefficients
``(k1, k2, p1, p2[, k3[, k4, k5, k6]])`` on normalised image coordinates (COLMAP's ``OPENCV``,
``RADIAL`` and ``SIMPLE_RADIAL`` models are special cases). A distorted camera of size W x H
becomes a pinhole camera of the same size whose image holds only valid pixels
(``cv2.getOptimalNewCameraMatrix`` with ``alpha = 0``: no black borders, a slightly narrower
field of view for barrel distortion; one zoom for both axes keeps the pixel aspect ratio). gdiff puts pixel centres at +0.5 and OpenCV at integer
coordinates; the conversion happens here.
"""

from __future__ import annotations

import logging
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

from ..cameras import Camera
from ..errors import SceneError
from ..io import atomic_path
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
    """``cv2.remap`` maps (float32 [H, W] each) from ``cam``'s distorted image to the image of
    ``pinhole`` (:func:`undistorted_camera`)."""
    return cv2.initUndistortRectifyMap(_cv_K(cam), np.asarray(cam.dist), None, _cv_K(pinhole),
                                       (pinhole.width, pinhole.height), cv2.CV_32FC1)


def undistort_points(xy: np.ndarray, cam: Camera, pinhole: Camera) -> np.ndarray:
    """Pixel positions [N, 2] (gdiff convention) in ``cam``'s distorted image -> positions in
    the undistorted image of ``pinhole``."""
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 1, 2) - 0.5
    out = cv2.undistortPoints(xy, _cv_K(cam), np.asarray(cam.dist), P=_cv_K(pinhole))
    return out.reshape(-1, 2) + 0.5


def _remap_file(src: Path, dst: Path, maps, nearest: bool) -> None:
    img = cv2.imread(str(src), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise SceneError(f"{src}: cannot be decoded as an image")
    out = cv2.remap(img, maps[0], maps[1],
                    cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_REPLICATE)
    with atomic_path(dst) as tmp:
        if not cv2.imwrite(str(tmp), out):
            raise OSError(f"could not write {dst}")


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
    root, out = Path(scene_dir), Path(out_dir)
    maps_cache: dict[tuple, tuple] = {}
    pinholes = []
    ident = None
    for cam in progress(cameras, desc="undistort", unit="image"):
        pin = undistorted_camera(cam)
        key = (cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy, cam.dist)
        if cam.dist is None:
            if ident is None or ident[0].shape != (cam.height, cam.width):
                gx, gy = np.meshgrid(np.arange(cam.width, dtype=np.float32),
                                     np.arange(cam.height, dtype=np.float32))
                ident = (gx, gy)
            maps = ident
        else:
            if key not in maps_cache:
                maps_cache[key] = undistort_maps(cam, pin)
            maps = maps_cache[key]
        _remap_file(root / cam.image, out / cam.image, maps, nearest=False)
        if cam.set in ("eval_before", "eval_after"):
            stem = Path(cam.image).stem
            for folder in MASK_FOLDERS:
                for m in sorted((root / folder).glob(stem + ".*")):
                    _remap_file(m, out / folder / m.name, maps, nearest=True)
        pinholes.append(pin)
    if maps_cache:
        c, p = next((c, p) for c, p in zip(cameras, pinholes) if c.dist is not None)
        log.info("undistorted %d image(s) into %s: fx %.1f -> %.1f, fy %.1f -> %.1f, "
                 "cx %.1f -> %.1f, cy %.1f -> %.1f (first distorted camera)",
                 sum(c.dist is not None for c in cameras), out, c.fx, p.fx, c.fy, p.fy, c.cx,
                 p.cx, c.cy, p.cy)
    return pinholes


def undistort_reconstruction(rec, distorted: dict[str, Camera], pinhole: dict[str, Camera]
                             ) -> None:
    """Turn a pycolmap Reconstruction of distorted cameras into the pinhole model of the
    undistorted photos, in place: keypoint positions of registered images are undistorted and
    their cameras become ``PINHOLE`` with the intrinsics of ``pinhole`` (keyed by image name;
    3D points and poses are unchanged)."""
    import pycolmap

    for iid in rec.reg_image_ids():
        im = rec.images[iid]
        c, p = distorted.get(im.name), pinhole.get(im.name)
        if c is None or p is None or c.dist is None:
            continue
        pts = im.points2D
        if len(pts):
            xy = undistort_points(np.stack([q.xy for q in pts]), c, p)
            for q, v in zip(pts, xy):
                q.xy = v
        cam = rec.cameras[im.camera_id]
        if cam.model.name != "PINHOLE":
            cam.model = pycolmap.CameraModelId.PINHOLE
            cam.params = [p.fx, p.fy, p.cx, p.cy]
