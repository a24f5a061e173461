"""Key-view masks completed from the training photos: what the photo of a key pose shows
differently from the other time's render there, next to a change the IDs found.

The partition learns from the key views' masks (:mod:`gdiff.partition.data`), so a changed
object marked in part there is learnt in part. On a sparse capture the segmenter, driven by
the rendered depth, often cuts a new object into pieces, some of which fail the evidence
checks: the fit renders the object's middle half-transparent, or at the depth of the wall
behind it, and the pieces cross its outline. The training photo of a key pose shows the object
whole and sharp, and the model rendered at the *other* time at that pose shows what stood there
then. Where they differ next to a piece of a change, the piece is grown into the difference:

1. ``difference``: the per-pixel colour distance (sRGB, both blurred by ``SMOOTH_PX``) between
   the photo and the other time's render, the render scaled per channel to the photo's median
   colour (auto exposure, another visit's light).
2. A floor on that distance below which a pixel does not count (:func:`noise_floor`): the
   larger of the fit's own error (the ``OWN_QUANTILE`` of the photo's distance to its own time's
   render: blur, texture the fit misses) and what the view's other-time render gets wrong
   everywhere (median + ``SPREAD_MADS`` robust deviations of the difference: a pose the other
   time's photos saw poorly renders worse all over).
3. Per piece of the key view's mask (:func:`grow_pieces`; fragments closer than the span of
   a disc of ``DISC_FRACTION`` of the image diagonal are one piece: the segmenter cut one object
   into them): a piece grows only when the photo confirms it (its median difference above the
   floor), into the pixels around which most of the disc (``MAJORITY``) differs by at least
   ``PIECE_SHARE`` of the piece's own median (as different as the object is, not just
   noticeably; the majority drops thin streaks along misaligned edges and texture, and fills
   the holes an object's print or highlights leave), connected to the piece and no farther
   from it than ``reach`` times its bounding box's longer side. Pixels where either render
   shows no surface are never added, nor those whose depth is observed at both times (enough
   photos of each time agree on it, :mod:`gdiff.compare.coverage`): there the IDs' masks, cut
   along that depth, follow the objects already, and what the photo shows differently beside
   them is a shadow the object casts or a surface the other time's object covers, not the
   object.
   So the step acts where a sparse capture leaves the depth untrusted. Nor are the pixels
   the other time's mask marks at that pose: there the photo differs from the other time's
   render because of the other time's change (at a before pose, the object put down later
   stands there in the after render), and the surface the photo shows there did not change.
   Grown into, it would teach the partition that surface as changed at this time, and
   rendered from another pose it would show as changed patches beside the new object.

Not under a change of light (the flat evidence's verdict, :mod:`gdiff.compare.geometry`): a
photo then differs from the other time's render wherever the light did, shadows beside an
object among them, and the difference no longer outlines objects (the stage skips this step
and says so in the log). Only the key poses have a photo; the other poses keep the IDs' masks.
At a key pose of time t the mask of time t (the one the partition trains on there) is
completed; the union written by the stage follows it.

Frames are sRGB float [H, W, 3] in [0, 1] at one size per pose; masks bool [H, W].
"""

from __future__ import annotations

import cv2
import numpy as np

from ..appearance import median_gain
from ..frames import TIMES
from ..io import linear_to_srgb

# Gaussian blur (pixels) of photo and render before they are compared: the render is smoother
# than the photo, and its pixels are not aligned with the photo's to the pixel
SMOOTH_PX = 1.0
# the fit's own error: this percentile of the photo's distance to its own time's render
OWN_QUANTILE = 99.0
# the other time's render's error all over the view: median + this many robust deviations
SPREAD_MADS = 3.0
# a grown pixel differs by at least this share of the piece's median difference
PIECE_SHARE = 0.5
# radius of the disc that joins fragments, filters the grown region and opens the observed
# depth, as a fraction of the image diagonal
DISC_FRACTION = 0.006
# a pixel is grown into when at least this share of the disc around it differs
MAJORITY = 0.5


def difference(photo: np.ndarray, render: np.ndarray) -> np.ndarray:
    """Per-pixel colour distance [H, W] between ``photo`` and ``render`` (sRGB [H, W, 3]),
    both blurred by :data:`SMOOTH_PX`, the render scaled per channel to the photo's median."""
    p = cv2.GaussianBlur(np.asarray(photo, np.float32), (0, 0), SMOOTH_PX)
    r = cv2.GaussianBlur(np.asarray(render, np.float32), (0, 0), SMOOTH_PX)
    gain = median_gain(p, r)
    return np.linalg.norm(p - r * gain, axis=-1)


def noise_floor(other: np.ndarray, own: np.ndarray) -> float:
    """The distance below which a pixel of ``other`` (photo vs the other time's render, [H, W])
    does not count: the larger of the fit's own error (``own``: photo vs its own time's render)
    and the other render's error all over the view (module docstring, step 2)."""
    med = float(np.median(other))
    mad = 1.4826 * float(np.median(np.abs(other - med)))
    return max(float(np.percentile(own, OWN_QUANTILE)), med + SPREAD_MADS * mad)


def _disc(shape: tuple[int, ...]) -> np.ndarray:
    """The disc for an image of ``shape`` (radius :data:`DISC_FRACTION` of its diagonal)."""
    rad = max(1, int(round(DISC_FRACTION * np.hypot(shape[0], shape[1]))))
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * rad + 1, 2 * rad + 1))


def grow_pieces(mask: np.ndarray, other: np.ndarray, floor: float, reach: float,
                valid: np.ndarray | None = None) -> tuple[np.ndarray, int]:
    """``mask`` [H, W] bool with each photo-confirmed piece grown into the differing pixels
    next to it (module docstring, step 3); ``other`` [H, W] the photo's distance to the other
    time's render, ``floor`` from :func:`noise_floor`, ``valid`` [H, W] bool the pixels that
    may be added (None: all). Returns (grown mask, number of pieces grown)."""
    mask = np.asarray(mask, bool)
    out = mask.copy()
    if not mask.any() or reach <= 0:
        return out, 0
    disc = _disc(mask.shape)
    rad = disc.shape[0] // 2
    share = disc.astype(np.float32) / float(disc.sum())  # a pixel's share of the disc
    # fragments of one object closer than the disc's span are one piece
    n, labels, stats, _ = cv2.connectedComponentsWithStats(
        cv2.dilate(mask.astype(np.uint8), disc), connectivity=8)
    labels[~mask] = 0
    h, w = mask.shape
    grown = 0
    for j in range(1, n):
        x0, y0, x1, y1 = stats[j, 0], stats[j, 1], stats[j, 0] + stats[j, 2], stats[j, 1] + stats[j, 3]
        ys, xs = np.nonzero(labels[y0:y1, x0:x1] == j)  # the piece's own bounding box
        x, y = x0 + int(xs.min()), y0 + int(ys.min())
        bw, bh = int(xs.max() - xs.min()) + 1, int(ys.max() - ys.min()) + 1
        limit = reach * max(bw, bh)
        # each piece works in a window: its reach, plus the disc's span (2 radii) so that the
        # filter inside the reach sees what it sees in the whole image
        m = int(np.ceil(limit)) + 2 * rad + 2
        win = (slice(max(0, y - m), min(h, y + bh + m)), slice(max(0, x - m), min(w, x + bw + m)))
        piece, o = labels[win] == j, other[win]
        level = float(np.median(o[piece]))
        if level <= floor:
            continue  # the photo does not confirm this piece
        above = (o > max(floor, PIECE_SHARE * level)).astype(np.float32)
        diff = cv2.filter2D(above, -1, share, borderType=cv2.BORDER_REFLECT) >= MAJORITY
        diff &= cv2.distanceTransform((~piece).astype(np.uint8), cv2.DIST_L2, 5) <= limit
        if valid is not None:
            diff &= valid[win]
        _, near = cv2.connectedComponents((diff | piece).astype(np.uint8), connectivity=8)
        touching = np.unique(near[piece])
        add = np.isin(near, touching[touching > 0]) & diff & ~out[win]
        if add.any():
            out[win] |= add
            grown += 1
    return out, grown


def key_differences(get, keys: dict[tuple[str, int], int], photos: dict
                    ) -> dict[tuple[str, int], tuple[np.ndarray, float]]:
    """Per key frame that has a photo and a render at both times: the photo's distance to the
    other time's render (:func:`difference`, [H, W]) and the floor below which it does not
    count (:func:`noise_floor`). ``get`` and ``keys`` as in :func:`complete_key_masks`;
    ``photos[(path, i)]`` the key frame's photo, linear RGB float32 at the frame's size."""
    out = {}
    for (p, i), t in sorted(keys.items()):
        if (p, i) not in photos:
            continue
        t = int(t)
        own, other = get((p, TIMES[t], i)), get((p, TIMES[1 - t], i))
        if own.get("rgb") is None or other.get("rgb") is None:
            continue
        photo = linear_to_srgb(np.asarray(photos[(p, i)], np.float32))
        if photo.shape != other["rgb"].shape:
            continue
        d_other = difference(photo, other["rgb"])
        out[(p, i)] = (d_other, noise_floor(d_other, difference(photo, own["rgb"])))
    return out


def complete_key_masks(masks: dict, get, keys: dict[tuple[str, int], int], diffs: dict,
                       reach: float, alpha_min: float, known: dict | None = None
                       ) -> tuple[int, int, int]:
    """Complete in place the masks of every key frame that has a photo (module docstring).

    ``masks[(path, i)] = (mask_t0, mask_t1)``; ``get((path, "t0" | "t1", i))`` the rendered
    frame dict (``rgb`` sRGB, optional ``alpha``); ``keys[(path, i)]`` the key frame's time;
    ``diffs``: :func:`key_differences` of the key frames' photos (a key frame without an
    entry is left as it is); ``known[(path, i)]`` (optional) bool [H, W], the pixels whose
    depth is observed at both times (:func:`gdiff.compare.coverage.observed`): never added;
    neither are the pixels of the other time's mask. Returns (key frames completed, pieces
    grown, pixels added)."""
    done = pieces = added = 0
    for (p, i), t in sorted(keys.items()):
        if (p, i) not in masks or (p, i) not in diffs:
            continue
        t = int(t)
        own, other = get((p, TIMES[t], i)), get((p, TIMES[1 - t], i))
        d_other, floor = diffs[(p, i)]
        valid = np.ones(d_other.shape, bool)
        for f in (own, other):
            if f.get("alpha") is not None:
                valid &= np.asarray(f["alpha"]) >= alpha_min
        if known is not None and (p, i) in known:  # there the IDs' masks follow the depth;
            # opened like the difference: a thin line of agreeing depth along an outline
            # (where the two depths cross) is no trusted surface
            trusted = cv2.morphologyEx(np.asarray(known[(p, i)], np.uint8), cv2.MORPH_OPEN,
                                       _disc(d_other.shape)) > 0
            valid &= ~trusted
        pair = list(masks[(p, i)])
        valid &= ~pair[1 - t]  # a difference the other time's change explains
        before = int(pair[t].sum())
        pair[t], n = grow_pieces(pair[t], d_other, floor, reach, valid)
        masks[(p, i)] = tuple(pair)
        done += 1
        pieces += n
        added += int(pair[t].sum()) - before
    return done, pieces, added
