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


def _unit_rows(x: np.ndarray) -> np.ndarray:
    x = np.asarray(x, dtype=np.float32)
    return x / np.maximum(np.linalg.norm(x, axis=1, keepdims=True), 1e-12)


def _nearest_word(desc: np.ndarray, words: np.ndarray, chunk: int = 65536) -> np.ndarray:
    """Index of the nearest row of ``words`` (W, D) for each row of ``desc`` (M, D), both
    unit rows: the largest dot product, computed in chunks by matrix products."""
    out = np.empty(len(desc), dtype=np.int64)
    for s in range(0, len(desc), chunk):
        out[s:s + chunk] = np.argmax(desc[s:s + chunk] @ words.T, axis=1)
    return out


def word_histograms(descriptors: list[np.ndarray], num_words: int = 256,
                    max_train: int = 50_000, seed: int = 0) -> np.ndarray:
    """Bag-of-visual-words image vectors from the images' own local features.

    A vocabulary of ``num_words`` words is learnt by k-means (OpenCV, k-means++ seeding) on at
    most ``max_train``
    descriptors sampled from all images; each image is then the tf-idf weighted, L2-normalised
    histogram of its descriptors' nearest words. No pre-trained vocabulary is needed.

    Args:
        descriptors: per image, its feature descriptors (M_i, D) (e.g. SIFT, uint8 or float).
        num_words: vocabulary size (capped by the number of descriptors).
        max_train: descriptors used to learn the vocabulary.
        seed: random seed of the sampling and of k-means.

    Returns:
        (N, W) float32 image vectors with unit norm (zero rows for images without features);
        their dot products are the images' similarities in [0, 1].
    """
    import cv2

    rng = np.random.default_rng(seed)
    sizes = np.array([len(d) for d in descriptors], dtype=np.int64)
    total = int(sizes.sum())
    if total == 0:
        return np.zeros((len(descriptors), 1), np.float32)
    # sample rows by their index in the images' concatenation, without building it (a copy
    # of every descriptor as floats is large for thousands of features per image)
    pick = rng.choice(total, size=min(max_train, total), replace=False)
    ends = np.cumsum(sizes)
    owner = np.searchsorted(ends, pick, side="right")
    train = _unit_rows(np.stack([descriptors[o][p - ends[o] + sizes[o]]
                                 for o, p in zip(owner, pick)]))
    w = max(1, min(num_words, len(train)))
    cv2.setRNGSeed(seed)
    criteria = (cv2.TERM_CRITERIA_MAX_ITER + cv2.TERM_CRITERIA_EPS, 10, 1e-4)
    _, _, words = cv2.kmeans(np.ascontiguousarray(train), w, None, criteria, 1,
                             cv2.KMEANS_PP_CENTERS)
    words = _unit_rows(words)
    counts = np.zeros((len(descriptors), w), np.float32)
    for i, d in enumerate(descriptors):
        if len(d):
            counts[i] = np.bincount(_nearest_word(_unit_rows(d), words), minlength=w)
    df = np.count_nonzero(counts, axis=0)
    idf = np.log((len(descriptors) + 1.0) / (df + 1.0)).astype(np.float32)
    tf = counts / np.maximum(counts.sum(axis=1, keepdims=True), 1.0)
    return _unit_rows(tf * idf)


def per_set_neighbours(neighbours: int, n_sets: int) -> int:
    """The most similar images :func:`retrieval_pairs` takes from each of ``n_sets`` sets:
    ``neighbours`` shared evenly among them, rounded up, at least one."""
    return max(1, -(-neighbours // max(n_sets, 1)))


def retrieval_pairs(groups: list[list[str]], vectors: dict[str, np.ndarray], neighbours: int,
                    overlap: int) -> list[tuple[str, str]]:
    """Image pairs for large, possibly unordered sets: each image with its most similar images
    (by ``vectors``, e.g. :func:`word_histograms`) *of every set*, ``neighbours`` in all, spread
    evenly over the sets (at least one per set), plus its next ``overlap`` images in capture
    order within its set (photo series and video frames overlap their neighbours; unordered
    sets lose nothing but a few pairs).

    Ranked over all images together, an image's own set fills its list: same light, same
    capture path. The pairs that tie the before and after visits together then rank low, and
    the two visits are registered to each other through a few of them.

    Returns:
        Unordered, de-duplicated pairs ``(a, b)`` with ``a < b``; at most
        ``N * (max(neighbours, len(groups)) + overlap)`` of them for N images, so matching grows
        linearly.
    """
    groups = [g for g in groups if g]
    pairs = set(sequential_pairs(groups, overlap, 0)) if overlap > 0 else set()
    if sum(len(g) for g in groups) < 2 or neighbours <= 0:
        return sorted(pairs)
    per_set = per_set_neighbours(neighbours, len(groups))
    vecs = [np.stack([vectors[n] for n in g]) for g in groups]
    for gi, (g, v) in enumerate(zip(groups, vecs)):
        for hi, (h, w) in enumerate(zip(groups, vecs)):
            sim = v @ w.T
            if gi == hi:  # an image is not its own neighbour
                np.fill_diagonal(sim, -np.inf)
            k = min(per_set, len(h) - (gi == hi))
            if k <= 0:
                continue
            top = np.argpartition(-sim, k - 1, axis=1)[:, :k]
            for i, row in enumerate(top):
                for j in row:
                    a, b = g[i], h[j]
                    pairs.add((a, b) if a < b else (b, a))
    return sorted(pairs)
