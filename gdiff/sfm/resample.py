"""Photos from different cameras: resample every photo once, in the poses stage, to one common
pinhole camera, so every later stage sees one image size and one set of intrinsics.

Before and after visits are often photographed with different cameras (other image sizes,
aspect ratios, focal lengths, portrait and landscape). When the registered cameras do not all
share one size, one set of intrinsics and one lens distortion, each photo is warped to the
*common camera* at its own pose (same rotation and centre, only the intrinsics change: the
homography ``K_common @ inv(K_i)``, with the lens distortion removed in the same remap, see
:func:`gdiff.sfm.undistort.undistort_maps`). The common camera (:func:`common_camera`):

* field of view: the part every photo covers. Per side (left, right, top, bottom) the smallest
  extent over the photos, measured from the principal point as ``tan`` of the angle off the
  optical axis (e.g. ``cx / fx`` to the left edge; for a distorted photo that of its
  undistorted, border-free pinhole view, :func:`gdiff.sfm.undistort.undistorted_camera`). So
  every pixel of every resampled photo is valid (no black border); a wider photo loses its
  margins.
* pixel density: that of the finest photo (the largest focal length in pixels), square pixels,
  with the longer side capped at ``poses.resample_max_side`` (0 = no cap).

Photos that shrink are area-averaged first (``cv2.INTER_AREA``), then remapped bilinearly.
"""

from __future__ import annotations

import logging
import math
from collections import Counter
from dataclasses import replace
from pathlib import Path

import numpy as np

from ..cameras import Camera, save_cameras
from ..errors import SceneError
from .undistort import remap_scene, undistort_scene, undistorted_camera

log = logging.getLogger("gdiff.sfm")


def _lens(cam: Camera) -> tuple:
    return cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy, cam.dist


def shares_one_camera(cameras: list[Camera]) -> bool:
    """Whether all cameras have the same size, intrinsics and lens distortion."""
    return len({_lens(c) for c in cameras}) <= 1


def view_extent(cam: Camera) -> np.ndarray:
    """``[left, right, top, bottom]``: tangents of the angles from the optical axis to the
    image edges of ``cam``'s valid pinhole view (undistorted if it has distortion)."""
    p = undistorted_camera(cam)
    return np.array([p.cx / p.fx, (p.width - p.cx) / p.fx, p.cy / p.fy,
                     (p.height - p.cy) / p.fy])


def common_camera(cameras: list[Camera], max_side: int = 0) -> Camera:
    """The pinhole camera (``c2w`` identity, no image) every photo is resampled to (module
    docstring): the field of view all ``cameras`` cover, the finest pixel density, the longer
    side at most ``max_side`` pixels (0 = no cap).

    Raises:
        SceneError: the photos share no field of view (a principal point outside its image).
    """
    ext = np.stack([view_extent(c) for c in cameras])
    lo = ext.min(axis=0)
    if not (lo > 0).all():
        bad = cameras[int(np.argmin(ext.min(axis=1)))]
        raise SceneError(f"{bad.image}: principal point ({bad.cx:.1f}, {bad.cy:.1f}) lies "
                         f"outside the {bad.width}x{bad.height} image; check its intrinsics "
                         "(cx, cy in pixels, pixel centres at +0.5)")
    span_x, span_y = lo[0] + lo[1], lo[2] + lo[3]
    f = max(max(undistorted_camera(c).fx, undistorted_camera(c).fy) for c in cameras)
    if max_side > 0 and f * max(span_x, span_y) > max_side:
        f = max_side / max(span_x, span_y)
    # whole pixels inside the common view; the principal point splits them as the view does
    w = max(1, math.floor(f * span_x + 1e-6))
    h = max(1, math.floor(f * span_y + 1e-6))
    return Camera(w, h, f, f, w * lo[0] / span_x, h * lo[2] / span_y)


def resample_scene(scene_dir: str | Path, out_dir: str | Path, cameras: list[Camera],
                   max_side: int = 0) -> list[Camera]:
    """Write every camera's photo resampled to the common camera (:func:`common_camera`)
    under ``out_dir`` with the same scene-relative path (eval masks too, nearest-neighbour);
    return the cameras of the written images (common intrinsics, own pose, image, set, time),
    in the same order."""
    common = common_camera(cameras, max_side)
    targets = [replace(common, c2w=c.c2w.copy(), image=c.image, set=c.set, time=c.time)
               for c in cameras]
    remap_scene(scene_dir, out_dir, cameras, targets, desc="resample")
    sizes = Counter(f"{c.width}x{c.height}" for c in cameras)
    focals = sorted({round(c.fx, 1) for c in cameras})
    log.info("photos from %d different cameras (sizes %s; fx %s px): resampled %d image(s) "
             "into %s to one pinhole camera %dx%d, f %.1f px, principal point (%.1f, %.1f) "
             "(the field of view all photos cover)", len({_lens(c) for c in cameras}),
             ", ".join(f"{s} x{n}" for s, n in sizes.items()),
             ", ".join(f"{v:g}" for v in focals[:6]) + (" ..." if len(focals) > 6 else ""),
             len(cameras), out_dir, common.width, common.height, common.fx, common.cx,
             common.cy)
    return targets


def to_one_pinhole(scene_dir: str | Path, out_dir: str | Path, cameras: list[Camera],
                   max_side: int = 0, photo_cameras: str | Path | None = None
                   ) -> tuple[list[Camera], bool]:
    """Bring the photos to one pinhole camera: resampled to the common camera when the
    cameras differ (:func:`resample_scene`), undistorted when they share one distorting lens
    (:func:`gdiff.sfm.undistort.undistort_scene`), else left alone. ``photo_cameras``
    (optional): where the photos' own ``cameras`` are saved (a ``cameras.json``) when new
    images were written (:data:`gdiff.cameras.PHOTO_CAMERAS`).

    Returns:
        ``(cameras, written)``: the cameras of the images to use, and whether new images were
        written to ``out_dir``.
    """
    if not shares_one_camera(cameras):
        new = resample_scene(scene_dir, out_dir, cameras, max_side)
    elif any(c.dist is not None for c in cameras):
        new = undistort_scene(scene_dir, out_dir, cameras)
    else:
        return cameras, False
    if photo_cameras is not None:
        save_cameras(photo_cameras, cameras)
    return new, True
