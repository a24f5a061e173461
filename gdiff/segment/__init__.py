"""Stage ``segment``: instance segmentation backends behind one interface
(:mod:`gdiff.segment.base`) and the stage that segments and tracks every rendered frame in one
ID space (:mod:`gdiff.segment.stage`)."""

from .base import BACKENDS, Instance, Segmenter, SegmentOptions, make_segmenter, mask_bbox

from .stage import segment_and_track, segment_labels, track_paths

__all__ = ["BACKENDS", "Instance", "Segmenter", "SegmentOptions", "make_segmenter", "mask_bbox",
           "segment_and_track", "segment_labels", "track_paths"]
