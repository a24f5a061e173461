"""Stage ``compare``: which tracked instances changed between t=0 and t=1, as masks per pose.

The rule ``compare`` maps to this package:

* :mod:`.stage` — the stage on files (:func:`compare`) and in memory (:func:`compare_paths`);
* :mod:`.change` — per pose, the candidates (IDs present at one time only, or with very
  different masks) and the evidence that confirms them (depth, texture, colour); per ID, the
  vote over poses, the type (added, removed, moved) and the grouping of pieces into objects;
  also :func:`detect_changes_pair`, the same comparison on one image pair (``idcompare``);
* :mod:`.coverage` — which pixels of a frame the training photos of each time saw, from
  several directions (only those are judged);
* :mod:`.geometry` — surfaces that appear or vanish in 3D, voted over all poses whatever
  their IDs (objects the segmenter merged with their support), added to the masks;
* :mod:`.photos` — whether the training photos of the two times differ where the flat
  evidence says a surface's appearance changed (the fit's own errors are photographed alike).
* :mod:`.spread` — a changed object's surface carried in 3D to the poses where the segmenter
  merged it with another ID (voxels the key frames show as changed IDs at one time only).

The appearance test (:mod:`gdiff.appearance`) stays a top-level module: the tracker of the
``segment`` stage uses it as well.
"""

from .change import (CHANGE_TYPES, CompareOptions, change_masks, decide, detect_changes_pair,
                     pose_stats)
from .coverage import DepthView, nearest_views, observed
from .geometry import GeometryEvidence, pose_flags
from .stage import compare, compare_paths, key_views

__all__ = ["CHANGE_TYPES", "CompareOptions", "DepthView", "GeometryEvidence", "change_masks",
           "compare", "compare_paths", "decide", "detect_changes_pair", "key_views",
           "nearest_views", "observed", "pose_flags", "pose_stats"]
