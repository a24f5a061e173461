"""The before-map gate of the union change map.

The union map of a viewpoint is what is there now and is new (the t=1 map) plus what was there
and changed (the t=0 map). The partition labels Gaussians from 2D masks, and a mask of a before
photo covers every pixel whose view changed, including the surface an added object hides from
that photo. Those surface Gaussians are then labelled changed at t=0 although they are still
there at t=1. Seen from another pose they show beside the new object, where nothing changed:
the scene renders the same there at both times. The gate keeps a pixel of the t=0 map in the
union only where the two times render differently at it (a removed or moved object: at t=1 the
ray shows what was behind it). The t=1 map is not gated: it is what the scene holds now, and a
4D model fitted with a price on change between the times draws a new object faintly at t=0 too,
so its render differs from the t=0 one by less than the object does from its surround.

"Differently" is relative to the view: the per-pixel colour difference of the two renders
(exposure and white balance matched by the per-channel median ratio over the pixels both maps
call unchanged, then averaged over a small window) must exceed the ``quantile`` of that
difference over those unchanged pixels. A fit to few photos renders unchanged surfaces with
differences well above zero, and this keeps the test relative to how well the two times agree
at that view. Under a change of light the renders differ everywhere (moved shadows, another
colour of light), a removed object's difference then falls within that spread, and the
partition stage leaves the union ungated when the compare stage took the scene for one.
"""

from __future__ import annotations

import cv2
import numpy as np

from ..appearance import median_gain

# the two renders are compared where both draw a surface at least this opaque (the exposure match)
GATE_MIN_ALPHA = 0.5
# window (pixels, per 128 of the longer image side) the colour difference is averaged over
GATE_WINDOW_PER_128 = 1.0


def render_difference(rgb0: np.ndarray, rgb1: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """Colour difference of two renders of one camera, float32 [H, W] in [0, 1].

    Args:
        rgb0, rgb1: float [H, W, 3] sRGB renders at t=0 and t=1.
        reference: bool [H, W], pixels assumed unchanged: ``rgb0`` is scaled per channel by the
            median ratio ``rgb1 / rgb0`` over them (exposure and white balance between the
            visits; no scaling when fewer than 16 such pixels).
    Returns:
        the largest absolute channel difference per pixel, box-averaged over a window of
        ``GATE_WINDOW_PER_128`` / 128 of the longer image side (at least 3 px, odd).
    """
    a = np.asarray(rgb0, np.float32)
    b = np.asarray(rgb1, np.float32)
    ref = np.asarray(reference, bool)
    if ref.sum() >= 16:
        a = np.clip(a * median_gain(b[ref], a[ref]), 0.0, 1.0)
    d = np.abs(a - b).max(-1)
    k = max(3, int(round(max(d.shape) * GATE_WINDOW_PER_128 / 128.0)) | 1)
    return cv2.blur(d, (k, k))


def gate_before_map(prob_t0: np.ndarray, prob_t1: np.ndarray, rgb0: np.ndarray,
                    rgb1: np.ndarray, alpha0: np.ndarray, alpha1: np.ndarray, threshold: float,
                    quantile: float) -> np.ndarray:
    """Bool [H, W]: the pixels where the t=0 map may count in the union (see the module).

    Args:
        prob_t0, prob_t1: float [H, W] change probabilities of the two times at one camera.
        rgb0, rgb1: float [H, W, 3] the renders at t=0 and t=1; alpha0, alpha1: [H, W] their
            accumulated opacities.
        threshold: the map threshold (``prob > threshold`` is changed).
        quantile: in (0, 1): the difference must exceed this quantile of the difference over
            the pixels neither map calls changed (drawn at both times). All True when there are
            fewer than 16 such pixels (nothing to compare against).
    """
    p0, p1 = np.asarray(prob_t0), np.asarray(prob_t1)
    drawn = (np.asarray(alpha0) >= GATE_MIN_ALPHA) & (np.asarray(alpha1) >= GATE_MIN_ALPHA)
    unchanged = drawn & (p0 <= threshold) & (p1 <= threshold)
    if unchanged.sum() < 16:
        return np.ones(p0.shape, bool)
    d = render_difference(rgb0, rgb1, unchanged)
    return d > float(np.quantile(d[unchanged], quantile))
