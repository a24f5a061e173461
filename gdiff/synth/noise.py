"""Deterministic, vectorised hashing and value noise for procedural textures."""

from __future__ import annotations

import functools

import numpy as np

_U64 = np.uint64
_PRIMES = (_U64(0x9E3779B97F4A7C15), _U64(0xC2B2AE3D27D4EB4F), _U64(0x165667B19E3779F9),
           _U64(0xD6E8FEB86659FD93))


def mix64(z: np.ndarray) -> np.ndarray:
    """splitmix64 finaliser on uint64 arrays (wrap-around arithmetic)."""
    z = z ^ (z >> _U64(30))
    z = z * _U64(0xBF58476D1CE4E5B9)
    z = z ^ (z >> _U64(27))
    z = z * _U64(0x94D049BB133111EB)
    return z ^ (z >> _U64(31))


def hash01(seed: int, *coords: np.ndarray) -> np.ndarray:
    """Uniform [0, 1) float64 per integer lattice cell ``coords`` (int arrays), for ``seed``."""
    with np.errstate(over="ignore"):
        h = mix64(np.full(np.shape(coords[0]), _U64(seed & 0xFFFFFFFFFFFFFFFF)))
        for k, c in enumerate(coords):
            h = mix64(h ^ (np.asarray(c, dtype=np.int64).view(np.uint64) * _PRIMES[k % 4]))
    return (h >> _U64(11)).astype(np.float64) * (1.0 / 9007199254740992.0)


_NOISE_N = 32  # value-noise lattice period (cells)


@functools.lru_cache(maxsize=128)
def _noise_table(seed: int) -> np.ndarray:
    """Random lattice values, flattened [32**3] float64, fixed per seed."""
    return np.random.default_rng(seed).random(_NOISE_N ** 3)


def value_noise(p: np.ndarray, seed: int) -> np.ndarray:
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
            out += wxy * ((1.0 - u[:, 2]) * tab.take(oxy + i[:, 2])
                          + u[:, 2] * tab.take(oxy + j[:, 2]))
    return out


def fbm(p: np.ndarray, seed: int, octaves: int = 3) -> np.ndarray:
    """Fractal sum of value noise, normalised to [0, 1]; ``p`` [N, 3] in lattice units."""
    out = np.zeros(len(p))
    amp, norm = 1.0, 0.0
    for k in range(octaves):
        out += amp * value_noise(p * (2.0 ** k) + 17.3 * k, seed + 101 * k)
        norm += amp
        amp *= 0.5
    return out / norm


def smoothstep(a: float, b: float, x: np.ndarray) -> np.ndarray:
    t = np.clip((x - a) / (b - a), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)
