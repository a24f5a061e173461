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
(relative): the point is not hidden from that photo behind another surface. Conventions:
OpenCV camera axes, ``c2w`` camera-to-world, pixel centres at +0.5, z-depth along the camera's
+z axis (scene units).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .cameras import Camera
from .track import world_points


@dataclass
class KeyView:
    """A training view rendered at its own time: ``camera`` and its z-depth float [H, W]."""

    camera: Camera
    depth: np.ndarray


def view_count(points: np.ndarray, views: list[KeyView], depth_tol: float) -> np.ndarray:
    """Number of ``views`` that see each world point, int [...] for ``points`` [..., 3].

    A view sees a point when it projects inside the view's image, in front of the camera, and
    the view's depth at that pixel (nearest pixel) agrees with the point's depth within
    ``depth_tol`` x the view's depth. Non-finite points are seen by no view.
    """
    shape = points.shape[:-1]
    P = np.asarray(points, np.float64).reshape(-1, 3)
    finite = np.isfinite(P).all(1)
    count = np.zeros(len(P), np.int32)
    for v in views:
        c = v.camera
        Q = (P - c.c2w[:3, 3]) @ c.c2w[:3, :3]  # world -> camera (rotation transposed)
        z = Q[:, 2]
        ok = finite & (z > 1e-9)
        zs = np.where(ok, z, 1.0)
        u = np.floor(c.fx * Q[:, 0] / zs + c.cx)
        w = np.floor(c.fy * Q[:, 1] / zs + c.cy)
        dz = np.asarray(v.depth)
        ok &= (u >= 0) & (u < dz.shape[1]) & (w >= 0) & (w < dz.shape[0])
        idx = np.flatnonzero(ok)
        zk = dz[w[idx].astype(np.int64), u[idx].astype(np.int64)].astype(np.float64)
        seen = np.isfinite(zk) & (zk > 0) & (np.abs(z[idx] - zk) <= depth_tol * np.abs(zk))
        count[idx[seen]] += 1
    return count.reshape(shape)


def observed(depth: np.ndarray, camera: Camera, views: list[KeyView], depth_tol: float = 0.05,
             min_views: int = 1, alpha: np.ndarray | None = None,
             alpha_min: float = 0.5) -> np.ndarray:
    """bool [H, W]: pixels of a frame (z-depth [H, W], ``camera``) rendered at time t whose
    surface at least ``min_views`` key views of time t see (see the module docstring).

    With ``alpha`` (rendered opacity [H, W]) pixels below ``alpha_min`` are not observed
    (nothing was rendered there). With no views every pixel with a surface counts as observed
    (nothing to check against).
    """
    z = np.asarray(depth)
    out = np.isfinite(z) & (z > 0)
    if alpha is not None:
        out &= np.asarray(alpha) >= alpha_min
    if not views:
        return out
    return out & (view_count(world_points(z, camera), views, depth_tol) >= min_views)
