"""Instance segmentation backends behind one interface (see :mod:`gdiff.segment.base`)."""

from .base import BACKENDS, Instance, Segmenter, SegmentOptions, make_segmenter, mask_bbox

__all__ = ["BACKENDS", "Instance", "Segmenter", "SegmentOptions", "make_segmenter", "mask_bbox"]
