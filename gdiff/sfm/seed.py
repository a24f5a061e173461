"""Seed points in the cameras' frusta where triangulation leaves a fit nothing to start from.

Where the triangulated points leave parts of a photo empty (:func:`empty_cells`: cells of a
grid over the image that no point projects into; a sparse capture of untextured furniture
leaves most of each photo so), points are seeded on the rays of those parts; with too few
points overall, on rays of the whole image. A point is drawn for a random pixel of a camera and
takes that pixel's colour. Its depth is found by a plane sweep where the photos can tell it
(:func:`sweep_depths`: the depth at which a small patch around the pixel looks the same in
another photo, for a textured patch that another photo sees from far enough away to tell
depths apart); elsewhere it is drawn log-uniformly (as many points per doubling of the
distance) between a near and a far distance. An object photographed at one visit only, from
two or three places, is so seeded where it stands, not somewhere along its rays: the fit's
densification can only copy Gaussians where they are, and a copy of the wall behind a new
object that takes on the object's colours stays at the wall's depth. The depth range is
scene-relative: from the depths of the triangulated points when there are some, else from the
point the optical axes pass closest to, else from the spread of the camera centres.

Coordinates: cameras are camera-to-world (``c2w``), OpenCV axes (x right, y down, z forward),
pixel centres at +0.5; depth is camera-frame z in world units.
"""

from __future__ import annotations

import logging
from pathlib import Path

import cv2
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
                        cells: list[np.ndarray] | None = None, sweep: bool = True,
                        extra: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points on random pixel rays of ``cams``, coloured by the pixel of the camera's photo
    (``image_root / cam.image``): ``n`` in all (round robin over the cameras), or ``n[i]`` for
    camera ``i``. With ``cells`` (per camera a bool grid, :func:`empty_cells`) the pixels are
    drawn from the True cells only. Each point's depth is the plane sweep's
    (:func:`sweep_depths` over all the photos, ``sweep``) where it finds one, else log-uniform
    over [near, far]. ``extra``: per point, this many more pixels are drawn the same way and
    swept, and those the sweep places are added (textured surfaces get denser seeds at their
    depth; the untextured rest keeps its ``n``).

    Returns:
        ``xyz`` float32 [N, 3] (world), ``rgb`` uint8 [N, 3], ``swept`` bool [N] (depth from
        the sweep); the ``n`` points first, camera by camera, then the extra ones.
    """
    rng = np.random.default_rng(seed)
    greys = [_grey(read_image(Path(image_root) / c.image)) for c in cams] if sweep else None
    extra = extra if sweep else 0
    counts = ([len(a) for a in np.array_split(np.arange(n), len(cams))] if np.isscalar(n)
              else [int(x) for x in n])
    parts: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
    more: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
    for i, (cam, m) in enumerate(zip(cams, counts)):
        if not m:
            continue
        img = read_image(Path(image_root) / cam.image)
        h, w = img.shape[:2]
        size = m * (1 + extra)
        if cells is None or not cells[i].any():
            u = rng.uniform(0, w, size)
            v = rng.uniform(0, h, size)
        else:  # a random empty cell, then a random pixel in it
            rows, cols = cells[i].shape
            r, k = np.nonzero(cells[i])
            pick = rng.integers(0, len(r), size)
            u = (k[pick] + rng.uniform(0, 1, size)) * w / cols
            v = (r[pick] + rng.uniform(0, 1, size)) * h / rows
        d = np.exp(rng.uniform(np.log(near), np.log(far), size))
        # camera pixel coordinates (the image may be stored at another size than the camera's)
        uc, vc = u * cam.width / w, v * cam.height / h
        ok = np.zeros(size, bool)
        if greys is not None:
            found = sweep_depths(cams, greys, i, uc, vc, near, far)
            ok = np.isfinite(found)
            d[ok] = found[ok]
        x = (uc - cam.cx) / cam.fx  # pixel -> camera ray
        y = (vc - cam.cy) / cam.fy
        p_cam = np.stack([x * d, y * d, d], axis=1)
        xyz = (cam.c2w[:3, :3] @ p_cam.T + cam.c2w[:3, 3:4]).T.astype(np.float32)
        col = img[np.minimum(v.astype(int), h - 1), np.minimum(u.astype(int), w - 1)]
        rgb = np.clip(col * 255.0 + 0.5, 0, 255).astype(np.uint8)
        parts.append((xyz[:m], rgb[:m], ok[:m]))
        keep = np.nonzero(ok[m:])[0] + m
        more.append((xyz[keep], rgb[keep], ok[keep]))
    if not parts:
        return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint8), np.zeros(0, bool)
    xyz, rgb, swept = (np.concatenate([q[j] for q in parts + more]) for j in range(3))
    return xyz, rgb, swept


# the plane sweep (sweep_depths): a patch of PATCH x PATCH samples STRIDE pixels apart (at the
# camera's size) around each pixel, compared at SWEEP_STEPS depths, SWEEP_CHUNK pixels at a time
# (bounds the memory: about 100 MB per chunk)
PATCH, STRIDE, SWEEP_STEPS, SWEEP_CHUNK = 7, 2, 64, 256
# a patch whose grey values vary less than this (standard deviation, photo values in [0, 1]:
# about 3 of 255 levels, a camera's noise) has no texture to match
MIN_PATCH_STD = 0.012
# zero-mean normalised cross-correlation a match must reach, and by how much the best depth must
# beat every depth more than SWEEP_APART steps from it (one peak, not a repeated pattern or a
# smooth gradient that matches along a whole stretch of the ray)
MIN_NCC, NCC_MARGIN, SWEEP_APART = 0.8, 0.1, 4


def _grey(img: np.ndarray) -> np.ndarray:
    """float32 [H, W] luma of an sRGB float image [H, W, 3]."""
    return np.ascontiguousarray(img @ np.float32([0.299, 0.587, 0.114]), dtype=np.float32)


def _sample(img: np.ndarray, cam: Camera, uv: np.ndarray) -> np.ndarray:
    """Bilinear samples of ``img`` (stored at any size) at camera pixel coordinates ``uv``
    [..., 2] of ``cam``; NaN outside the image."""
    h, w = img.shape
    x = (uv[..., 0] * (w / cam.width) - 0.5).astype(np.float32)
    y = (uv[..., 1] * (h / cam.height) - 0.5).astype(np.float32)
    flat_x, flat_y = x.reshape(-1, 1), y.reshape(-1, 1)
    out = np.empty(flat_x.shape, np.float32)
    for a in range(0, len(flat_x), 32000):  # cv2.remap maps must stay below 32767 rows
        out[a:a + 32000] = cv2.remap(img, flat_x[a:a + 32000], flat_y[a:a + 32000],
                                     cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                                     borderValue=np.nan)
    inside = (x >= 0) & (x <= w - 1) & (y >= 0) & (y <= h - 1)
    return np.where(inside, out.reshape(x.shape), np.nan)


def _zncc(ref: np.ndarray, other: np.ndarray) -> np.ndarray:
    """Zero-mean NCC of patches ``ref`` [M, P] and ``other`` [M, D, P] -> [M, D] (NaN where a
    sample of ``other`` is missing)."""
    a = ref - ref.mean(-1, keepdims=True)
    b = other - other.mean(-1, keepdims=True)
    den = np.sqrt((a * a).sum(-1))[:, None] * np.sqrt((b * b).sum(-1))
    with np.errstate(invalid="ignore", divide="ignore"):
        return (a[:, None, :] * b).sum(-1) / np.maximum(den, 1e-12)


def sweep_depths(cams: list[Camera], greys: list[np.ndarray], ref: int, u: np.ndarray,
                 v: np.ndarray, near: float, far: float) -> np.ndarray:
    """Depths [M] of the pixels ``(u, v)`` [M] (camera pixel coordinates) of camera ``ref``
    by a fronto-parallel plane sweep, NaN where the photos do not tell.

    At ``SWEEP_STEPS`` depths log-uniform over [near, far], the patch around each pixel
    (``PATCH`` x ``PATCH`` samples ``STRIDE`` px apart, on the plane at that depth parallel to
    the image) is projected into every other photo (``greys[k]``, luma [H, W] at any size) and
    compared by zero-mean NCC, at the depths where the whole patch lies inside that photo and
    in front of it. A photo counts for a pixel when, over those depths, the sweep moves the
    patch across it by more than the patch's width (a photo from nearly the same place cannot
    tell depths apart). The pixel takes the depth of the best match over the photos that count,
    when the reference patch is textured (``MIN_PATCH_STD``), the match reaches ``MIN_NCC`` and
    beats every depth farther than ``SWEEP_APART`` steps from it in that photo by
    ``NCC_MARGIN``. No occlusion reasoning: another photo that sees something else in front is
    simply not the best match.
    """
    u, v = np.asarray(u, np.float64), np.asarray(v, np.float64)
    out = np.full(u.shape, np.nan)
    if u.size == 0 or len(cams) < 2 or not far > near > 0:
        return out
    for a in range(0, u.size, SWEEP_CHUNK):
        out[a:a + SWEEP_CHUNK] = _sweep_chunk(cams, greys, ref, u[a:a + SWEEP_CHUNK],
                                              v[a:a + SWEEP_CHUNK], near, far)
    return out


def _sweep_chunk(cams: list[Camera], greys: list[np.ndarray], ref: int, u: np.ndarray,
                 v: np.ndarray, near: float, far: float) -> np.ndarray:
    """:func:`sweep_depths` for one chunk of pixels."""
    cam = cams[ref]
    out = np.full(u.shape, np.nan)
    half = (PATCH - 1) / 2 * STRIDE
    off = np.arange(PATCH) * STRIDE - half
    ox, oy = np.meshgrid(off, off)
    pu = u[:, None] + ox.ravel()[None]  # [M, P]
    pv = v[:, None] + oy.ravel()[None]
    patch = _sample(greys[ref], cam, np.stack([pu, pv], -1))
    textured = np.isfinite(patch).all(-1) & (np.nan_to_num(patch).std(-1) >= MIN_PATCH_STD)
    if not textured.any():
        return out
    keep = np.nonzero(textured)[0]
    patch, pu, pv = patch[keep], pu[keep], pv[keep]
    depths = np.exp(np.linspace(np.log(near), np.log(far), SWEEP_STEPS))
    rays = np.stack([(pu - cam.cx) / cam.fx, (pv - cam.cy) / cam.fy, np.ones_like(pu)], -1)
    # world points [M, D, P, 3] of the patch samples on each plane
    pc = rays[:, None] * depths[None, :, None, None]
    pw = pc @ cam.c2w[:3, :3].T + cam.c2w[:3, 3]
    best = np.full(len(keep), -np.inf)
    best_d = np.full(len(keep), np.nan)
    idx = np.arange(len(keep))
    for k, other in enumerate(cams):
        if k == ref:
            continue
        q = pw @ other.w2c[:3, :3].T + other.w2c[:3, 3]
        z = q[..., 2]
        with np.errstate(invalid="ignore", divide="ignore"):
            uv = np.stack([other.fx * q[..., 0] / z + other.cx,
                           other.fy * q[..., 1] / z + other.cy], -1)
        front = (z > 1e-6).all(-1)  # [M, D]
        ncc = _zncc(patch, _sample(greys[k], other, np.where(front[..., None, None], uv, -1)))
        valid = front & np.isfinite(ncc)  # the whole patch inside the photo, in front of it
        if not valid.any():
            continue
        # how far the patch moves across this photo over the depths it is compared at
        first = np.argmax(valid, 1)
        last = SWEEP_STEPS - 1 - np.argmax(valid[:, ::-1], 1)
        centre = uv[:, :, PATCH * PATCH // 2]  # [M, D, 2]
        travel = np.linalg.norm(centre[idx, first] - centre[idx, last], axis=-1)
        counts = valid.any(1) & (travel > 2 * half + STRIDE)
        if not counts.any():
            continue
        score = np.where(valid, ncc, -np.inf)
        j = np.argmax(score, 1)
        top = score[idx, j]
        steps = np.arange(SWEEP_STEPS)[None]
        far_off = np.abs(steps - j[:, None]) > SWEEP_APART
        rival = np.where(far_off, score, -np.inf).max(1)
        with np.errstate(invalid="ignore"):  # -inf - -inf: no depth compared at all
            good = counts & (top >= MIN_NCC) & (top - rival >= NCC_MARGIN) & (top > best)
        best[good], best_d[good] = top[good], depths[j[good]]
    out[keep] = best_d
    return out
