"""Segmenter interface: one image (+ optional rendered depth and alpha) -> instance masks.

Every backend (``geometric``: weight-free, the default; ``sam``: Segment Anything through
onnxruntime with user-supplied model files) implements :class:`Segmenter` and is built from the
``segment`` config section by :func:`make_segmenter`.

Inputs (same for all backends)
------------------------------
* ``rgb``: float32 [H, W, 3], sRGB-encoded values in [0, 1].
* ``depth``: float32 [H, W] expected depth along the camera z axis (OpenCV axes, z forward), in
  scene units; ``None`` when unknown (e.g. a photo). Non-finite or <= 0 means "no surface".
* ``alpha``: float32 [H, W] accumulated opacity in [0, 1]; ``None`` when unknown. Pixels with
  low alpha are background (nothing rendered) and may be left out of every instance.
* ``K``: float [3, 3] pinhole intrinsics of the image (pixel centres at +0.5), or ``None``.
  Backends that use geometry (surface normals from ``depth``) use it; others ignore it. All
  backends must accept the keyword.

Output
------
A list of :class:`Instance`, masks bool [H, W]. Masks of one call do not overlap (a backend that
produces overlapping proposals resolves them, higher score first); pixels covered by no mask are
"no instance". The order is by decreasing score.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np

from ..appearance import mask_box
from ..errors import ConfigError

BACKENDS = ("geometric", "sam")
SHARED_MODES = ("auto", "always", "never")


@dataclass
class Instance:
    """One instance proposal in an image.

    ``mask``: bool [H, W]. ``score``: confidence in [0, 1] (higher is better; backends define
    it, e.g. SAM's predicted IoU x stability, or the geometric backend's boundary strength).
    ``bbox``: (x0, y0, x1, y1) in pixels, x1/y1 exclusive; filled from the mask when omitted.
    """

    mask: np.ndarray
    score: float = 1.0
    bbox: tuple[int, int, int, int] | None = None

    def __post_init__(self):
        self.mask = np.asarray(self.mask, dtype=bool)
        if self.mask.ndim != 2:
            raise ValueError(f"Instance mask must be 2-D [H, W], got shape {self.mask.shape}")
        if self.bbox is None:
            self.bbox = mask_bbox(self.mask)

    @property
    def area(self) -> int:
        """Number of pixels in the mask."""
        return int(self.mask.sum())


def mask_bbox(mask: np.ndarray) -> tuple[int, int, int, int]:
    """Bounding box (x0, y0, x1, y1) of a bool mask, x1/y1 exclusive; (0, 0, 0, 0) if empty
    (:func:`gdiff.appearance.mask_box` as numbers)."""
    sl = mask_box(mask)
    if sl is None:
        return (0, 0, 0, 0)
    return (int(sl[1].start), int(sl[0].start), int(sl[1].stop), int(sl[0].stop))


@runtime_checkable
class Segmenter(Protocol):
    """Splits one image into instances. See the module docstring for shapes and units.

    A segmenter class may set ``parallel_safe = True`` when its frames can be segmented in
    forked worker processes (no state, no threads of its own); the segment stage then
    segments ahead on the rule's threads (:func:`gdiff.segment.stage.track_paths`)."""

    def segment(self, rgb: np.ndarray, depth: np.ndarray | None = None,
                alpha: np.ndarray | None = None, K: np.ndarray | None = None) -> list[Instance]:
        ...


# Rendered opacity from which a pixel shows a surface (gets an instance, is compared). A fit to
# few photos draws surfaces it has little evidence for semi-transparent - above all an object
# that is there at one time only, whose Gaussians must vanish at the other - so a pixel that
# is a quarter opaque already shows the model's surface; below that, too little was rendered.
ALPHA_MIN = 0.25


@dataclass
class SegmentOptions:
    """Options of the ``segment`` config section (defaults are the config defaults).

    Shared
    ------
    backend: ``geometric`` (weight-free, default) or ``sam`` (needs the two ONNX files).
    min_region_area: instances smaller than this many pixels are dropped (both backends).
    alpha_min: pixels with rendered alpha below this are background (no instance); the compare
        stage judges no pixel below it either (:data:`ALPHA_MIN`).
    overlays: also write a colour overlay of the IDs on each frame
        (``instances/overlay/<path>/<t>/NNNNN.jpg``, for inspection; nothing downstream reads
        them).

    ``geometric`` backend (gdiff/segment/geometric.py)
    ---------------------------------------------------
    depth_edge_rel: a depth jump between neighbouring pixels larger than this fraction of the
        depth is an occlusion edge.
    normal_edge_deg: a change of the surface normal (from the depth map) larger than this angle,
        in degrees, is a crease edge.
    color_edge: threshold on the illumination-invariant colour gradient (chromaticity and
        log-intensity structure, see geometric.py) that makes a colour edge; 0 disables colour.
    smooth_sigma: Gaussian blur (pixels, at the working resolution) before edge detection.
    max_side: images are segmented at a resolution whose longer side is at most this many
        pixels; masks are returned at full resolution.
    shared_partition: segment the two times of a pose together (the union of their edges,
        linked by appearance instead of depth; gdiff/segment/pair.py): ``auto`` at the poses
        whose two rendered depths agree on less than half of the frame (a sparse capture),
        ``always``, or ``never`` (the default: measured on the robot captures it cleans the
        compare stage's masks but not the partition's maps, see docs/design.md).

    ``sam`` backend (gdiff/segment/sam_onnx.py)
    --------------------------------------------
    sam_encoder, sam_decoder: paths of the user's SAM image-encoder and mask-decoder ONNX files.
    points_per_side: prompt grid density (points_per_side^2 point prompts).
    pred_iou_thresh, stability_score_thresh, box_nms_thresh: the usual automatic-mask-generator
        filters.
    points_per_batch, stability_score_offset, crop_n_layers, crop_nms_thresh,
    crop_overlap_ratio, crop_n_points_downscale_factor, min_mask_region_area: as in
        segment-anything's automatic mask generator (see docs/sam.md).
    threads: onnxruntime intra-op threads (0 = the rule's threads / onnxruntime's choice).
    providers: onnxruntime execution providers (None = CUDA when available, else CPU).
    """

    backend: str = "geometric"
    min_region_area: int = 64
    alpha_min: float = ALPHA_MIN
    overlays: bool = False
    # geometric
    depth_edge_rel: float = 0.04
    normal_edge_deg: float = 35.0
    color_edge: float = 0.15
    smooth_sigma: float = 1.0
    max_side: int = 640
    shared_partition: str = "never"
    # sam
    sam_encoder: str | None = None
    sam_decoder: str | None = None
    points_per_side: int = 16
    pred_iou_thresh: float = 0.8
    stability_score_thresh: float = 0.9
    box_nms_thresh: float = 0.7
    points_per_batch: int = 64
    stability_score_offset: float = 1.0
    crop_n_layers: int = 0
    crop_nms_thresh: float = 0.7
    crop_overlap_ratio: float = 512 / 1500
    crop_n_points_downscale_factor: int = 1
    min_mask_region_area: int = 0
    threads: int = 0
    providers: list[str] | None = None

    def __post_init__(self):
        if self.backend not in BACKENDS:
            raise ConfigError(f"config key 'segment.backend': unknown value {self.backend!r}; "
                              f"use one of {', '.join(BACKENDS)}")
        if self.min_region_area < 1:
            raise ConfigError("config key 'segment.min_region_area' must be >= 1")
        if self.shared_partition not in SHARED_MODES:
            raise ConfigError(f"config key 'segment.shared_partition': unknown value "
                              f"{self.shared_partition!r}; use one of {', '.join(SHARED_MODES)}")


def make_segmenter(options: SegmentOptions | None = None) -> Segmenter:
    """Build the backend named by ``options.backend``.

    ``sam`` is imported lazily (it needs onnxruntime and the user's model files);
    :class:`gdiff.errors.ModelFileError` is raised by it when the files are missing.
    """
    options = options or SegmentOptions()
    if options.backend == "geometric":
        from .geometric import GeometricSegmenter

        return GeometricSegmenter(options)
    if options.backend == "sam":
        if not options.sam_encoder or not options.sam_decoder:
            raise ConfigError("segment.backend is 'sam' but 'segment.sam_encoder' and/or "
                              "'segment.sam_decoder' are not set; give the paths of the SAM "
                              "ONNX files, or use backend: geometric (needs no model files)")
        from .sam_onnx import SamOnnxSegmenter

        return SamOnnxSegmenter(options)
    raise ConfigError(f"config key 'segment.backend': unknown value {options.backend!r}")
