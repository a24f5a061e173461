"""The two times of one pose segmented together, where their depths cannot be compared.

The tracker links an instance across the two times at a pose by carrying its ID map from one
time's render to the other's through the rendered depth (:func:`gdiff.track.reproject_ids`):
a pixel keeps its ID only where the two depths agree within ``track.depth_tol_rel``. A model
fitted to a sparse capture (a few photos per visit, each surface seen by one or two of them)
renders the two times' depths of an unchanged room apart by more than that over most of the
frame, and its segmenter cuts the two renders differently, so unchanged surfaces lose their
link and are compared as new at the other time.

At such a pose (:func:`depths_agree` below ``SHARED_BELOW``) both renders are cut along the
union of their edges (:meth:`gdiff.segment.geometric.GeometricSegmenter.label` with
``other``): the two times then have the same regions, and the tracker links them pixel for
pixel, by their appearance instead of their depth (:attr:`gdiff.track.TrackFrame.shared`): the
texture test of every cross-time link, and the colours of the linked pixels. An object added,
removed or replaced is cut along the other time's edges too; its pieces keep no link where
their texture or colours differ from what the other time shows there. (Keeping each time's own
regions where the two renders' colours differ was tried: a sparse fit renders unchanged
surfaces in other colours at the two times in many places, and there the regions then differ
again.)
"""

from __future__ import annotations

import numpy as np

#: a pose's two times are segmented together when their depths agree on less than this share
#: of the pixels both show
SHARED_BELOW = 0.5


def depths_agree(depth0: np.ndarray, depth1: np.ndarray, valid: np.ndarray,
                 tol_rel: float) -> float:
    """Share of the pixels ``valid`` bool [H, W] (shown at both times) whose two z-depths
    (float32 [H, W], scene units) agree within ``tol_rel`` of the nearer one: the pixels the
    tracker's depth test can link. NaN when no pixel has a finite, positive depth at both."""
    z0, z1 = np.asarray(depth0, np.float64), np.asarray(depth1, np.float64)
    ok = valid & np.isfinite(z0) & np.isfinite(z1) & (z0 > 0) & (z1 > 0)
    if not ok.any():
        return float("nan")
    near = np.minimum(z0[ok], z1[ok])
    return float((np.abs(z0[ok] - z1[ok]) <= tol_rel * near).mean())


def shared_pose(frame0: dict, frame1: dict, tol_rel: float, alpha_min: float) -> bool:
    """Whether the two renders of one pose (dicts with ``depth`` and ``alpha``, float32
    [H, W]) are segmented together: their depths agree (:func:`depths_agree`, pixels of
    alpha >= ``alpha_min`` at both times) on less than ``SHARED_BELOW`` of what they show.
    False without depth."""
    if frame0.get("depth") is None or frame1.get("depth") is None:
        return False
    valid = np.ones(np.shape(frame0["depth"]), bool)
    for f in (frame0, frame1):
        if f.get("alpha") is not None:
            valid &= np.asarray(f["alpha"]) >= alpha_min
    share = depths_agree(frame0["depth"], frame1["depth"], valid, tol_rel)
    return bool(share < SHARED_BELOW)
