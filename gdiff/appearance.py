"""Illumination-invariant comparison of one image region seen at two times from the same pose.

Used by the tracker (is the segment linked across times the same object?) and by the change
decision (does a candidate segment show different content at the other time?).

Model: a pixel's linear colour is albedo x irradiance, per channel. A lighting change (light
direction, colour, strength, exposure, a shadow's interior) multiplies the colour by a factor
that varies slowly across a surface, i.e. it *adds* a slowly varying term to the log colour.
Spatial gradients of the log colour are therefore kept by a lighting change, while a different
object or surface has unrelated gradients. Three steps make this hold on real renders:

* the log has a floor proportional to the image's median intensity (dark pixels' noise is not
  texture, and a global exposure change scales the floor with the image, so it stays exact);
* the log colour blurred at ``SHADING_SIGMA`` is subtracted (the shading of curved surfaces,
  which a moved light changes, varies slowly; texture and edges do not);
* the gradients are divided by their local RMS (``CONTRAST_SIGMA``, with a floor): a camera's
  tone curve compresses contrast in bright areas, which changes edge strengths but not where
  the edges are.

The similarity of two views of a region is the normalised correlation of these gradient fields
(all three channels, both image axes) over the region: ~1 for the same texture under any
lighting, ~0 for unrelated textures, and undefined (NaN) when the region has too little texture
at either time.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from .io import srgb_to_linear

#: log floor as a fraction of the image's median linear intensity
LOG_FLOOR_REL = 0.1
#: Gaussian sigma (pixels) of the shading removed before comparing texture
SHADING_SIGMA = 3.0
#: Gaussian sigma (pixels) of the pre-blur (noise) before differentiation
GRAD_SIGMA = 1.0
#: Gaussian sigma (pixels) of the window for local contrast normalisation
CONTRAST_SIGMA = 4.0
#: pixels along a region's boundary left out of the comparison (the background there differs)
BORDER = 2


@dataclass
class Texture:
    """Texture of an image for :func:`region_similarity`.

    ``grad``: contrast-normalised log-colour gradients, float32 [H, W, 3, 2];
    ``energy``: squared raw log-colour gradient magnitude per pixel (log units^2), [H, W].
    """

    grad: np.ndarray
    energy: np.ndarray


def log_gradients(rgb: np.ndarray, sigma: float = GRAD_SIGMA,
                  highpass: float = SHADING_SIGMA) -> np.ndarray:
    """Gradients of the log linear colour, float32 [H, W, 3, 2] (d/dx, d/dy per channel).

    ``rgb``: sRGB-encoded float [H, W, 3] in [0, 1]. The log has a floor of ``LOG_FLOOR_REL``
    x the median linear intensity. With ``highpass`` > 0 the log colour blurred by that sigma
    (pixels) is subtracted (shading removed). Central differences (Sobel / 8) after a Gaussian
    blur of ``sigma`` pixels; units: log-colour change per pixel.
    """
    lin = srgb_to_linear(np.asarray(rgb, np.float32))
    floor = max(LOG_FLOOR_REL * float(np.median(lin.mean(-1))), 1e-3)
    lg = np.log(lin + floor).astype(np.float32)
    if highpass > 0:
        lg = lg - cv2.GaussianBlur(lg, (0, 0), highpass)
    if sigma > 0:
        lg = cv2.GaussianBlur(lg, (0, 0), sigma)
    gx = cv2.Sobel(lg, cv2.CV_32F, 1, 0, ksize=3) / 8.0
    gy = cv2.Sobel(lg, cv2.CV_32F, 0, 1, ksize=3) / 8.0
    return np.stack([gx, gy], axis=-1)


def texture(rgb: np.ndarray, min_texture: float = 0.03) -> Texture:
    """:class:`Texture` of ``rgb`` (sRGB float [H, W, 3]); gradients are divided by their local
    RMS (window ``CONTRAST_SIGMA``) floored at ``min_texture`` so flat areas stay ~0."""
    g = log_gradients(rgb)
    e = (g * g).sum((-1, -2))
    local = cv2.GaussianBlur(e, (0, 0), CONTRAST_SIGMA)
    return Texture(g / np.sqrt(local + min_texture ** 2)[..., None, None], e)


def interior(mask: np.ndarray, width: int) -> np.ndarray:
    """``mask`` bool [H, W] eroded by ``width`` pixels (the whole mask if erosion empties it)."""
    if width <= 0:
        return mask
    er = cv2.erode(mask.astype(np.uint8), np.ones((2 * width + 1, 2 * width + 1), np.uint8)) > 0
    return er if er.sum() >= 8 else mask


def mask_box(mask: np.ndarray, margin: int = 0) -> tuple[slice, slice] | None:
    """The slices of the bounding box of ``mask`` (bool [H, W]) grown by ``margin`` pixels
    (clipped to the image), or None when it is empty: work on a region's pixels touches only
    its box."""
    rows, cols = np.flatnonzero(mask.any(1)), np.flatnonzero(mask.any(0))
    if not len(rows):
        return None
    h, w = mask.shape
    return (slice(max(0, rows[0] - margin), min(h, rows[-1] + 1 + margin)),
            slice(max(0, cols[0] - margin), min(w, cols[-1] + 1 + margin)))


def region_similarity(t0: Texture, t1: Texture, mask: np.ndarray, min_texture: float) -> float:
    """Texture similarity in [-1, 1] of a region (bool [H, W]) between two pixel-aligned views.

    The region's border (``BORDER`` pixels) is left out. NaN when the region is empty or the
    RMS raw gradient of the weaker view is below ``min_texture`` log units per pixel
    (untextured: nothing to compare).
    """
    # the region's box with room for the erosion (the same pixels as on the whole image)
    sl = mask_box(mask, BORDER + 1)
    if sl is None:
        return float("nan")
    region = interior(mask[sl], BORDER)
    n = int(region.sum())
    if n == 0:
        return float("nan")
    e0, e1 = t0.energy[sl], t1.energy[sl]
    if np.sqrt(min(e0[region].mean(), e1[region].mean())) < min_texture:
        return float("nan")
    a = t0.grad[sl][region].reshape(-1)
    b = t1.grad[sl][region].reshape(-1)
    ea, eb = float(a @ a), float(b @ b)
    if ea <= 0 or eb <= 0:
        return float("nan")
    return float(a @ b) / np.sqrt(ea * eb)


def normalised_chroma(rgb: np.ndarray, linear: np.ndarray | None = None
                       ) -> tuple[np.ndarray, np.ndarray]:
    """Grey-world-normalised chromaticity [H, W, 3] (sums to 1) and its confidence [H, W] of
    ``rgb`` (sRGB [H, W, 3]); ``linear`` (optional): its linear values as float64, when the
    caller has them (:func:`linear_rgb`)."""
    lin = linear_rgb(rgb) if linear is None else linear
    return _chroma_of(lin / np.maximum(lin.reshape(-1, 3).mean(0), 1e-6))  # cast removed


def _chroma_of(lin: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Chromaticity [H, W, 3] (sums to 1) of linear colours ``lin`` [H, W, 3] and its
    confidence [H, W] in [0, 1] (0 for dark pixels)."""
    s = lin.sum(-1)
    return lin / np.maximum(s, 1e-6)[..., None], np.clip(s / 0.15, 0, 1)


def linear_rgb(rgb: np.ndarray) -> np.ndarray:
    """Linear values (float64 [..., 3]) of sRGB ``rgb``."""
    return srgb_to_linear(rgb).astype(np.float64)


def chroma_bin(c: np.ndarray, bins: int) -> np.ndarray:
    """Flat bin index int64 [K] (``r * bins + g``) of chromaticities ``c`` [K, 3]: bins of equal
    width over [0, 1) (the same bins as np.histogram2d with that range)."""
    r = np.floor(np.clip(c[:, 0], 0, 0.999) * bins).astype(np.int64)
    g = np.floor(np.clip(c[:, 1], 0, 0.999) * bins).astype(np.int64)
    return r * bins + g


def chroma_hist(rgb: np.ndarray | tuple, mask: np.ndarray, bins: int = 8) -> np.ndarray:
    """2-D histogram [bins, bins] of the grey-world chromaticity (r, g) of ``mask`` bool [H, W]
    in ``rgb`` (sRGB [H, W, 3], or its :func:`normalised_chroma` pair, to reuse it)."""
    c, w = rgb if isinstance(rgb, tuple) else normalised_chroma(rgb)
    sl = mask_box(mask)
    if sl is None:
        return np.zeros((bins, bins))
    c, w = c[sl], w[sl]
    sel = mask[sl] & (w > 0.3)
    if not sel.any():
        return np.zeros((bins, bins))
    return np.bincount(chroma_bin(c[sel], bins), minlength=bins * bins
                       ).reshape(bins, bins).astype(np.float64)


def bhattacharyya(h1, h2) -> float:
    """Bhattacharyya coefficient in [0, 1] of two histograms (any shape, normalised here):
    1 for the same distribution; 0 when either is None or empty."""
    if h1 is None or h2 is None or h1.sum() == 0 or h2.sum() == 0:
        return 0.0
    return float(np.sqrt(h1 / h1.sum() * h2 / h2.sum()).sum())


def median_gain(target: np.ndarray, source: np.ndarray, floor: float = 1e-3) -> np.ndarray:
    """float32 [3]: the per-channel gain that brings ``source`` to ``target``'s exposure and
    white balance, the ratio of their channel medians over the same pixels (``target``,
    ``source``: float [..., 3], pixel for pixel the same surfaces; a source median below
    ``floor`` counts as ``floor``). A change covering a minority of the pixels moves a median
    little, where it would move a mean."""
    t = np.asarray(target, np.float32).reshape(-1, 3)
    s = np.asarray(source, np.float32).reshape(-1, 3)
    return (np.median(t, 0) / np.maximum(np.median(s, 0), floor)).astype(np.float32)


def matched_chroma(rgb0: np.ndarray, rgb1: np.ndarray
                   ) -> tuple[tuple[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]:
    """Chromaticities of two pixel-aligned views of one scene (sRGB [H, W, 3] each), with
    ``rgb0`` first brought to ``rgb1``'s exposure and white balance: each channel scaled by
    the median ratio of their linear values over the pixels lit in both, which a change
    covering a minority of the frame does not move (a grey-world normalisation of each view on
    its own would: an added red object shifts the mean). Returns ``((c0, w0), (c1, w1))``,
    each chromaticity [H, W, 3] (sums to 1) and its confidence [H, W] in [0, 1] (0 for dark
    pixels), in the pair form :func:`chroma_hist` takes."""
    lin0, lin1 = linear_rgb(rgb0), linear_rgb(rgb1)
    lit = (lin0.sum(-1) > 0.05) & (lin1.sum(-1) > 0.05)
    if lit.any():
        lin0 = lin0 * np.median(lin1[lit] / np.maximum(lin0[lit], 1e-6), axis=0)
    return _chroma_of(lin0), _chroma_of(lin1)
