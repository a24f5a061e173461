"""Whether the two times' renders of one pose line up.

The ID comparison compares the t0 and the t1 render of a pose pixel by pixel: it assumes that
the models of the two visits put an unchanged surface at the same pixel. Where they do not (a
photo of one visit placed inconsistently with the photos of the other, e.g. turned where the
matches of a flat counter allow two turns; a sparse capture's model rendered far from its few
photos), every surface there looks changed to it and marks follow by chance. A render is
compared with the other time's render of the *same* pose, so corresponding features of the
unchanged scene sit at the same pixel: the share of feature matches that do is how well the
pose lines up. The matches are OpenCV SIFT features of each render (luma), paired by the ratio
test both renders take part in; a change covers some of them, a change of light moves shadow
edges, but neither moves the rest of the image.

Coordinates: pixel positions (x right, y down) of the renders, which have the same size.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

#: a match is in place when its two features lie within this share of the image's longer side
#: (2 px at 640), and at least within :data:`IN_PLACE_MIN_PX` (a feature's position is no finer)
IN_PLACE_FRAC = 1 / 320
IN_PLACE_MIN_PX = 1.0
#: Lowe's ratio test: a feature's best match must be nearer than this share of its second best
RATIO = 0.8
#: SIFT features kept per render (the strongest)
N_FEATURES = 2000


@dataclass(frozen=True)
class Lineup:
    """``matches``: feature matches between the two renders of a pose; ``in_place``: the share
    of them whose two features lie at the same pixel (within :func:`in_place_px`), NaN when
    there is no match."""

    matches: int
    in_place: float


def in_place_px(shape: tuple[int, ...]) -> float:
    """The distance in pixels within which a match is in place on an image of ``shape``
    ([H, W, ...])."""
    return max(IN_PLACE_MIN_PX, IN_PLACE_FRAC * max(shape[:2]))


def _luma8(rgb: np.ndarray) -> np.ndarray:
    """uint8 [H, W] luma of an sRGB float image [H, W, 3] in [0, 1]."""
    return cv2.cvtColor((np.clip(rgb, 0, 1) * 255 + 0.5).astype(np.uint8), cv2.COLOR_RGB2GRAY)


def sift_matches(grey0: np.ndarray, grey1: np.ndarray, n_features: int = N_FEATURES,
                 ratio: float = RATIO) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV SIFT features of two uint8 grey images ([H, W] each; sizes may differ), the
    strongest ``n_features`` of each, paired by Lowe's ratio test at ``ratio``: their pixel
    positions ``(p0, p1)``, float32 [M, 2] each (x right, y down; M may be 0)."""
    sift = cv2.SIFT_create(n_features)
    k0, d0 = sift.detectAndCompute(grey0, None)
    k1, d1 = sift.detectAndCompute(grey1, None)
    if d0 is None or d1 is None or len(k0) < 2 or len(k1) < 2:
        return np.zeros((0, 2), np.float32), np.zeros((0, 2), np.float32)
    pairs = cv2.BFMatcher(cv2.NORM_L2).knnMatch(d0, d1, k=2)
    good = [m[0] for m in pairs if len(m) == 2 and m[0].distance < ratio * m[1].distance]
    return (np.float32([k0[m.queryIdx].pt for m in good]).reshape(-1, 2),
            np.float32([k1[m.trainIdx].pt for m in good]).reshape(-1, 2))


def render_lineup(rgb0: np.ndarray, rgb1: np.ndarray) -> Lineup:
    """How well the renders ``rgb0`` and ``rgb1`` (sRGB float [H, W, 3] in [0, 1], the same
    pose at the two times) line up: their SIFT feature matches and the share in place."""
    if rgb0.shape != rgb1.shape:
        raise ValueError(f"renders of one pose differ in size: {rgb0.shape} and {rgb1.shape}")
    p0, p1 = sift_matches(_luma8(rgb0), _luma8(rgb1))
    if not len(p0):
        return Lineup(0, float("nan"))
    tol = in_place_px(rgb0.shape)
    return Lineup(len(p0), float((np.linalg.norm(p1 - p0, axis=1) <= tol).mean()))


def poorly_lined_up(in_place: np.ndarray, share: float) -> np.ndarray:
    """bool [K]: the poses (``in_place`` [K], :attr:`Lineup.in_place` of a scene's key poses)
    whose renders line up on less than ``share`` times the scene's median, or not at all (no
    feature match: NaN) while other poses do. The scene is its own measure: how many features a
    render has and how many stay in place under a change depend on the scene."""
    x = np.asarray(in_place, np.float64)
    if share <= 0 or not np.isfinite(x).any():
        return np.zeros(x.shape, bool)
    return ~(x >= share * float(np.nanmedian(x)))
