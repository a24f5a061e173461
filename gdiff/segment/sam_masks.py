"""Mask-proposal bookkeeping of SAM's automatic ("segment everything") mask generator.

Model-free numpy/OpenCV pieces used by :mod:`gdiff.segment.sam_onnx`: the prompt point grid,
the crop boxes, the stability score, mask bounding boxes, box non-maximum suppression and the
removal of small islands and holes. They follow the semantics of segment-anything's
``SamAutomaticMaskGenerator`` (same definitions and thresholds), written for numpy arrays.

Conventions: images and masks are [H, W] (row = y, column = x); pixel (x, y) covers
[x, x+1) x [y, y+1), so its centre is at (x + 0.5, y + 0.5). Boxes are (x0, y0, x1, y1) in pixels
with x1/y1 exclusive (the same as :func:`gdiff.segment.base.mask_bbox`).
"""

from __future__ import annotations

import math

import cv2
import numpy as np


def point_grid(n_per_side: int) -> np.ndarray:
    """Regular grid of ``n_per_side**2`` prompt points in normalised image coordinates.

    Returns float64 [n*n, 2] (x, y) in (0, 1): the centres of an n x n tiling of the unit
    square, row by row (y outer, x inner). Multiply by (width, height) to get pixel positions.
    """
    if n_per_side < 1:
        raise ValueError(f"points per side must be >= 1, got {n_per_side}")
    centres = (np.arange(n_per_side) + 0.5) / n_per_side
    xs, ys = np.meshgrid(centres, centres)
    return np.stack([xs.ravel(), ys.ravel()], axis=1)


def crop_boxes(height: int, width: int, n_layers: int,
               overlap_ratio: float) -> tuple[list[tuple[int, int, int, int]], list[int]]:
    """Crop windows for multi-layer segmentation: the whole image, then 2^i x 2^i tiles.

    Layer ``i`` (1..n_layers) splits the image into ``2**i`` overlapping tiles per side; the
    overlap is ``overlap_ratio`` times the short side, scaled by 2 / tiles-per-side. Returns the
    boxes (x0, y0, x1, y1), x1/y1 exclusive, and each box's layer index (0 = whole image).
    """
    boxes = [(0, 0, int(width), int(height))]
    layers = [0]
    short_side = min(height, width)
    for layer in range(1, n_layers + 1):
        n = 2 ** layer
        overlap = int(overlap_ratio * short_side * (2.0 / n))
        tile_w = int(math.ceil((overlap * (n - 1) + width) / n))
        tile_h = int(math.ceil((overlap * (n - 1) + height) / n))
        for y0 in (int((tile_h - overlap) * k) for k in range(n)):
            for x0 in (int((tile_w - overlap) * k) for k in range(n)):
                boxes.append((x0, y0, min(x0 + tile_w, width), min(y0 + tile_h, height)))
                layers.append(layer)
    return boxes, layers


def stability_score(logits: np.ndarray, threshold: float, offset: float) -> np.ndarray:
    """IoU between each mask thresholded at ``threshold + offset`` and at ``threshold - offset``.

    ``logits``: float [N, H, W] mask logits. Returns float32 [N] in [0, 1] (1 when the binary mask
    does not move as the threshold moves by +-offset; an empty loose mask scores 0).
    """
    logits = np.asarray(logits)
    n = logits.shape[0]
    if n == 0:
        return np.zeros(0, dtype=np.float32)
    flat = logits.reshape(n, -1)
    inter = np.count_nonzero(flat > threshold + offset, axis=1)
    union = np.count_nonzero(flat > threshold - offset, axis=1)
    return np.where(union > 0, inter / np.maximum(union, 1), 0.0).astype(np.float32)


def mask_boxes(masks: np.ndarray) -> np.ndarray:
    """Bounding boxes of bool masks [N, H, W] -> int64 [N, 4] (x0, y0, x1, y1), exclusive ends.

    Empty masks get (0, 0, 0, 0).
    """
    masks = np.asarray(masks, dtype=bool)
    n = masks.shape[0]
    boxes = np.zeros((n, 4), dtype=np.int64)
    if n == 0:
        return boxes
    rows = masks.any(axis=2)  # [N, H]
    cols = masks.any(axis=1)  # [N, W]
    nonempty = rows.any(axis=1)
    h, w = masks.shape[1:]
    boxes[:, 0] = np.argmax(cols, axis=1)
    boxes[:, 1] = np.argmax(rows, axis=1)
    boxes[:, 2] = w - np.argmax(cols[:, ::-1], axis=1)
    boxes[:, 3] = h - np.argmax(rows[:, ::-1], axis=1)
    boxes[~nonempty] = 0
    return boxes


def box_nms(boxes: np.ndarray, scores: np.ndarray, iou_thresh: float) -> np.ndarray:
    """Greedy non-maximum suppression on boxes (OpenCV ``cv2.dnn.NMSBoxes``).

    ``boxes``: [N, 4] (x0, y0, x1, y1); ``scores``: [N] (any real values, higher is kept first).
    A box is dropped when its IoU with a kept, higher-scoring box exceeds ``iou_thresh``.
    Returns the kept indices (int64, by decreasing score).
    """
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
    scores = np.asarray(scores, dtype=np.float64).reshape(-1)
    if boxes.shape[0] == 0:
        return np.zeros(0, dtype=np.int64)
    rects = [(b[0], b[1], b[2] - b[0], b[3] - b[1]) for b in boxes]
    # OpenCV keeps only scores > score_threshold >= 0: shift to positive (order unchanged)
    shifted = scores - scores.min() + 1.0
    keep = cv2.dnn.NMSBoxes(rects, shifted.tolist(), score_threshold=0.0,
                            nms_threshold=float(iou_thresh))
    return np.asarray(keep, dtype=np.int64).reshape(-1)


def remove_small_regions(mask: np.ndarray, area_thresh: float,
                         mode: str) -> tuple[np.ndarray, bool]:
    """Fill small holes (``mode="holes"``) or drop small islands (``mode="islands"``) of a mask.

    Regions are 8-connected components (of the background for holes, of the mask for islands)
    with fewer than ``area_thresh`` pixels. When every island is small, the largest one is kept so
    the mask does not vanish. Returns the new bool [H, W] mask and whether it changed.
    """
    if mode not in ("holes", "islands"):
        raise ValueError(f"mode must be 'holes' or 'islands', got {mode!r}")
    mask = np.asarray(mask, dtype=bool)
    fill_holes = mode == "holes"
    work = (~mask if fill_holes else mask).astype(np.uint8)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(work, connectivity=8)
    areas = stats[1:, cv2.CC_STAT_AREA]  # component 0 is the other class
    small = np.flatnonzero(areas < area_thresh) + 1
    if small.size == 0:
        return mask, False
    if fill_holes:
        return mask | np.isin(labels, small), True
    keep = np.setdiff1d(np.arange(1, n), small)
    if keep.size == 0:
        keep = np.array([int(np.argmax(areas)) + 1])
    return np.isin(labels, keep), True


def near_crop_edge(boxes: np.ndarray, crop_box: tuple[int, int, int, int],
                   image_box: tuple[int, int, int, int], atol: float = 20.0) -> np.ndarray:
    """Which boxes touch an edge of their crop that is not an edge of the image.

    ``boxes``: [N, 4] in image coordinates; ``crop_box`` and ``image_box`` (x0, y0, x1, y1).
    A mask cut by an inner crop edge is a fragment of something larger and is dropped. Returns
    bool [N].
    """
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
    crop = np.asarray(crop_box, dtype=np.float64)[None]
    image = np.asarray(image_box, dtype=np.float64)[None]
    at_crop = np.isclose(boxes, crop, atol=atol, rtol=0)
    at_image = np.isclose(boxes, image, atol=atol, rtol=0)
    return np.any(at_crop & ~at_image, axis=1)
