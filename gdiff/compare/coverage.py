"""Observation coverage: which pixels of a rendered frame show a surface some photo of that time saw.

A 4D model fitted to before photos (t=0) and after photos (t=1) is constrained at time t only
where a photo of time t saw the surface. Elsewhere its time-dependent opacity, colour and
position are free, and a render at that time says nothing about the scene (e.g. a wall only the
before photos saw renders dark or blurred at t=1). A comparison of the two times must ignore
such pixels.

A pixel of a frame rendered at time t is *observed* when its surface point (rendered z-depth
back-projected through the pixel centre) projects into at least ``min_views`` key views of time
t - the training cameras of that time, rendered at that time - inside the image, in front of
the camera, and with the key view's rendered depth there agreeing within ``depth_tol``
(relative): the point is not hidden from that photo behind another surface. "There" is the
pixel the point projects to and, with a :class:`DepthView` ``window`` > 0, the pixels within
that many of it (the point's depth must lie within the range the key view renders around it,
widened by ``depth_tol``): a model fitted to few photos renders a surface's depth with noise
from pixel to pixel and from view to view, and a one-pixel test then calls half of a surface
that every photo shows unseen, at random. Conventions:
OpenCV camera axes, ``c2w`` camera-to-world, pixel centres at +0.5, z-depth along the camera's
+z axis (scene units).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import cv2
import numpy as np

from ..cameras import Camera
from ..segment.base import ALPHA_MIN
from ..track import world_points


@dataclass
class DepthView:
    """A training view rendered at its own time: ``camera`` and its z-depth float [H, W].

    ``window`` (pixels, >= 0): a point is tested against the depths the view renders within
    this many pixels of its own (a square window, see the module docstring); 0 tests the one
    pixel."""

    camera: Camera
    depth: np.ndarray
    window: int = 0

    def depth_range(self) -> tuple[np.ndarray, np.ndarray]:
        """float32 [H, W] each: the smallest and largest valid z-depth within ``window`` pixels
        of each pixel (+inf and -inf where there is none); computed once per view."""
        return self._range

    @cached_property
    def _range(self) -> tuple[np.ndarray, np.ndarray]:
        z = np.asarray(self.depth, np.float32)
        ok = np.isfinite(z) & (z > 0)
        lo = np.where(ok, z, np.float32(np.inf))
        hi = np.where(ok, z, np.float32(-np.inf))
        if self.window > 0:
            k = cv2.getStructuringElement(cv2.MORPH_RECT, (2 * self.window + 1,) * 2)
            lo = cv2.erode(lo, k, borderType=cv2.BORDER_REPLICATE)
            hi = cv2.dilate(hi, k, borderType=cv2.BORDER_REPLICATE)
        return lo, hi


def project_to_depth(P: np.ndarray, finite: np.ndarray, v: DepthView
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The world points ``P`` [N, 3] (``finite`` bool [N]: the ones to consider) that fall in
    front of ``v``'s camera and inside its depth map: their indices ``idx`` int [K], their
    camera-frame z [K] and their pixel's row and column (int64 [K]; pixel centres at +0.5)."""
    c = v.camera
    Q = (P - c.c2w[:3, 3]) @ c.c2w[:3, :3]  # world -> camera (rotation transposed)
    z = Q[:, 2]
    ok = finite & (z > 1e-9)
    zs = np.where(ok, z, 1.0)
    u = np.floor(c.fx * Q[:, 0] / zs + c.cx)
    w = np.floor(c.fy * Q[:, 1] / zs + c.cy)
    h, wd = np.asarray(v.depth).shape
    ok &= (u >= 0) & (u < wd) & (w >= 0) & (w < h)
    idx = np.flatnonzero(ok)
    return idx, z[idx], w[idx].astype(np.int64), u[idx].astype(np.int64)


def _sees(P: np.ndarray, finite: np.ndarray, v: DepthView, depth_tol: float) -> np.ndarray:
    """bool [N]: ``v`` sees the world points ``P`` [N, 3] (see :func:`view_count`)."""
    idx, z, row, col = project_to_depth(P, finite, v)
    seen = np.zeros(len(P), bool)
    lo, hi = v.depth_range()  # the view's depth itself with no window
    lo, hi = lo[row, col].astype(np.float64), hi[row, col].astype(np.float64)
    seen[idx[(z >= lo * (1 - depth_tol)) & (z <= hi * (1 + depth_tol))]] = True
    return seen


def _rays(P: np.ndarray, v: DepthView) -> np.ndarray:
    """Unit directions float32 [N, 3] from the centre of ``v``'s camera to the points ``P``."""
    d = (P - v.camera.c2w[:3, 3]).astype(np.float32)
    n = np.sqrt(np.einsum("ij,ij->i", d, d))
    return d / np.maximum(n, 1e-12)[:, None]


#: points handled at once (bounds the memory of the per-view rays: views x CHUNK x 3 floats)
CHUNK = 1 << 16


def view_count(points: np.ndarray, views: list[DepthView], depth_tol: float,
               parallax: bool = False):
    """Number of ``views`` that see each world point, int [...] for ``points`` [..., 3].

    A view sees a point when it projects inside the view's image, in front of the camera, and
    the view's depth at that pixel (nearest pixel) agrees with the point's depth within
    ``depth_tol`` x the view's depth. Non-finite points are seen by no view.

    With ``parallax`` also returns the widest angle (degrees, float [...]) between the rays of
    two views that see the point (0 when fewer than two do): found by two sweeps (the view
    farthest in angle from the first seeing view, then the view farthest from that one), which
    is at least half the exact widest angle and usually equals it.
    """
    shape = points.shape[:-1]
    P = np.asarray(points, np.float64).reshape(-1, 3)
    count = np.zeros(len(P), np.int32)
    angle = np.zeros(len(P), np.float32)
    for a in range(0, len(P), CHUNK):
        Pc = P[a:a + CHUNK]
        finite = np.isfinite(Pc).all(1)
        seen = np.stack([_sees(Pc, finite, v, depth_tol) for v in views])  # [V, n]
        cnt = seen.sum(0)
        count[a:a + CHUNK] = cnt
        if not parallax or not views:
            continue
        rays = np.stack([_rays(Pc, v) for v in views])  # [V, n, 3]
        cols = np.arange(len(Pc))
        ref = rays[np.argmax(seen, 0), cols]  # the first view that sees each point
        for _ in range(2):  # the ray farthest in angle from the reference becomes the reference
            cos = np.where(seen, np.einsum("vnk,nk->vn", rays, ref), 2.0)
            far = np.argmin(cos, 0)
            ref = rays[far, cols]
        best = cos[far, cols]
        ang = np.degrees(np.arccos(np.clip(best, -1.0, 1.0)))
        angle[a:a + CHUNK] = np.where(cnt >= 2, ang, 0.0)
    if parallax:
        return count.reshape(shape), angle.reshape(shape)
    return count.reshape(shape)


def nearest_views(points: np.ndarray, views: list[DepthView], depth_tol: float, max_views: int,
                  stride: int = 61, spread: bool = False) -> list[DepthView]:
    """The (at most) ``max_views`` of ``views`` that see the most of a frame's surface.

    ``points``: the frame's world points [..., 3] (:func:`gdiff.track.world_points`), tested
    with :func:`view_count`'s visibility test on every ``stride``-th point (in memory order).
    Views that see none of them are dropped; ties keep the earlier view. The views keep
    their order. ``max_views`` <= 0 keeps every view that sees some point.

    With ``spread``, the views are picked for parallax as well: among the views that see at
    least half as much of the frame as the best one, the best one first, then each time the
    one farthest in direction (seen from the surface's centroid) from those already picked;
    remaining places go to the next views by share. Photos taken close together along a path
    share most of a frame but see it from nearly one direction, so the plain ranking can
    leave every pixel short of the parallax a depth test needs.
    """
    if not views:
        return []
    P = np.asarray(points, np.float64).reshape(-1, 3)[::stride]
    finite = np.isfinite(P).all(1)
    hits = np.array([_sees(P, finite, v, depth_tol).sum() for v in views])
    order = np.argsort(-hits, kind="stable")
    order = order[hits[order] > 0]
    if max_views > 0 and len(order) > max_views:
        if spread and finite.any():
            order = _spread(order, hits, views, P[finite].mean(0), max_views)
        else:
            order = order[:max_views]
    return [views[i] for i in sorted(order)]


def _spread(order: np.ndarray, hits: np.ndarray, views: list[DepthView], centre: np.ndarray,
            max_views: int) -> np.ndarray:
    """``max_views`` of the ranked views ``order`` chosen for direction spread (see
    :func:`nearest_views`): farthest-point sampling of the unit directions from ``centre`` [3]
    to the camera centres, over the views with at least half the best view's hits."""
    d = np.stack([views[i].camera.c2w[:3, 3] - centre for i in order])
    d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
    good = hits[order] >= 0.5 * hits[order[0]]
    chosen = [0]
    closest = d @ d[0]  # cosine to the nearest chosen direction, per ranked view
    while len(chosen) < max_views:
        cand = np.flatnonzero(good)
        cand = cand[~np.isin(cand, chosen)]
        if len(cand) == 0:
            break
        k = int(cand[np.argmin(closest[cand])])  # argmin keeps the better-ranked on ties
        chosen.append(k)
        closest = np.maximum(closest, d @ d[k])
    rest = [k for k in range(len(order)) if k not in chosen]
    return order[chosen + rest[:max_views - len(chosen)]]


def surface(depth: np.ndarray, alpha: np.ndarray | None = None,
            alpha_min: float = ALPHA_MIN) -> np.ndarray:
    """bool [H, W]: pixels of a rendered frame that show a surface: finite positive z-depth
    [H, W] and, with ``alpha`` (rendered opacity [H, W]), opacity >= ``alpha_min``."""
    z = np.asarray(depth)
    out = np.isfinite(z) & (z > 0)
    if alpha is not None:
        out &= np.asarray(alpha) >= alpha_min
    return out


#: levels of a judged map (:func:`judged_map`, ``change/<path>/judged/NNNNN.png``)
NO_SURFACE, NOT_JUDGED, JUDGED_SEEN, JUDGED_DEPTH = 0, 64, 128, 255


def judged_map(surfaces: np.ndarray, shown: np.ndarray, known: np.ndarray) -> np.ndarray:
    """uint8 [H, W]: how the compare stage could judge each pixel of a pose.

    ``surfaces`` bool [H, W]: a surface is rendered there at both times (:func:`surface`);
    ``shown``: a photo of each time shows it (:func:`observed`'s second mask, both times);
    ``known``: its depth is observed at both times (:func:`observed`'s first mask, both
    times). Levels: :data:`NO_SURFACE` (no surface at one of the times: nothing to compare),
    :data:`NOT_JUDGED` (a surface no photo of one of the times shows: the model there is a
    guess, and no change is marked by the ID comparison), :data:`JUDGED_SEEN` (judged by its
    IDs and appearance) and :data:`JUDGED_DEPTH` (judged also by its depth)."""
    surfaces = np.asarray(surfaces, bool)
    out = np.full(surfaces.shape, NO_SURFACE, np.uint8)
    out[surfaces] = NOT_JUDGED
    seen = surfaces & np.asarray(shown, bool)
    out[seen] = JUDGED_SEEN
    out[seen & np.asarray(known, bool)] = JUDGED_DEPTH
    return out


def judged_counts(judged: np.ndarray) -> dict[str, int]:
    """Pixel counts of a :func:`judged_map`: ``surface`` (a surface at both times), ``seen``
    (judged: shown by a photo of each time) and ``depth`` (judged also by depth)."""
    j = np.asarray(judged)
    return {"surface": int((j != NO_SURFACE).sum()), "seen": int((j >= JUDGED_SEEN).sum()),
            "depth": int((j == JUDGED_DEPTH).sum())}


def observed(depth: np.ndarray, camera: Camera, views: list[DepthView], depth_tol: float = 0.05,
             min_views: int = 1, alpha: np.ndarray | None = None,
             alpha_min: float = ALPHA_MIN, min_parallax: float = 0.0,
             max_views: int = 0, seen: bool = False, step: int = 1,
             points: np.ndarray | None = None):
    """bool [H, W]: pixels of a frame (z-depth [H, W], ``camera``) rendered at time t whose
    surface at least ``min_views`` key views of time t see (see the module docstring), from
    directions at least ``min_parallax`` degrees apart (a surface seen from one direction only
    has an undetermined depth: the model may put it anywhere along the rays).

    With ``alpha`` (rendered opacity [H, W]) pixels below ``alpha_min`` are not observed
    (nothing was rendered there). With no views every pixel with a surface counts as observed
    (nothing to check against). With ``max_views`` > 0 only the views that see most of the
    frame decide first (:func:`nearest_views`), and only the pixels they leave unobserved
    are tested against every view: the same result (a point a subset of the views observes,
    all views observe; up to the two-sweep parallax estimate, exact for views along an arc)
    at a cost per frame that grows with the number of views only on those pixels.

    With ``seen`` returns a pair (observed, seen): ``seen`` bool [H, W] marks the pixels whose
    surface at least one key view sees (a photo of that time shows it, so the render there
    reproduces a photo, though with fewer views or too little parallax its depth is not
    determined).

    With ``step`` > 1 the test runs on every ``step``-th pixel of every ``step``-th row only
    (the top-left pixel of each ``step`` x ``step`` block), and each block takes its tested
    pixel's answer (a pixel with a surface in a block whose tested pixel has none is not
    observed): coverage changes over many pixels, so a coarser grid keeps the cost per frame
    down at the price of block-sized steps along its borders.

    ``points`` (optional): the frame's world points [H, W, 3]
    (:func:`gdiff.track.world_points` of ``depth`` and ``camera``) when the caller has them.
    """
    z = np.asarray(depth)
    out = surface(z, alpha, alpha_min)
    if not views:
        return (out, out.copy()) if seen else out
    P = world_points(z, camera) if points is None else points
    if step > 1:
        H, W = out.shape
        # pixel centres of the tested pixels: the full-size camera, every step-th pixel
        P = P[::step, ::step]
        grid = out[::step, ::step]
        masks = _observed_points(P, grid, views, depth_tol, min_views, min_parallax, max_views,
                                 seen)
        full = [np.repeat(np.repeat(m, step, 0), step, 1)[:H, :W] & out for m in masks]
        return tuple(full) if seen else full[0]
    masks = _observed_points(P, out, views, depth_tol, min_views, min_parallax, max_views, seen)
    return tuple(masks) if seen else masks[0]


def _observed_points(P: np.ndarray, out: np.ndarray, views: list[DepthView], depth_tol: float,
                     min_views: int, min_parallax: float, max_views: int,
                     seen: bool) -> list[np.ndarray]:
    """The masks of :func:`observed` (observed, and with ``seen`` the seen one) for the world
    points ``P`` [h, w, 3] of the pixels ``out`` bool [h, w] that show a surface."""

    def sees(pts, vs):
        """(observed, seen by one view at least), bool [n] each."""
        if min_parallax > 0:
            count, angle = view_count(pts, vs, depth_tol, parallax=True)
            return (count >= min_views) & (angle >= min_parallax), count >= 1
        count = view_count(pts, vs, depth_tol)
        return count >= min_views, count >= 1

    todo = np.flatnonzero(out.ravel())
    P = P.reshape(-1, 3)[todo]
    res = np.zeros(len(todo), bool)
    one = np.zeros(len(todo), bool)
    if max_views > 0 and len(views) > max_views:
        # the views that share most of the frame decide most pixels; only the pixels they
        # leave unobserved are tested against every view
        near = nearest_views(P, views, depth_tol, max_views, spread=min_parallax > 0)
        if near:
            res, one = sees(P, near)
        rest = np.flatnonzero(~res)
        if len(rest):
            res[rest], one[rest] = sees(P[rest], views)
    else:
        res, one = sees(P, views)
    masks = []
    for r in (res, one) if seen else (res,):
        ok = np.zeros(out.size, bool)
        ok[todo] = r
        masks.append(ok.reshape(out.shape))
    return masks
