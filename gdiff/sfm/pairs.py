"""Image pair lists for vocabulary-free matching of large image sets."""

from __future__ import annotations

import numpy as np

from ..cameras import Camera


def sequential_pairs(groups: list[list[str]], overlap: int, links: int) -> list[tuple[str, str]]:
    """Image pairs for large sets: capture-order neighbours plus evenly spaced links.

    Args:
        groups: image names per set, each in capture order.
        overlap: each image is paired with the next ``overlap`` images of its set (cyclically,
            so the end of an orbit meets its start).
        links: each image is also paired with ``links`` evenly spaced images of every set
            (its own included), which ties the sets together and closes loops.

    Returns:
        Unordered, de-duplicated pairs ``(a, b)`` with ``a < b``; roughly
        ``N * (overlap + links * len(groups))`` of them for N images.
    """
    pairs: set[tuple[str, str]] = set()

    def add(a, b):
        if a != b:
            pairs.add((a, b) if a < b else (b, a))

    for g in groups:
        n = len(g)
        for i in range(n):
            for k in range(1, min(overlap, n - 1) + 1):
                add(g[i], g[(i + k) % n])
    if links > 0:
        for g in groups:
            for h in groups:
                if not h:
                    continue
                m = min(links, len(h))
                for j, a in enumerate(g):
                    # offset by j so different images link to different members of h
                    start = (j * len(h)) // max(len(g), 1)
                    for q in range(m):
                        add(a, h[(start + (q * len(h)) // m) % len(h)])
    return sorted(pairs)


def proximity_pairs(cameras: list[Camera], k: int) -> list[tuple[str, str]]:
    """Pairs of known cameras that likely overlap: each camera with its ``k`` nearest
    neighbours by centre distance among cameras whose viewing directions differ by < 90°."""
    centers = np.stack([c.center for c in cameras])
    dirs = np.stack([c.c2w[:3, 2] for c in cameras])
    d = np.linalg.norm(centers[:, None] - centers[None], axis=2)
    facing = dirs @ dirs.T > 0.0
    d = np.where(facing, d, np.inf)
    np.fill_diagonal(d, np.inf)
    pairs = set()
    for i, c in enumerate(cameras):
        for j in np.argsort(d[i])[:k]:
            if np.isfinite(d[i, j]):
                a, b = c.image, cameras[j].image
                pairs.add((a, b) if a < b else (b, a))
    return sorted(pairs)
