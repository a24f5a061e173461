"""Illumination-invariant comparison of one image region seen at two times from the same pose.

Used by the tracker (is the segment linked across times the same object?) and by the change
decision (does a candidate segment show different content at the other time?).

Model: a pixel's linear colour is albedo x irradiance, per channel. A lighting change (light
direction, colour, strength, exposure, a shadow's interior) multiplies the colour by a factor
that varies slowly across a surface, i.e. it *adds* a slowly varying term to the log colour.
Spatial gradients of the log colour are therefore kept by a lighting change (up to the gradient
of the shading, small against texture edges, and the edges of moving cast shadows, which are
few pixels), while a different object or surface has unrelated gradients. The similarity of two
views of a region is the normalised correlation of their log-colour gradient fields (all three
channels, both image axes) over the region: 1 for the same texture under any lighting, ~0 for
unrelated textures, and undefined (NaN) when the region has too little texture at either time.
"""

from __future__ import annotations

import cv2
import numpy as np

from .io import srgb_to_linear

#: floor added to linear values before the log (sensor-level noise in dark pixels is not texture)
LOG_FLOOR = 0.02


def log_gradients(rgb: np.ndarray, sigma: float = 1.0, highpass: float = 0.0) -> np.ndarray:
    """Gradients of the log linear colour, float32 [H, W, 3, 2] (d/dx, d/dy per channel).

    ``rgb``: sRGB-encoded float [H, W, 3] in [0, 1]. Central differences (Sobel / 8) after a
    Gaussian blur of ``sigma`` pixels; units: log-colour change per pixel. With ``highpass``
    > 0 the log colour blurred by that sigma (pixels) is subtracted first, which removes the
    slowly varying shading of curved surfaces and keeps the texture.
    """
    lin = srgb_to_linear(np.asarray(rgb, np.float32))
    lg = np.log(lin + LOG_FLOOR).astype(np.float32)
    if highpass > 0:
        lg = lg - cv2.GaussianBlur(lg, (0, 0), highpass)
    if sigma > 0:
        lg = cv2.GaussianBlur(lg, (0, 0), sigma)
    gx = cv2.Sobel(lg, cv2.CV_32F, 1, 0, ksize=3) / 8.0
    gy = cv2.Sobel(lg, cv2.CV_32F, 0, 1, ksize=3) / 8.0
    return np.stack([gx, gy], axis=-1)


def interior(mask: np.ndarray, width: int) -> np.ndarray:
    """``mask`` bool [H, W] eroded by ``width`` pixels (the whole mask if erosion empties it)."""
    if width <= 0:
        return mask
    er = cv2.erode(mask.astype(np.uint8), np.ones((2 * width + 1, 2 * width + 1), np.uint8)) > 0
    return er if er.sum() >= 8 else mask


def gradient_similarity(g0: np.ndarray, g1: np.ndarray, region: np.ndarray,
                        min_texture: float) -> tuple[float, float]:
    """Normalised correlation of two gradient fields [H, W, 3, 2] over ``region`` bool [H, W].

    Returns ``(similarity, texture)``: similarity in [-1, 1] (NaN when the RMS gradient of the
    weaker of the two views is below ``min_texture`` log units per pixel, or the region is
    empty) and that RMS gradient.
    """
    a = g0[region].reshape(-1)
    b = g1[region].reshape(-1)
    if a.size == 0:
        return float("nan"), 0.0
    n = region.sum()
    ea, eb = float(a @ a), float(b @ b)
    texture = float(np.sqrt(min(ea, eb) / n))
    if texture < min_texture:
        return float("nan"), texture
    return float(a @ b) / np.sqrt(ea * eb), texture


#: Gaussian sigma (pixels) of the shading removed before comparing texture
SHADING_SIGMA = 3.0
#: pixels along a region's boundary left out of the comparison (the background there differs)
BORDER = 2


def texture_gradients(rgb: np.ndarray) -> np.ndarray:
    """Log-colour gradients of the texture of ``rgb`` (shading removed), [H, W, 3, 2]."""
    return log_gradients(rgb, sigma=1.0, highpass=SHADING_SIGMA)


def region_similarity(g0: np.ndarray, g1: np.ndarray, mask: np.ndarray,
                      min_texture: float) -> float:
    """Texture similarity of a region (bool [H, W]) between two pixel-aligned views, from their
    :func:`texture_gradients`; NaN when the region is untextured or empty (see
    :func:`gradient_similarity`). The region's border (``BORDER`` pixels) is left out."""
    return gradient_similarity(g0, g1, interior(mask, BORDER), min_texture)[0]
