"""Weight-free instance proposals from rendered geometry and illumination-invariant colour.

The image is cut along three kinds of boundaries, then the pieces are the instances:

* occlusion edges: jumps of the rendered depth. Measured on inverse depth ``w = 1/z``, which is
  an affine function of the pixel coordinates on any plane seen by a pinhole camera, so its
  second difference is ~0 on planes (also a floor seen at a grazing angle) and ~ the relative
  depth jump at an occlusion boundary (intrinsics-free).
* crease edges: a change of the surface normal (normals from the back-projected depth with the
  intrinsics ``K``; when ``K`` is unknown a 53-degree field of view is assumed). Separates an
  object from the support it stands on, where depth is continuous.
* colour edges: gradients of linear-RGB chromaticity (r, g over r+g+b). Chromaticity does not
  change when a surface gets brighter or darker (shading, shadows of a white light, exposure),
  so these edges stay put under lighting changes; raw intensity edges are not used. They are
  left out where the depth shows the surface bending (shading under a coloured light changes
  chromaticity too). On a fitted model's depth the normals vary from pixel to pixel and such
  "bends" cover most of every frame, so there colour edges rarely count and the regions follow
  depth and concave creases. Letting colour count everywhere on such frames separates objects
  the depth misses on a real capture, but it cuts textured surfaces, and under a change of
  coloured light lit and shaded ones, into pieces that differ between the times (tried, not
  kept).

Pixels on edges are then given to the adjacent region of most similar depth (or colour when
there is no depth), so masks cover the objects up to their silhouettes. All work happens at a
resolution whose longer side is ``max_side``; masks are returned at full resolution.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import cv2
import numpy as np

from ..io import srgb_to_linear
from .base import Instance, SegmentOptions

log = logging.getLogger("gdiff.segment.geometric")

_DEFAULT_FOCAL_FACTOR = 1.0  # f = factor * max(H, W): ~53 degree field of view


def _fill_invalid(x: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Replace invalid pixels of ``x`` [H, W] by the value of the nearest valid pixel."""
    if valid.all() or not valid.any():
        return x
    from scipy.ndimage import distance_transform_edt

    idx = distance_transform_edt(~valid, return_distances=False, return_indices=True)
    return x[idx[0], idx[1]]


def _shift_pairs(step: int):
    """Offsets (dy, dx) of the four directions (horizontal, vertical, two diagonals)."""
    return [(0, step), (step, 0), (step, step), (step, -step)]


def _pad_linear(x: np.ndarray, pad: int) -> np.ndarray:
    """Pad [H, W(, C)] by ``pad`` pixels with linear extrapolation (point reflection), which
    keeps affine functions affine (so planes show no edge at the image border)."""
    widths = [(pad, pad), (pad, pad)] + [(0, 0)] * (x.ndim - 2)
    return np.pad(x, widths, mode="reflect", reflect_type="odd")


def _blur(x: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian blur that leaves affine functions unchanged up to the image border."""
    if sigma <= 0:
        return x
    pad = int(np.ceil(3 * sigma))
    y = cv2.GaussianBlur(_pad_linear(x, pad), (0, 0), sigma)
    return y[pad:-pad, pad:-pad]


def _shifted(x: np.ndarray, dy: int, dx: int, linear: bool = False) -> np.ndarray:
    """``x`` moved by (dy, dx): out[y, x] = x[y + dy, x + dx]; outside the image the border is
    replicated, or linearly extrapolated when ``linear``."""
    H, W = x.shape[:2]
    pad = max(abs(dy), abs(dx))
    if pad == 0:
        return x
    xp = _pad_linear(x, pad) if linear else cv2.copyMakeBorder(x, pad, pad, pad, pad,
                                                                cv2.BORDER_REPLICATE)
    return xp[pad + dy:pad + dy + H, pad + dx:pad + dx + W]


def depth_edges(depth: np.ndarray, valid: np.ndarray, rel: float, sigma: float,
                step: int = 2) -> np.ndarray:
    """Occlusion edges of a depth map.

    ``depth``: float32 [H, W] z-depth (scene units). Returns bool [H, W]: the second difference of
    inverse depth over ``step`` pixels, relative to the inverse depth, exceeds ``rel`` in any of
    four directions. Zero on planes; ~ the relative depth jump across an occlusion boundary.
    """
    z = _fill_invalid(depth.astype(np.float32), valid)
    w = _blur(1.0 / np.maximum(z, 1e-6), sigma)
    out = np.zeros(w.shape, dtype=bool)
    for dy, dx in _shift_pairs(step):
        d2 = np.abs(_shifted(w, dy, dx, True) - 2.0 * w + _shifted(w, -dy, -dx, True))
        out |= d2 > rel * w
    return out


def depth_points(depth: np.ndarray, K: np.ndarray, sigma: float) -> np.ndarray:
    """Camera-frame points [H, W, 3] (OpenCV axes) of a z-depth map [H, W] through the pixel
    centres (+0.5) with intrinsics ``K`` [3, 3]. Depth is smoothed as inverse depth, which is
    affine on planes, so planes stay planar."""
    H, W = depth.shape
    z = 1.0 / np.maximum(_blur(1.0 / np.maximum(depth.astype(np.float32), 1e-6), sigma), 1e-9)
    u = (np.arange(W, dtype=np.float32) + 0.5 - K[0, 2]) / K[0, 0]
    v = (np.arange(H, dtype=np.float32) + 0.5 - K[1, 2]) / K[1, 1]
    return np.stack([z * u[None, :], z * v[:, None], z], axis=-1)


def _dot3(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Per-pixel dot product [H, W] of two [H, W, 3] maps (``(a * b).sum(-1)``, summed in the
    same order, without numpy's slow reduction over a length-3 axis)."""
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]


def point_normals(P: np.ndarray) -> np.ndarray:
    """Unit normals [H, W, 3] of a point map [H, W, 3], facing the camera at the origin."""
    du = np.gradient(P, axis=1)  # one-sided at the image border
    dv = np.gradient(P, axis=0)
    n = np.cross(du, dv)
    n /= np.linalg.norm(n, axis=-1, keepdims=True) + 1e-12
    flip = _dot3(n, P) > 0  # face the camera: normal . viewing ray < 0
    n[flip] *= -1
    return n


def depth_normals(depth: np.ndarray, K: np.ndarray, sigma: float) -> np.ndarray:
    """Unit surface normals [H, W, 3] (camera frame, OpenCV axes) from a z-depth map [H, W]."""
    return point_normals(depth_points(depth, K, sigma))


def crease_edges(depth: np.ndarray, valid: np.ndarray, K: np.ndarray, max_deg: float,
                 sigma: float, step: int = 2, concave_only: bool = True,
                 surface: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """Crease edges: the normals ``step`` pixels apart on either side differ by > ``max_deg``.

    With ``concave_only`` only concave creases count (where an object meets its support or
    another object); convex creases (the edges of a box) lie inside one object. Convexity test
    of two surface points x1, x2 with normals n1, n2: convex when (n1 - n2) . (x1 - x2) > 0.
    ``surface``: the (points, normals) :func:`crease_surface` returns for these arguments, to
    reuse them across calls.
    """
    P, n = surface if surface is not None else crease_surface(depth, valid, K, sigma)
    cos_max = np.cos(np.deg2rad(max_deg))
    out = np.zeros(depth.shape, dtype=bool)
    for dy, dx in _shift_pairs(step):
        n1, n2 = _shifted(n, dy, dx), _shifted(n, -dy, -dx)
        e = _dot3(n1, n2) < cos_max
        if concave_only:
            x1, x2 = _shifted(P, dy, dx, True), _shifted(P, -dy, -dx, True)
            e &= _dot3(n1 - n2, x1 - x2) <= 0
        out |= e
    return out


def crease_surface(depth: np.ndarray, valid: np.ndarray, K: np.ndarray,
                   sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """Camera-frame points [H, W, 3] and unit normals [H, W, 3] of a z-depth map [H, W]
    (invalid pixels filled from the nearest valid one), as :func:`crease_edges` uses them."""
    z = _fill_invalid(depth.astype(np.float32), valid)
    P = depth_points(z, K, sigma)
    return P, point_normals(P)


def chromaticity(rgb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Chromaticity (r, g) / (r + g + b) of linear RGB [H, W, 2] and a confidence in [0, 1] [H, W].

    ``rgb`` is sRGB-encoded float32 [H, W, 3]. The confidence falls to 0 for dark pixels, whose
    chromaticity is dominated by noise.
    """
    lin = srgb_to_linear(rgb)
    s = lin.sum(-1)
    chrom = lin[..., :2] / np.maximum(s, 1e-4)[..., None]
    conf = np.clip(s / 0.06, 0.0, 1.0)  # below ~2% mean linear intensity: unreliable
    return chrom.astype(np.float32), conf.astype(np.float32)


def color_edges(rgb: np.ndarray, thresh: float, sigma: float) -> np.ndarray:
    """Chromaticity edges: bool [H, W] where the confidence-weighted gradient magnitude of
    the chromaticity (per pixel, Sobel) exceeds ``thresh``."""
    chrom, conf = chromaticity(rgb)
    chrom = _blur(chrom, sigma)
    g = np.zeros(conf.shape, dtype=np.float32)
    for c in range(2):
        gx = cv2.Sobel(chrom[..., c], cv2.CV_32F, 1, 0, ksize=3) / 8.0
        gy = cv2.Sobel(chrom[..., c], cv2.CV_32F, 0, 1, ksize=3) / 8.0
        g += gx * gx + gy * gy
    g = np.sqrt(g) * cv2.erode(conf, np.ones((3, 3), np.uint8))
    # chromaticity varies within ~[0, 1]; normalise so thresh is a fraction of that per pixel
    return g > thresh * 0.1


def grow_into(labels: np.ndarray, todo: np.ndarray, feat: np.ndarray, max_iter: int = 50) -> np.ndarray:
    """Give unlabelled pixels (``todo``) the label of the adjacent region with the closest mean
    feature, growing one pixel ring per iteration.

    ``labels``: int32 [H, W], 0 = unlabelled. ``feat``: float32 [H, W, C] (e.g. log depth).
    Per iteration every pixel still to do looks at its 8 neighbours (the image's border
    replicated) in the labels the iteration started with and takes the label of the closest
    mean feature (L1; the first of equals in row-major neighbour order). Only the pixels still
    to do are touched, not the whole image.
    """
    labels = labels.copy()
    n = int(labels.max())
    if n == 0:
        return labels
    H, W = labels.shape
    C = feat.shape[-1]
    flat = labels.ravel()  # a view: the labels as they grow
    means = np.zeros((n + 1, C), np.float64)
    counts = np.bincount(flat, minlength=n + 1).astype(np.float64)
    for c in range(C):
        means[:, c] = np.bincount(flat, weights=feat[..., c].ravel(), minlength=n + 1)
    means /= np.maximum(counts, 1)[:, None]
    F = feat.reshape(-1, C)
    T = np.flatnonzero(todo & (labels == 0))  # the pixels to do, in row-major order
    ty, tx = np.divmod(T, W)
    nbs = [np.clip(ty + dy, 0, H - 1) * W + np.clip(tx + dx, 0, W - 1)
           for dy in (-1, 0, 1) for dx in (-1, 0, 1) if dy or dx]
    for _ in range(max_iter):
        if not T.size:
            break
        best = np.full(T.size, np.inf, np.float32)
        new = np.zeros(T.size, labels.dtype)
        for nb_idx in nbs:
            nb = flat[nb_idx]
            cand = nb > 0
            if not cand.any():
                continue
            d = np.abs(F[T[cand]] - means[nb[cand]]).sum(-1).astype(np.float32)
            better = d < best[cand]
            idx = np.flatnonzero(cand)[better]
            best[idx] = d[better]
            new[idx] = nb[cand][better]
        grown = new > 0
        if not grown.any():
            break
        flat[T[grown]] = new[grown]
        keep = ~grown
        T = T[keep]
        nbs = [a[keep] for a in nbs]
    return labels


@dataclass
class _Cut:
    """A frame at the segmenter's working resolution [h, w]: ``valid`` bool [h, w] (a
    surface), ``edges`` bool [h, w], ``feat`` float32 [h, w, C] (what edge pixels are grown by:
    log depth, or chromaticity without depth), ``full`` the frame's (H, W) and ``scale`` h / H."""

    valid: np.ndarray
    edges: np.ndarray
    feat: np.ndarray
    full: tuple[int, int]
    scale: float


class GeometricSegmenter:
    """Weight-free segmenter (``segment.backend: geometric``); see the module docstring."""

    # frames may be segmented in forked worker processes (plain numpy / OpenCV, no state)
    parallel_safe = True
    # label() can cut a frame together with the other time's render of its pose (``other``)
    pairs_times = True

    def __init__(self, options: SegmentOptions | None = None):
        self.options = options or SegmentOptions()

    def label(self, rgb: np.ndarray, depth: np.ndarray | None = None,
              alpha: np.ndarray | None = None, K: np.ndarray | None = None,
              other: tuple | None = None) -> np.ndarray:
        """Region labels int32 [H, W] at full resolution (0 = no instance), by decreasing area.

        ``other``: ``(rgb, depth, alpha)`` of the same pose rendered at the other time (the
        same camera ``K`` and size), or None. When given, the frame is also cut along the other
        time's edges, so the two times of the pose are cut into the same regions (up to the
        pixels each time shows; edge pixels grow back by each time's own depth), see
        :mod:`gdiff.segment.pair`.
        """
        cut = self._cut(rgb, depth, alpha, K)
        edges = cut.edges
        if other is not None:
            o_rgb, o_depth, o_alpha = other
            if np.shape(o_rgb)[:2] != np.shape(rgb)[:2]:
                raise ValueError("the two times of a pose must be rendered at one size, got "
                                 f"{np.shape(rgb)[:2]} and {np.shape(o_rgb)[:2]}")
            oc = self._cut(o_rgb, o_depth, o_alpha, K)
            edges = edges | oc.edges
        return self._regions(cut, edges, alpha)

    def _cut(self, rgb, depth, alpha, K) -> "_Cut":
        """The frame at the working resolution and its edges (see the module docstring)."""
        o = self.options
        rgb = np.asarray(rgb, dtype=np.float32)
        H, W = rgb.shape[:2]
        s = min(1.0, o.max_side / max(H, W))
        h, w = max(1, int(round(H * s))), max(1, int(round(W * s)))
        interp = cv2.INTER_AREA

        def small(x):
            return x if (h, w) == (H, W) else cv2.resize(x, (w, h), interpolation=interp)

        rgb_s = small(rgb)
        valid = np.ones((h, w), bool)
        if alpha is not None:
            valid &= small(np.asarray(alpha, np.float32)) >= o.alpha_min
        edges = np.zeros((h, w), bool)
        feat = None
        if depth is not None:
            z = np.asarray(depth, np.float32)
            zvalid = np.isfinite(z) & (z > 0)
            z = np.where(zvalid, z, 0).astype(np.float32)
            z_s = cv2.resize(z, (w, h), interpolation=cv2.INTER_NEAREST)
            zv_s = cv2.resize(zvalid.astype(np.uint8), (w, h), interpolation=cv2.INTER_NEAREST) > 0
            valid &= zv_s
            if zv_s.any():
                if K is None:
                    f = _DEFAULT_FOCAL_FACTOR * max(h, w)
                    Ks = np.array([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1]], np.float64)
                else:
                    Ks = np.asarray(K, np.float64).copy()
                    Ks[0] *= w / W
                    Ks[1] *= h / H
                edges |= depth_edges(z_s, zv_s, o.depth_edge_rel, o.smooth_sigma)
                surf = crease_surface(z_s, zv_s, Ks, o.smooth_sigma)
                edges |= crease_edges(z_s, zv_s, Ks, o.normal_edge_deg, o.smooth_sigma,
                                      surface=surf)
                # where the surface bends (either way) shading changes the colour, and under a
                # coloured light also the chromaticity: no colour edges there
                shading = crease_edges(z_s, zv_s, Ks, o.normal_edge_deg / 2, o.smooth_sigma,
                                       concave_only=False, surface=surf)
                no_color = cv2.dilate(shading.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
                feat = np.log(np.maximum(_fill_invalid(z_s, zv_s), 1e-6))[..., None]
        if o.color_edge > 0:
            ce = color_edges(rgb_s, o.color_edge, o.smooth_sigma)
            if feat is not None:
                ce &= ~no_color
            edges |= ce
        if feat is None:
            chrom, _ = chromaticity(rgb_s)
            feat = chrom
        return _Cut(valid=valid, edges=edges, feat=feat.astype(np.float32),
                    full=(H, W), scale=s)

    def _regions(self, cut: "_Cut", edges: np.ndarray, alpha) -> np.ndarray:
        """Labels int32 [H, W] (full resolution, by decreasing area) of the regions ``edges``
        bool [h, w] (working resolution) leave of ``cut``'s valid pixels."""
        o = self.options
        (H, W), (h, w), s, valid = cut.full, cut.valid.shape, cut.scale, cut.valid
        n, labels = cv2.connectedComponents((valid & ~edges).astype(np.uint8), connectivity=4)
        # keep small cores (edge bands eat into small objects); the final area test is after
        # the cores have grown back over the edge pixels
        min_core = max(3, int(round(o.min_region_area * s * s / 8)))
        areas = np.bincount(labels.ravel(), minlength=n)
        small_ids = np.flatnonzero(areas < min_core)
        labels[np.isin(labels, small_ids)] = 0
        labels = grow_into(labels.astype(np.int32), valid & (labels == 0), cut.feat)
        if (h, w) != (H, W):
            labels = cv2.resize(labels, (W, H), interpolation=cv2.INTER_NEAREST)
            if alpha is not None:
                labels[np.asarray(alpha) < o.alpha_min] = 0
        # relabel by decreasing area, dropping regions that ended up too small
        areas = np.bincount(labels.ravel())
        areas[0] = 0
        order = [i for i in np.argsort(-areas) if areas[i] >= o.min_region_area]
        lut = np.zeros(len(areas), np.int32)
        lut[order] = np.arange(1, len(order) + 1)
        return lut[labels]

    def segment(self, rgb: np.ndarray, depth: np.ndarray | None = None,
                alpha: np.ndarray | None = None, K: np.ndarray | None = None) -> list[Instance]:
        """Instances (non-overlapping, by decreasing area); see :mod:`gdiff.segment.base`.

        The score is 1 - the fraction of the region touching the image border, so regions cut
        by the frame rank lower.
        """
        labels = self.label(rgb, depth, alpha, K)
        out = []
        n = int(labels.max())
        if n == 0:
            return out
        border = np.zeros(labels.shape, bool)
        border[[0, -1], :] = True
        border[:, [0, -1]] = True
        per = np.bincount(labels[border], minlength=n + 1).astype(np.float64)
        H, W = labels.shape
        for i in range(1, n + 1):
            m = labels == i
            score = 1.0 - min(1.0, per[i] / (2.0 * (H + W)) * 4.0)
            out.append(Instance(mask=m, score=float(score)))
        return out
