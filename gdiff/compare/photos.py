"""The training photos' word on a change of appearance in 3D: do the photos of the two times
differ where the fitted model's renders do?

The flat evidence (:func:`gdiff.compare.geometry.flat_flags`) marks surfaces that stay in place
but render differently at t0 and t1. Some of those differences are the fit's own: each time has
its own photos, and a patch of table that one time's photos constrain less well renders a
little differently, the same way from every pose, so it passes the vote over poses like a
book put down on the table. The photos tell them apart. Each component of the evidence (its
voxels at its time, world frame) is projected into the training photos of both times
(:class:`KeyPhoto`: a photo with its camera and the z-depth the model renders there at that
photo's time); a voxel counts in a photo when it lies on the surface the photo shows there
(rendered depth within ``tol`` of the voxel's depth). Each photo gives the mean linear colour
of the voxels it shows; :func:`photos_differ` then compares the two times' photos against the
spread of the photos within each time (view-dependent shading, noise): a component whose
photos of the two times look alike, to within ``contrast`` times that spread in brightness and
in chromaticity, did not change.

Coordinates: world frame of the poses stage; cameras are camera-to-world (OpenCV axes: x
right, y down, z forward; pixel centres at +0.5); depth is camera-frame z, as in the EXR ``Z``
channel.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from statistics import NormalDist

import cv2
import numpy as np

from ..io import read_image_sized, srgb_to_linear
from ..track import world_points
from .coverage import DepthView, project_to_depth


# noise floors of the spreads, so that photos that agree exactly (a rendered test scene) do
# not make every small difference significant: log intensity and chromaticity (r, g, b
# summing to 1) of a mean over many pixels
_LOG_FLOOR = 0.01
_CHROMA_FLOOR = 0.005
# linear values a photo's exposure is not taken from (near black: noise; near white: clipped),
# and the fewest pixels it is taken from
_DARK, _CLIPPED = 0.005, 0.95
_MIN_EXPOSURE_PX = 500


@dataclass
class KeyPhoto:
    """One training photo: ``time`` (0 or 1), ``camera`` (:class:`gdiff.cameras.Camera`,
    camera-to-world), ``depth`` float [H, W] the z-depth rendered from the model at this camera
    and time (NaN or <= 0: no surface) and ``photo`` float32 [H, W, 3] linear RGB, at the
    camera's size; ``pose`` (optional) the key frame ``(path, i)`` it was taken at."""
    time: int
    camera: object
    depth: np.ndarray
    photo: np.ndarray
    pose: tuple[str, int] | None = None

    def depth_camera(self):
        """The camera at the size of ``depth`` (scaled when the frame was rendered at
        another size)."""
        h, w = np.shape(self.depth)
        c = self.camera
        return c if (c.width, c.height) == (w, h) else c.scaled(w / c.width)


def load_photo(path: str | Path, width: int, height: int) -> np.ndarray:
    """A photo as linear RGB float32 [height, width, 3] (area-resampled when its size differs);
    a missing or unreadable file is a :class:`~gdiff.errors.SceneError` naming it."""
    return srgb_to_linear(read_image_sized(path, width, height))


def visit_exposure(photo: np.ndarray, renders: list[np.ndarray],
                   valid: np.ndarray | None = None, blur: float = 1 / 320) -> np.ndarray:
    """``photo`` (linear RGB [H, W, 3]) scaled per channel to the exposure and white balance
    both visits' photos are compared at: by the geometric mean, over ``renders`` (linear RGB
    [H, W, 3] each, at the photo's camera), of the median ratio of render to photo over the
    pixels ``valid`` (bool [H, W], None: all) where neither is clipped nor near black (both
    blurred first as in :func:`_blurred`).

    Given the renders of the photo's own time and of the other time at its camera: where the
    fit learnt a visit's exposure as a change over time (each time's render has its visit's
    exposure), the photos of both visits come out at the mean of the two, in log; where the
    fit's per-image correction took it up (both renders at the model's own exposure), at
    that. A change covers a minority of a view and moves the medians little; a photo test
    that compares means of the two visits' photos (:func:`photos_differ`) then no longer
    sees the visits' exposure as a difference."""
    p = np.asarray(photo, np.float32)
    pb = _blurred(p, blur)
    ok = (pb > _DARK).all(-1) & (pb < _CLIPPED).all(-1)
    if valid is not None:
        ok &= np.asarray(valid, bool)
    logs = []
    for r in renders:
        rb = _blurred(np.asarray(r, np.float32), blur)
        use = ok & (rb > _DARK).all(-1) & (rb < _CLIPPED).all(-1)
        if use.sum() >= _MIN_EXPOSURE_PX:
            logs.append(np.median(np.log(rb[use]) - np.log(pb[use]), 0))
    if not logs:
        return p
    return p * np.exp(np.mean(logs, 0)).astype(np.float32)


def view_means(points: np.ndarray, photos: list[KeyPhoto], tol: float, min_points: int = 3
               ) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Per time, the mean linear colour [3] of ``points`` (float [M, 3], world frame) in every
    photo of that time that shows at least ``min_points`` of them (in the frame, in front of
    the camera, and within ``tol`` world units of the depth rendered there)."""
    out: tuple[list, list] = ([], [])
    P = np.asarray(points, np.float64)
    finite = np.isfinite(P).all(-1)
    for kp in photos:
        _, z, row, col = project_to_depth(P, finite, DepthView(kp.depth_camera(), kp.depth))
        d = np.asarray(kp.depth)[row, col]
        on = np.isfinite(d) & (d > 0) & (np.abs(d - z) <= tol)
        if on.sum() < min_points:
            continue
        out[int(kp.time)].append(np.asarray(kp.photo)[row[on], col[on]].mean(0))
    return out


def photos_differ(means0: list[np.ndarray], means1: list[np.ndarray], contrast: float,
                  min_views: int = 2) -> bool | None:
    """Whether the photos of the two times show a region differently: the difference of the
    two times' mean log intensity is at least ``contrast`` times the spread (standard
    deviation) of the per-photo log intensities within a time, or the L1 difference of their
    mean chromaticities (r, g, b over r + g + b) is at least ``contrast`` times the mean L1
    deviation of the per-photo chromaticities from their time's mean. ``means0`` /
    ``means1``: per photo of each time, the region's mean linear colour [3]
    (:func:`view_means`). None (cannot tell) when either time has fewer than ``min_views``
    photos of the region."""
    if len(means0) < min_views or len(means1) < min_views:
        return None
    m0, m1 = np.asarray(means0, np.float64), np.asarray(means1, np.float64)
    l0, l1 = np.log(m0.mean(1) + 0.02), np.log(m1.mean(1) + 0.02)
    s_log = max(np.sqrt((l0.var() + l1.var()) / 2), _LOG_FLOOR)
    c0 = m0 / np.maximum(m0.sum(1, keepdims=True), 1e-9)
    c1 = m1 / np.maximum(m1.sum(1, keepdims=True), 1e-9)
    s_chroma = max((np.abs(c0 - c0.mean(0)).sum(1).mean()
                    + np.abs(c1 - c1.mean(0)).sum(1).mean()) / 2, _CHROMA_FLOOR)
    d_log = abs(l0.mean() - l1.mean())
    d_chroma = np.abs(c0.mean(0) - c1.mean(0)).sum()
    return bool(d_log >= contrast * s_log or d_chroma >= contrast * s_chroma)


def alike_components(keys: list[np.ndarray], components: list[np.ndarray], voxel: float,
                     to_points, photos: list[KeyPhoto], contrast: float,
                     tol_voxels: float = 1.5) -> tuple[np.ndarray, int]:
    """The components of a 3D evidence whose photos of the two times look alike
    (:func:`photos_differ` False), and how many components the photos could judge.

    ``keys[t]`` (int64 [K_t]) and ``components[t]`` (int [K_t]) are the evidence's changed
    voxels at time t and their component numbers (:class:`GeometryEvidence` ``changed`` and
    ``component``); ``to_points`` maps voxel keys to their centres (float [K, 3], world);
    ``voxel`` is the voxel side, and a voxel counts in a photo within ``tol_voxels`` voxels of
    the rendered depth."""
    alike, judged = [], 0
    for t in (0, 1):
        for c in np.unique(components[t]):
            pts = to_points(keys[t][components[t] == c])
            verdict = photos_differ(*view_means(pts, photos, tol_voxels * voxel), contrast)
            if verdict is None:
                continue
            judged += 1
            if not verdict:
                alike.append(int(c))
    return np.asarray(sorted(alike), np.int64), judged


def region_photos_differ(region: np.ndarray, points: tuple[np.ndarray, np.ndarray],
                         depths: tuple[np.ndarray, np.ndarray], photos: list[KeyPhoto],
                         depth_tol: float, contrast: float) -> bool | None:
    """Whether the training photos of the two times show a region of a pose differently
    (:func:`photos_differ`): at each time the region's surface there, ``points[t]`` [H, W, 3]
    (world frame) at the pixels ``region`` (bool [H, W]), is looked up in that time's photos
    (:func:`view_means`, within ``depth_tol`` times the region's median rendered depth
    ``depths[t]`` [H, W], z, of the depth each photo renders). None when a time has no
    surface there or too few photos of it."""
    means = []
    for t in (0, 1):
        z = np.asarray(depths[t])[region]
        z = z[np.isfinite(z) & (z > 0)]
        if not z.size:
            return None
        means.append(view_means(np.asarray(points[t])[region],
                                [k for k in photos if k.time == t],
                                depth_tol * float(np.median(z)))[t])
    return photos_differ(means[0], means[1], contrast)


def _log_chroma(rgb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Log brightness [...] and chromaticity [..., 3] (r, g, b over their sum) of linear RGB."""
    c = np.maximum(np.asarray(rgb, np.float32), 1e-4)
    s = c.sum(-1)
    return np.log(s / 3 + 0.02), c / s[..., None]


def _blurred(photo: np.ndarray, blur: float) -> np.ndarray:
    """float32 [H, W, 3]: ``photo`` blurred by a Gaussian of sigma ``blur`` x its longer side
    (itself for ``blur`` 0)."""
    photo = np.asarray(photo, np.float32)
    if blur <= 0:
        return photo
    return cv2.GaussianBlur(photo, (0, 0), blur * max(photo.shape[:2]),
                            borderType=cv2.BORDER_REPLICATE)


def interior(ids: np.ndarray, rim: int) -> np.ndarray:
    """bool [H, W]: pixels of the ID map ``ids`` int [H, W] whose ID fills the disc of radius
    ``rim`` pixels around them (each ID's mask eroded by ``rim``; all True when ``rim`` is 0)."""
    if rim <= 0:
        return np.ones(ids.shape, bool)
    k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * rim + 1,) * 2)
    m = np.asarray(ids, np.float32)  # exact for IDs below 2**24
    return (cv2.erode(m, k, borderType=cv2.BORDER_REPLICATE) == m) & (
        cv2.dilate(m, k, borderType=cv2.BORDER_REPLICATE) == m)


def point_photo_counts(own: KeyPhoto, ids: np.ndarray, changed: np.ndarray,
                       others: list[KeyPhoto], depth_tol: float, n: int,
                       quantile: float = 0.9, rim: int = 2, min_reference: int = 200,
                       window: float = 0.125, blur: float = 1 / 320
                       ) -> tuple[np.ndarray, np.ndarray]:
    """How the other time's photos show the surface points of one key photo's IDs.

    ``own``: a training photo and the depth its own time's model renders there (its camera
    camera-to-world; photo linear RGB [H, W, 3]); ``ids`` int [H, W] the ID map of that time at
    that pose; ``changed`` bool [n]: the changed IDs. Each pixel's surface point (the rendered
    depth back-projected) is looked up in every photo of ``others`` (the other time's): where
    no surface is rendered in front of it there (nearer by more than ``depth_tol`` x its depth),
    that photo shows what stands at or behind the point at its time, and the point's colour in
    the two photos is compared: absolute difference of log brightness plus L1 difference of
    chromaticity.

    Both photos are blurred first by a Gaussian of ``blur`` x their longer side (sigma;
    :func:`_blurred`): the fit's depth puts a point a pixel or two off its place in the other
    photo, and on a finely textured surface (granite, carpet, wood grain) one pixel off is
    another colour, while what stands in front of it at one time only is not. And the pair's
    exposure and white balance are taken out: the median of the signed differences over the
    reference points (below) is subtracted from every point's. Auto exposure differs between
    visits; uncorrected, every point differs by it, and a changed point whose own change runs
    against it looks alike.

    The reference is the unchanged surface of the same pair of photos: the pixels of IDs not
    ``changed`` that the other photo shows, chosen the same way; their differences come from
    view-dependent shading and the fit's depth error, which moves a point off its surface in
    the other photo as much as a changed ID's point. A
    changed ID's point counts as *differing* when its difference exceeds the ``quantile`` of
    the reference's around it (so about 1 - ``quantile`` of an unchanged surface's points
    differ): within a square of ``window`` x the photo's longer side (:func:`_local_cut`; the
    fit's depth, and with it the error of the lookup, is worse in some parts of a view than
    in others, e.g. at its edge, seen by fewer photos), or over the whole photo with
    ``window`` 0. Only each ID's interior counts (:func:`interior` with ``rim``): on an
    outline a point projects past the object as often as onto it. A pair with fewer than
    ``min_reference`` reference pixels is not used.

    Returns int64 [n] counts per ID: its points shown by the other photos (over all of them),
    and those that differ.
    """
    total, above = np.zeros(n, np.int64), np.zeros(n, np.int64)
    z = np.asarray(own.depth, np.float64)
    H, W = z.shape
    if ids.shape != (H, W) or not len(others):
        return total, above
    P = world_points(z, own.depth_camera()).reshape(-1, 3)
    flat_ids = np.asarray(ids).ravel()
    ok = np.isfinite(z).ravel() & (z.ravel() > 0) & (flat_ids > 0) & (flat_ids < n)
    is_changed = np.zeros(len(flat_ids), bool)
    is_changed[ok] = changed[flat_ids[ok]]
    inside = interior(np.asarray(ids), rim).ravel()
    lum, chroma = _log_chroma(_blurred(own.photo, blur))
    lum, chroma = lum.ravel(), chroma.reshape(-1, 3)
    for kp in others:
        idx, zz, row, col = project_to_depth(P, ok, DepthView(kp.depth_camera(), kp.depth))
        d = np.asarray(kp.depth, np.float64)[row, col]
        surf = np.isfinite(d) & (d > 0)
        tol = depth_tol * z.ravel()[idx]
        shown = ~(surf & (d < zz - tol))
        l2, c2 = _log_chroma(_blurred(kp.photo, blur)[row, col])
        ref = shown & ~is_changed[idx]
        if ref.sum() < min_reference:
            continue
        # the two photos' exposure and white balance: the unchanged surface's median
        # difference, taken out of every point's
        d_lum, d_chroma = lum[idx] - l2, chroma[idx] - c2
        diff = (np.abs(d_lum - np.median(d_lum[ref]))
                + np.abs(d_chroma - np.median(d_chroma[ref], 0)).sum(-1))
        cut = np.quantile(diff[ref], quantile)
        if window > 0:
            cut = _local_cut(idx[ref], diff[ref], (H, W), window, quantile, cut)[idx]
        sel = shown & is_changed[idx] & inside[idx]
        total += np.bincount(flat_ids[idx[sel]], minlength=n)
        above += np.bincount(flat_ids[idx[sel & (diff > cut)]], minlength=n)
    return total, above


def _local_cut(pix: np.ndarray, values: np.ndarray, shape: tuple[int, int], window: float,
               quantile: float, fallback: float) -> np.ndarray:
    """float [H * W]: per pixel of an H x W image, the ``quantile`` of the ``values`` (float
    [K], at the flat pixel indices ``pix``) around it, within a square of ``window`` x the
    image's longer side: that of a normal distribution with their mean and standard deviation
    there. ``fallback`` where fewer than 50 values lie in the square."""
    H, W = shape
    k = max(3, int(round(window * max(H, W))) | 1)
    a = np.zeros(H * W, np.float32)
    b = np.zeros(H * W, np.float32)
    c = np.zeros(H * W, np.float32)
    a[pix], b[pix], c[pix] = values, values.astype(np.float32) ** 2, 1.0
    a, b, c = (cv2.boxFilter(x.reshape(H, W), -1, (k, k), normalize=False,
                             borderType=cv2.BORDER_CONSTANT).ravel() for x in (a, b, c))
    ok = c >= 50
    mean = np.where(ok, a / np.maximum(c, 1), 0)
    std = np.sqrt(np.maximum(np.where(ok, b / np.maximum(c, 1), 0) - mean ** 2, 0))
    return np.where(ok, mean + NormalDist().inv_cdf(quantile) * std, fallback)
