"""Procedural solid textures: ``f(p [N, 3] in the surface's own frame, metres, params)`` ->
sRGB-encoded albedo [N, 3]. Parameters are plain JSON-able dicts (recorded in meta.json)."""

from __future__ import annotations

from typing import Callable

import numpy as np

from .noise import fbm, hash01, smoothstep, value_noise

def _pal(prm: dict, idx: np.ndarray) -> np.ndarray:
    pal = np.asarray(prm["palette"], dtype=np.float64)
    return pal[np.asarray(idx, dtype=np.int64) % len(pal)]


def _detail(p: np.ndarray, prm: dict, scale: float, amount: float = 0.25) -> np.ndarray:
    """Multiplicative fine noise [N, 1] around 1 (breaks up flat areas for feature matching)."""
    return (1.0 - amount / 2 + amount * fbm(p / scale, prm["seed"] + 7, 2))[:, None]


def _tex_checker(p, prm):
    s = prm["scale"]
    q = (p + prm["offset"]) / s
    c = (np.floor(q).astype(np.int64).sum(axis=1)) & 1
    return _pal(prm, c) * _detail(p, prm, s * 0.5)


def _tex_stripes(p, prm):
    s = prm["scale"]
    v = p @ np.asarray(prm["axis"]) / s + 1.2 * fbm(p / (2 * s), prm["seed"], 2)
    band = np.floor(v)
    rgb = _pal(prm, band.astype(np.int64))
    edge = np.minimum(v - band, 1.0 - (v - band))
    rgb = rgb * (0.55 + 0.45 * smoothstep(0.0, 0.08, edge))[:, None]
    return rgb * _detail(p, prm, s * 0.4, 0.2)


def _tex_dots(p, prm):
    s = prm["scale"]
    q = (p + prm["offset"]) / s
    cell = np.floor(q).astype(np.int64)
    sd = prm["seed"]
    jit = np.stack([hash01(sd + k, cell[:, 0], cell[:, 1], cell[:, 2]) for k in range(3)], 1)
    centre = cell + 0.5 + 0.3 * (jit - 0.5)
    d = np.linalg.norm(q - centre, axis=1)
    dot_col = _pal(prm, 1 + (hash01(sd + 9, cell[:, 0], cell[:, 1], cell[:, 2])
                             * (len(prm["palette"]) - 1)).astype(np.int64))
    bg = np.asarray(prm["palette"][0]) * _detail(p, prm, s * 0.7, 0.3)
    w = smoothstep(0.36, 0.30, d)[:, None]
    return bg * (1 - w) + dot_col * w


def _tex_marble(p, prm):
    s = prm["scale"]
    v = p @ np.asarray(prm["axis"]) / s + 4.0 * fbm(p / (1.5 * s), prm["seed"], 4)
    w = np.abs(np.sin(np.pi * v))
    c0, c1 = (np.asarray(c) for c in prm["palette"][:2])
    rgb = c0 + (c1 - c0) * (w ** 0.6)[:, None]
    vein = smoothstep(0.12, 0.0, w)[:, None]
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
                d = np.sqrt(sum((diff[:, k] - hash01(seed + k, *cc)) ** 2
                                for k in range(dims)))
                closer = d < d1
                d2 = np.where(closer, d1, np.minimum(d2, d))
                best[closer] = c[closer]
                d1 = np.where(closer, d, d1)
    return d1, d2, best


def _tex_mosaic(p, prm):
    s = prm["scale"]
    d1, d2, cell = _voronoi(p / s, prm["seed"], prm.get("dims", 3))
    h = hash01(prm["seed"] + 5, cell[:, 0], cell[:, 1], cell[:, 2])
    rgb = _pal(prm, (h * len(prm["palette"])).astype(np.int64))
    rgb = rgb * (0.8 + 0.4 * hash01(prm["seed"] + 6, cell[:, 0], cell[:, 1], cell[:, 2]))[:, None]
    grout = smoothstep(0.10, 0.04, d2 - d1)[:, None]
    rgb = rgb * (1 - grout) + np.asarray(prm["grout"]) * grout
    return rgb * _detail(p, prm, s * 0.3, 0.2)


def _tex_noise(p, prm):
    s = prm["scale"]
    n = fbm(p / s, prm["seed"], 4)
    c0, c1 = (np.asarray(c) for c in prm["palette"][:2])
    w = smoothstep(0.42, 0.58, n)[:, None]
    spk = smoothstep(0.72, 0.8, value_noise(p / (0.2 * s), prm["seed"] + 3))[:, None]
    c2 = np.asarray(prm["palette"][2 % len(prm["palette"])])
    return (c0 * (1 - w) + c1 * w) * (1 - spk) + c2 * spk


def _bricks(u, v, p, prm):
    """Running-bond bricks in planar coordinates (u along, v up), metres."""
    bw, bh = prm["brick"]
    row = np.floor(v / bh)
    uu = u / bw + 0.5 * (row.astype(np.int64) & 1)
    col = np.floor(uu)
    sd = prm["seed"]
    h = hash01(sd, row.astype(np.int64), col.astype(np.int64))
    rgb = _pal(prm, (h * len(prm["palette"])).astype(np.int64))
    rgb = rgb * (0.75 + 0.5 * hash01(sd + 1, row.astype(np.int64), col.astype(np.int64)))[:, None]
    fu = np.minimum(uu - col, 1 - (uu - col)) * bw
    fv = np.minimum(v / bh - row, 1 - (v / bh - row)) * bh
    mortar = smoothstep(0.012, 0.004, np.minimum(fu, fv))[:, None]
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
    rgb = _pal(prm, (hash01(sd, c[:, 0], c[:, 1]) * len(prm["palette"])).astype(np.int64))
    # a second, smaller square inside some tiles
    fq = q - c
    inner = (np.abs(fq - 0.5).max(axis=1) < 0.22) & (hash01(sd + 2, c[:, 0], c[:, 1]) < 0.5)
    rgb = np.where(inner[:, None], _pal(prm, (hash01(sd + 3, c[:, 0], c[:, 1])
                                              * len(prm["palette"])).astype(np.int64)), rgb)
    g = np.minimum(fq, 1 - fq).min(axis=1) * s
    grout = smoothstep(0.014, 0.006, g)[:, None]
    rgb = rgb * (1 - grout) + np.asarray(prm["grout"]) * grout
    return rgb * _detail(p, prm, s * 0.15, 0.3)


def _tex_wood(p, prm):
    """Planks along x (width ``plank`` in y, staggered joints), grain lines and knots."""
    pw, pl = prm["plank"], prm["length"]
    sd = prm["seed"]
    row = np.floor(p[:, 1] / pw).astype(np.int64)
    x = p[:, 0] + hash01(sd, row) * pl
    col = np.floor(x / pl).astype(np.int64)
    tone = 0.7 + 0.55 * hash01(sd + 1, row, col)
    q = np.stack([p[:, 0] * 1.5, p[:, 1] * 12.0, p[:, 2] * 12.0], 1)
    grain = 0.5 + 0.5 * np.sin(2 * np.pi * (p[:, 1] / pw * 5 + 2.5 * fbm(q, sd + 2, 3)))
    c0, c1 = (np.asarray(c) for c in prm["palette"][:2])
    rgb = (c0 + (c1 - c0) * grain[:, None]) * tone[:, None]
    fy = p[:, 1] / pw - row
    fx = x / pl - col
    gap = np.minimum(np.minimum(fy, 1 - fy) * pw, np.minimum(fx, 1 - fx) * pl)
    seam = smoothstep(0.008, 0.003, gap)[:, None]
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
