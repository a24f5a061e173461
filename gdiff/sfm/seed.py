"""Seed points in the cameras' frusta where triangulation leaves a fit nothing to start from.

Where the triangulated points leave parts of a photo empty (:func:`empty_cells`: cells of a
grid over the image that no point projects into; a sparse capture of untextured furniture
leaves most of each photo so), points are seeded on the rays of those parts; with too few
points overall, on rays of the whole image. A point is drawn for a random pixel of a camera, at a depth drawn log-uniformly (as many points
per doubling of the distance) between a near and a far distance, and takes that pixel's colour. The depth range
is scene-relative: from the depths of the triangulated points when there are some, else from
the point the optical axes pass closest to, else from the spread of the camera centres.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from ..cameras import Camera
from ..io import read_image

log = logging.getLogger("gdiff.sfm")


def _project(c: Camera, xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates [M, 2] and depths [M] of the points of ``xyz`` [N, 3] (world) in
    front of ``c``."""
    p = (c.w2c[:3, :3] @ xyz.T + c.w2c[:3, 3:4]).T
    p = p[p[:, 2] > 1e-6]
    uv = (c.K @ p.T).T
    return uv[:, :2] / uv[:, 2:3], p[:, 2]


def _depths(cams: list[Camera], xyz: np.ndarray) -> np.ndarray:
    """Depths of ``xyz`` [N, 3] in every camera where they lie in front and inside the image."""
    out = []
    for c in cams:
        uv, z = _project(c, xyz)
        inside = (uv[:, 0] >= 0) & (uv[:, 0] <= c.width) & (uv[:, 1] >= 0) & \
            (uv[:, 1] <= c.height)
        out.append(z[inside])
    return np.concatenate(out) if out else np.zeros(0)


def _axes_focus(cams: list[Camera]) -> np.ndarray | None:
    """The point closest (least squares) to all optical axes, or None if ill-conditioned."""
    A = np.zeros((3, 3))
    b = np.zeros(3)
    for c in cams:
        d = c.c2w[:3, 2] / np.linalg.norm(c.c2w[:3, 2])
        P = np.eye(3) - np.outer(d, d)
        A += P
        b += P @ c.center
    if np.linalg.cond(A) > 1e6:
        return None
    return np.linalg.solve(A, b)


def depth_range(cams: list[Camera], xyz: np.ndarray, min_points: int = 3
                ) -> tuple[float, float, str]:
    """``(near, far, how)``: the depth range (scene units) to seed points in.

    * With at least ``min_points`` triangulated points visible in front of a camera:
      ``0.5 x`` their 2nd-percentile depth to ``1.5 x`` their 98th-percentile depth.
    * Else, if the optical axes pass near a common point in front of the cameras at median
      depth ``d``: ``0.1 d`` to ``3 d``.
    * Else ``0.05 s`` to ``2 s`` with ``s`` the largest distance between camera centres.
    """
    z = _depths(cams, np.asarray(xyz, np.float64).reshape(-1, 3))
    if z.size >= min_points:
        near, far = 0.5 * np.quantile(z, 0.02), 1.5 * np.quantile(z, 0.98)
        if far > near > 0:
            return float(near), float(far), f"depths of {z.size} triangulated observations"
    focus = _axes_focus(cams)
    if focus is not None:
        d = np.array([(c.w2c[:3, :3] @ focus + c.w2c[:3, 3])[2] for c in cams])
        if np.all(d > 0):
            m = float(np.median(d))
            return 0.1 * m, 3.0 * m, "distance to the point the optical axes meet"
    centres = np.stack([c.center for c in cams])
    s = float(np.max(np.linalg.norm(centres[:, None] - centres[None], axis=-1))) or 1.0
    return 0.05 * s, 2.0 * s, "spread of the camera centres"


def grid_shape(cam: Camera, cells: int) -> tuple[int, int]:
    """(rows, columns) of the seeding grid of ``cam``: ``cells`` along the longer side, square
    cells."""
    side = max(cam.width, cam.height) / cells
    return max(1, int(round(cam.height / side))), max(1, int(round(cam.width / side)))


def empty_cells(cams: list[Camera], xyz: np.ndarray, cells: int) -> list[np.ndarray]:
    """Per camera, bool [rows, cols] (:func:`grid_shape`): the cells of its image that no point
    of ``xyz`` [N, 3] (world) projects into, in front of the camera (no occlusion test: a
    point behind a nearer surface still counts)."""
    out = []
    xyz = np.asarray(xyz, np.float64).reshape(-1, 3)
    for c in cams:
        rows, cols = grid_shape(c, cells)
        uv, _ = _project(c, xyz)
        r = np.floor(uv[:, 1] / c.height * rows).astype(np.int64)
        k = np.floor(uv[:, 0] / c.width * cols).astype(np.int64)
        ok = (r >= 0) & (r < rows) & (k >= 0) & (k < cols)
        covered = np.zeros((rows, cols), bool)
        covered[r[ok], k[ok]] = True
        out.append(~covered)
    return out


def seed_frustum_points(cams: list[Camera], image_root: str | Path, n: int | list[int],
                        near: float, far: float, seed: int = 0,
                        cells: list[np.ndarray] | None = None
                        ) -> tuple[np.ndarray, np.ndarray]:
    """Points on random pixel rays of ``cams``, depths log-uniform over [near, far], coloured by
    the pixel of the camera's photo (``image_root / cam.image``): ``n`` in all (round robin
    over the cameras), or ``n[i]`` for camera ``i``. With ``cells`` (per camera a bool grid,
    :func:`empty_cells`) the pixels are drawn from the True cells only.

    Returns:
        ``xyz`` float32 [N, 3] (world), ``rgb`` uint8 [N, 3].
    """
    rng = np.random.default_rng(seed)
    counts = ([len(a) for a in np.array_split(np.arange(n), len(cams))] if np.isscalar(n)
              else [int(x) for x in n])
    total = int(sum(counts))
    xyz = np.zeros((total, 3), np.float32)
    rgb = np.zeros((total, 3), np.uint8)
    ends = np.cumsum(counts)
    for i, (cam, m) in enumerate(zip(cams, counts)):
        if not m:
            continue
        idx = np.arange(ends[i] - m, ends[i])
        img = read_image(Path(image_root) / cam.image)
        h, w = img.shape[:2]
        if cells is None or not cells[i].any():
            u = rng.uniform(0, w, idx.size)
            v = rng.uniform(0, h, idx.size)
        else:  # a random empty cell, then a random pixel in it
            rows, cols = cells[i].shape
            r, k = np.nonzero(cells[i])
            pick = rng.integers(0, len(r), idx.size)
            u = (k[pick] + rng.uniform(0, 1, idx.size)) * w / cols
            v = (r[pick] + rng.uniform(0, 1, idx.size)) * h / rows
        d = np.exp(rng.uniform(np.log(near), np.log(far), idx.size))
        # pixel -> camera ray (the image may be stored at another size than the camera's)
        x = (u * cam.width / w - cam.cx) / cam.fx
        y = (v * cam.height / h - cam.cy) / cam.fy
        p_cam = np.stack([x * d, y * d, d], axis=1)
        xyz[idx] = (cam.c2w[:3, :3] @ p_cam.T + cam.c2w[:3, 3:4]).T
        col = img[np.minimum(v.astype(int), h - 1), np.minimum(u.astype(int), w - 1)]
        rgb[idx] = np.clip(col * 255.0 + 0.5, 0, 255).astype(np.uint8)
    return xyz, rgb
