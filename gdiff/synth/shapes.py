"""Analytic shapes resting on the table: local frame with the base centre at the origin and z
up. ``intersect(o, d)`` takes ray origins and unit directions [N, 3] in that frame and returns
``t`` [N] (inf = miss) and outward normals [N, 3]."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

_EPS = 1e-6  # minimum ray parameter (metres) for a valid hit

def safe_dir(d: np.ndarray) -> np.ndarray:
    return np.where(np.abs(d) < 1e-12, 1e-12, d)


@dataclass(frozen=True)
class Box:
    """Box with half extents (a, b) in x, y and height h: [-a, a] x [-b, b] x [0, h]."""
    a: float
    b: float
    h: float
    kind = "box"

    @property
    def lo(self):
        return np.array([-self.a, -self.b, 0.0])

    @property
    def hi(self):
        return np.array([self.a, self.b, self.h])

    @property
    def footprint(self) -> float:
        return math.hypot(self.a, self.b)

    def intersect(self, o, d):
        return box_hit(o, d, self.lo, self.hi)


def box_hit(o, d, lo, hi):
    inv = 1.0 / safe_dir(d)
    t1 = (lo - o) * inv
    t2 = (hi - o) * inv
    tn = np.minimum(t1, t2)
    tf = np.maximum(t1, t2)
    tmin = tn.max(axis=1)
    tmax = tf.min(axis=1)
    hit = (tmax >= tmin) & (tmin > _EPS)
    t = np.where(hit, tmin, np.inf)
    ax = tn.argmax(axis=1)
    n = np.zeros_like(o)
    n[np.arange(len(o)), ax] = -np.sign(safe_dir(d)[np.arange(len(o)), ax])
    return t, n


@dataclass(frozen=True)
class Sphere:
    """Sphere of radius r resting on the table: centre (0, 0, r)."""
    r: float
    kind = "sphere"

    @property
    def lo(self):
        return np.array([-self.r, -self.r, 0.0])

    @property
    def hi(self):
        return np.array([self.r, self.r, 2 * self.r])

    @property
    def footprint(self) -> float:
        return self.r

    def intersect(self, o, d):
        oc = o - np.array([0.0, 0.0, self.r])
        b = np.einsum("ij,ij->i", oc, d)
        c = np.einsum("ij,ij->i", oc, oc) - self.r ** 2
        disc = b * b - c
        sq = np.sqrt(np.maximum(disc, 0.0))
        t = -b - sq
        t = np.where((disc >= 0) & (t > _EPS), t, np.inf)
        n = (oc + np.where(np.isfinite(t), t, 0.0)[:, None] * d) / self.r
        return t, n


@dataclass(frozen=True)
class _Upright:
    """A solid of revolution about the local z axis: radius r, height h (z in [0, h])."""
    r: float
    h: float

    @property
    def lo(self):
        return np.array([-self.r, -self.r, 0.0])

    @property
    def hi(self):
        return np.array([self.r, self.r, self.h])

    @property
    def footprint(self) -> float:
        return self.r


@dataclass(frozen=True)
class Cylinder(_Upright):
    """Upright capped cylinder of radius r and height h (z in [0, h])."""
    kind = "cylinder"

    def intersect(self, o, d):
        a = d[:, 0] ** 2 + d[:, 1] ** 2
        b = o[:, 0] * d[:, 0] + o[:, 1] * d[:, 1]
        c = o[:, 0] ** 2 + o[:, 1] ** 2 - self.r ** 2
        disc = b * b - a * c
        with np.errstate(divide="ignore", invalid="ignore"):
            ts = (-b - np.sqrt(np.maximum(disc, 0.0))) / a
        zs = o[:, 2] + ts * d[:, 2]
        ts = np.where((disc >= 0) & (a > 1e-14) & (ts > _EPS) & (zs >= 0) & (zs <= self.h),
                      ts, np.inf)
        t, n = ts, np.zeros_like(o)
        hs = np.isfinite(ts)
        n[hs, 0] = (o[hs, 0] + ts[hs] * d[hs, 0]) / self.r
        n[hs, 1] = (o[hs, 1] + ts[hs] * d[hs, 1]) / self.r
        dz = safe_dir(d[:, 2])
        for zc, sign in ((self.h, 1.0), (0.0, -1.0)):
            tc = (zc - o[:, 2]) / dz
            x = o[:, 0] + tc * d[:, 0]
            y = o[:, 1] + tc * d[:, 1]
            ok = (tc > _EPS) & (x * x + y * y <= self.r ** 2) & (tc < t)
            t = np.where(ok, tc, t)
            n[ok] = (0.0, 0.0, sign)
        return t, n


@dataclass(frozen=True)
class Cone(_Upright):
    """Upright cone: base disc of radius r at z = 0, apex at (0, 0, h)."""
    kind = "cone"

    def intersect(self, o, d):
        k2 = (self.r / self.h) ** 2
        w0 = self.h - o[:, 2]  # w = h - z along the ray: w0 - t dz
        a = d[:, 0] ** 2 + d[:, 1] ** 2 - k2 * d[:, 2] ** 2
        b = o[:, 0] * d[:, 0] + o[:, 1] * d[:, 1] + k2 * w0 * d[:, 2]
        c = o[:, 0] ** 2 + o[:, 1] ** 2 - k2 * w0 ** 2
        disc = b * b - a * c
        sq = np.sqrt(np.maximum(disc, 0.0))
        t = np.full(len(o), np.inf)
        with np.errstate(divide="ignore", invalid="ignore"):
            for root in ((-b - sq) / a, (-b + sq) / a):
                z = o[:, 2] + root * d[:, 2]
                ok = (disc >= 0) & (np.abs(a) > 1e-14) & (root > _EPS) & (z >= 0) & \
                     (z <= self.h) & (root < t)
                t = np.where(ok, root, t)
        p = o + np.where(np.isfinite(t), t, 0.0)[:, None] * d
        n = np.stack([p[:, 0], p[:, 1], k2 * (self.h - p[:, 2])], 1)
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        tc = -o[:, 2] / safe_dir(d[:, 2])
        x = o[:, 0] + tc * d[:, 0]
        y = o[:, 1] + tc * d[:, 1]
        ok = (tc > _EPS) & (x * x + y * y <= self.r ** 2) & (tc < t)
        t = np.where(ok, tc, t)
        n[ok] = (0.0, 0.0, -1.0)
        return t, n


SHAPES = {"box": Box, "sphere": Sphere, "cylinder": Cylinder, "cone": Cone}


def random_shape(rng: np.random.Generator, kind: str, max_footprint: float | None = None):
    """A shape of ``kind`` with random dimensions (metres); footprint <= max_footprint."""
    for _ in range(20):
        if kind == "box":
            s = Box(a=rng.uniform(0.09, 0.17), b=rng.uniform(0.08, 0.16),
                    h=rng.uniform(0.14, 0.34))
        elif kind == "sphere":
            s = Sphere(r=rng.uniform(0.11, 0.17))
        elif kind == "cylinder":
            s = Cylinder(r=rng.uniform(0.08, 0.14), h=rng.uniform(0.18, 0.4))
        elif kind == "cone":
            s = Cone(r=rng.uniform(0.11, 0.17), h=rng.uniform(0.22, 0.38))
        else:
            raise ValueError(f"unknown shape kind {kind!r}")
        if max_footprint is None or s.footprint <= max_footprint:
            return s
    f = max_footprint / s.footprint  # scale the last draw down to fit
    return dataclasses.replace(s, **{k: v * f for k, v in dataclasses.asdict(s).items()})
