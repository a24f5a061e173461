"""A changed object's surface, carried to the poses where the segmenter merged it.

The ID comparison (:mod:`gdiff.compare.change`) marks an object at the poses where it has an
ID of its own. At other poses the segmenter may cut it as part of the surface it lies on (a
low ring on a floor, one segment with the floor), and no ID marks it there. The partition
learns from the key views' masks, so those poses teach it the opposite of the others.

The object is one surface in 3D. Per time, every key frame (a training camera of either time,
rendered at that time) looks at the voxels its surface pixels fall in, and flags those of the
pixels of changed IDs (:func:`count_voxels`). A voxel belongs to a changed object when at
least ``vote`` of the key frames that look at it flag it, at least :data:`MIN_VIEWS` do, and
the same key poses at the other time mostly see no surface in it (:data:`VACATED`;
:func:`object_voxels`): an object the segmenter cut out at a third of the views that see it is
carried to the rest, while the floor at its foot, which the segments of some views take along
with its shadow, is there at both times and is not. Then at every pose the pixels whose
surface at that time lies in such a voxel join that time's mask (:func:`spread_masks`; the
stage also asks that the two renders look different there). Pixels at a jump of the rendered
depth count nowhere (:func:`depth_edges`): their depth mixes an object's outline with what
lies behind it, and their world points lie on neither.

Voxels are those of the 3D evidence (:class:`gdiff.compare.geometry.GeometryEvidence`): a side
of ``geometry_voxel_px`` pixels at the median depth of the frames, in world units of the poses
stage. Depth is camera-frame z (OpenCV axes), as rendered into the EXR ``Z`` channel.
"""

from __future__ import annotations

from collections.abc import Iterable

import cv2
import numpy as np

from ..track import world_points
from .geometry import voxel_keys_of

# a voxel flagged by a single key frame is never carried: one view's segment is not checked
MIN_VIEWS = 2
# a voxel is carried only when fewer than this share of the key frames that see a surface in it
# at its time see one there at the other time: the object left it (or came to it)
VACATED = 0.5
# pixels within this many pixels of a depth edge carry nothing (:func:`depth_edges`)
EDGE_WIDTH = 2


def depth_edges(depth: np.ndarray, rel: float, width: int = EDGE_WIDTH) -> np.ndarray:
    """bool [H, W]: pixels within ``width`` pixels of a jump of the z-depth [H, W] by more
    than ``rel`` (largest over smallest depth in the window, minus 1), or of a pixel without a
    surface. A rendered depth there mixes the surfaces on both sides, and its world point
    lies on neither."""
    z = np.asarray(depth, np.float32)
    ok = np.isfinite(z) & (z > 0)
    k = np.ones((2 * width + 1, 2 * width + 1), np.uint8)
    hi = cv2.dilate(np.where(ok, z, np.float32(np.inf)), k)
    lo = cv2.erode(np.where(ok, z, np.float32(0)), k)
    return ~(np.isfinite(hi) & (lo > 0) & (hi <= (1 + rel) * lo))


def voxel_keys(depth: np.ndarray, camera, voxel: float, edge_rel: float | None = None
               ) -> np.ndarray:
    """int64 [H, W] packed key of the voxel (side ``voxel``, world units) each pixel's surface
    lies in (z-depth [H, W] seen by ``camera``, camera-to-world ``c2w``); -1 where there is no
    surface (depth not finite and positive) and, with ``edge_rel``, at the depth's edges
    (:func:`depth_edges`)."""
    P = world_points(depth, camera)
    ok = np.isfinite(P).all(-1)
    if edge_rel is not None:
        ok &= ~depth_edges(depth, edge_rel)
    keys = np.full(ok.shape, -1, np.int64)
    keys[ok] = voxel_keys_of(P[ok], voxel)
    return keys


def count_voxels(views: Iterable[tuple[np.ndarray, np.ndarray]]
                 ) -> tuple[tuple[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]:
    """Per voxel, how many frames look at it and how many flag it, at one time.

    ``views`` (any iterable, read once): per key frame, ``(keys, flagged)``: its pixels' voxel
    keys (int64 [H, W], :func:`voxel_keys`, -1 = no surface) and bool [H, W], the pixels of
    changed IDs. Returns ``((looked keys, frame counts), (flagged keys, frame counts))``, keys
    sorted and unique."""
    looks, flags = [np.zeros(0, np.int64)], [np.zeros(0, np.int64)]
    for keys, flagged in views:
        surface = keys >= 0
        looks.append(np.unique(keys[surface]))
        flags.append(np.unique(keys[surface & np.asarray(flagged, bool)]))
    return (np.unique(np.concatenate(looks), return_counts=True),
            np.unique(np.concatenate(flags), return_counts=True))


def _count(table: tuple[np.ndarray, np.ndarray], keys: np.ndarray) -> np.ndarray:
    """The counts of ``table`` (sorted keys, counts) at ``keys``; 0 where absent."""
    k, n = table
    if not len(k):
        return np.zeros(len(keys), np.int64)
    j = np.minimum(np.searchsorted(k, keys), len(k) - 1)
    return np.where(k[j] == keys, n[j], 0)


def object_voxels(here, other, vote: float, min_views: int = MIN_VIEWS,
                  vacated: float = VACATED) -> np.ndarray:
    """Sorted int64 keys of the voxels of changed objects at one time.

    ``here`` and ``other``: :func:`count_voxels` of the key frames at this time and at the
    other time (the same key poses rendered at both). A voxel is kept when at least
    ``min_views`` frames flag it, at least ``vote`` of the frames with a surface in it do, and
    fewer than ``vacated`` times as many frames have a surface in it at the other time: the
    object is there at its time only, while the surface it stands on (which the segments of
    some frames take along at the object's foot, where its shadow falls) is there at both."""
    (lk, ln), (fk, fn) = here
    if not len(fk):
        return fk
    seen = _count((lk, ln), fk)  # every flag is a look too
    there = _count(other[0], fk)
    return fk[(fn >= min_views) & (fn >= vote * seen) & (there < vacated * seen)]


def spread_masks(keys: np.ndarray, voxels: np.ndarray) -> np.ndarray:
    """bool [H, W]: pixels whose voxel key (int64 [H, W], :func:`voxel_keys`; -1, no surface,
    is never a voxel) is one of ``voxels`` (from :func:`object_voxels`)."""
    return np.isin(keys, voxels)
