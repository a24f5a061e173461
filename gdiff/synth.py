"""Procedural change-detection scenes with exact ground truth (a small vectorised ray tracer).

A scene is a closed textured room (floor, four walls, ceiling) with a slab table in the middle
and a handful of analytic objects (boxes, spheres, cylinders, cones) on it, each with its own
procedural solid texture. The scene has two *states*, ``before`` and ``after``, differing by
object changes (added, removed, moved, replaced) and optionally by the lighting (sun direction,
colour and strength, so hard shadows move).

World frame: z up, metres, floor at z = 0 (the same frame as the shared path-traced scenes).
Cameras use the project conventions (``gdiff.cameras.Camera``): OpenCV axes (x right, y down,
z forward), ``c2w`` camera-to-world, pinhole, pixel (col i, row j) centred at (i+0.5, j+0.5).

Rendering (:meth:`SynthScene.render`):

* colour: ``supersample x supersample`` rays per pixel on a regular sub-pixel grid,
  Lambertian albedo x (hemispherical ambient + sun with cast shadows, a soft sun is sampled
  over its angular disc), an exponential tone curve, averaged in linear space and returned
  sRGB-encoded in [0, 1];
* ground truth (instance ids, depth, normals, changed mask, cast-shadow mask): one ray through
  every pixel centre, so it is pixel-exact and independent of the anti-aliasing.

Walls and ceiling do not cast shadows (the sun shines "through" them, as in the shared scenes);
the table and the objects do.

:func:`make_scene` writes a gdiff scene folder with the layout of the shared scenes (see
``/work/shared/scenes/README.md``)::

    before/NNN.png after/NNN.png eval/before/NNN.png eval/after/NNN.png
    eval/masks/NNN.png eval/mask_before/NNN.png eval/mask_after/NNN.png
    gt_cameras.json meta.json timing.json

Everything is deterministic for a given preset and seed (``timing.json`` aside).
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import logging
import math
import os
import shutil
import sys
import tempfile
import time
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from .cameras import Camera, look_at
from .errors import ConfigError, GdiffError
from .io import linear_to_srgb, srgb_to_linear, write_image, write_json, write_mask
from .log import progress

log = logging.getLogger("gdiff.synth")

STATES = ("before", "after")
_EPS = 1e-6  # minimum ray parameter (metres) for a valid hit
_SHADOW_OFFSET = 1e-4  # shadow-ray origin offset along the normal (metres)


# ---------------------------------------------------------------------------------------------
# Presets and options
# ---------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class SynthPreset:
    """Everything that defines a procedural scene apart from the seed.

    Image size in pixels; angles in degrees; lengths in metres. Orbits are arcs around the
    table centre: the before arc is centred on a random azimuth, the after arc on that azimuth
    plus ``after_shift_deg``; elevations vary smoothly along each arc between the two values.
    ``lighting`` is ``"uniform"`` (the same soft high sun before and after) or ``"change"``
    (a hard sun that moves, changes colour and strength; ambient changes too).
    """

    name: str
    description: str
    width: int = 192
    height: int = 144
    hfov_deg: float = 52.0
    supersample: int = 2
    n_before: int = 18
    n_after: int = 18
    n_eval: int = 5
    n_static: int = 5
    n_added: int = 1
    n_removed: int = 1
    n_moved: int = 1
    n_replaced: int = 0
    lighting: str = "uniform"
    before_span_deg: float = 120.0
    after_span_deg: float = 110.0
    after_shift_deg: float = 15.0
    radius_before: float = 2.1
    radius_after: float = 2.35
    elevation_before: tuple[float, float] = (26.0, 40.0)
    elevation_after: tuple[float, float] = (34.0, 46.0)
    jitter_m: float = 0.03
    room_half_size: float = 3.2
    room_height: float = 2.8
    table_half_size: tuple[float, float] = (1.0, 0.75)
    table_height: float = 0.08

    def __post_init__(self):
        if self.width < 8 or self.height < 8:
            raise ConfigError(f"synth preset '{self.name}': width/height must be >= 8 pixels")
        if self.supersample < 1:
            raise ConfigError(f"synth preset '{self.name}': supersample must be >= 1")
        if min(self.n_before, self.n_after) < 2 or self.n_eval < 1:
            raise ConfigError(f"synth preset '{self.name}': need n_before, n_after >= 2 and "
                              "n_eval >= 1")
        if self.lighting not in ("uniform", "change"):
            raise ConfigError(f"synth preset '{self.name}': lighting must be 'uniform' or "
                              f"'change', not {self.lighting!r}")
        n_changes = self.n_added + self.n_removed + self.n_moved + self.n_replaced
        if min(self.n_static, self.n_added, self.n_removed, self.n_moved, self.n_replaced) < 0:
            raise ConfigError(f"synth preset '{self.name}': object counts must be >= 0")
        if n_changes + self.n_static > 12:
            raise ConfigError(f"synth preset '{self.name}': at most 12 objects fit on the table")
        r_max = max(self.radius_before, self.radius_after)
        if r_max + self.jitter_m >= self.room_half_size - 0.2:
            raise ConfigError(f"synth preset '{self.name}': camera orbits must stay inside the "
                              "room (radius < room_half_size - 0.2)")


PRESETS: dict[str, SynthPreset] = {
    "tiny": SynthPreset(
        name="tiny",
        description="test scene: 128x96, 10+10 training views, 3 eval views; "
                    "1 object added + 1 removed; uniform light",
        width=128, height=96, n_before=10, n_after=10, n_eval=3,
        n_static=4, n_added=1, n_removed=1, n_moved=0,
        before_span_deg=100.0, after_span_deg=90.0, after_shift_deg=12.0),
    "demo": SynthPreset(
        name="demo",
        description="demo scene: 192x144, 18+18 training views, 5 eval views; "
                    "1 object added, 1 removed, 1 moved; uniform light",
        width=192, height=144, n_before=18, n_after=18, n_eval=5,
        n_static=5, n_added=1, n_removed=1, n_moved=1),
    "lightchange": SynthPreset(
        name="lightchange",
        description="lighting-change scene: 192x144, 18+18 training views, 5 eval views; "
                    "1 object replaced, 1 moved; the sun moves, changes colour and strength "
                    "(hard shadows move) - lighting differences are not changes",
        width=192, height=144, n_before=18, n_after=18, n_eval=5,
        n_static=5, n_added=0, n_removed=0, n_moved=1, n_replaced=1, lighting="change"),
}


@dataclass
class SynthOptions:
    """Options of the ``synth`` step (config section ``synth``).

    ``preset`` names an entry of :data:`PRESETS`; the other fields, when not ``None``, override
    that preset's field of the same name.
    """

    preset: str = "demo"
    seed: int = 0
    width: int | None = None
    height: int | None = None
    supersample: int | None = None
    n_before: int | None = None
    n_after: int | None = None
    n_eval: int | None = None

    def to_preset(self) -> SynthPreset:
        """The :class:`SynthPreset` these options describe."""
        base = get_preset(self.preset)
        over = {k: v for k, v in dataclasses.asdict(self).items()
                if k not in ("preset", "seed") and v is not None}
        return dataclasses.replace(base, **over) if over else base


def get_preset(preset: str | SynthPreset) -> SynthPreset:
    """Look up a preset by name (a :class:`SynthPreset` is returned as is)."""
    if isinstance(preset, SynthPreset):
        return preset
    try:
        return PRESETS[preset]
    except KeyError:
        raise ConfigError(f"synth preset {preset!r} is unknown; choose one of "
                          f"{', '.join(PRESETS)}") from None


# ---------------------------------------------------------------------------------------------
# Hashing and noise (deterministic, vectorised)
# ---------------------------------------------------------------------------------------------

_U64 = np.uint64
_PRIMES = (_U64(0x9E3779B97F4A7C15), _U64(0xC2B2AE3D27D4EB4F), _U64(0x165667B19E3779F9),
           _U64(0xD6E8FEB86659FD93))


def _mix64(z: np.ndarray) -> np.ndarray:
    """splitmix64 finaliser on uint64 arrays (wrap-around arithmetic)."""
    z = z ^ (z >> _U64(30))
    z = z * _U64(0xBF58476D1CE4E5B9)
    z = z ^ (z >> _U64(27))
    z = z * _U64(0x94D049BB133111EB)
    return z ^ (z >> _U64(31))


def _hash01(seed: int, *coords: np.ndarray) -> np.ndarray:
    """Uniform [0, 1) float64 per integer lattice cell ``coords`` (int arrays), for ``seed``."""
    with np.errstate(over="ignore"):
        h = _mix64(np.full(np.shape(coords[0]), _U64(seed & 0xFFFFFFFFFFFFFFFF)))
        for k, c in enumerate(coords):
            h = _mix64(h ^ (np.asarray(c, dtype=np.int64).view(np.uint64) * _PRIMES[k % 4]))
    return (h >> _U64(11)).astype(np.float64) * (1.0 / 9007199254740992.0)


_NOISE_N = 32  # value-noise lattice period (cells)


@functools.lru_cache(maxsize=128)
def _noise_table(seed: int) -> np.ndarray:
    """Random lattice values, flattened [32**3] float64, fixed per seed."""
    return np.random.default_rng(seed).random(_NOISE_N ** 3)


def _value_noise(p: np.ndarray, seed: int) -> np.ndarray:
    """Smooth value noise in [0, 1] at points ``p`` [N, 3] (lattice spacing 1, period 32)."""
    tab = _noise_table(seed)
    fl = np.floor(p)
    f = p - fl
    u = f * f * (3.0 - 2.0 * f)
    i = fl.astype(np.int64) & (_NOISE_N - 1)
    j = (i + 1) & (_NOISE_N - 1)
    sx, sy = _NOISE_N * _NOISE_N, _NOISE_N
    out = np.zeros(len(p))
    for dx in (0, 1):
        ox = (j[:, 0] if dx else i[:, 0]) * sx
        wx = u[:, 0] if dx else 1.0 - u[:, 0]
        for dy in (0, 1):
            oxy = ox + (j[:, 1] if dy else i[:, 1]) * sy
            wxy = wx * (u[:, 1] if dy else 1.0 - u[:, 1])
            out += wxy * ((1.0 - u[:, 2]) * tab.take(oxy + i[:, 2]) + u[:, 2] * tab.take(oxy + j[:, 2]))
    return out


def _fbm(p: np.ndarray, seed: int, octaves: int = 3) -> np.ndarray:
    """Fractal sum of value noise, normalised to [0, 1]; ``p`` [N, 3] in lattice units."""
    out = np.zeros(len(p))
    amp, norm = 1.0, 0.0
    for k in range(octaves):
        out += amp * _value_noise(p * (2.0 ** k) + 17.3 * k, seed + 101 * k)
        norm += amp
        amp *= 0.5
    return out / norm


def _smoothstep(a: float, b: float, x: np.ndarray) -> np.ndarray:
    t = np.clip((x - a) / (b - a), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


# ---------------------------------------------------------------------------------------------
# Procedural textures: f(p [N,3] in the surface's own frame, metres, params) -> sRGB [N,3]
# ---------------------------------------------------------------------------------------------

def _pal(prm: dict, idx: np.ndarray) -> np.ndarray:
    pal = np.asarray(prm["palette"], dtype=np.float64)
    return pal[np.asarray(idx, dtype=np.int64) % len(pal)]


def _detail(p: np.ndarray, prm: dict, scale: float, amount: float = 0.25) -> np.ndarray:
    """Multiplicative fine noise [N, 1] around 1 (breaks up flat areas for feature matching)."""
    return (1.0 - amount / 2 + amount * _fbm(p / scale, prm["seed"] + 7, 2))[:, None]


def _tex_checker(p, prm):
    s = prm["scale"]
    q = (p + prm["offset"]) / s
    c = (np.floor(q).astype(np.int64).sum(axis=1)) & 1
    return _pal(prm, c) * _detail(p, prm, s * 0.5)


def _tex_stripes(p, prm):
    s = prm["scale"]
    v = p @ np.asarray(prm["axis"]) / s + 1.2 * _fbm(p / (2 * s), prm["seed"], 2)
    band = np.floor(v)
    rgb = _pal(prm, band.astype(np.int64))
    edge = np.minimum(v - band, 1.0 - (v - band))
    rgb = rgb * (0.55 + 0.45 * _smoothstep(0.0, 0.08, edge))[:, None]
    return rgb * _detail(p, prm, s * 0.4, 0.2)


def _tex_dots(p, prm):
    s = prm["scale"]
    q = (p + prm["offset"]) / s
    cell = np.floor(q).astype(np.int64)
    sd = prm["seed"]
    jit = np.stack([_hash01(sd + k, cell[:, 0], cell[:, 1], cell[:, 2]) for k in range(3)], 1)
    centre = cell + 0.5 + 0.3 * (jit - 0.5)
    d = np.linalg.norm(q - centre, axis=1)
    dot_col = _pal(prm, 1 + (_hash01(sd + 9, cell[:, 0], cell[:, 1], cell[:, 2])
                             * (len(prm["palette"]) - 1)).astype(np.int64))
    bg = np.asarray(prm["palette"][0]) * _detail(p, prm, s * 0.7, 0.3)
    w = _smoothstep(0.36, 0.30, d)[:, None]
    return bg * (1 - w) + dot_col * w


def _tex_marble(p, prm):
    s = prm["scale"]
    v = p @ np.asarray(prm["axis"]) / s + 4.0 * _fbm(p / (1.5 * s), prm["seed"], 4)
    w = np.abs(np.sin(np.pi * v))
    c0, c1 = (np.asarray(c) for c in prm["palette"][:2])
    rgb = c0 + (c1 - c0) * (w ** 0.6)[:, None]
    vein = _smoothstep(0.12, 0.0, w)[:, None]
    return rgb * (1 - 0.6 * vein)


def _voronoi(q: np.ndarray, seed: int, dims: int):
    """Nearest and second-nearest feature distances and nearest cell [N, 3] (jittered grid)."""
    base = np.floor(q).astype(np.int64)
    n = len(q)
    d1 = np.full(n, np.inf)
    d2 = np.full(n, np.inf)
    best = np.zeros((n, 3), dtype=np.int64)
    rz = (-1, 0, 1) if dims == 3 else (0,)
    for ox in (-1, 0, 1):
        for oy in (-1, 0, 1):
            for oz in rz:
                c = base + np.array([ox, oy, oz])
                cc = [c[:, 0], c[:, 1]] if dims == 2 else [c[:, 0], c[:, 1], c[:, 2]]
                diff = q[:, :dims] - c[:, :dims]
                d = np.sqrt(sum((diff[:, k] - _hash01(seed + k, *cc)) ** 2
                                for k in range(dims)))
                closer = d < d1
                d2 = np.where(closer, d1, np.minimum(d2, d))
                best[closer] = c[closer]
                d1 = np.where(closer, d, d1)
    return d1, d2, best


def _tex_mosaic(p, prm):
    s = prm["scale"]
    d1, d2, cell = _voronoi(p / s, prm["seed"], prm.get("dims", 3))
    h = _hash01(prm["seed"] + 5, cell[:, 0], cell[:, 1], cell[:, 2])
    rgb = _pal(prm, (h * len(prm["palette"])).astype(np.int64))
    rgb = rgb * (0.8 + 0.4 * _hash01(prm["seed"] + 6, cell[:, 0], cell[:, 1], cell[:, 2]))[:, None]
    grout = _smoothstep(0.10, 0.04, d2 - d1)[:, None]
    rgb = rgb * (1 - grout) + np.asarray(prm["grout"]) * grout
    return rgb * _detail(p, prm, s * 0.3, 0.2)


def _tex_noise(p, prm):
    s = prm["scale"]
    n = _fbm(p / s, prm["seed"], 4)
    c0, c1 = (np.asarray(c) for c in prm["palette"][:2])
    w = _smoothstep(0.42, 0.58, n)[:, None]
    spk = _smoothstep(0.72, 0.8, _value_noise(p / (0.2 * s), prm["seed"] + 3))[:, None]
    c2 = np.asarray(prm["palette"][2 % len(prm["palette"])])
    return (c0 * (1 - w) + c1 * w) * (1 - spk) + c2 * spk


def _bricks(u, v, p, prm):
    """Running-bond bricks in planar coordinates (u along, v up), metres."""
    bw, bh = prm["brick"]
    row = np.floor(v / bh)
    uu = u / bw + 0.5 * (row.astype(np.int64) & 1)
    col = np.floor(uu)
    sd = prm["seed"]
    h = _hash01(sd, row.astype(np.int64), col.astype(np.int64))
    rgb = _pal(prm, (h * len(prm["palette"])).astype(np.int64))
    rgb = rgb * (0.75 + 0.5 * _hash01(sd + 1, row.astype(np.int64), col.astype(np.int64)))[:, None]
    fu = np.minimum(uu - col, 1 - (uu - col)) * bw
    fv = np.minimum(v / bh - row, 1 - (v / bh - row)) * bh
    mortar = _smoothstep(0.012, 0.004, np.minimum(fu, fv))[:, None]
    rgb = rgb * (1 - mortar) + np.asarray(prm["grout"]) * mortar
    return rgb * _detail(p, prm, 0.05, 0.3)


def _tex_bricks(p, prm):
    """Bricks wrapped around the object's vertical axis (u = azimuth x radius, v = height)."""
    u = np.arctan2(p[:, 1], p[:, 0]) * prm["radius"]
    return _bricks(u, p[:, 2], p, prm)


def _tex_wall_bricks(p, prm):
    """Bricks on a planar surface given as (u, v, 0)."""
    return _bricks(p[:, 0], p[:, 1], p, prm)


def _tex_tiles(p, prm):
    """Square tiles with a random palette colour each, grout lines and speckle; planar (u, v)."""
    s = prm["scale"]
    q = p[:, :2] / s
    c = np.floor(q).astype(np.int64)
    sd = prm["seed"]
    rgb = _pal(prm, (_hash01(sd, c[:, 0], c[:, 1]) * len(prm["palette"])).astype(np.int64))
    # a second, smaller square inside some tiles
    fq = q - c
    inner = (np.abs(fq - 0.5).max(axis=1) < 0.22) & (_hash01(sd + 2, c[:, 0], c[:, 1]) < 0.5)
    rgb = np.where(inner[:, None], _pal(prm, (_hash01(sd + 3, c[:, 0], c[:, 1])
                                              * len(prm["palette"])).astype(np.int64)), rgb)
    g = np.minimum(fq, 1 - fq).min(axis=1) * s
    grout = _smoothstep(0.014, 0.006, g)[:, None]
    rgb = rgb * (1 - grout) + np.asarray(prm["grout"]) * grout
    return rgb * _detail(p, prm, s * 0.15, 0.3)


def _tex_wood(p, prm):
    """Planks along x (width ``plank`` in y, staggered joints), grain lines and knots."""
    pw, pl = prm["plank"], prm["length"]
    sd = prm["seed"]
    row = np.floor(p[:, 1] / pw).astype(np.int64)
    x = p[:, 0] + _hash01(sd, row) * pl
    col = np.floor(x / pl).astype(np.int64)
    tone = 0.7 + 0.55 * _hash01(sd + 1, row, col)
    q = np.stack([p[:, 0] * 1.5, p[:, 1] * 12.0, p[:, 2] * 12.0], 1)
    grain = 0.5 + 0.5 * np.sin(2 * np.pi * (p[:, 1] / pw * 5 + 2.5 * _fbm(q, sd + 2, 3)))
    c0, c1 = (np.asarray(c) for c in prm["palette"][:2])
    rgb = (c0 + (c1 - c0) * grain[:, None]) * tone[:, None]
    fy = p[:, 1] / pw - row
    fx = x / pl - col
    gap = np.minimum(np.minimum(fy, 1 - fy) * pw, np.minimum(fx, 1 - fx) * pl)
    seam = _smoothstep(0.008, 0.003, gap)[:, None]
    return rgb * (1 - 0.7 * seam) * _detail(p, prm, 0.04, 0.2)


TEXTURES: dict[str, Callable[[np.ndarray, dict], np.ndarray]] = {
    "checker": _tex_checker, "stripes": _tex_stripes, "dots": _tex_dots,
    "marble": _tex_marble, "mosaic": _tex_mosaic, "noise": _tex_noise, "bricks": _tex_bricks,
    "wall_bricks": _tex_wall_bricks, "tiles": _tex_tiles, "wood": _tex_wood,
}
OBJECT_TEXTURES = ("checker", "stripes", "dots", "marble", "mosaic", "noise", "bricks")


def texture_albedo(kind: str, p: np.ndarray, params: dict) -> np.ndarray:
    """Evaluate texture ``kind`` at points ``p`` [N, 3] (surface frame, metres) ->
    sRGB-encoded albedo [N, 3] in [0.02, 0.95]."""
    if len(p) == 0:
        return np.zeros((0, 3))
    return np.clip(TEXTURES[kind](p, params), 0.02, 0.95)


# ---------------------------------------------------------------------------------------------
# Analytic shapes (local frame: base centre at the origin, z up). intersect() takes ray
# origins/directions [N, 3] (unit directions) and returns t [N] (inf = miss) and normals [N, 3].
# ---------------------------------------------------------------------------------------------

def _safe_dir(d: np.ndarray) -> np.ndarray:
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
        return _box_hit(o, d, self.lo, self.hi)


def _box_hit(o, d, lo, hi):
    inv = 1.0 / _safe_dir(d)
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
    n[np.arange(len(o)), ax] = -np.sign(_safe_dir(d)[np.arange(len(o)), ax])
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
class Cylinder:
    """Upright capped cylinder of radius r and height h (z in [0, h])."""

    r: float
    h: float
    kind = "cylinder"

    @property
    def lo(self):
        return np.array([-self.r, -self.r, 0.0])

    @property
    def hi(self):
        return np.array([self.r, self.r, self.h])

    @property
    def footprint(self) -> float:
        return self.r

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
        dz = _safe_dir(d[:, 2])
        for zc, sign in ((self.h, 1.0), (0.0, -1.0)):
            tc = (zc - o[:, 2]) / dz
            x = o[:, 0] + tc * d[:, 0]
            y = o[:, 1] + tc * d[:, 1]
            ok = (tc > _EPS) & (x * x + y * y <= self.r ** 2) & (tc < t)
            t = np.where(ok, tc, t)
            n[ok] = (0.0, 0.0, sign)
        return t, n


@dataclass(frozen=True)
class Cone:
    """Upright cone: base disc of radius r at z = 0, apex at (0, 0, h)."""

    r: float
    h: float
    kind = "cone"

    @property
    def lo(self):
        return np.array([-self.r, -self.r, 0.0])

    @property
    def hi(self):
        return np.array([self.r, self.r, self.h])

    @property
    def footprint(self) -> float:
        return self.r

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
        tc = -o[:, 2] / _safe_dir(d[:, 2])
        x = o[:, 0] + tc * d[:, 0]
        y = o[:, 1] + tc * d[:, 1]
        ok = (tc > _EPS) & (x * x + y * y <= self.r ** 2) & (tc < t)
        t = np.where(ok, tc, t)
        n[ok] = (0.0, 0.0, -1.0)
        return t, n


SHAPES = {"box": Box, "sphere": Sphere, "cylinder": Cylinder, "cone": Cone}


def _random_shape(rng: np.random.Generator, kind: str, max_footprint: float | None = None):
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


# ---------------------------------------------------------------------------------------------
# Scene description
# ---------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class Pose2D:
    """Placement of an object on the table: centre (x, y) in metres, rotation about z (rad)."""

    x: float
    y: float
    rot_z: float


@dataclass
class SynthObject:
    """One object. ``id`` >= 1 is stable across states; ``poses[state]`` is None if absent.

    ``change`` is None (unchanged), ``"added"``, ``"removed"`` or ``"moved"``; a replaced object
    is ``"removed"`` with ``replaced_by`` set, its replacement ``"added"`` with ``replaces`` set.
    """

    id: int
    name: str
    shape: Box | Sphere | Cylinder | Cone
    texture: str
    texture_params: dict
    poses: dict[str, Pose2D | None]
    change: str | None = None
    replaces: int | None = None
    replaced_by: int | None = None

    @property
    def kind(self) -> str:
        return self.shape.kind

    def present(self, state: str) -> bool:
        return self.poses[state] is not None


@dataclass(frozen=True)
class Sun:
    """Directional light. ``azimuth``/``elevation`` in degrees give the direction *towards* the
    sun (azimuth from +x towards +y); ``angle_deg`` is its angular diameter (soft shadows);
    ``color`` linear RGB, ``strength`` irradiance scale."""

    azimuth: float
    elevation: float
    color: tuple[float, float, float]
    strength: float
    angle_deg: float = 0.5

    @property
    def direction(self) -> np.ndarray:
        """Unit vector [3] from a surface point towards the sun (world)."""
        az, el = math.radians(self.azimuth), math.radians(self.elevation)
        return np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])


@dataclass(frozen=True)
class Lighting:
    """Ambient (linear RGB colour x strength, brighter for up-facing surfaces) and suns."""

    ambient_color: tuple[float, float, float]
    ambient: float
    suns: tuple[Sun, ...]
    description: str = ""

    def to_json(self) -> dict:
        return {"description": self.description,
                "ambient": {"color_linear": list(self.ambient_color), "strength": self.ambient},
                "lights": [{"type": "SUN", **dataclasses.asdict(s),
                            "direction_to_light": s.direction.tolist()} for s in self.suns]}


def _kelvin_rgb(k: float) -> tuple[float, float, float]:
    """Approximate linear RGB (max channel 1) of a black body at ``k`` kelvin (1000-12000 K)."""
    t = k / 100.0
    r = 255.0 if t <= 66 else 329.7 * (t - 60) ** -0.1332
    g = 99.47 * math.log(t) - 161.12 if t <= 66 else 288.12 * (t - 60) ** -0.0755
    b = 255.0 if t >= 66 else (0.0 if t <= 19 else 138.52 * math.log(t - 10) - 305.04)
    srgb = np.clip(np.array([r, g, b]) / 255.0, 0, 1)
    lin = srgb_to_linear(srgb)
    return tuple(float(v) for v in lin / lin.max())


@dataclass(frozen=True)
class Orbit:
    """A smooth camera arc around ``target``: azimuth from ``az0`` to ``az1`` (degrees),
    elevation e(s) = e0 + (e1 - e0) * (1 - cos(pi s)) / 2 over s in [0, 1], fixed radius."""

    az0: float
    az1: float
    e0: float
    e1: float
    radius: float
    target: tuple[float, float, float]

    def center(self, s: float) -> np.ndarray:
        az = math.radians(self.az0 + (self.az1 - self.az0) * s)
        el = math.radians(self.e0 + (self.e1 - self.e0) * 0.5 * (1 - math.cos(math.pi * s)))
        tgt = np.asarray(self.target)
        return tgt + self.radius * np.array([math.cos(el) * math.cos(az),
                                             math.cos(el) * math.sin(az), math.sin(el)])

    def c2w(self, s: float) -> np.ndarray:
        return look_at(self.center(s), self.target)


def _jittered_pose(rng: np.random.Generator, center: np.ndarray, target, jitter: float):
    """look-at pose with position/target jitter (uniform +-jitter metres) and roll (+-1.5 deg)."""
    c = center + rng.uniform(-jitter, jitter, 3)
    tg = np.asarray(target) + rng.uniform(-jitter, jitter, 3)
    c2w = look_at(c, tg)
    roll = math.radians(rng.uniform(-1.5, 1.5))
    cr, sr = math.cos(roll), math.sin(roll)
    rz = np.array([[cr, -sr, 0], [sr, cr, 0], [0, 0, 1.0]])
    c2w[:3, :3] = c2w[:3, :3] @ rz
    return c2w


# ---------------------------------------------------------------------------------------------
# The scene
# ---------------------------------------------------------------------------------------------

_ROOM_FACES = ("floor", "ceiling", "wall_+x", "wall_-x", "wall_+y", "wall_-y")
_TABLE = 6  # primitive code of the table; objects are 7 + index into SynthScene.objects
_FIRST_OBJECT = 7


class SynthScene:
    """A procedural scene in two states, with cameras and a ray tracer.

    Build with :func:`build_scene`. Objects are in :attr:`objects`; :attr:`changed_ids` lists
    the ids of every changed object (added, removed, moved, replaced and replacement);
    :attr:`change_types` maps id -> ``"added" | "removed" | "moved"``; :attr:`changes` lists the
    change events (with ``"replaced"`` events pairing two ids).
    """

    def __init__(self, preset: SynthPreset, seed: int, objects: list[SynthObject],
                 lighting: dict[str, Lighting], orbits: dict[str, Orbit],
                 train_c2w: dict[str, list[np.ndarray]], eval_c2w: list[np.ndarray],
                 room_textures: dict[str, tuple[str, dict]], changes: list[dict]):
        self.preset = preset
        self.seed = seed
        self.objects = objects
        self.lighting = lighting
        self.orbits = orbits
        self._train_c2w = train_c2w
        self._eval_c2w = eval_c2w
        self.room_textures = room_textures
        self.changes = changes
        self.table_lo = np.array([-preset.table_half_size[0], -preset.table_half_size[1], 0.0])
        self.table_hi = np.array([preset.table_half_size[0], preset.table_half_size[1],
                                  preset.table_height])
        self._by_id = {o.id: o for o in objects}

    # -- bookkeeping --------------------------------------------------------------------------
    @property
    def target(self) -> np.ndarray:
        """The point all cameras look at (table centre, slightly raised), world [3]."""
        return np.array([0.0, 0.0, self.preset.table_height + 0.15])

    @property
    def changed_ids(self) -> list[int]:
        return sorted(o.id for o in self.objects if o.change is not None)

    @property
    def change_types(self) -> dict[int, str]:
        return {o.id: o.change for o in self.objects if o.change is not None}

    def object(self, obj_id: int) -> SynthObject:
        return self._by_id[obj_id]

    def objects_in(self, state: str) -> list[SynthObject]:
        _check_state(state)
        return [o for o in self.objects if o.present(state)]

    def object_transform(self, obj: SynthObject, state: str) -> tuple[np.ndarray, np.ndarray]:
        """Rotation R [3, 3] and translation T [3] with world = R @ local + T (None if absent)."""
        pose = obj.poses[state]
        if pose is None:
            raise ValueError(f"object {obj.id} is not present in state {state!r}")
        c, s = math.cos(pose.rot_z), math.sin(pose.rot_z)
        R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        return R, np.array([pose.x, pose.y, self.preset.table_height])

    def object_center(self, obj: SynthObject, state: str) -> np.ndarray:
        """World centre [3] of the object's local bounding box in ``state``."""
        R, T = self.object_transform(obj, state)
        return R @ (0.5 * (obj.shape.lo + obj.shape.hi)) + T

    def object_top(self, obj: SynthObject, state: str) -> np.ndarray:
        """World point [3] at the top of the object's axis (its highest surface point)."""
        R, T = self.object_transform(obj, state)
        return R @ np.array([0.0, 0.0, obj.shape.hi[2]]) + T

    def object_bbox(self, obj: SynthObject, state: str) -> np.ndarray:
        """World axis-aligned bounding box [2, 3] (min, max) in ``state``."""
        R, T = self.object_transform(obj, state)
        lo, hi = obj.shape.lo, obj.shape.hi
        corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])
                            for z in (lo[2], hi[2])]) @ R.T + T
        return np.stack([corners.min(0), corners.max(0)])

    # -- cameras ------------------------------------------------------------------------------
    def intrinsics(self) -> dict:
        """Shared pinhole intrinsics (pixels; principal point at the image centre)."""
        p = self.preset
        f = 0.5 * p.width / math.tan(math.radians(p.hfov_deg) / 2)
        return {"width": p.width, "height": p.height, "fx": f, "fy": f,
                "cx": p.width / 2.0, "cy": p.height / 2.0}

    def _camera(self, c2w, image=None, set_=None, time_=None) -> Camera:
        return Camera(**self.intrinsics(), c2w=c2w, image=image, set=set_, time=time_)

    def cameras(self, split: str) -> list[Camera]:
        """Cameras of ``split``: ``before``/``after`` (training views, with image paths, set and
        time), ``eval`` (evaluation viewpoints, no image/state), or ``eval_before`` /
        ``eval_after`` (the eval viewpoints as the frames of that state)."""
        if split in STATES:
            return [self._camera(c, f"{split}/{i:03d}.png", split, STATES.index(split))
                    for i, c in enumerate(self._train_c2w[split])]
        if split == "eval":
            return [self._camera(c) for c in self._eval_c2w]
        if split in ("eval_before", "eval_after"):
            st = split[5:]
            return [self._camera(c, f"eval/{st}/{i:03d}.png", split, STATES.index(st))
                    for i, c in enumerate(self._eval_c2w)]
        raise ValueError(f"unknown split {split!r}; use before, after, eval, eval_before or "
                         "eval_after")

    # -- ray tracing --------------------------------------------------------------------------
    def _casters(self, state: str):
        """(code, intersect fn, R, T, bounding-sphere centre [3], radius) for the table and
        every object present in ``state`` (world = R @ local + T)."""
        lo, hi = self.table_lo, self.table_hi
        out = [(_TABLE, lambda o, d: _box_hit(o, d, lo, hi), np.eye(3), np.zeros(3),
                0.5 * (lo + hi), 0.5 * float(np.linalg.norm(hi - lo)))]
        for k, obj in enumerate(self.objects):
            if obj.present(state):
                R, T = self.object_transform(obj, state)
                lo_, hi_ = obj.shape.lo, obj.shape.hi
                out.append((_FIRST_OBJECT + k, obj.shape.intersect, R, T,
                            R @ (0.5 * (lo_ + hi_)) + T, 0.5 * float(np.linalg.norm(hi_ - lo_))))
        return out

    def _room_hit(self, o, d):
        """Exit point of rays from inside the room box: t [N], face code [N], inward normal."""
        R, H = self.preset.room_half_size, self.preset.room_height
        lo = np.array([-R, -R, 0.0])
        hi = np.array([R, R, H])
        dd = _safe_dir(d)
        bound = np.where(dd > 0, hi, lo)
        ts = (bound - o) / dd
        ax = ts.argmin(axis=1)
        t = ts[np.arange(len(o)), ax]
        pos = dd[np.arange(len(o)), ax] > 0
        # faces: z- floor 0, z+ ceiling 1, x+ 2, x- 3, y+ 4, y- 5
        code = np.select([ax == 2, ax == 0, ax == 1], [np.where(pos, 1, 0), np.where(pos, 2, 3),
                                                        np.where(pos, 4, 5)])
        n = np.zeros_like(o)
        n[np.arange(len(o)), ax] = np.where(pos, -1.0, 1.0)
        return t, code, n

    def trace(self, o: np.ndarray, d: np.ndarray, state: str):
        """Nearest hit of rays ``o``, ``d`` [N, 3] (world, unit directions) in ``state``.

        Returns ``t`` [N] (ray parameter, metres), ``code`` [N] (0-5 room faces, 6 table,
        7 + k object k of :attr:`objects`) and world normals ``n`` [N, 3] facing the ray.
        """
        t, code, n = self._room_hit(o, d)
        cull = _RayCull(o, d)
        for c, fn, R, T, bc, br in self._casters(state):
            idx = cull.candidates(bc, br, t)
            if len(idx) == 0:
                continue
            tl, nl = fn((o[idx] - T) @ R, d[idx] @ R)
            better = tl < t[idx]
            sel = idx[better]
            t[sel] = tl[better]
            code[sel] = c
            n[sel] = nl[better] @ R.T
        return t, code.astype(np.int64), n

    def occluded(self, o: np.ndarray, d: np.ndarray, state: str) -> np.ndarray:
        """Whether rays ``o``, ``d`` [N, 3] hit the table or an object (shadow rays) -> bool [N]."""
        occ = np.zeros(len(o), dtype=bool)
        far = np.full(len(o), np.inf)
        cull = _RayCull(o, d)
        for _, fn, R, T, bc, br in self._casters(state):
            idx = cull.candidates(bc, br, far)
            idx = idx[~occ[idx]]
            if len(idx) == 0:
                continue
            tl, _ = fn((o[idx] - T) @ R, d[idx] @ R)
            occ[idx[np.isfinite(tl)]] = True
        return occ

    def _albedo(self, p: np.ndarray, code: np.ndarray, state: str) -> np.ndarray:
        """sRGB albedo [N, 3] at world points ``p`` on primitives ``code``."""
        out = np.zeros_like(p)
        for c in np.unique(code):
            m = code == c
            q = p[m]
            if c < _TABLE:
                kind, prm = self.room_textures[_ROOM_FACES[c]]
                if c in (0, 1):
                    uv = q[:, [0, 1]]
                elif c in (2, 3):
                    uv = q[:, [1, 2]]
                else:
                    uv = q[:, [0, 2]]
                local = np.concatenate([uv, np.zeros((len(q), 1))], 1)
            elif c == _TABLE:
                kind, prm = self.room_textures["table"]
                local = q
            else:
                obj = self.objects[c - _FIRST_OBJECT]
                R, T = self.object_transform(obj, state)
                kind, prm, local = obj.texture, obj.texture_params, (q - T) @ R
            out[m] = texture_albedo(kind, local, prm)
        return out

    def _irradiance(self, p, n, state, sun_dirs=None, shadows=True):
        """Linear RGB irradiance [N, 3] at points ``p`` with normals ``n``; ``sun_dirs`` gives
        per-sun [N, 3] directions to the light (default: the sun's centre)."""
        L = self.lighting[state]
        e = np.outer(L.ambient * (0.75 + 0.25 * n[:, 2]), np.asarray(L.ambient_color))
        for k, sun in enumerate(L.suns):
            ld = sun.direction[None, :].repeat(len(p), 0) if sun_dirs is None else sun_dirs[k]
            ndl = np.einsum("ij,ij->i", n, ld)
            lit = ndl > 0
            vis = lit.copy()
            if shadows and lit.any():
                idx = np.flatnonzero(lit)
                vis[idx] = ~self.occluded(p[idx] + _SHADOW_OFFSET * n[idx], ld[idx], state)
            e += np.outer(sun.strength * np.maximum(ndl, 0.0) * vis, np.asarray(sun.color))
        return e

    def render(self, camera: Camera, state: str, supersample: int | None = None,
               shadows: bool = True) -> dict[str, np.ndarray]:
        """Render ``camera`` in ``state`` ("before" | "after").

        Returns a dict of numpy arrays:

        * ``rgb`` float32 [H, W, 3]: sRGB-encoded colour in [0, 1], ``supersample`` x
          ``supersample`` rays per pixel (default: the preset's);
        * ``depth`` float32 [H, W]: z-depth along the camera's +z axis (metres), pixel centres;
        * ``normal`` float32 [H, W, 3]: world unit normal facing the camera, pixel centres;
        * ``ids`` int32 [H, W]: object id (>= 1) or 0 (room, table), pixel centres;
        * ``changed`` bool [H, W]: pixel centre shows an object of :attr:`changed_ids`;
        * ``shadow`` bool [H, W]: the pixel-centre surface faces the sun but the sun's centre
          is blocked (a cast shadow), for the first sun.

        ``shadows=False`` skips shadow rays (no cast shadows; for tests and comparisons).
        """
        _check_state(state)
        ss = int(supersample or self.preset.supersample)
        H, W = camera.height, camera.width
        gt = self._trace_centres(camera, state, shadows)

        o, d = _camera_rays(camera, ss)
        t, code, n = self.trace(o, d, state)
        p = o + t[:, None] * d
        alb = srgb_to_linear(self._albedo(p, code, state))
        L = self.lighting[state]
        dirs = [_sun_disc_dirs(s, H, W, ss, self.seed + 31 * k) for k, s in enumerate(L.suns)]
        e = self._irradiance(p, n, state, dirs, shadows)
        radiance = 1.0 - np.exp(-alb * e)  # exponential tone curve (linear in, linear out)
        lin = radiance.reshape(H, W, ss * ss, 3).mean(axis=2)
        gt["rgb"] = linear_to_srgb(lin).astype(np.float32)
        return gt

    def _trace_centres(self, camera: Camera, state: str, shadows: bool) -> dict:
        H, W = camera.height, camera.width
        o, d = _camera_rays(camera, 1)
        t, code, n = self.trace(o, d, state)
        zaxis = camera.c2w[:3, 2]
        depth = t * (d @ zaxis)
        ids = np.zeros(len(o), dtype=np.int32)
        obj_ids = np.array([ob.id for ob in self.objects], dtype=np.int32)
        is_obj = code >= _FIRST_OBJECT
        ids[is_obj] = obj_ids[code[is_obj] - _FIRST_OBJECT]
        shadow = np.zeros(len(o), dtype=bool)
        suns = self.lighting[state].suns
        if shadows and suns:
            ld = suns[0].direction
            p = o + t[:, None] * d
            lit = n @ ld > 0
            idx = np.flatnonzero(lit)
            shadow[idx] = self.occluded(p[idx] + _SHADOW_OFFSET * n[idx],
                                        np.broadcast_to(ld, (len(idx), 3)), state)
        changed = np.isin(ids, np.asarray(self.changed_ids, dtype=np.int32))
        return {"depth": depth.reshape(H, W).astype(np.float32),
                "normal": n.reshape(H, W, 3).astype(np.float32),
                "ids": ids.reshape(H, W),
                "changed": changed.reshape(H, W),
                "shadow": shadow.reshape(H, W)}

    # -- metadata -----------------------------------------------------------------------------
    def meta(self) -> dict:
        """JSON-ready description of the scene (objects, changes, lighting, cameras, room)."""
        p = self.preset
        objs = []
        for o in self.objects:
            entry = {"name": o.name, "id": o.id, "kind": o.kind,
                     "dimensions": dataclasses.asdict(o.shape),
                     "footprint_radius": o.shape.footprint, "height": float(o.shape.hi[2]),
                     "texture": o.texture, "texture_params": o.texture_params,
                     "changed": o.change is not None, "change": o.change}
            if o.replaces is not None:
                entry["replaces"] = o.replaces
            if o.replaced_by is not None:
                entry["replaced_by"] = o.replaced_by
            for st in STATES:
                if o.present(st):
                    bb = self.object_bbox(o, st)
                    pose = o.poses[st]
                    entry[st] = {"present": True,
                                 "location": [pose.x, pose.y, p.table_height],
                                 "rotation_z": pose.rot_z, "support": "table",
                                 "bbox_world": bb.tolist(),
                                 "bbox_center_world": self.object_center(o, st).tolist(),
                                 "anchor_world": self.object_top(o, st).tolist()}
                else:
                    entry[st] = {"present": False}
            objs.append(entry)
        light_changes = self.lighting["before"] != self.lighting["after"]
        return {
            "scene_center": self.target.tolist(),
            "room": {"room_half_size": p.room_half_size, "wall_height": p.room_height,
                     "support": "table slab {:.2f}x{:.2f}x{:.2f} m (wood)".format(
                         2 * p.table_half_size[0], 2 * p.table_half_size[1], p.table_height),
                     "textures": {k: {"kind": v[0], "params": v[1]}
                                  for k, v in self.room_textures.items()},
                     "note": "walls and ceiling do not cast shadows; table and objects do"},
            "changes": self.changes,
            "changed_objects": [self.object(i).name for i in self.changed_ids],
            "changed_ids": self.changed_ids,
            "n_objects": {st: len(self.objects_in(st)) for st in STATES},
            "objects": objs,
            "lighting": {"mode": p.lighting, "changes": light_changes,
                         "before": self.lighting["before"].to_json(),
                         "after": self.lighting["after"].to_json()},
            "cameras": {"n_before": p.n_before, "n_after": p.n_after, "n_eval": p.n_eval,
                        "hfov_deg": p.hfov_deg,
                        "orbits": {st: dataclasses.asdict(self.orbits[st]) for st in STATES},
                        "jitter_m": p.jitter_m,
                        "eval_min_distance_to_training_camera_m":
                            self.eval_min_distance_to_training()},
        }

    def eval_min_distance_to_training(self) -> float:
        """Smallest distance (metres) from an eval camera centre to a training camera centre."""
        tr = np.array([c[:3, 3] for st in STATES for c in self._train_c2w[st]])
        ev = np.array([c[:3, 3] for c in self._eval_c2w])
        return float(np.linalg.norm(ev[:, None] - tr[None], axis=2).min())


def _check_state(state: str) -> None:
    if state not in STATES:
        raise ValueError(f"state must be 'before' or 'after', not {state!r}")


class _RayCull:
    """Cheap bounding-sphere culling for a batch of rays ``o``, ``d`` [N, 3] (unit ``d``)."""

    def __init__(self, o: np.ndarray, d: np.ndarray):
        self.o, self.d = o, d
        self.od = np.einsum("ij,ij->i", o, d)
        self.oo = np.einsum("ij,ij->i", o, o)

    def candidates(self, centre: np.ndarray, radius: float, t_max: np.ndarray) -> np.ndarray:
        """Indices of rays passing within ``radius`` of ``centre`` at some t in (0, t_max)."""
        tca = self.d @ centre - self.od
        d2 = centre @ centre - 2.0 * (self.o @ centre) + self.oo - tca * tca
        ok = (d2 <= radius * radius) & (tca + radius > 0) & (tca - radius < t_max)
        return np.flatnonzero(ok)


def _camera_rays(cam: Camera, ss: int) -> tuple[np.ndarray, np.ndarray]:
    """World ray origins and unit directions [H*W*ss*ss, 3], ordered (row, col, sub-sample).

    Sub-sample (a, b) of pixel (col i, row j) passes through pixel coordinates
    (i + (a + 0.5)/ss, j + (b + 0.5)/ss); ss = 1 gives the pixel centres (i + 0.5, j + 0.5).
    """
    off = (np.arange(ss) + 0.5) / ss
    jj, ii, bb, aa = np.meshgrid(np.arange(cam.height), np.arange(cam.width), off, off,
                                 indexing="ij")
    u = (ii + aa).ravel()
    v = (jj + bb).ravel()
    dc = np.stack([(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, np.ones_like(u)], 1)
    d = dc @ cam.c2w[:3, :3].T
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    o = np.broadcast_to(cam.c2w[:3, 3], d.shape).copy()
    return o, d


def _sun_disc_dirs(sun: Sun, H: int, W: int, ss: int, seed: int) -> np.ndarray:
    """Directions [H*W*ss*ss, 3] to points on the sun's disc, one per colour ray.

    Sub-sample k of a pixel takes the k-th point of a golden-angle spiral over the disc,
    rotated by a per-pixel hash angle, so averaged penumbrae are smooth and deterministic.
    """
    n = ss * ss
    centre = sun.direction
    if sun.angle_deg <= 0:
        return np.broadcast_to(centre, (H * W * n, 3)).copy()
    half = math.radians(sun.angle_deg) / 2
    a = np.cross(centre, [0.0, 0.0, 1.0])
    if np.linalg.norm(a) < 1e-6:
        a = np.cross(centre, [1.0, 0.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(centre, a)
    k = np.arange(n)
    rad = np.sqrt((k + 0.5) / n) * math.tan(half)
    ang0 = k * 2.39996322972865332
    jj, ii = np.meshgrid(np.arange(H), np.arange(W), indexing="ij")
    rot = _hash01(seed, jj.ravel(), ii.ravel()) * 2 * np.pi
    ang = (rot[:, None] + ang0[None, :]).ravel()
    r = np.tile(rad, H * W)
    dirs = centre + (r * np.cos(ang))[:, None] * a + (r * np.sin(ang))[:, None] * b
    return dirs / np.linalg.norm(dirs, axis=1, keepdims=True)


# ---------------------------------------------------------------------------------------------
# Scene construction
# ---------------------------------------------------------------------------------------------

def _random_color(rng, sat=(0.45, 0.9), val=(0.45, 0.92)) -> list[float]:
    """A random sRGB colour from HSV ranges."""
    import colorsys

    h = rng.uniform()
    return list(colorsys.hsv_to_rgb(h, rng.uniform(*sat), rng.uniform(*val)))


def _contrast_pair(rng) -> list[list[float]]:
    """Two colours of clearly different hue and value."""
    import colorsys

    h = rng.uniform()
    c0 = colorsys.hsv_to_rgb(h, rng.uniform(0.5, 0.9), rng.uniform(0.25, 0.45))
    c1 = colorsys.hsv_to_rgb((h + rng.uniform(0.25, 0.75)) % 1, rng.uniform(0.2, 0.7),
                             rng.uniform(0.8, 0.95))
    return [list(c0), list(c1)]


def _object_texture(rng, kind: str, shape) -> dict:
    seed = int(rng.integers(0, 2 ** 31))
    pal = _contrast_pair(rng) + [_random_color(rng) for _ in range(2)]
    axis = rng.normal(size=3)
    axis[2] += 1.5 * np.sign(axis[2] or 1.0)
    axis = (axis / np.linalg.norm(axis)).tolist()
    prm = {"seed": seed, "palette": pal, "offset": rng.uniform(0, 1, 3).tolist(), "axis": axis,
           "scale": float(rng.uniform(0.035, 0.055)),
           "grout": [0.08, 0.08, 0.08]}
    if kind == "marble":
        prm["scale"] = float(rng.uniform(0.06, 0.09))
    elif kind == "noise":
        prm["scale"] = float(rng.uniform(0.05, 0.08))
    elif kind == "bricks":
        prm["brick"] = [float(rng.uniform(0.05, 0.07)), float(rng.uniform(0.025, 0.035))]
        prm["radius"] = float(shape.footprint)
    return prm


def _room_textures(rng) -> dict[str, tuple[str, dict]]:
    def pal(n, val=(0.35, 0.92)):
        return [_random_color(rng, sat=(0.25, 0.85), val=val) for _ in range(n)]

    def seed():
        return int(rng.integers(0, 2 ** 31))

    floor = ("mosaic", {"seed": seed(), "palette": pal(6), "scale": 0.2, "dims": 2,
                        "grout": [0.85, 0.85, 0.82]})
    bricks = ("wall_bricks", {"seed": seed(), "palette": pal(4, (0.3, 0.7)),
                              "brick": [0.3, 0.12], "grout": [0.8, 0.78, 0.74]})
    tiles = ("tiles", {"seed": seed(), "palette": pal(6), "scale": 0.28,
                       "grout": [0.15, 0.15, 0.15]})
    tiles2 = ("tiles", {"seed": seed(), "palette": pal(5), "scale": 0.34,
                        "grout": [0.9, 0.9, 0.9]})
    bricks2 = ("wall_bricks", {"seed": seed(), "palette": pal(4, (0.4, 0.85)),
                               "brick": [0.26, 0.1], "grout": [0.25, 0.22, 0.2]})
    ceiling = ("noise", {"seed": seed(), "palette": pal(3), "scale": 0.4})
    wood = ("wood", {"seed": seed(), "palette": [[0.36, 0.2, 0.1], [0.62, 0.4, 0.22]],
                     "plank": 0.14, "length": 0.9})
    walls = [bricks, tiles, bricks2, tiles2]
    order = rng.permutation(4)
    return {"floor": floor, "ceiling": ceiling, "table": wood,
            **{f: walls[i] for f, i in zip(_ROOM_FACES[2:], order)}}


def _lighting(rng, mode: str) -> dict[str, Lighting]:
    if mode == "uniform":
        sun = Sun(azimuth=float(rng.uniform(0, 360)), elevation=float(rng.uniform(62, 75)),
                  color=_kelvin_rgb(6000), strength=0.9, angle_deg=20.0)
        L = Lighting(ambient_color=_kelvin_rgb(6500), ambient=0.75, suns=(sun,),
                     description="soft uniform light: high soft sun + strong ambient")
        return {"before": L, "after": L}
    az = float(rng.uniform(0, 360))
    before = Lighting(
        ambient_color=_kelvin_rgb(6500), ambient=0.45,
        suns=(Sun(azimuth=az, elevation=float(rng.uniform(42, 52)), color=_kelvin_rgb(4000),
                  strength=1.3, angle_deg=0.5),),
        description="warm hard sun from one side at mid elevation, moderate ambient")
    after = Lighting(
        ambient_color=_kelvin_rgb(10000), ambient=0.12,
        suns=(Sun(azimuth=az + float(rng.uniform(150, 210)),
                  elevation=float(rng.uniform(18, 24)), color=_kelvin_rgb(9000),
                  strength=2.6, angle_deg=0.3),),
        description="cold, stronger, low sun from the opposite side (long hard shadows move), "
                    "ambient almost off")
    return {"before": before, "after": after}


class _PlacementFailed(Exception):
    """Internal: a random layout did not fit; the caller retries with another draw."""


class _Placer:
    """Rejection sampling of non-overlapping object footprints on the table top."""

    def __init__(self, rng, preset: SynthPreset, gap: float = 0.06):
        self.rng = rng
        self.hx, self.hy = preset.table_half_size
        self.gap = gap
        self.taken: dict[str, list[tuple[float, float, float]]] = {"before": [], "after": []}

    def free(self, x, y, r, states) -> bool:
        return all(math.hypot(x - a, y - b) >= r + rr + self.gap
                   for st in states for a, b, rr in self.taken[st])

    def place(self, r: float, states, away_from=None, min_shift=0.0) -> Pose2D:
        m = r + 0.05
        for _ in range(500):
            x = float(self.rng.uniform(-self.hx + m, self.hx - m))
            y = float(self.rng.uniform(-self.hy + m, self.hy - m))
            if away_from is not None and math.hypot(x - away_from[0],
                                                    y - away_from[1]) < min_shift:
                continue
            if self.free(x, y, r, states):
                return Pose2D(x, y, float(self.rng.uniform(0, 2 * np.pi)))
        raise _PlacementFailed()

    def take(self, pose: Pose2D, r: float, states) -> None:
        for st in states:
            self.taken[st].append((pose.x, pose.y, r))


def build_scene(preset: str | SynthPreset = "tiny", seed: int = 0) -> SynthScene:
    """Build (but do not render) the scene of ``preset`` (a name of :data:`PRESETS` or a
    :class:`SynthPreset`) for ``seed``. Deterministic: the same arguments give the same scene."""
    p = get_preset(preset)
    base = [int(seed), zlib.crc32(p.name.encode())]
    for attempt in range(50):
        rng = np.random.default_rng(base + [attempt])
        try:
            objects, changes = _layout(rng, p)
            break
        except _PlacementFailed:
            continue
    else:
        raise GdiffError(f"synth preset '{p.name}': could not place the objects on the table "
                         "without overlap; reduce the object counts or enlarge the table")
    room = _room_textures(rng)
    lighting = _lighting(rng, p.lighting)
    return _finish_scene(rng, p, int(seed), objects, changes, room, lighting)


def _layout(rng: np.random.Generator, p: SynthPreset) -> tuple[list[SynthObject], list[dict]]:
    """Objects with their poses in both states, and the list of change events."""
    kinds = list(SHAPES)
    tex_cycle = list(rng.permutation(OBJECT_TEXTURES))
    objects: list[SynthObject] = []
    placer = _Placer(rng, p)
    changes: list[dict] = []

    def new_object(kind=None, max_fp=None) -> SynthObject:
        k = kind or kinds[int(rng.integers(len(kinds)))]
        shape = _random_shape(rng, k, max_fp)
        tex = str(tex_cycle[len(objects) % len(tex_cycle)])
        oid = len(objects) + 1
        obj = SynthObject(id=oid, name=f"obj{oid:02d}_{k}", shape=shape, texture=tex,
                          texture_params=_object_texture(rng, tex, shape),
                          poses={"before": None, "after": None})
        objects.append(obj)
        return obj

    both = ("before", "after")
    # objects present before: static, removed, moved (old place), replaced (old)
    roles = (["static"] * p.n_static + ["removed"] * p.n_removed + ["moved"] * p.n_moved
             + ["replaced"] * p.n_replaced)
    role_of: dict[int, str] = {}
    for role in roles:
        obj = new_object()
        role_of[obj.id] = role
        r = obj.shape.footprint
        pose = placer.place(r, both)
        obj.poses["before"] = pose
        if role == "static":
            obj.poses["after"] = pose
            placer.take(pose, r, both)
        elif role == "replaced":
            obj.change = "removed"
            placer.take(pose, r, both)  # its replacement will stand here
        else:
            obj.change = role
            placer.take(pose, r, ("before",))
        if role == "removed":
            changes.append({"type": "removed", "object": obj.name, "id": obj.id,
                            "kind": obj.kind, "location_before": [pose.x, pose.y]})
    # after-state placements of moved objects and replacements
    for obj in list(objects):
        b = obj.poses["before"]
        if role_of[obj.id] == "moved":
            pose = placer.place(obj.shape.footprint, both, away_from=(b.x, b.y),
                                min_shift=2 * obj.shape.footprint + 0.1)
            obj.poses["after"] = pose
            placer.take(pose, obj.shape.footprint, ("after",))
            changes.append({"type": "moved", "object": obj.name, "id": obj.id,
                            "kind": obj.kind, "location_before": [b.x, b.y],
                            "location_after": [pose.x, pose.y]})
        elif role_of[obj.id] == "replaced":
            others = [k for k in kinds if k != obj.kind]
            new = new_object(others[int(rng.integers(len(others)))],
                             max_fp=obj.shape.footprint + 0.02)
            new.poses["after"] = Pose2D(b.x, b.y, float(rng.uniform(0, 2 * np.pi)))
            new.change = "added"
            new.replaces, obj.replaced_by = obj.id, new.id
            changes.append({"type": "replaced", "object": obj.name, "id": obj.id,
                            "kind": obj.kind, "new_object": new.name, "new_id": new.id,
                            "new_kind": new.kind, "location": [b.x, b.y]})
    for _ in range(p.n_added):
        obj = new_object()
        pose = placer.place(obj.shape.footprint, both)
        obj.poses["after"] = pose
        obj.change = "added"
        placer.take(pose, obj.shape.footprint, ("after",))
        changes.append({"type": "added", "object": obj.name, "id": obj.id, "kind": obj.kind,
                        "location_after": [pose.x, pose.y]})
    return objects, changes


def _finish_scene(rng, p: SynthPreset, seed: int, objects, changes, room, lighting):
    """Add the camera orbits, training and eval poses and assemble the :class:`SynthScene`."""
    # cameras
    target = (0.0, 0.0, p.table_height + 0.15)
    az_c = float(rng.uniform(0, 360))
    orbits = {
        "before": Orbit(az_c - p.before_span_deg / 2, az_c + p.before_span_deg / 2,
                        *p.elevation_before, p.radius_before, target),
        "after": Orbit(az_c + p.after_shift_deg + p.after_span_deg / 2,
                       az_c + p.after_shift_deg - p.after_span_deg / 2,
                       *p.elevation_after, p.radius_after, target),
    }
    train = {}
    for st, n in (("before", p.n_before), ("after", p.n_after)):
        orb = orbits[st]
        train[st] = [_jittered_pose(rng, orb.center(i / (n - 1)), target, p.jitter_m)
                     for i in range(n)]
    lo = max(min(orbits["before"].az0, orbits["before"].az1),
             min(orbits["after"].az0, orbits["after"].az1))
    hi = min(max(orbits["before"].az0, orbits["before"].az1),
             max(orbits["after"].az0, orbits["after"].az1))
    r_eval = 0.5 * (p.radius_before + p.radius_after)
    el_mid = 0.25 * (sum(p.elevation_before) + sum(p.elevation_after))
    eval_c2w = []
    for k in range(p.n_eval):
        az = math.radians(lo + (hi - lo) * (k + 0.5) / p.n_eval + rng.uniform(-2, 2))
        el = math.radians(el_mid + rng.uniform(-3, 3))
        c = np.asarray(target) + r_eval * np.array([math.cos(el) * math.cos(az),
                                                    math.cos(el) * math.sin(az), math.sin(el)])
        eval_c2w.append(_jittered_pose(rng, c, target, p.jitter_m))
    return SynthScene(p, seed, objects, lighting, orbits, train, eval_c2w, room, changes)


def orbit_path(scene: SynthScene, state: str, n: int) -> list[Camera]:
    """``n`` cameras evenly spaced along the (jitter-free) training orbit of ``state``, from its
    first to its last view: a smooth path for rendering ground-truth sequences. The cameras
    carry ``set=state`` and ``time`` 0/1 but no image path."""
    _check_state(state)
    if n < 1:
        raise ValueError("orbit_path needs n >= 1")
    orb = scene.orbits[state]
    ss = [0.5] if n == 1 else [i / (n - 1) for i in range(n)]
    return [scene._camera(orb.c2w(s), None, state, STATES.index(state)) for s in ss]


# ---------------------------------------------------------------------------------------------
# Writing a scene folder
# ---------------------------------------------------------------------------------------------

CONVENTION = (
    "c2w is the 4x4 camera-to-world matrix in the OpenCV camera convention (camera x right, "
    "y down, z forward/viewing direction). World frame: z up, metres, floor at z=0. Pixel "
    "coordinates (u right, v down) have their origin at the top-left CORNER of the image, i.e. "
    "the centre of pixel (col i, row j) is (i+0.5, j+0.5) (COLMAP/NeRF convention). No lens "
    "distortion.")

MASK_DEFINITION = (
    "union of the visible pixels of all changed objects (removed/moved/replaced objects in the "
    "BEFORE render, added/moved/replacement objects in the AFTER render) at the eval "
    "viewpoint, one ray through each pixel centre; occlusion by other geometry is respected; "
    "shadows of changed objects are NOT included; lighting differences are NOT changes")


def _gt_cameras(scene: SynthScene, name: str) -> dict:
    intr = scene.intrinsics()
    K = [[intr["fx"], 0.0, intr["cx"]], [0.0, intr["fy"], intr["cy"]], [0.0, 0.0, 1.0]]
    frames = []
    for st in STATES:
        for i, cam in enumerate(scene.cameras(st)):
            frames.append({"file": cam.image, "split": "train", "state": st, "index": i,
                           "c2w": cam.c2w.tolist()})
    views = []
    for i, cam in enumerate(scene.cameras("eval")):
        mask = f"eval/masks/{i:03d}.png"
        for st in STATES:
            frames.append({"file": f"eval/{st}/{i:03d}.png", "split": "eval", "state": st,
                           "index": i, "c2w": cam.c2w.tolist(), "mask": mask})
        views.append({"index": i, "before": f"eval/before/{i:03d}.png",
                      "after": f"eval/after/{i:03d}.png", "mask": mask,
                      "c2w": cam.c2w.tolist()})
    return {"scene": name, "convention": CONVENTION,
            "intrinsics": {"model": "PINHOLE", **intr, "K": K},
            "frames": frames, "eval_views": views}


def _check_target(out: Path, overwrite: bool) -> None:
    if out.exists() and not out.is_dir():
        raise GdiffError(f"{out}: exists and is not a folder; choose another output path")
    if out.is_dir() and any(out.iterdir()) and not overwrite:
        raise GdiffError(f"{out}: folder exists and is not empty; choose another path or pass "
                         "overwrite=True (--overwrite) to replace it")


def make_scene(out_dir: str | os.PathLike, preset: str | SynthPreset = "tiny", seed: int = 0,
               overwrite: bool = False) -> Path:
    """Render the scene of ``preset``/``seed`` into the gdiff scene folder ``out_dir``.

    The folder is rendered into a temporary sibling and renamed into place when complete, so
    ``out_dir`` is either absent/unchanged or complete. An existing non-empty ``out_dir`` is a
    :class:`GdiffError` unless ``overwrite`` is true. Returns the folder path.
    """
    p = get_preset(preset)
    out = Path(out_dir)
    _check_target(out, overwrite)
    out.parent.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    scene = build_scene(p, seed)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.tmp-", dir=out.parent))
    try:
        times = _render_folder(scene, tmp)
        meta = {"scene": out.name, "seed": int(seed), "preset": p.name,
                "description": p.description, "generator": "gdiff.synth",
                "preset_settings": dataclasses.asdict(p), **scene.meta(),
                "render": {"engine": "gdiff.synth ray tracer (numpy)",
                           "resolution": [p.width, p.height],
                           "supersample": p.supersample,
                           "shading": "Lambertian albedo x (hemispherical ambient + sun with "
                                      "cast shadows, soft sun sampled over its disc); "
                                      "tone curve 1-exp(-x); sRGB 8-bit",
                           "mask_render": "1 ray per pixel centre, object ids"},
                "gt_mask": {"definition": MASK_DEFINITION, "per_view": times.pop("per_view")}}
        write_json(tmp / "gt_cameras.json", _gt_cameras(scene, out.name))
        write_json(tmp / "meta.json", meta)
        total = time.perf_counter() - t_start
        write_json(tmp / "timing.json", {"scene": out.name, "preset": p.name,
                                         "total_seconds": round(total, 3), **times})
        _check_target(out, overwrite)
        if out.exists():
            old = Path(tempfile.mkdtemp(prefix=f".{out.name}.old-", dir=out.parent))
            os.replace(out, old / out.name)
            os.replace(tmp, out)
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.replace(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    log.info("wrote synthetic scene %s (preset %s, seed %d) in %.1f s", out, p.name, seed,
             time.perf_counter() - t_start)
    return out


def _render_folder(scene: SynthScene, root: Path) -> dict:
    """Render every image and mask of ``scene`` into ``root``; returns timing + mask counts."""
    p = scene.preset
    jobs = [(st, cam) for st in STATES for cam in scene.cameras(st)]
    n_total = len(jobs) + 2 * p.n_eval
    rgb_times = []
    per_view = []
    bar = progress(total=n_total, desc=f"synth {p.name}")
    try:
        for st, cam in jobs:
            t0 = time.perf_counter()
            write_image(root / cam.image, scene.render(cam, st)["rgb"])
            rgb_times.append(time.perf_counter() - t0)
            bar.update(1)
        for i, cam in enumerate(scene.cameras("eval")):
            masks = {}
            for st in STATES:
                t0 = time.perf_counter()
                r = scene.render(cam, st)
                write_image(root / "eval" / st / f"{i:03d}.png", r["rgb"])
                rgb_times.append(time.perf_counter() - t0)
                masks[st] = r["changed"]
                bar.update(1)
            union = masks["before"] | masks["after"]
            write_mask(root / "eval" / "masks" / f"{i:03d}.png", union)
            write_mask(root / "eval" / "mask_before" / f"{i:03d}.png", masks["before"])
            write_mask(root / "eval" / "mask_after" / f"{i:03d}.png", masks["after"])
            per_view.append({"index": i, "changed_pixels": int(union.sum()),
                             "before_pixels": int(masks["before"].sum()),
                             "after_pixels": int(masks["after"].sum()),
                             "fraction": round(float(union.mean()), 5)})
    finally:
        bar.close()
    rt = np.asarray(rgb_times)
    return {"n_rgb_images": len(rt), "rgb_mean_seconds": round(float(rt.mean()), 4),
            "rgb_min_seconds": round(float(rt.min()), 4),
            "rgb_max_seconds": round(float(rt.max()), 4),
            "resolution": [p.width, p.height], "supersample": p.supersample,
            "per_view": per_view}


def main(argv: list[str] | None = None) -> int:
    """``gdiff synth OUT --preset NAME [--seed N] [--overwrite]``; returns the exit code."""
    ap = argparse.ArgumentParser(
        prog="gdiff synth",
        description="Render a procedural before/after scene with ground-truth change masks "
                    "into a gdiff scene folder.")
    ap.add_argument("out", help="output scene folder")
    ap.add_argument("--preset", default="tiny", choices=sorted(PRESETS),
                    help="scene preset (default: tiny)")
    ap.add_argument("--seed", type=int, default=0, help="random seed (default: 0)")
    ap.add_argument("--overwrite", action="store_true",
                    help="replace the output folder if it exists and is not empty")
    args = ap.parse_args(argv)
    try:
        out = make_scene(args.out, args.preset, args.seed, args.overwrite)
    except GdiffError as e:
        print(f"gdiff synth: error: {e}", file=sys.stderr)
        return 1
    print(out)
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
