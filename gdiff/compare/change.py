"""Instance-level change detection by comparing tracked IDs at the same pose and two times.

For every pose of a path the ID maps at t=0 and t=1 (one shared ID space, see
:mod:`gdiff.track`) are compared:

* an ID visible at one time and absent at the other, or visible at both with drastically
  different masks (IoU < ``presence_iou``), is a *candidate* change at that pose;
* the candidate is *confirmed* by evidence inside its mask that the scene really differs there:
  the fraction of pixels whose rendered depth differs between the two times by more than
  ``depth_change_rel`` (when depth exists), or a texture that does not correlate between the
  two times (:mod:`gdiff.appearance`: log-colour gradients with the shading removed, invariant
  to light direction, colour and strength); untextured regions without depth fall back to
  per-pixel chromaticity. This rejects segments that only exist because a shadow or a
  highlight moved, and confirms a replaced object whose depth barely changed;
* renders of a fitted 4D model differ between the two times also where nothing changed, so
  the evidence must be real: (a) with the training cameras (key views) only pixels whose
  surface several photos of *each* time saw are compared (:mod:`gdiff.compare.coverage`; elsewhere
  the model is unconstrained at one time) and an ID mostly outside them is not judged at that
  pose; (b) changed depth counts only in blobs wider than thin noise streaks
  (``evidence_open``); (c) a texture difference confirms only when the colours differ too,
  and not at all - with depth - for a piece split off a segment that stays at the other time
  (a fragment of an unchanged surface) or for a partly disoccluded region (a surface revealed
  by something that moved): there only a change of geometry shows a change - except for a flat
  object lying on a staying surface (observed at both times, surrounded by that surface, which
  shows at the other time, while the object stands out from it in colour): removed or added,
  its thickness is below any depth threshold, so its texture and colour decide;
* per ID, over all poses where it is visible (and judged), the share of confirmed candidates
  decides (``vote_frac``): changed IDs are changed on every frame (temporal consistency);
* an ID seen at one time only that a change of the other time hides in part at most of its
  poses was replaced in place by it (:func:`replaced`: its leftover rim is too thin for the
  depth test, and an object still standing behind a newcomer would show at the other time);
* a changed ID is ``removed`` (seen at t0 only), ``added`` (t1 only) or ``moved`` (seen at both
  at different places, or a removed/added pair with the same appearance and size standing at
  different places - a removed/added pair at one place is a replacement and keeps its types).

Masks per pose: ``mask_t0`` = changed instances visible at t0 (removed, moved away),
``mask_t1`` = changed instances visible at t1 (added, moved in), union = the change map.
"""

from __future__ import annotations

import logging
from collections import defaultdict
from dataclasses import dataclass

import cv2
import numpy as np
import pandas as pd
from scipy.optimize import linear_sum_assignment

from ..appearance import (bhattacharyya as _bhattacharyya, chroma_bin as _chroma_bin,
                          chroma_hist as _chroma_hist, linear_rgb as _linear,
                          normalised_chroma as _normalised_chroma, region_similarity,
                          texture as image_texture)
from ..errors import ConfigError
from ..io import srgb_to_linear
from ..track import (TrackFrame, TrackOptions, labels_from_instances, link_groups,
                    track_sequence, world_points)

log = logging.getLogger("gdiff.compare")

CHANGE_TYPES = ("added", "removed", "moved")

# share of a candidate's region hidden at the other time behind a nearer surface from which it
# counts as disoccluded (its texture not trusted) and, by one changed ID, as replaced by it
HIDDEN_SHARE = 0.25
# largest ratio of two objects' sizes for one to be the other moved, or its replacement
SIZE_RATIO = 1.5
# the ring around a piece of a new object (surround_colour_change) is widened up to this many
# times its width to pass the other pieces and reach the surface around the object
SURROUND_REACH = 8
# a surface lies farther at the other time when its depth grew by more than this many times the
# pose's depth noise (the median relative depth difference of the surfaces that stay)
RECEDED_NOISE = 2.0


@dataclass
class CompareOptions:
    """Options of the ``compare`` config section.

    presence_iou: an ID visible at both times whose two masks at one pose overlap with IoU
        below this is "drastically different" (candidate change).
    min_area: instance masks smaller than this (pixels) are ignored at that pose.
    depth_change_rel: a pixel's depth changed when |z0 - z1| / min(z0, z1) exceeds this.
    same_similarity: a candidate is confirmed when the texture of its changed region correlates
        less than this between the two times (:func:`gdiff.appearance.region_similarity`;
        lighting-invariant).
    min_texture: RMS log-colour gradient below which a region is untextured (no texture test).
    chroma_tol: a pixel's chromaticity (grey-world normalised, L1) changed above this (fallback
        for untextured regions without depth).
    ncc_min: local normalised cross-correlation of log intensity (9x9) below this on textured
        pixels counts as an appearance change (same fallback).
    min_evidence: a candidate is confirmed at a pose when at least this fraction of its mask
        changed depth (or, untextured and without depth, chromaticity).
    vote_frac: an ID is changed when confirmed at >= this fraction of the poses where visible.
    moved_similarity: a removed and an added instance are one moved object when the
        Bhattacharyya coefficient of their chromaticity histograms is >= this and their metric
        sizes agree within a factor 1.5.
    evidence_open: changed-depth pixels count as evidence only inside blobs at least this
        fraction of the image's longer side wide (morphological opening); thinner structures
        (depth noise of a fitted model along texture edges and silhouettes) do not. 0 disables.
    texture_color_similarity: a candidate confirmed by texture alone must also differ in
        colour: the Bhattacharyya coefficient of the chromaticity histograms of its region at
        the two times below this (1 disables this requirement).
    min_observed: with key views (training cameras, see :mod:`gdiff.compare.coverage`) an ID is judged
        at a pose only when at least this fraction of its mask there is seen by a key view of
        each time; the evidence is measured on those pixels only (the depth evidence on the
        observed ones).
    observed_depth_tol: relative depth agreement for a key view to see a surface point.
    observed_min_views: key views of a time that must see a point for it to be observed (its
        rendered depth trusted; :func:`pose_stats`).
    observed_min_parallax: ... and two of them from directions at least this many degrees
        apart (seen from one direction only, a surface's depth is not determined: a fitted
        model may put it anywhere along the rays).
    observed_max_views: per frame only the key views of each time that see most of its
        surface are used, at most this many (:func:`gdiff.compare.coverage.nearest_views`; keeps the
        cost per frame independent of the number of photos). 0 uses every key view.
    observed_grid: coverage is tested on a grid of about this many pixels along each frame's
        longer side (every k-th pixel of every k-th row, k = longer side // observed_grid,
        at least 1; each k x k block takes its tested pixel's answer): coverage changes over
        many pixels, and the test's cost grows with the pixels tested. 0 tests every pixel.
    observed_window: a key view sees a point when the point's depth lies within the range of
        depths the view renders within this many pixels of the point's pixel (a fraction of
        the view's longer side, rounded; widened by ``observed_depth_tol``), not at that one
        pixel only: a fit to few photos renders a surface's depth with noise between
        neighbouring pixels and between views (:class:`gdiff.compare.coverage.DepthView`).
        0 tests the one pixel.
    geometry: also mark surfaces that appear or vanish in 3D (depth voted over all poses,
        :mod:`gdiff.compare.geometry`), whatever their IDs: objects the segmenter merged with
        their support.
    geometry_voxel_px: voxel side of that vote, in pixels at the median depth of the frames.
    geometry_vote: a voxel is changed when flagged at >= this fraction of the poses seeing it.
    geometry_min_poses: ... and at this many poses at least.
    geometry_min_object: smallest changed object kept, as a fraction of the image area at the
        median depth.
    flat: also mark surfaces that stay in place but whose appearance changed, voted in 3D the
        same way (:func:`gdiff.compare.geometry.flat_flags`): flat objects (a sheet, a book, a
        poster) put onto or taken off a surface that the segmenter merged with them. Only
        when the light stayed the same: see ``flat_max_rate``.
    flat_max_rate: when more than this share of the surfaces judged in 3D (seen from
        ``geometry_min_poses`` poses) changed appearance, the change is taken to be one of
        light (moved shadows, another sun) and the flat evidence is not used.
    flat_photo_contrast: a component of the flat evidence is kept only when the training
        photos of the two times differ there by at least this many times their spread within
        a time, in brightness or chromaticity (:mod:`gdiff.compare.photos`): the fit renders
        some unchanged surfaces differently at the two times, the photos show them alike.
        The same test decides for a region of the ID comparison that only its colours would
        confirm (depth not trusted, a sparse capture: see :func:`pose_stats`).
        0: not checked (also when the stage has no photos).
    confirm_support: a changed object of the ID comparison is kept only when at least this
        share of its pixels lie within two voxels of the 3D evidence (the geometry evidence:
        its shape changed; and, when the light stayed the same, the flat evidence: its
        surface's appearance changed) ...
    confirm_colour: ... or its colour relative to its surroundings changed by at least this
        (``colour`` of the changes table, :func:`surround_colour_change`;
        :func:`gdiff.compare.stage._confirm_by_evidence`). ``confirm_support`` 0 keeps them
        all.
    confirm_photo: ... or the training photos of both visits show it changed: at least half
        of its pixels at the key poses of its own time differ from the other time's render by
        at least this many times the photo's noise floor (:mod:`gdiff.compare.complete`), and
        so do at least half of them at the key poses of the other time, where the other
        visit's photos are compared with this time's render
        (:func:`gdiff.compare.stage._confirm_by_evidence`; only pixels whose surface photos of
        both times show count; and the ID comparison confirmed it at two poses or more). Not
        when the light changed (a photo then differs from the other time's render wherever
        the light did). 0: off.
    confirm_colour_points: an object kept by its colour alone (``confirm_colour``) is dropped
        when fewer than this share of its surface points at the key poses of its own time look
        different in the other visit's photos, against the unchanged surface of the same
        photos (``photo_points`` of the changes table,
        :func:`gdiff.compare.stage._photo_points`): the rendered colours of the other time at
        a pose its photos did not see are a guess, the photos are not. Not when the light
        changed. 0: off.
    confirm_colour_own_view: an object kept by its colour alone (``confirm_colour``) must show
        at the key poses of its own time (where that time's photos were taken, so its render
        there reproduces a photo) on at least ``min_area`` pixels a photo of each time shows
        (``own_px`` of the changes table, :func:`gdiff.compare.stage._own_view`). An object of
        one time that shows only from the other visit's poses is that time's model seen from
        where none of its photos was taken: on a sparse capture such a render is blurred or
        doubled, and its colour relative to its surroundings differs from the other time's by
        chance. Its shape (``confirm_support``) still counts. False: off.
    confirm_colour_lined_up: an object kept by its colour alone (``confirm_colour``) that the ID
        comparison found at one pose only (each of its IDs shows at that pose alone), a key
        pose whose t0 and t1 renders do not line up (``lined_up`` false, see
        ``lineup_share``), is dropped unless the photo taken there shows it changed too
        (``photo`` at least one half, see ``confirm_photo``): the two models disagree there on
        where things are, so its colour and its surroundings' are compared with another
        surface's. Its shape (``confirm_support``) still counts. Not when the light changed
        (moved shadows move features too). False: off.
    surround_width: width of the ring around a region whose mean colour stands for the local
        light in :func:`surround_colour_change`, as a fraction of the image's longer side.
    spread_vote: a changed object's surface is marked at every pose, also where the segmenter
        merged it into another ID: the voxels (``geometry_voxel_px``) that at least this share
        of the key frames looking at them show as pixels of changed IDs, and at least two
        (:mod:`gdiff.compare.spread`). 0: off.
    complete_reach: at a key pose, a piece of the mask that the training photo confirms
        (it differs there from the other time's render) grows into the pixels next to it
        where the photo differs as much, up to this many times the piece's size away
        (:mod:`gdiff.compare.complete`): an object cut into pieces is marked whole where the
        partition learns from. Only where the depth of both times is not observed, and not
        under a change of light. 0: off.
    photo_agree: at a key pose, the mask of the photo's own time loses the pixels whose
        surface a photo of the other visit shows alike: matched by optical flow both ways, on
        the pixel's ray, and within this many times the pair's median colour difference
        (:mod:`gdiff.compare.agree`). Where the photos of both visits agree nothing changed,
        whatever the other time's model renders there. 0: off.
    lineup_share: a key pose whose t0 and t1 renders line up on less than this share of the
        scene's median (the share of feature matches in place, :mod:`gdiff.compare.lineup`)
        is named in the log and ``coverage.csv`` (``lined_up`` false): the models of the two
        visits disagree there on where things are, and the ID comparison's marks there are
        uncertain (see ``confirm_colour_lined_up``). 0: not checked.
    """

    presence_iou: float = 0.3
    min_area: int = 24
    depth_change_rel: float = 0.05
    chroma_tol: float = 0.08
    ncc_min: float = 0.5
    min_evidence: float = 0.3
    vote_frac: float = 0.5
    moved_similarity: float = 0.85
    same_similarity: float = 0.35
    min_texture: float = 0.03
    evidence_open: float = 0.02
    texture_color_similarity: float = 0.85
    min_observed: float = 0.5
    observed_depth_tol: float = 0.05
    observed_min_views: int = 3
    observed_min_parallax: float = 10.0
    observed_max_views: int = 8
    observed_grid: int = 160
    observed_window: float = 0.005
    geometry: bool = True
    geometry_voxel_px: float = 4.0
    geometry_vote: float = 0.5
    geometry_min_poses: int = 3
    geometry_min_object: float = 0.003
    flat: bool = True
    flat_max_rate: float = 0.05
    flat_photo_contrast: float = 3.0
    confirm_support: float = 0.5
    confirm_colour: float = 0.25
    confirm_photo: float = 2.0
    confirm_colour_points: float = 0.2
    confirm_colour_own_view: bool = True
    confirm_colour_lined_up: bool = True
    surround_width: float = 0.05
    spread_vote: float = 0.3
    complete_reach: float = 1.0
    photo_agree: float = 3.0
    lineup_share: float = 0.5

    def observed_step(self, height: int, width: int) -> int:
        """Pixel step of the coverage test on a ``height`` x ``width`` frame (see
        ``observed_grid``)."""
        return max(1, max(height, width) // self.observed_grid) if self.observed_grid else 1

    def __post_init__(self):
        if not 0 <= self.observed_min_parallax < 180:
            raise ConfigError("config key 'compare.observed_min_parallax' must lie in [0, 180) "
                              "degrees")
        if self.observed_grid < 0:
            raise ConfigError("config key 'compare.observed_grid' must be >= 0 (0: every pixel)")
        if not 0 <= self.observed_window < 0.5:
            raise ConfigError("config key 'compare.observed_window' must lie in [0, 0.5) (a "
                              "fraction of the frame's longer side; 0: the one pixel)")
        if self.observed_max_views < 0:
            raise ConfigError("config key 'compare.observed_max_views' must be >= 0 (0: every "
                              "key view)")
        if self.evidence_open < 0 or self.observed_depth_tol <= 0 or self.observed_min_views < 1:
            raise ConfigError("config keys 'compare.evidence_open' (>= 0), "
                              "'compare.observed_depth_tol' (> 0) and "
                              "'compare.observed_min_views' (>= 1) are out of range")
        if not 0 <= self.confirm_colour <= 2:
            raise ConfigError("config key 'compare.confirm_colour' must lie in [0, 2]")
        if self.confirm_photo < 0:
            raise ConfigError("config key 'compare.confirm_photo' must be >= 0")
        if not 0 <= self.lineup_share <= 1:
            raise ConfigError("config key 'compare.lineup_share' must lie in [0, 1] (0: not "
                              "checked)")
        if not 0 <= self.confirm_colour_points <= 1:
            raise ConfigError("config key 'compare.confirm_colour_points' must lie in [0, 1]")
        if not 0 < self.surround_width < 0.5:
            raise ConfigError("config key 'compare.surround_width' must lie in (0, 0.5)")
        if not 0 < self.flat_max_rate <= 1:
            raise ConfigError("config key 'compare.flat_max_rate' must lie in (0, 1]")
        if self.complete_reach < 0:
            raise ConfigError("config key 'compare.complete_reach' must be >= 0 (0: the key "
                              "views' masks are not completed)")
        if self.photo_agree < 0:
            raise ConfigError("config key 'compare.photo_agree' must be >= 0 (0: the photos of "
                              "the two visits are not matched)")
        if self.flat_photo_contrast < 0:
            raise ConfigError("config key 'compare.flat_photo_contrast' must be >= 0 (0: the "
                              "photos are not asked)")
        if self.geometry_voxel_px <= 0 or self.geometry_min_poses < 1 \
                or not 0 <= self.geometry_min_object < 1:
            raise ConfigError("config keys 'compare.geometry_voxel_px' (> 0), "
                              "'compare.geometry_min_poses' (>= 1) and "
                              "'compare.geometry_min_object' (in [0, 1)) are out of range")
        for k in ("presence_iou", "min_evidence", "vote_frac", "moved_similarity",
                  "same_similarity", "min_observed", "texture_color_similarity",
                  "geometry_vote", "confirm_support", "spread_vote"):
            if not 0.0 <= getattr(self, k) <= 1.0:
                raise ConfigError(f"config key 'compare.{k}' must lie in [0, 1]")


# ------------------------------------------------------------------------------------------
# per-pixel evidence
# ------------------------------------------------------------------------------------------

def depth_change(depth0: np.ndarray, depth1: np.ndarray, rel: float) -> np.ndarray:
    """bool [H, W]: z-depth differs by more than ``rel`` (relative to the nearer depth), or a
    surface exists at only one of the times."""
    z0 = np.asarray(depth0, np.float64)
    z1 = np.asarray(depth1, np.float64)
    v0 = np.isfinite(z0) & (z0 > 0)
    v1 = np.isfinite(z1) & (z1 > 0)
    both = v0 & v1
    out = v0 ^ v1
    zmin = np.where(both, np.minimum(z0, z1), 1.0)
    out[both] = (np.abs(z0 - z1)[both] > rel * zmin[both])
    return out


def coherent(mask: np.ndarray, width_frac: float) -> np.ndarray:
    """``mask`` bool [H, W] opened (eroded, then dilated) by a square of odd side
    ~``width_frac`` x max(H, W) pixels (at least 3): only blobs at least that wide remain.
    ``width_frac`` <= 0 returns the mask unchanged."""
    if width_frac <= 0:
        return mask
    k = max(3, 2 * int(round(width_frac * max(mask.shape) / 2)) + 1)
    return cv2.morphologyEx(mask.astype(np.uint8), cv2.MORPH_OPEN,
                            np.ones((k, k), np.uint8)) > 0


def _local_ncc(a: np.ndarray, b: np.ndarray, k: int = 7) -> tuple[np.ndarray, np.ndarray]:
    """Local normalised cross-correlation [H, W] of two images over k x k windows, and the
    texture strength min(std_a, std_b) [H, W]."""
    def box(x):
        return cv2.blur(x, (k, k))

    ma, mb = box(a), box(b)
    va = np.maximum(box(a * a) - ma * ma, 0)
    vb = np.maximum(box(b * b) - mb * mb, 0)
    cov = box(a * b) - ma * mb
    ncc = cov / np.sqrt(np.maximum(va * vb, 1e-12))
    return ncc, np.sqrt(np.minimum(va, vb))


def appearance_change(rgb0: np.ndarray, rgb1: np.ndarray, chroma_tol: float,
                      ncc_min: float) -> np.ndarray:
    """bool [H, W]: illumination-invariant appearance differs between two images of one pose.

    On textured pixels (local std of log intensity > 0.1 in both images) the structure decides:
    local normalised cross-correlation of log intensity (9 x 9) below ``ncc_min`` (a gain
    change - shading, a shadow's interior, exposure - keeps the correlation). On untextured
    pixels the grey-world-normalised chromaticity decides (L1 difference > ``chroma_tol``).
    Inputs sRGB float32 [H, W, 3]. The log has a floor (+0.02) so sensor-level noise in dark
    pixels is not texture.
    """
    c0, w0 = _normalised_chroma(rgb0)
    c1, w1 = _normalised_chroma(rgb1)
    dc = np.abs(c0 - c1).sum(-1) * np.minimum(w0, w1)
    l0 = np.log(srgb_to_linear(rgb0).mean(-1) + 0.02).astype(np.float32)
    l1 = np.log(srgb_to_linear(rgb1).mean(-1) + 0.02).astype(np.float32)
    ncc, tex = _local_ncc(l0, l1, 9)
    textured = tex > 0.1
    return np.where(textured, ncc < ncc_min, dc > chroma_tol)


# ------------------------------------------------------------------------------------------
# per-pose comparison and per-ID decision
# ------------------------------------------------------------------------------------------

def _id_chroma_hists(ids: np.ndarray, chroma: tuple[np.ndarray, np.ndarray], bins: int = 8
                     ) -> np.ndarray:
    """:func:`_chroma_hist` of every ID of ``ids`` (int [H, W]) at once: float64
    [max ID + 1, bins, bins], row ``i`` the histogram of ``ids == i`` (the same bins and
    pixels; ``chroma``: the image's :func:`_normalised_chroma` pair)."""
    c, w = chroma
    sel = (w > 0.3) & (ids > 0)
    n = int(ids.max()) + 1 if ids.size else 1
    key = ids[sel].astype(np.int64) * (bins * bins) + _chroma_bin(c[sel], bins)
    return np.bincount(key, minlength=n * bins * bins).reshape(n, bins, bins).astype(np.float64)


def _dilate_disc(mask: np.ndarray, width: int) -> np.ndarray:
    """bool [H, W]: ``mask`` (bool [H, W]) dilated by OpenCV's elliptic structuring element of
    side ``2 * width + 1`` (``cv2.dilate`` with ``cv2.getStructuringElement(MORPH_ELLIPSE)``,
    the same pixels), as the union over the element's rows of the mask dilated along the row by
    that row's span and shifted by its offset: a few one-row dilations instead of one by the
    whole disc, whose cost grows with its area."""
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * width + 1, 2 * width + 1))
    m = mask.astype(np.uint8)
    h = m.shape[0]
    out = np.zeros(m.shape, bool)
    rows: dict[int, np.ndarray] = {}
    for v in range(-width, width + 1):
        half = int(kernel[v + width].sum()) // 2  # each row is one centred run
        if half not in rows:
            rows[half] = cv2.dilate(m, np.ones((1, 2 * half + 1), np.uint8)) > 0
        r = rows[half]
        # out[y] |= r[y + v]
        if v >= 0:
            out[:h - v] |= r[v:]
        else:
            out[-v:] |= r[:h + v]
    return out


def surround_colour_change(rgb0: np.ndarray, rgb1: np.ndarray, region: np.ndarray,
                           exclude: np.ndarray, width: int, min_px: int = 1,
                           reach: int = 1,
                           linear: tuple[np.ndarray, np.ndarray] | None = None) -> float:
    """How much the colour of ``region`` (bool [H, W]) changed between the two times once each
    time's local light is divided out: the L1 distance (0: the same, at most 2) between the
    chromaticities (r, g, b summing to 1) of the ratio, per channel in linear light, of the
    region's mean colour to the mean colour of a ring ``width`` pixels wide around it
    (``exclude`` bool [H, W] left out of the ring), in ``rgb0`` and in ``rgb1`` (sRGB
    [H, W, 3]).

    A change of light falls on an object and on the surface next to it alike (a moved
    shadow, a warmer sun, a dimmer ambient; means are linear, so even a pattern of shadows
    over both keeps the ratio); the ratio of their colours keeps the object's own colour.

    With ``reach`` > 1, a ring left with fewer than ``min_px`` pixels (``exclude`` covers the
    region's neighbourhood) is widened, doubling its width, up to ``reach`` x ``width``: the
    nearest surface that is not excluded stands for the light. NaN when the region or the
    widest ring has fewer than ``min_px`` pixels, or the ring is black. ``linear``
    (optional): the two images' linear values as float64 (:func:`_linear`), when the caller
    has them."""
    ys, xs = np.nonzero(region)
    if len(ys) < max(min_px, 1):
        return float("nan")
    h, w = region.shape
    far = width * max(int(reach), 1)
    sl = (slice(max(0, ys.min() - far - 1), min(h, ys.max() + far + 2)),
          slice(max(0, xs.min() - far - 1), min(w, xs.max() + far + 2)))
    reg = region[sl]
    free = ~reg & ~exclude[sl]
    ring = _dilate_disc(reg, width) & free
    k, dist = width, None
    while ring.sum() < max(min_px, 1):
        if k >= far:
            return float("nan")
        k = min(2 * k, far)
        if dist is None:  # distance of every pixel of the window to the region (0 on it)
            dist = cv2.distanceTransform((~reg).astype(np.uint8), cv2.DIST_L2,
                                         cv2.DIST_MASK_PRECISE)
        ring = free & (dist <= k)
    chroma = []
    for k, rgb in enumerate((rgb0, rgb1)):
        lin = _linear(rgb[sl]) if linear is None else linear[k][sl]
        light = lin[ring].mean(0)
        if light.sum() < 1e-3:
            return float("nan")  # the surroundings are black at this time
        q = lin[reg].mean(0) / np.maximum(light, 1e-6)
        chroma.append(q / max(q.sum(), 1e-9))
    return float(np.abs(chroma[0] - chroma[1]).sum())


def pose_stats(ids0: np.ndarray, ids1: np.ndarray, o: CompareOptions,
               rgb0: np.ndarray | None = None, rgb1: np.ndarray | None = None,
               depth0: np.ndarray | None = None, depth1: np.ndarray | None = None,
               focal: float | None = None, camera=None, observed0: np.ndarray | None = None,
               observed1: np.ndarray | None = None, seen0: np.ndarray | None = None,
               seen1: np.ndarray | None = None,
               appearance: np.ndarray | None = None,
               points: tuple[np.ndarray, np.ndarray] | None = None,
               photos_differ=None) -> dict[int, dict]:
    """Compare the ID maps int [H, W] of one pose at t0 and t1.

    Returns, per ID visible at this pose: ``area0``, ``area1`` (pixels), ``candidate`` (absent
    at one time or IoU < presence_iou), ``evidence`` (fraction of the candidate's changed region
    whose depth changed; NaN without depth), ``similarity`` (texture similarity of that region
    between the two times, :mod:`gdiff.appearance`; NaN when untextured or without images),
    ``confirmed``, ``hist`` (chromaticity histogram, for moved pairing), ``size`` (metric size
    sqrt(area) * z / f when depth and ``focal`` are known, else sqrt(area) in pixels) and
    ``pos`` (median world point [3] with depth and ``camera``, else the mask centroid in
    pixels; same units as ``size``), ``observed`` (the ID can be judged at this pose) and,
    for a candidate absent at the other time, ``hidden_by`` / ``hidden``: the ID of the other
    time that hides most of its region there behind a nearer surface, and the share of the
    region it hides (0 / 0.0 when nothing does, or when that share reaches
    :data:`HIDDEN_SHARE` but the rest of the region does not show a farther surface at the
    other time, :func:`_receded`: the candidate may still stand there, relit or re-segmented,
    behind the newcomer; with depth only).

    A candidate is confirmed when its depth changed (``evidence >= min_evidence``) or its
    texture differs between the times (``similarity < same_similarity``); without depth an
    untextured candidate falls back to the per-pixel chromaticity test (``chroma_tol``). With
    depth, pixels of the candidate that are hidden at the other time behind a nearer surface
    are left out of both tests (the instance may still stand behind the newcomer); a candidate
    hidden so for more than three quarters is not a candidate at this pose.

    Depth evidence counts changed-depth pixels inside coherent blobs only
    (:func:`coherent`, ``evidence_open``). ``observed0`` / ``observed1`` (bool [H, W], see
    :mod:`gdiff.compare.coverage`): pixels whose surface a photo of that time saw. An ID whose mask is
    observed at both times for less than ``min_observed`` is not judged at this pose
    (``observed`` False: no candidate, left out of the vote); otherwise its evidence is measured
    on the pixels observed at both times. ``seen0`` / ``seen1`` (bool [H, W], optional, with
    the ``observed`` masks): pixels whose surface at least one photo of that time saw, a
    superset of the observed ones. With them the ID comparison is judged on the pixels seen at
    both times (its share decides whether the ID is judged), and the rendered depth is trusted
    only on the observed pixels: there alone it decides whether a region is hidden at the
    other time, changed depth, or is the same surface. A region only seen (a sparse capture:
    an object one photo shows, whose depth the fit could put anywhere along that photo's rays)
    is judged by its appearance. At a pose of a sparse capture (depth trusted on less than
    half of what the photos show) a region counts as only seen unless its depth is trusted
    on at least half of its pixels: a few trusted pixels on its rim, often the surface next
    to it, do not make it "the same surface". There its colours confirm it (the
    chromaticity histogram test below, ``texture_color_similarity``, without the texture
    test: a box the fit draws faintly from one or two photos keeps part of the texture
    behind it) where the training photos of the two times differ there too:
    ``photos_differ`` (optional) is called with the region (bool [H, W]) and returns True,
    False or None (cannot tell; see :func:`gdiff.compare.photos.region_photos_differ`); only
    True confirms. The renders of glass, metal and translucent plastic differ between the
    times in colour as well, the photos of them do not. Without ``photos_differ`` the colours
    alone decide.
    ``appearance`` (bool [H, W], optional): the pose's
    :func:`appearance_change` of ``rgb0`` and ``rgb1`` when the caller has it already;
    ``points`` (optional): the world points [H, W, 3] of ``depth0`` and ``depth1``
    (:func:`gdiff.track.world_points` with ``camera``), likewise.

    Texture-only confirmation also needs different colours (Bhattacharyya coefficient of the
    region's chromaticity histograms < ``texture_color_similarity``) and, with depth, is not
    used when half of the region lies, at the other time, on IDs that stay at this pose
    (visible at both times with IoU >= ``presence_iou``), when the depth of half of it did not
    change (``depth_change_rel``: the surface is where it was, e.g. a floor re-segmented
    because shadows or glare moved) unless another ID of the same footprint took its place
    at the other time (:func:`_swapped`: an object replaced by one of the same shape), or
    when more than a quarter of it is hidden at the other time behind a nearer surface
    (disoccluded). Exception to the first two rules: with key-view coverage, a region
    surrounded by the staying surface that shows that surface's colours at the other time and
    stands out from it at its own time is a flat object removed from or put onto it
    (:func:`_support_shows`) and may be confirmed so.
    """
    has_depth = depth0 is not None and depth1 is not None
    has_rgb = rgb0 is not None and rgb1 is not None
    cache: dict[str, np.ndarray] = {}
    if appearance is not None:
        cache["chroma"] = np.asarray(appearance, bool)
    if points is not None:
        cache["P0"], cache["P1"] = points

    def raw_depth_change():
        if "raw" not in cache:
            cache["raw"] = depth_change(depth0, depth1, o.depth_change_rel)
        return cache["raw"]

    def ev_depth():
        if "depth" not in cache:
            cache["depth"] = coherent(raw_depth_change(), o.evidence_open)
        return cache["depth"]

    def nearer():
        """(t1 surface nearer than t0, t0 nearer than t1), bool [H, W] each."""
        if "near1" not in cache:
            z0 = np.where(np.isfinite(depth0) & (depth0 > 0), depth0, np.inf)
            z1 = np.where(np.isfinite(depth1) & (depth1 > 0), depth1, np.inf)
            cache["near1"] = z1 < z0 * (1 - o.depth_change_rel)
            cache["near0"] = z0 < z1 * (1 - o.depth_change_rel)
        return cache["near1"], cache["near0"]

    def grads():
        if "g0" not in cache:
            cache["g0"] = image_texture(rgb0, o.min_texture)
            cache["g1"] = image_texture(rgb1, o.min_texture)
        return cache["g0"], cache["g1"]

    def points(time: int):
        """World points [H, W, 3] of the depth at ``time``, or None."""
        z = depth0 if time == 0 else depth1
        if z is None or camera is None:
            return None
        if f"P{time}" not in cache:
            cache[f"P{time}"] = world_points(z, camera)
        return cache[f"P{time}"]

    def linear(time: int):
        if f"lin{time}" not in cache:
            cache[f"lin{time}"] = _linear(rgb0 if time == 0 else rgb1)
        return cache[f"lin{time}"]

    def chroma(time: int):
        if f"c{time}" not in cache:
            cache[f"c{time}"] = _normalised_chroma(rgb0 if time == 0 else rgb1, linear(time))
        return cache[f"c{time}"]

    def id_hists(time: int):
        """Every ID's chromaticity histogram at ``time`` (:func:`_id_chroma_hists`)."""
        if f"h{time}" not in cache:
            cache[f"h{time}"] = _id_chroma_hists(ids0 if time == 0 else ids1, chroma(time))
        return cache[f"h{time}"]

    present = (np.unique(ids0), np.unique(ids1))  # the IDs shown at each time

    def only(time: int):
        """bool [H, W]: the pixels of the IDs that show at ``time`` and not at the other time
        at this pose."""
        if f"only{time}" not in cache:
            u = np.setdiff1d(present[time], present[1 - time])
            cache[f"only{time}"] = np.isin(ids0 if time == 0 else ids1, u[u != 0])
        return cache[f"only{time}"]

    def ev_chroma():
        if "chroma" not in cache:
            cache["chroma"] = appearance_change(rgb0, rgb1, o.chroma_tol, o.ncc_min)
        return cache["chroma"]

    known = None  # depth trusted (observed at both times)
    if observed0 is not None and observed1 is not None:
        known = np.asarray(observed0, bool) & np.asarray(observed1, bool)
    visible = known  # the ID comparison judged (seen by a photo at both times)
    if known is not None and seen0 is not None and seen1 is not None:
        visible = np.asarray(seen0, bool) & np.asarray(seen1, bool)
    trusted = known if known is not None else True
    # a pose of a sparse capture: its depth is trusted on less than half of what the photos show
    sparse = bool(known is not None and visible is not None and visible.any()
                  and known[visible].mean() < 0.5)
    cont0, cont1 = _continuing(ids0, ids1, o)
    out: dict[int, dict] = {}
    labels = np.union1d(*present)
    boxes = _boxes(ids0, ids1)
    for t in labels[labels != 0]:
        # each ID is measured inside its bounding box (both times): most IDs at a pose are
        # not candidates and need only their areas, overlap, coverage and summaries
        sl = boxes[int(t)]
        c0, c1 = ids0[sl] == t, ids1[sl] == t
        a0, a1 = int(c0.sum()), int(c1.sum())
        a0 = a0 if a0 >= o.min_area else 0
        a1 = a1 if a1 >= o.min_area else 0
        if a0 == 0 and a1 == 0:
            continue
        cand = True
        if a0 and a1:
            cand = (c0 & c1).sum() / (c0 | c1).sum() < o.presence_iou
        seen = True
        if visible is not None:
            known_box = visible[sl]
            seen = bool(known_box[(c0 if a0 else False) | (c1 if a1 else False)].mean()
                        >= o.min_observed)
            if not seen:
                cand = False  # the model is not constrained there at one of the times
        if cand:  # full-size masks for the evidence tests (they look around the region)
            m0, m1 = _embed(c0, sl, ids0.shape), _embed(c1, sl, ids1.shape)
            if a0 and a1:
                region0, region1 = m0 & ~m1, m1 & ~m0
            else:
                region0, region1 = (m0, np.zeros_like(m0)) if a0 else (np.zeros_like(m1), m1)
            if visible is not None:
                region0, region1 = region0 & visible, region1 & visible
        evidence, sim, confirmed = float("nan"), float("nan"), bool(cand)
        disoccluded = only_seen = False
        hidden_by, hidden = 0, 0.0
        if cand and (has_depth or has_rgb):
            region = region0 | region1
            if has_depth:
                # pixels hidden at the other time behind a nearer surface say nothing about
                # the instance (it may stand behind the newcomer): leave them out
                near1, near0 = nearer()
                region = (region0 & ~(near1 & trusted)) | (region1 & ~(near0 & trusted))
                full = (region0 | region1).sum()
                if full and not (a0 and a1):  # absent at the other time: what hides it there
                    other = ids1 if a0 else ids0
                    behind = (region0 & near1 & trusted) | (region1 & near0 & trusted)
                    cover = other[behind]
                    cover = cover[cover != 0]
                    if cover.size:
                        vals, counts = np.unique(cover, return_counts=True)
                        k = int(np.argmax(counts))
                        hidden_by, hidden = int(vals[k]), float(counts[k] / full)
                    # gone, not only covered: where it is not hidden, the other time shows
                    # what stood behind it (tested only where the share would count, see
                    # decide)
                    if hidden >= HIDDEN_SHARE:
                        if "noise" not in cache:
                            cache["noise"] = _depth_noise(ids0, ids1, depth0, depth1, cont0,
                                                          cont1, known)
                        own, there = (depth0, depth1) if a0 else (depth1, depth0)
                        if not _receded(own, there, region & trusted, cache["noise"]):
                            hidden_by, hidden = 0, 0.0
                if region.sum() < 0.25 * full:
                    cand = confirmed = False  # mostly hidden at the other time: undecidable
                # partly hidden: a surface revealed (or covered) by something that moved; next
                # to the occluder's outline the two images show different things anyway, so
                # only the depth can tell whether this instance itself changed
                disoccluded = region.sum() < (1 - HIDDEN_SHARE) * full
            if cand and has_depth:
                depth_region = region & trusted
                evidence = (float(ev_depth()[depth_region].mean()) if depth_region.any()
                            else 0.0 if not region.any() else float("nan"))
            texture_ok = True
            if cand and has_depth and region.any():
                # a piece split off a segment that stays at the other time (same place):
                # the surface is still there, only a change of geometry shows a change
                on_cont = ((region0 & region & cont1) | (region1 & region & cont0)).sum()
                # likewise a region whose surface did not move, unless another instance took
                # its place (an object swapped for one of the same shape): a lighting change
                # re-segments a floor under moved shadows or glare, but leaves its depth. On
                # a sparse capture the depth says so only where trusted on half the region;
                # otherwise the region is only seen and its colours judge it
                depth_judges = bool(depth_region.any()) and (
                    not sparse or depth_region.sum() >= 0.5 * region.sum())
                only_seen = sparse and not depth_judges
                same_surface = on_cont >= 0.5 * region.sum() or (
                    depth_judges and (~raw_depth_change()[depth_region]).mean() >= 0.5
                    and not _swapped(ids0, ids1, t, region0 & region, region1 & region, o))
                texture_ok = not (disoccluded or (same_surface and not (has_rgb and _support_shows(
                    region0 & region, region1 & region, cont0, cont1, chroma, o, visible))))
            if cand and has_rgb and texture_ok:
                sim = region_similarity(*grads(), region, o.min_texture)
            if cand:
                differs = sim < o.same_similarity
                by_colour = not differs and only_seen and texture_ok and has_rgb
                differs = differs or by_colour
                if differs and o.texture_color_similarity < 1:
                    colour = _bhattacharyya(_chroma_hist(chroma(0), region),
                                            _chroma_hist(chroma(1), region))
                    differs = colour < o.texture_color_similarity
                if differs and by_colour and photos_differ is not None:
                    # asked last: it projects the region into the photos
                    differs = photos_differ(region) is True
                confirmed = bool((has_depth and evidence >= o.min_evidence) or differs)
            if cand and np.isnan(evidence) and np.isnan(sim) and has_rgb and region.any():
                evidence = float(ev_chroma()[region].mean())
                confirmed = evidence >= o.min_evidence
        surround = float("nan")
        if cand and confirmed and has_rgb and region.any():
            width = max(2, int(round(o.surround_width * max(ids0.shape))))
            if bool(a0) != bool(a1) and sparse:
                # the ring stands for the staying surface around the region: other IDs that
                # show at this time only (pieces of the same new object, cut apart by the
                # segmenter) are left out of it, and it is widened up to SURROUND_REACH
                # times to reach the surface around them. Only at a pose whose depth is
                # mostly not trusted (a sparse capture): there the colour is all that can
                # tell an object, while with depth the 3D evidence judges objects and the
                # ring stays next to the region (a moved shadow cuts a surface into pieces
                # too, and only the light right next to a piece is its light)
                surround = surround_colour_change(rgb0, rgb1, region, m0 | m1 | only(
                    0 if a0 else 1), width, o.min_area, reach=SURROUND_REACH,
                    linear=(linear(0), linear(1)))
            if np.isnan(surround):
                surround = surround_colour_change(rgb0, rgb1, region, m0 | m1, width,
                                                  o.min_area, linear=(linear(0), linear(1)))
        rec = dict(area0=a0, area1=a1, candidate=bool(cand), evidence=evidence,
                   similarity=sim, confirmed=confirmed, observed=seen, surround=surround,
                   hidden_by=hidden_by, hidden=hidden)
        time = 0 if a0 else 1
        rgb, m, z = (rgb0, c0, depth0) if a0 else (rgb1, c1, depth1)
        if rgb is not None:
            rec["hist"] = id_hists(time)[int(t)].copy()
        else:
            rec["hist"] = None
        size = np.sqrt(m.sum())
        if z is not None and focal:
            size = size * float(np.median(z[sl][m])) / focal
        rec["size"] = float(size)
        P = points(time)
        rec["pos"] = _position(m, P[sl] if P is not None else None, (sl[0].start, sl[1].start))
        rec["pos_size"] = rec["size"] if len(rec["pos"]) == 3 else float(np.sqrt(m.sum()))
        out[int(t)] = rec
    return out


def surfaces(depth0: np.ndarray, depth1: np.ndarray, known: np.ndarray | None
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """float64 z-depths [H, W] at t0 and t1 and bool [H, W] where each has a surface (finite,
    positive depth), restricted to ``known`` when given."""
    z0 = np.asarray(depth0, np.float64)
    z1 = np.asarray(depth1, np.float64)
    v0 = np.isfinite(z0) & (z0 > 0)
    v1 = np.isfinite(z1) & (z1 > 0)
    if known is not None:
        v0, v1 = v0 & known, v1 & known
    return z0, z1, v0, v1


def _depth_noise(ids0: np.ndarray, ids1: np.ndarray, depth0: np.ndarray, depth1: np.ndarray,
                 cont0: np.ndarray, cont1: np.ndarray, known: np.ndarray | None) -> float:
    """The depth noise of one pose: the median of ``|z1 - z0| / z0`` over the pixels that
    show, at both times, the same ID of those that stay (``cont0`` / ``cont1``, see
    :func:`_continuing`), where both times have a surface (:func:`surfaces`, within
    ``known``, bool [H, W], when given); NaN when there are none. Unitless (relative depth)."""
    z0, z1, v0, v1 = surfaces(depth0, depth1, known)
    m = cont0 & cont1 & (ids0 == ids1) & v0 & v1
    if not m.any():
        return float("nan")
    return float(np.median(np.abs(z1[m] - z0[m]) / z0[m]))


def _receded(own: np.ndarray, there: np.ndarray, rest: np.ndarray, noise: float) -> bool:
    """True when the pixels ``rest`` (bool [H, W]) of a candidate, z-depth ``own`` [H, W] at
    its own time, show at the other time (z-depth ``there``) a surface farther away: the
    median of ``(there - own) / own`` over the pixels with both depths exceeds
    :data:`RECEDED_NOISE` times the pose's depth ``noise`` (:func:`_depth_noise`). An object
    taken away leaves what stood behind it in view; one still standing there (relit,
    re-segmented) keeps its depth. False without such pixels or a finite noise."""
    if not np.isfinite(noise):
        return False
    a, b = own[rest].astype(np.float64), there[rest].astype(np.float64)
    ok = np.isfinite(a) & np.isfinite(b) & (a > 0) & (b > 0)
    if not ok.any():
        return False
    return bool(np.median((b[ok] - a[ok]) / a[ok]) > RECEDED_NOISE * noise)


def _swapped(ids0: np.ndarray, ids1: np.ndarray, t: int, reg0: np.ndarray, reg1: np.ndarray,
             o: CompareOptions) -> bool:
    """True when the candidate ``t``'s region (``reg0`` / ``reg1``: its pixels seen at t0 /
    t1) is, at the other time, mostly (>= 1/2) covered by one other ID whose mask there
    matches the candidate's own mask (IoU >= 1/2, and >= ``presence_iou``): an instance of the
    same footprint took its place (an object replaced by one of the same shape). A surface
    re-segmented by a lighting change is covered by pieces of larger or smaller segments."""
    own, other = (ids0, ids1) if reg0.sum() >= reg1.sum() else (ids1, ids0)
    reg = reg0 if own is ids0 else reg1
    cover = other[reg]
    cover = cover[(cover != 0) & (cover != t)]
    if not cover.size or cover.size < 0.5 * reg.sum():
        return False
    vals, counts = np.unique(cover, return_counts=True)
    k = int(np.argmax(counts))
    if counts[k] < 0.5 * reg.sum():
        return False
    a, b = own == t, other == vals[k]
    return bool((a & b).sum() >= max(0.5, o.presence_iou) * (a | b).sum())


def _support_shows(reg0: np.ndarray, reg1: np.ndarray, cont0: np.ndarray, cont1: np.ndarray,
                   chroma, o: CompareOptions, known: np.ndarray | None) -> bool:
    """A candidate region lying on a segment that stays is a flat object removed from (or
    added onto) that surface, not a fragment of it: True when the region is observed at both
    times (``known`` given: key-view coverage, so the model is constrained at both times) and,
    at the time it is missing, it shows the colours of the staying surface around it, while at
    the time it is seen its colours differ from that surface (an object of its own on it).

    ``reg0`` / ``reg1``: bool [H, W] the region's pixels where the ID is seen at t0 / t1;
    ``cont0`` / ``cont1``: pixels of IDs that stay (:func:`_continuing`); ``chroma(t)``: the
    :func:`_normalised_chroma` pair of the render at time t. The surroundings at each time are
    a ring of width ~1/4 of the region's size on the IDs that stay (minus the region); at
    least 3/4 of the ring must lie on them at both times (a region next to an object that
    changed - its contact shadow or rim - is not surrounded by the staying surface). Their
    colours agree when the Bhattacharyya coefficient of the chromaticity histograms is >=
    ``texture_color_similarity``; the caller still needs the region's own colours to differ
    between the times (a moved shadow keeps its chromaticity under white light)."""
    if known is None:
        return False
    if reg0.sum() >= reg1.sum():
        reg, own, other, cont_own, cont_other = reg0, 0, 1, cont0, cont1
    else:
        reg, own, other, cont_own, cont_other = reg1, 1, 0, cont1, cont0
    n = int(reg.sum())
    if n == 0:
        return False
    k = 2 * max(2, int(round(0.25 * np.sqrt(n)))) + 1
    near = (cv2.dilate(reg.astype(np.uint8), np.ones((k, k), np.uint8)) > 0) & ~reg & known
    ring_other, ring_own = near & cont_other, near & cont_own
    if (min(ring_other.sum(), ring_own.sum()) < max(0.75 * near.sum(), 0.25 * n)):
        return False  # not surrounded by the staying surface (e.g. the rim of a moved object)
    c_own, c_other = chroma(own), chroma(other)
    shows = _bhattacharyya(_chroma_hist(c_other, reg), _chroma_hist(c_other, ring_other))
    stands_out = _bhattacharyya(_chroma_hist(c_own, reg), _chroma_hist(c_own, ring_own))
    return shows >= o.texture_color_similarity > stands_out


def _continuing(ids0: np.ndarray, ids1: np.ndarray, o: CompareOptions
                ) -> tuple[np.ndarray, np.ndarray]:
    """bool [H, W] masks at t0 and t1 of the IDs that stay at this pose: visible at both times
    (>= ``min_area``) with mask IoU >= ``presence_iou`` (not candidates)."""
    a, b = np.asarray(ids0, np.int64), np.asarray(ids1, np.int64)
    n = int(max(a.max(initial=0), b.max(initial=0))) + 1
    area0 = np.bincount(a.ravel(), minlength=n)
    area1 = np.bincount(b.ravel(), minlength=n)
    same = a == b
    inter = np.bincount(a[same].ravel(), minlength=n)
    union = np.maximum(area0 + area1 - inter, 1)
    stay = (area0 >= o.min_area) & (area1 >= o.min_area) & (inter / union >= o.presence_iou)
    stay[0] = False
    return stay[a], stay[b]


def _position(mask: np.ndarray, points: np.ndarray | None,
              offset: tuple[int, int] = (0, 0)) -> np.ndarray:
    """Median world point [3] of a mask (``points``: world points [H, W, 3] of its image, or
    None), else its pixel centroid [2] (x, y; ``offset``: (row, column) of the mask's first
    pixel in the image, for a mask cut from a larger image)."""
    if points is not None:
        pts = points[mask]
        pts = pts[np.isfinite(pts).all(1)]
        if len(pts):
            return np.median(pts, 0)
    jj, ii = np.nonzero(mask)
    return np.array([ii.mean() + 0.5 + offset[1], jj.mean() + 0.5 + offset[0]])


def _boxes(ids0: np.ndarray, ids1: np.ndarray) -> dict[int, tuple[slice, slice]]:
    """Bounding box (row slice, column slice) of each ID over both ID maps int [H, W]."""
    from scipy.ndimage import find_objects

    out: dict[int, tuple[slice, slice]] = {}
    for ids in (ids0, ids1):
        for k, sl in enumerate(find_objects(np.asarray(ids, np.int64)), start=1):
            if sl is None:
                continue
            if k in out:
                a = out[k]
                sl = (slice(min(a[0].start, sl[0].start), max(a[0].stop, sl[0].stop)),
                      slice(min(a[1].start, sl[1].start), max(a[1].stop, sl[1].stop)))
            out[k] = sl
    return out


def _embed(crop: np.ndarray, sl: tuple[slice, slice], shape) -> np.ndarray:
    """bool ``shape`` mask that is ``crop`` inside the box ``sl`` and False elsewhere."""
    out = np.zeros(shape, bool)
    out[sl] = crop
    return out


def _kind(n0: int, n1: int) -> str:
    """The type of a changed ID seen at ``n0`` poses at t0 and ``n1`` at t1: ``removed`` when
    it is (almost) only seen at t0, ``added`` when only at t1, else ``moved`` (it stands at
    both times, in another place: the tracker kept its ID)."""
    return "removed" if n1 <= 0.1 * n0 else "added" if n0 <= 0.1 * n1 else "moved"


def decide(stats: list[tuple[object, dict[int, dict]]], o: CompareOptions) -> pd.DataFrame:
    """Per-ID decision from the per-pose stats ``[(pose_name, pose_stats(...)), ...]``.

    Returns a DataFrame with columns id, changed, type, partner, n_t0, n_t1 (poses where seen
    at each time), n_confirmed, first, last (pose names), area (mean pixels), colour (median
    over the poses where it was confirmed of :func:`surround_colour_change`; NaN when never
    measured), n_colour (those poses), instance (the object a changed ID belongs to, see
    :func:`_group_instances`; 0 when unchanged), place (the pieces of it at one place, see
    the same; 0 when unchanged), x, y, z (median over poses of the median world
    point of its mask, in the frame of the cameras: where it is) and size (median over poses of
    sqrt(mask area) * depth / focal: its extent, in the same units); x, y, z and size are NaN
    for an ID seen only where there was no depth or camera.
    """
    acc: dict[int, dict] = defaultdict(lambda: dict(n0=0, n1=0, n=0, conf=0, poses=[],
                                                    area=[], hist=None, size=[], pos={},
                                                    surround=[], hiders=defaultdict(int)))
    for name, st in stats:
        for t, r in st.items():
            if not r.get("observed", True):
                continue  # not judged at this pose (see pose_stats)
            a = acc[t]
            a["n"] += 1
            a["n0"] += r["area0"] > 0
            a["n1"] += r["area1"] > 0
            a["conf"] += r["confirmed"]
            if r.get("hidden", 0.0) >= HIDDEN_SHARE:
                a["hiders"][r["hidden_by"]] += 1
            a["poses"].append(name)
            a["area"].append(max(r["area0"], r["area1"]))
            a["size"].append(r["size"])
            if np.isfinite(r.get("surround", np.nan)):
                a["surround"].append(r["surround"])
            if r.get("pos") is not None:
                a["pos"].setdefault(len(r["pos"]), []).append((r["pos"], r["pos_size"]))
            if r["hist"] is not None:
                a["hist"] = r["hist"] if a["hist"] is None else a["hist"] + r["hist"]
    rows = []
    for t, a in sorted(acc.items()):
        changed = a["conf"] >= o.vote_frac * a["n"] and a["conf"] > 0
        typ = _kind(a["n0"], a["n1"]) if changed else ""
        rows.append(dict(id=t, changed=bool(changed), type=typ, partner=0, n_t0=a["n0"],
                         n_t1=a["n1"], n_confirmed=a["conf"], first=a["poses"][0],
                         last=a["poses"][-1], area=float(np.mean(a["area"])),
                         colour=(float(np.median(a["surround"])) if a["surround"]
                                 else float("nan")), n_colour=len(a["surround"]),
                         _hist=a["hist"], _size=float(np.median(a["size"])),
                         _pos=_median_position(a["pos"])))
    df = pd.DataFrame(rows, columns=["id", "changed", "type", "partner", "n_t0", "n_t1",
                                     "n_confirmed", "first", "last", "area", "colour",
                                     "n_colour", "_hist", "_size", "_pos"])
    df["changed"] = df["changed"].astype(bool)  # also when empty: a mask, not column labels
    df.attrs["hidden_by"] = {t: dict(a["hiders"]) for t, a in acc.items() if a["hiders"]}
    _pair_moved(df, o)
    _group_instances(df)
    world = [p if p is not None and len(p[0]) == 3 else None for p in df["_pos"]]
    for k, c in enumerate("xyz"):
        df[c] = [float(p[0][k]) if p is not None else np.nan for p in world]
    df["size"] = [float(p[1]) if p is not None else np.nan for p in world]
    return df.drop(columns=["_hist", "_size", "_pos"])


def replaced(df: pd.DataFrame, o: CompareOptions) -> list[int]:
    """Mark the objects that a change of the other time now stands in front of (in place):
    returns the IDs newly marked changed.

    Where a new object stands in front of an old one, :func:`pose_stats` leaves out the pixels
    of the old one that it hides (the old object may still stand behind it), and with a
    quarter or more hidden does not trust its texture either. When the new object replaced the
    old one in place (a sphere put where a ring lay), that leaves only a thin rim of the old
    object to judge, whose depth barely differs from the floor now seen there: the old
    object is never confirmed. It differs from an object that still stands behind the
    newcomer in that it is seen at the other time at none of its poses, and in that its rim
    shows at the other time what stood behind it, farther than the pose's depth noise
    (:func:`_receded`; a surface still there keeps its depth). So an unchanged ID
    that is absent at the other time at every pose where it was judged (and judged at >= 2)
    is changed (``removed`` or ``added``, ``partner`` the newcomer) when at least
    ``vote_frac`` of those poses had at least :data:`HIDDEN_SHARE` of its region hidden at the
    other time, with the rest receded, by an ID of one and the same changed object
    (``instance``: a newcomer the segmenter cut into pieces hides it with one piece here and
    another there) of the other type or moved (a moved object stands at both times, at
    its new place at the other time; and a newcomer paired by mistake with something apart
    is typed moved too), after the 3D and colour confirmation (``df.attrs["hidden_by"]``,
    from :func:`decide`), and that newcomer (its largest piece, the instance's own ID)
    stands in its place: the two are of about one size (within :data:`SIZE_RATIO`) and
    their footprints overlap in the world (not :func:`_apart`; an ID without a world position
    is never replaced). A piece of the surface behind or beside a new object is hidden by it
    too, but keeps its depth where it is not hidden, or is smaller than the object, or lies
    off its centre. Its ``instance`` is its own ID."""
    hidden_by = df.attrs.get("hidden_by", {})
    ch = df.loc[df["changed"]]
    kind = dict(zip(ch["id"].astype(int), ch["type"]))
    # the changed object an ID belongs to (its pieces hide the old object pose by pose)
    owner = dict(zip(ch["id"].astype(int), ch["instance"].astype(int)))
    marked = []
    for i in df.index[~df["changed"]]:
        t = int(df.at[i, "id"])
        n0, n1 = int(df.at[i, "n_t0"]), int(df.at[i, "n_t1"])
        if t not in hidden_by or (n0 > 0) == (n1 > 0) or n0 + n1 < 2:
            continue
        typ, other = ("removed", "added") if n0 else ("added", "removed")
        votes: dict[int, int] = defaultdict(int)
        for h, c in hidden_by[t].items():
            if kind.get(h) in (other, "moved"):
                votes[owner[h]] += c
        if not votes:
            continue
        h = max(votes, key=votes.get)
        head = df.index[df["id"] == h]
        if votes[h] < o.vote_frac * (n0 + n1) or not len(head):
            continue
        j = head[0]
        s0, s1 = float(df.at[i, "size"]), float(df.at[j, "size"])
        here = (df.loc[i, ["x", "y", "z"]].to_numpy(float), s0)
        there = (df.loc[j, ["x", "y", "z"]].to_numpy(float), s1)
        if np.isfinite(np.r_[here[0], there[0], s0, s1]).all() and \
                max(s0, s1) <= SIZE_RATIO * min(s0, s1) and not _apart(here, there):
            df.at[i, "changed"], df.at[i, "type"] = True, typ
            df.loc[i, ["partner", "instance", "place"]] = [h, t, t]  # may add the columns
            marked.append(t)
    return marked


def _group_instances(df: pd.DataFrame) -> None:
    """Column ``instance`` (in place): changed IDs that are pieces of one object share it.

    Two changed IDs seen at the same time (both mostly at t0, or both mostly at t1) whose
    footprints overlap in the world (not :func:`_apart`: the distance of their median world
    points is below their mean size) are pieces of one object (a segmenter split it, or its
    track broke). A moved pair joins the removed object and the added one it belongs to when
    each of the two has no moved pair with any other object: one object left one place for
    another. (On a sparse capture the renders are cut differently at the two times all over
    a textured surface; lookalike pieces then pair up as moved between many objects, and
    joining them all would chain objects across the scene into one.) The instance is named by
    the ID of its largest member (mean area); 0 for unchanged IDs.

    Column ``place`` (in place): the same without the moved pairs, the pieces at one place
    (named by the ID of their largest member; 0 for unchanged IDs). A change is confirmed place
    by place (:func:`gdiff.compare.stage._confirm_by_evidence`): an object that moved changed
    both where it stood and where it stands, and the evidence of the one place does not vouch
    for the other.
    """
    df["instance"] = 0
    df["place"] = 0
    ch = df.index[df["changed"]].tolist()
    if not ch:
        return
    side = (df.loc[ch, "n_t1"].to_numpy() > df.loc[ch, "n_t0"].to_numpy()).astype(int)
    records = df.loc[ch, "_pos"].tolist()
    near = ~_apart_all(records, records) & (side[:, None] == side[None, :])
    piece = link_groups(len(ch), list(zip(*np.nonzero(np.triu(near, 1)))))
    _name_groups(df, ch, piece, "place")
    pos = {int(df.at[i, "id"]): k for k, i in enumerate(ch)}
    pairs = set()  # moved pairs between objects (groups of pieces)
    for k, a in enumerate(ch):
        partner = pos.get(int(df.at[a, "partner"]))
        if partner is not None and piece[k] != piece[partner]:
            pairs.add((min(piece[k], piece[partner]), max(piece[k], piece[partner])))
    n_pairs = np.bincount(np.array(list(pairs), np.int64).ravel(), minlength=piece.max() + 1)
    links = [(a, b) for a, b in pairs if n_pairs[a] == 1 and n_pairs[b] == 1]
    _name_groups(df, ch, link_groups(int(piece.max()) + 1, links)[piece], "instance")


def _name_groups(df: pd.DataFrame, rows: list, group: np.ndarray, column: str) -> None:
    """Column ``column`` of the rows ``rows`` of ``df`` (in place): per value of ``group``
    (one per row), the ID of the group's largest member (mean area; the first on ties)."""
    for g in np.unique(group):
        members = [rows[k] for k in np.flatnonzero(group == g)]
        head = max(members, key=lambda i: df.at[i, "area"])
        df.loc[members, column] = int(df.at[head, "id"])


def unpair(df: pd.DataFrame) -> None:
    """The changed IDs of ``df`` whose ``partner`` is no longer changed are what they were
    before :func:`_pair_moved` paired them (in place): ``added`` or ``removed``
    (:func:`_kind`), no ``partner``; an object that lost one of its places is its other place
    (``instance`` = ``place``)."""
    ch = df.index[df["changed"]]
    still = set(df.loc[ch, "id"].astype(int))
    lone = [i for i in ch if int(df.at[i, "partner"]) and int(df.at[i, "partner"]) not in still]
    for i in lone:
        df.at[i, "type"] = _kind(int(df.at[i, "n_t0"]), int(df.at[i, "n_t1"]))
        df.at[i, "partner"] = 0
    broken = df.loc[ch, "instance"].isin(df.loc[lone, "instance"]).to_numpy()
    df.loc[ch[broken], "instance"] = df.loc[ch[broken], "place"]


def _median_position(by_dim: dict[int, list]) -> tuple[np.ndarray, float] | None:
    """(median position, median size) over poses, world points preferred over pixels."""
    for d in (3, 2):
        if by_dim.get(d):
            return (np.median(np.stack([p for p, _ in by_dim[d]]), 0),
                    float(np.median([s for _, s in by_dim[d]])))
    return None


def _apart(p0, p1) -> bool:
    """Two (position, size) records lie at different places: the distance between them exceeds
    their mean size, so their footprints do not overlap (a replacement stands where the removed
    object stood; a moved object stands elsewhere). Unknown positions count as apart."""
    if p0 is None or p1 is None or len(p0[0]) != len(p1[0]):
        return True
    return float(np.linalg.norm(p0[0] - p1[0])) > 0.5 * (p0[1] + p1[1])


def _pair_moved(df: pd.DataFrame, o: CompareOptions) -> None:
    """Pair removed and added IDs of the same appearance and size, at different places, into
    ``moved`` (in place). Every removed-added pair is scored at once (arrays, not a loop over
    pairs: a sparse capture's renders give thousands of each)."""
    rem = df.index[df["type"] == "removed"].tolist()
    add = df.index[df["type"] == "added"].tolist()
    if not rem or not add:
        return
    size_r = df.loc[rem, "_size"].to_numpy(float)[:, None]
    size_a = df.loc[add, "_size"].to_numpy(float)[None, :]
    ok = np.maximum(size_r, size_a) <= SIZE_RATIO * np.minimum(size_r, size_a)
    ok &= _apart_all(df.loc[rem, "_pos"].tolist(), df.loc[add, "_pos"].tolist())
    S = np.where(ok, _root_hists(df.loc[rem, "_hist"].tolist())
                 @ _root_hists(df.loc[add, "_hist"].tolist()).T, 0.0)
    S[S < o.moved_similarity] = 0.0  # only eligible pairs compete in the assignment
    rows, cols = linear_sum_assignment(-S)
    for i, j in zip(rows, cols):
        if S[i, j] >= o.moved_similarity:
            r, a = rem[i], add[j]
            df.at[r, "type"] = df.at[a, "type"] = "moved"
            df.at[r, "partner"] = int(df.at[a, "id"])
            df.at[a, "partner"] = int(df.at[r, "id"])


def _root_hists(hists: list) -> np.ndarray:
    """float [N, B]: the square roots of the normalised, flattened histograms (rows of zeros
    for missing or empty ones), so that the Bhattacharyya coefficient of two is a dot product
    (:func:`_bhattacharyya`)."""
    size = next((np.size(h) for h in hists if h is not None), 0)
    out = np.zeros((len(hists), size))
    for k, h in enumerate(hists):
        if h is not None and h.sum() > 0:
            out[k] = np.sqrt(np.ravel(h) / h.sum())
    return out


def _apart_all(pos_r: list, pos_a: list) -> np.ndarray:
    """bool [R, A]: :func:`_apart` of every pair of the records ``pos_r`` and ``pos_a``."""
    out = np.ones((len(pos_r), len(pos_a)), bool)
    dims = {len(p[0]) for p in pos_r + pos_a if p is not None}
    for d in dims:
        ir = [k for k, p in enumerate(pos_r) if p is not None and len(p[0]) == d]
        ia = [k for k, p in enumerate(pos_a) if p is not None and len(p[0]) == d]
        if not ir or not ia:
            continue
        P = np.array([pos_r[k][0] for k in ir], float).reshape(len(ir), d)
        Q = np.array([pos_a[k][0] for k in ia], float).reshape(len(ia), d)
        sr = np.array([pos_r[k][1] for k in ir], float)
        sa = np.array([pos_a[k][1] for k in ia], float)
        ia = np.asarray(ia)
        for b in range(0, len(ir), 512):  # rows in blocks: bounded memory
            rows = slice(b, b + 512)
            dist = np.linalg.norm(P[rows, None, :] - Q[None, :, :], axis=-1)
            out[np.ix_(ir[rows], ia)] = dist > 0.5 * (sr[rows, None] + sa[None, :])
    return out


def change_masks(ids0: np.ndarray, ids1: np.ndarray, changed_ids) -> tuple[np.ndarray, np.ndarray]:
    """Masks bool [H, W] of the changed instances visible at t0 and at t1 at one pose."""
    ch = np.asarray(sorted(changed_ids), dtype=np.int64)
    return np.isin(ids0, ch) & (ids0 > 0), np.isin(ids1, ch) & (ids1 > 0)


def detect_changes_pair(rgb0: np.ndarray, rgb1: np.ndarray, depth0: np.ndarray | None = None,
                        depth1: np.ndarray | None = None, K: np.ndarray | None = None,
                        segment_options=None, track_options=None,
                        options: CompareOptions | None = None) -> tuple[np.ndarray, np.ndarray]:
    """ID-compare change detection on one before/after image pair of the same pose.

    ``rgb0``, ``rgb1``: float32 [H, W, 3] sRGB in [0, 1]; ``depth0``, ``depth1``: float32
    [H, W] z-depth or None; ``K``: [3, 3] intrinsics or None. Segments both images, carries IDs
    from t0 to t1 (same pose: identity, with a depth-agreement check when depth is given),
    compares them and returns (mask_t0, mask_t1), bool [H, W]: changed instances visible at t0
    (removed / moved away) and at t1 (added / moved in). Their union is the change map.
    """
    from ..cameras import Camera
    from ..segment import SegmentOptions, make_segmenter
    o = options or CompareOptions()
    seg = make_segmenter(segment_options or SegmentOptions())
    H, W = rgb0.shape[:2]
    cam = None
    if K is not None:
        K = np.asarray(K, float)
        cam = Camera(W, H, K[0, 0], K[1, 1], K[0, 2], K[1, 2])
    frames = []
    for time, (rgb, z) in enumerate(((rgb0, depth0), (rgb1, depth1))):
        inst = seg.segment(rgb, z, None, K)
        frames.append(TrackFrame(labels=labels_from_instances(inst, (H, W)), rgb=rgb, depth=z,
                                 camera=cam if z is not None else None, pose_key="pair",
                                 time=time))
    to = track_options or TrackOptions()
    to = TrackOptions(**{**to.__dict__, "vote_window": 0})  # two frames: nothing to vote on
    res = track_sequence(frames, to)
    st = pose_stats(res.ids[0], res.ids[1], o, rgb0, rgb1, depth0, depth1,
                    focal=float(K[0, 0]) if K is not None else None, camera=cam)
    df = decide([("pair", st)], o)
    return change_masks(res.ids[0], res.ids[1], df.loc[df["changed"], "id"].tolist())
