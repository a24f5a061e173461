"""Where the two visits' photos agree: the pixels of a training photo whose surface a photo of
the other visit shows alike, found without the fitted model.

A sparse capture's model renders poorly from some poses, so a render of the other time can
differ from a photo on a surface nothing happened to (a knob, a wall spot, the edge of a
shelf), and the ID comparison may keep it by its colour. Two photos of the two visits taken
from nearby places settle it directly. The other photo is matched to the key photo by dense
optical flow both ways (:func:`gdiff.track.flow_matches`, the tracker's); a pixel agrees
when

- the match is consistent both ways (forward then backward flow returns within ``fb_tol``
  pixels): on a changed object the other photo has nothing to match, and the flow fails there;
- the match lies where a static point on the pixel's ray can appear in the other photo: on
  the image of the ray from half the rendered depth to infinity (where the photos of both
  times agree on the depth, only within ``depth_tol`` of it), within a tolerance taken
  from the pair itself (``max(2 px, 3 x`` the median distance of the consistent matches),
  so that a pose error shared by the pair does not count). An object that moved between the
  visits matches off that segment. A pair whose consistent matches lie off it by more than
  ``max_pose_error`` of the image width (views too far apart for the flow, or poses too far
  off) says nothing;
- the colours agree: the other photo, warped by the flow and scaled per channel by the median
  ratio over the consistent matches (exposure), differs from the key photo by less than
  ``contrast`` times the median difference of those matches (their noise floor).

The test can only say "unchanged": where the flow fails (a changed object, a textureless wall
it cannot lock onto, a specular sink) nothing is decided.

Coordinates: cameras are camera-to-world (OpenCV axes: x right, y down, z forward; pixel
centres at +0.5); depth is camera-frame z, as in the EXR ``Z`` channel; photos are linear RGB.
"""

from __future__ import annotations

import cv2
import numpy as np

from ..appearance import median_gain
from ..io import linear_to_srgb
from ..track import flow_matches
from .photos import KeyPhoto

# fewest consistent matches a pair must have to say anything
_MIN_MATCHES = 100


def _grey8(photo: np.ndarray) -> np.ndarray:
    """uint8 [H, W] sRGB luma of a linear RGB photo [H, W, 3] (the flow's input)."""
    s = np.clip(linear_to_srgb(np.asarray(photo, np.float32)), 0, 1)
    return np.round(255 * (s @ np.array([0.299, 0.587, 0.114], np.float32))).astype(np.uint8)


def ray_segment_distance(cam_a, cam_b, depth_a: np.ndarray, matches: np.ndarray,
                         near=0.5, far=np.inf) -> np.ndarray:
    """Per pixel of camera ``cam_a`` (:class:`gdiff.cameras.Camera`, camera-to-world, at the
    size of ``depth_a``), the distance in pixels of ``matches`` (float [H, W, 2], x and y pixel
    indices in camera ``cam_b``) from the image in ``cam_b`` of the pixel's ray between
    ``near`` and ``far`` times its depth ``depth_a`` (float [H, W], camera-frame z; NaN or
    <= 0: the median valid depth). ``near`` and ``far``: scalars or float [H, W] (``far``
    inf: to infinity). Both cameras must have the same pixel grid convention (centres at
    +0.5)."""
    h, w = depth_a.shape
    T = cam_b.w2c @ cam_a.c2w  # camera a -> camera b
    R, t = T[:3, :3], T[:3, 3]
    col, row = np.meshgrid(np.arange(w, dtype=np.float64) + 0.5,
                           np.arange(h, dtype=np.float64) + 0.5)
    rays = np.stack([col, row, np.ones_like(col)], -1).reshape(-1, 3) @ np.linalg.inv(cam_a.K).T
    d = np.asarray(depth_a, np.float64).reshape(-1)
    good = np.isfinite(d) & (d > 0)
    d = np.where(good, d, np.median(d[good]) if good.any() else 1.0)
    near = np.broadcast_to(np.asarray(near, np.float64), (h, w)).reshape(-1, 1)
    far = np.broadcast_to(np.asarray(far, np.float64), (h, w)).reshape(-1, 1)
    Kb = cam_b.K
    turned = rays @ R.T
    # the far end: the ray's vanishing point (far = inf), else the point at far x depth
    at_inf = turned @ Kb.T
    finite = np.isfinite(far)
    at_far = (np.where(finite, far, 1.0) * d[:, None] * turned + t) @ Kb.T
    far_h = np.where(finite, at_far, at_inf)
    close = (near * d[:, None] * turned + t) @ Kb.T
    p_far = far_h[:, :2] / np.where(np.abs(far_h[:, 2:]) > 1e-12, far_h[:, 2:], 1e-12)
    p_close = close[:, :2] / np.maximum(close[:, 2:], 1e-9)
    # where the near end lies behind camera b, its ray's image starts at the far end only
    p_close = np.where(close[:, 2:] > 1e-9, p_close, p_far)
    q = np.asarray(matches, np.float64).reshape(-1, 2) + 0.5
    seg = p_far - p_close
    length = (seg * seg).sum(1)
    s = np.clip(((q - p_close) * seg).sum(1) / np.maximum(length, 1e-12), 0, 1)
    return np.linalg.norm(q - (p_close + s[:, None] * seg), axis=1).reshape(h, w)


def photos_agree(own: KeyPhoto, other: KeyPhoto, contrast: float = 3.0, fb_tol: float = 2.0,
                 max_pose_error: float = 0.01, blur: float = 2.0,
                 trusted: np.ndarray | None = None, depth_tol: float = 0.05
                 ) -> np.ndarray | None:
    """Bool [H, W] at ``own``'s depth size: the pixels of ``own.photo`` whose surface
    ``other.photo`` shows alike (module docstring); None when the pair says nothing (too few
    consistent matches, or they lie off the rays' images by more than ``max_pose_error`` of
    the image width). ``blur``: Gaussian sigma in pixels before the colours are compared.
    ``trusted`` (bool [H, W], optional): the pixels whose rendered depth the photos of both
    times agree on (:func:`gdiff.compare.coverage.observed`); there a static point lies within
    ``depth_tol`` (relative) of it, and the match must lie on that stretch of the ray; elsewhere
    anywhere from half the depth to infinity."""
    h, w = np.shape(own.depth)
    a = np.asarray(own.photo, np.float32)
    b = np.asarray(other.photo, np.float32)
    if a.shape[:2] != (h, w) or b.shape[:2] != (h, w):
        return None
    mx, my, err = flow_matches(_grey8(a), _grey8(b))
    inside = (mx >= 0) & (mx <= w - 1) & (my >= 0) & (my <= h - 1)
    consistent = inside & (err < fb_tol)
    if consistent.sum() < _MIN_MATCHES:
        return None
    near, far = 0.5, np.inf
    if trusted is not None and np.shape(trusted) == (h, w):
        near = np.where(trusted, 1.0 - depth_tol, near)
        far = np.where(trusted, 1.0 + depth_tol, far)
    off = ray_segment_distance(own.depth_camera(), other.depth_camera(), np.asarray(own.depth),
                               np.stack([mx, my], -1), near, far)
    typical = float(np.median(off[consistent]))
    if typical > max_pose_error * w:
        return None
    matched = consistent & (off < max(2.0, 3.0 * typical))
    if matched.sum() < _MIN_MATCHES:
        return None
    warped = cv2.remap(b, mx, my, cv2.INTER_LINEAR)
    sa = cv2.GaussianBlur(linear_to_srgb(a), (0, 0), blur)
    sb = cv2.GaussianBlur(linear_to_srgb(warped), (0, 0), blur)
    gain = median_gain(sa[matched], sb[matched], 1e-4)
    diff = np.abs(sa - sb * gain).max(-1)
    floor = float(np.median(diff[matched]))
    return matched & (diff <= contrast * max(floor, 1e-4))


def nearest_photos(own: KeyPhoto, others: list[KeyPhoto], n: int = 3,
                  max_angle: float = 45.0) -> list[KeyPhoto]:
    """The ``n`` photos of ``others`` taken nearest to ``own``'s: ranked by the distance between
    the camera centres over the median depth ``own`` renders (its scene scale) plus the angle
    between the viewing directions in radians; only those within ``max_angle`` degrees of
    ``own``'s viewing direction (others cannot show much of the same surface)."""
    d = np.asarray(own.depth, np.float64)
    good = np.isfinite(d) & (d > 0)
    scale = float(np.median(d[good])) if good.any() else 1.0
    za = own.camera.c2w[:3, 2]
    ranked = []
    for k, o in enumerate(others):
        cos = float(np.clip(za @ o.camera.c2w[:3, 2], -1.0, 1.0))
        angle = np.arccos(cos)
        if np.degrees(angle) > max_angle:
            continue
        ranked.append((np.linalg.norm(own.camera.center - o.camera.center) / scale + angle, k))
    return [others[k] for _, k in sorted(ranked)[:n]]


def agreeing(own: KeyPhoto, others: list[KeyPhoto], contrast: float = 3.0,
             n_views: int = 3, trusted: np.ndarray | None = None,
             depth_tol: float = 0.05) -> np.ndarray:
    """Bool [H, W] at ``own``'s depth size: the pixels of ``own``'s photo that at least one
    photo of ``others`` (the other visit's key photos; the ``n_views`` nearest,
    :func:`nearest_photos`) shows alike (:func:`photos_agree`, with ``trusted`` and
    ``depth_tol``)."""
    out = np.zeros(np.shape(own.depth), bool)
    for o in nearest_photos(own, others, n_views):
        m = photos_agree(own, o, contrast, trusted=trusted, depth_tol=depth_tol)
        if m is not None:
            out |= m
    return out
