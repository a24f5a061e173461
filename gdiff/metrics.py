"""Change-detection metrics: pixel precision/recall/F1/IoU and box detection scores.

Pure functions on numpy arrays (no torch, no other gdiff stage imported).

Conventions
-----------
* Masks are ``[H, W]`` arrays; the *change class* is ``mask > 0``.
* Pixel counts per view: ``TP`` (predicted and true change), ``FP`` (predicted, not true),
  ``FN`` (true change missed).
* ``P = TP / (TP + FP)``, ``R = TP / (TP + FN)``, ``F1 = 2 TP / (2 TP + FP + FN)``,
  ``IoU = TP / (TP + FP + FN)``. A ratio whose denominator is zero is *undefined* and reported
  as NaN:

  - empty prediction, non-empty truth: P = NaN, R = F1 = IoU = 0;
  - non-empty prediction, empty truth: R = NaN, P = F1 = IoU = 0;
  - both empty: all four NaN (nothing to score in that view).

  The *mean over views* ignores NaN (a view without ground-truth change does not pull recall
  down or up); the *pooled* (micro) figures are computed from the summed counts of all views of
  a scene and are defined as soon as any view has a prediction or a true change.
* Boxes: the axis-aligned minimum bounding rectangle of each 8-connected change region
  (``x0, y0, x1, y1`` in pixels, ``x1``/``y1`` exclusive), as used to compare pixel methods with
  box detectors such as CYWS-3D. Regions smaller than ``min_area`` pixels are dropped, for
  predictions and ground truth alike. A predicted box is a true positive when it overlaps a
  not-yet-matched ground-truth box with IoU >= ``iou_threshold`` (0.5); predictions are matched
  greedily in descending score order (PASCAL VOC rule). The score of a predicted box is the mean
  of the probability map over its region's pixels when a probability map is given, else the
  region's area in pixels. AP is the area under the precision-recall curve with the precision
  made monotone (all-point interpolation, VOC 2010+); NaN when there is no ground-truth box.
* Objects: every 8-connected region (of at least ``min_area`` pixels) of a view's ground-truth
  object masks is one *object view* (an object seen in that view; the before and after masks are
  split separately, so a moved object counts once at each place). It is *found* when at least
  ``found_fraction`` (0.5) of its pixels are predicted changed. Per view ``obj_N`` objects,
  ``obj_found`` found, ``obj_R = obj_found / obj_N`` (NaN without objects); the pooled object
  recall is the summed ``obj_found`` over the summed ``obj_N``.
* Ground-truth boxes (datasets that give boxes, not masks; ``x0, y0, x1, y1`` in pixels of the
  scored map, end exclusive, fractional values allowed): a box is *found* when at least
  ``found_fraction`` of its *core* (the centred box of ``core`` (0.5) times its width and height)
  is predicted changed; ``gtbox_N`` boxes, ``gtbox_found`` found, ``gtbox_R`` their ratio.
  ``far_FP`` counts predicted pixels farther than ``margin`` pixels from every box (Chebyshev
  distance, i.e. outside every box grown by ``margin`` on each side) and ``far_N`` the pixels
  of the map; ``far_frac = far_FP / far_N`` is the fraction of the image predicted changed far
  from any annotated change.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import pandas as pd

PIXEL_METRICS = ("P", "R", "F1", "IoU")
BOX_METRICS = ("box_P", "box_R", "box_F1", "box_AP")


def _ratio(num: float, den: float) -> float:
    return float(num) / float(den) if den > 0 else float("nan")


def confusion(pred: np.ndarray, gt: np.ndarray) -> tuple[int, int, int]:
    """Pixel counts ``(TP, FP, FN)`` of the change class for masks of equal shape ``[H, W]``."""
    pred = np.asarray(pred) > 0
    gt = np.asarray(gt) > 0
    if pred.shape != gt.shape:
        raise ValueError(f"prediction shape {pred.shape} != ground-truth shape {gt.shape}")
    tp = int(np.count_nonzero(pred & gt))
    fp = int(np.count_nonzero(pred & ~gt))
    fn = int(np.count_nonzero(~pred & gt))
    return tp, fp, fn


def scores_from_counts(tp: float, fp: float, fn: float) -> dict[str, float]:
    """Precision, recall, F1 and IoU from counts; undefined ratios are NaN (module docstring)."""
    return {"P": _ratio(tp, tp + fp), "R": _ratio(tp, tp + fn),
            "F1": _ratio(2 * tp, 2 * tp + fp + fn), "IoU": _ratio(tp, tp + fp + fn)}


def pixel_scores(pred: np.ndarray, gt: np.ndarray) -> dict[str, float]:
    """``{"P","R","F1","IoU","TP","FP","FN"}`` of one view."""
    tp, fp, fn = confusion(pred, gt)
    return {**scores_from_counts(tp, fp, fn), "TP": tp, "FP": fp, "FN": fn}


# ----------------------------------------------------------------------------------- boxes


@dataclass
class Regions:
    """Connected change regions of a mask.

    ``boxes``: int64 [K, 4] as ``x0, y0, x1, y1`` (pixels, end exclusive); ``areas``: int64 [K]
    pixel counts; ``labels``: int32 [H, W] region index + 1 (0 = background) for the kept
    regions.
    """

    boxes: np.ndarray
    areas: np.ndarray
    labels: np.ndarray

    def scores(self, prob: np.ndarray | None = None) -> np.ndarray:
        """Score per region [K]: mean of ``prob`` [H, W] over the region, else its area."""
        if prob is None or len(self.boxes) == 0:
            return self.areas.astype(np.float64)
        prob = np.asarray(prob, dtype=np.float64)
        if prob.shape != self.labels.shape:
            raise ValueError(f"probability map shape {prob.shape} != mask shape "
                             f"{self.labels.shape}")
        sums = np.bincount(self.labels.ravel(), weights=prob.ravel(),
                           minlength=len(self.boxes) + 1)[1:]
        return sums / np.maximum(self.areas, 1)


def connected_regions(mask: np.ndarray, min_area: int = 0, connectivity: int = 8) -> Regions:
    """8- (or 4-) connected regions of ``mask > 0`` with at least ``min_area`` pixels."""
    m = (np.asarray(mask) > 0).astype(np.uint8)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(m, connectivity=connectivity,
                                                           ltype=cv2.CV_32S)
    stats = stats[1:]
    keep = np.nonzero(stats[:, cv2.CC_STAT_AREA] >= max(int(min_area), 1))[0]
    remap = np.zeros(n, dtype=np.int32)
    remap[keep + 1] = np.arange(1, len(keep) + 1, dtype=np.int32)
    s = stats[keep].astype(np.int64)
    x, y = s[:, cv2.CC_STAT_LEFT], s[:, cv2.CC_STAT_TOP]
    boxes = np.stack([x, y, x + s[:, cv2.CC_STAT_WIDTH], y + s[:, cv2.CC_STAT_HEIGHT]], axis=1)
    return Regions(boxes=boxes.reshape(-1, 4), areas=s[:, cv2.CC_STAT_AREA].copy(),
                   labels=remap[labels])


def box_iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Pairwise IoU [Na, Nb] of boxes ``x0, y0, x1, y1`` (end exclusive, pixel units)."""
    a = np.asarray(a, dtype=np.float64).reshape(-1, 4)
    b = np.asarray(b, dtype=np.float64).reshape(-1, 4)
    w = np.clip(np.minimum(a[:, None, 2], b[None, :, 2]) - np.maximum(a[:, None, 0], b[None, :, 0]),
                0, None)
    h = np.clip(np.minimum(a[:, None, 3], b[None, :, 3]) - np.maximum(a[:, None, 1], b[None, :, 1]),
                0, None)
    inter = w * h
    area_a = (a[:, 2] - a[:, 0]) * (a[:, 3] - a[:, 1])
    area_b = (b[:, 2] - b[:, 0]) * (b[:, 3] - b[:, 1])
    union = area_a[:, None] + area_b[None, :] - inter
    return np.where(union > 0, inter / np.where(union > 0, union, 1.0), 0.0)


def match_boxes(pred: np.ndarray, scores: np.ndarray, gt: np.ndarray,
                iou_threshold: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """Greedy VOC matching. Returns ``matched`` bool [Np] (a TP or not) and ``best_iou`` [Np]
    (IoU with the ground-truth box it matched, or its best overlap if it is a FP)."""
    pred = np.asarray(pred).reshape(-1, 4)
    gt = np.asarray(gt).reshape(-1, 4)
    matched = np.zeros(len(pred), dtype=bool)
    best = np.zeros(len(pred), dtype=np.float64)
    if len(pred) == 0 or len(gt) == 0:
        return matched, best
    iou = box_iou(pred, gt)
    taken = np.zeros(len(gt), dtype=bool)
    for i in np.argsort(-np.asarray(scores, dtype=np.float64), kind="stable"):
        cand = np.where(taken, -1.0, iou[i])
        j = int(np.argmax(cand))
        best[i] = iou[i].max()
        if cand[j] >= iou_threshold:
            matched[i], taken[j], best[i] = True, True, iou[i, j]
    return matched, best


def average_precision(scores: np.ndarray, matched: np.ndarray, n_gt: int) -> float:
    """All-point interpolated AP from detections pooled over any number of views.

    ``scores`` [N] rank the detections, ``matched`` [N] says which are true positives and
    ``n_gt`` is the number of ground-truth boxes. NaN when ``n_gt == 0``; 0 when nothing is
    detected but ground truth exists.
    """
    if n_gt <= 0:
        return float("nan")
    scores = np.asarray(scores, dtype=np.float64)
    matched = np.asarray(matched, dtype=bool)
    if len(scores) == 0:
        return 0.0
    order = np.argsort(-scores, kind="stable")
    tp = np.cumsum(matched[order])
    fp = np.cumsum(~matched[order])
    recall = tp / n_gt
    precision = tp / (tp + fp)
    r = np.concatenate([[0.0], recall])
    p = np.concatenate([[0.0], precision])
    p = np.maximum.accumulate(p[::-1])[::-1]  # monotone envelope
    return float(np.sum((r[1:] - r[:-1]) * p[1:]))


def box_scores(pred: np.ndarray, gt: np.ndarray, prob: np.ndarray | None = None,
               iou_threshold: float = 0.5, min_area: int = 0
               ) -> tuple[dict[str, float], pd.DataFrame]:
    """Box detection scores of one view and the per-predicted-box records.

    Returns ``({"box_TP","box_FP","box_FN","box_P","box_R","box_F1","box_AP"}, boxes)`` where
    ``boxes`` has one row per predicted box: ``x0, y0, x1, y1, score, matched, iou`` plus one
    row per ground-truth box with ``kind == "gt"`` (so AP can be pooled over views later).
    """
    pr = connected_regions(pred, min_area)
    gr = connected_regions(gt, min_area)
    scores = pr.scores(prob)
    matched, best = match_boxes(pr.boxes, scores, gr.boxes, iou_threshold)
    tp = int(matched.sum())
    fp, fn = len(pr.boxes) - tp, len(gr.boxes) - tp
    out = {"box_TP": tp, "box_FP": fp, "box_FN": fn,
           "box_P": _ratio(tp, tp + fp), "box_R": _ratio(tp, tp + fn),
           "box_F1": _ratio(2 * tp, 2 * tp + fp + fn),
           "box_AP": average_precision(scores, matched, len(gr.boxes))}
    rows = pd.DataFrame({"kind": "pred", "x0": pr.boxes[:, 0], "y0": pr.boxes[:, 1],
                         "x1": pr.boxes[:, 2], "y1": pr.boxes[:, 3], "score": scores,
                         "matched": matched, "iou": best})
    gt_rows = pd.DataFrame({"kind": "gt", "x0": gr.boxes[:, 0], "y0": gr.boxes[:, 1],
                            "x1": gr.boxes[:, 2], "y1": gr.boxes[:, 3], "score": np.nan,
                            "matched": False, "iou": np.nan})
    frames = [f for f in (rows, gt_rows) if len(f)]
    boxes = (pd.concat(frames, ignore_index=True) if frames
             else pd.DataFrame(columns=list(rows.columns)))
    return out, boxes


def score_view(pred: np.ndarray, gt: np.ndarray, prob: np.ndarray | None = None,
               iou_threshold: float = 0.5, min_area: int = 0
               ) -> tuple[dict[str, float], pd.DataFrame]:
    """Pixel and box scores of one view: ``(metrics dict, per-box records)``."""
    px = pixel_scores(pred, gt)
    bx, boxes = box_scores(pred, gt, prob, iou_threshold, min_area)
    return {**px, **bx}, boxes


# --------------------------------------------------------------------------------- objects

OBJECT_METRICS = ("obj_R",)
GTBOX_METRICS = ("gtbox_R", "far_frac")


def object_regions(masks, min_area: int = 0) -> list[np.ndarray]:
    """The object views of a view: the 8-connected regions of each mask in ``masks`` (an
    ``[H, W]`` mask or a list of them, e.g. the before and the after object masks) with at least
    ``min_area`` pixels, as a list of bool ``[H, W]`` masks."""
    if isinstance(masks, np.ndarray) and masks.ndim == 2:
        masks = [masks]
    out = []
    for m in masks:
        r = connected_regions(m, min_area)
        out += [r.labels == k for k in range(1, len(r.boxes) + 1)]
    return out


def object_scores(pred: np.ndarray, objects: list[np.ndarray],
                  found_fraction: float = 0.5) -> dict[str, float]:
    """``{"obj_N", "obj_found", "obj_R"}`` of one view: how many of ``objects`` (bool [H, W]
    masks, :func:`object_regions`) have at least ``found_fraction`` of their pixels in
    ``pred > 0``."""
    pred = np.asarray(pred) > 0
    found = 0
    for o in objects:
        if o.shape != pred.shape:
            raise ValueError(f"object mask shape {o.shape} != prediction shape {pred.shape}")
        n = np.count_nonzero(o)
        found += int(n > 0 and np.count_nonzero(pred & o) >= found_fraction * n)
    return {"obj_N": len(objects), "obj_found": found, "obj_R": _ratio(found, len(objects))}


def _box_slices(box, shape: tuple[int, int], scale: float = 1.0, grow: float = 0.0
                ) -> tuple[slice, slice]:
    """Pixel rows/cols of box ``x0, y0, x1, y1`` scaled by ``scale`` about its centre and grown
    by ``grow`` pixels per side; pixel (i, j) is inside when its centre (i+0.5, j+0.5) is."""
    x0, y0, x1, y1 = (float(v) for v in box)
    cx, cy, hw, hh = (x0 + x1) / 2, (y0 + y1) / 2, (x1 - x0) / 2, (y1 - y0) / 2
    hw, hh = hw * scale + grow, hh * scale + grow
    h, w = shape

    def rng(lo, hi, n):
        a = int(np.clip(np.ceil(lo - 0.5), 0, n))
        b = int(np.clip(np.ceil(hi - 0.5), 0, n))
        return slice(a, max(a, b))

    return rng(cy - hh, cy + hh, h), rng(cx - hw, cx + hw, w)


def gt_box_cores(pred: np.ndarray, boxes, core: float = 0.5, found_fraction: float = 0.5
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Per ground-truth box [K, 4] (xyxy pixels of ``pred`` [H, W]): the fraction of its core
    (the centred ``core`` of its width and height; a core thinner than a pixel is widened to
    one) that ``pred`` marks changed, float [K] (NaN for a core outside the image), and
    whether the box is found (at least ``found_fraction`` of its core marked), bool [K]."""
    pred = np.asarray(pred) > 0
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
    frac = np.full(len(boxes), np.nan)
    found = np.zeros(len(boxes), bool)
    for k, b in enumerate(boxes):
        rs, cs = _box_slices(b, pred.shape, scale=core)
        if rs.stop == rs.start or cs.stop == cs.start:  # a core thinner than a pixel
            rs, cs = _box_slices(b, pred.shape, scale=core, grow=0.5)
        n = (rs.stop - rs.start) * (cs.stop - cs.start)
        if n > 0:
            hit = np.count_nonzero(pred[rs, cs])
            frac[k], found[k] = hit / n, hit >= found_fraction * n
    return frac, found


def gt_box_scores(pred: np.ndarray, boxes, core: float = 0.5, found_fraction: float = 0.5,
                  margin: float = 25.0) -> dict[str, float]:
    """Scores of a change map ``pred`` [H, W] against ground-truth boxes [K, 4] (module
    docstring): ``gtbox_N, gtbox_found, gtbox_R, far_FP, far_N, far_frac``."""
    pred = np.asarray(pred) > 0
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
    found = int(gt_box_cores(pred, boxes, core, found_fraction)[1].sum())
    near = np.zeros(pred.shape, bool)
    for b in boxes:
        rs, cs = _box_slices(b, pred.shape, grow=margin)
        near[rs, cs] = True
    far = int(np.count_nonzero(pred & ~near))
    return {"gtbox_N": len(boxes), "gtbox_found": found, "gtbox_R": _ratio(found, len(boxes)),
            "far_FP": far, "far_N": int(pred.size), "far_frac": _ratio(far, pred.size)}


# ----------------------------------------------------------------------------- aggregation

COUNT_COLUMNS = ("TP", "FP", "FN", "box_TP", "box_FP", "box_FN", "obj_N", "obj_found",
                 "gtbox_N", "gtbox_found", "far_FP", "far_N")


def _as_bool(col: pd.Series) -> np.ndarray:
    """A True/False column that may have been read back from CSV as text."""
    if col.dtype == bool:
        return col.to_numpy()
    return col.astype(str).str.strip().str.lower().isin(("true", "1", "1.0")).to_numpy()


def aggregate(metrics: pd.DataFrame, boxes: pd.DataFrame | None = None,
              by: tuple[str, ...] = ("scene", "method")) -> pd.DataFrame:
    """Per group (default scene x method): mean over views and pooled (micro) figures.

    ``metrics``: one row per view with the columns of :func:`score_view` (plus the ``by``
    columns and ``view``). Output columns: ``n_views``, ``<m>_mean`` for every pixel/box metric
    (NaN views ignored; ``n_<m>`` counts the views that had a defined value), the summed counts,
    and ``<m>_pooled`` from the summed counts. ``box_AP_pooled`` ranks the predicted boxes of all
    views of the group together; it needs ``boxes`` (rows of :func:`box_scores` with the ``by``
    columns) and is NaN without it.
    """
    by = list(by)
    rows = []
    for key, g in metrics.groupby(by, sort=True, dropna=False):
        key = key if isinstance(key, tuple) else (key,)
        row = dict(zip(by, key))
        row["n_views"] = int(g["view"].nunique()) if "view" in g else len(g)
        for m in PIXEL_METRICS + BOX_METRICS + OBJECT_METRICS + GTBOX_METRICS:
            if m in g:
                vals = pd.to_numeric(g[m], errors="coerce")
                row[f"{m}_mean"] = float(vals.mean()) if vals.notna().any() else float("nan")
                row[f"n_{m}"] = int(vals.notna().sum())
        for c in COUNT_COLUMNS:
            if c in g:
                row[c] = int(pd.to_numeric(g[c], errors="coerce").fillna(0).sum())
        if {"TP", "FP", "FN"} <= set(row):
            for k, v in scores_from_counts(row["TP"], row["FP"], row["FN"]).items():
                row[f"{k}_pooled"] = v
        if {"box_TP", "box_FP", "box_FN"} <= set(row):
            for k, v in scores_from_counts(row["box_TP"], row["box_FP"], row["box_FN"]).items():
                if k != "IoU":
                    row[f"box_{k}_pooled"] = v
        for found, n, out in (("obj_found", "obj_N", "obj_R_pooled"),
                              ("gtbox_found", "gtbox_N", "gtbox_R_pooled"),
                              ("far_FP", "far_N", "far_frac_pooled")):
            if n in row:
                row[out] = _ratio(row[found], row[n])
        row["box_AP_pooled"] = float("nan")
        if boxes is not None and len(boxes):
            sel = np.ones(len(boxes), dtype=bool)
            for c, v in zip(by, key):
                sel &= (boxes[c] == v).to_numpy()
            b = boxes[sel]
            pred = b[b["kind"] == "pred"]
            row["box_AP_pooled"] = average_precision(pred["score"].to_numpy(float),
                                                     _as_bool(pred["matched"]),
                                                     int((b["kind"] == "gt").sum()))
        rows.append(row)
    return pd.DataFrame(rows)
