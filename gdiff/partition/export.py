"""Outputs of the partition stage: changed / unchanged PLY split, change maps and overlays at
the key poses with their scores.

Conventions: see :mod:`gdiff.partition`.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import torch

from ..io import write_image, write_mask
from ..log import progress
from ..metrics import pixel_scores, scores_from_counts
from ..splat.gaussians import Gaussians
from ..splat.ply import write_gaussians
from .data import KeyView, _load_image, _load_mask
from .model import PartitionModel, render_change_map

MIN_VISIBLE_OPACITY = 0.005  # a Gaussian below this opacity at time t is absent at t


@torch.no_grad()
def split_gaussians(pm: PartitionModel, t: float, threshold: float = 0.5):
    """Changed and unchanged Gaussians at time ``t`` (activated, deformed to ``t``).

    A Gaussian is changed when its probability ``softmax(Conv(e))[changed]`` exceeds
    ``threshold``; Gaussians whose opacity at ``t`` is below ``MIN_VISIBLE_OPACITY`` are absent
    at ``t`` (e.g. a removed object's Gaussians after the change) and left out.
    Returns (changed, unchanged) :class:`gdiff.splat.gaussians.Gaussians`.
    """
    g = pm.fit.at_time(float(t)).detach()
    p = pm.gaussian_probability()
    present = g.opacities >= MIN_VISIBLE_OPACITY
    return g.subset((p > threshold) & present), g.subset((p <= threshold) & present)


def write_split_ply(pm: PartitionModel, out_dir, threshold: float = 0.5) -> dict:
    """Write ``changed_t0.ply`` / ``changed_t1.ply`` (the changed Gaussians deformed to t=0 / t=1),
    ``changed.ply`` (those present at t=0 followed by those present at t=1: what was there and
    changed plus what is new) and ``unchanged.ply`` (the unchanged Gaussians at t=0), all in the
    3DGS PLY layout. The unchanged Gaussians at t=1 are not written: they are the same
    Gaussians, and a copy per time would double the largest file of the stage.
    Returns the Gaussian counts per file (``n_changed_t0``, ``n_changed_t1``, ``n_changed``,
    ``n_unchanged``)."""
    out = Path(out_dir)
    parts = {}
    for t in (0, 1):
        parts[f"changed_t{t}"], unchanged = split_gaussians(pm, t, threshold)
        if t == 0:
            parts["unchanged"] = unchanged
    c0, c1 = parts["changed_t0"], parts["changed_t1"]
    parts["changed"] = Gaussians(*(torch.cat([getattr(c0, k), getattr(c1, k)])
                                   for k in ("means", "quats", "scales", "opacities", "sh")),
                                 sh_degree=c0.sh_degree)
    counts = {}
    for name, g in parts.items():
        write_gaussians(out / f"{name}.ply", g)
        counts[f"n_{name}"] = len(g)
    return counts


def overlay(image: np.ndarray, mask: np.ndarray, colour=(1.0, 0.15, 0.1), alpha: float = 0.5,
            outline: np.ndarray | None = None) -> np.ndarray:
    """The image [H, W, 3] (float sRGB) with ``mask`` [H, W] tinted in ``colour`` and its
    outline drawn; ``outline`` (optional bool [H, W], e.g. a target mask) is drawn in green."""
    img = np.clip(np.asarray(image, np.float32), 0, 1).copy()
    m = np.asarray(mask, bool)
    img[m] = (1 - alpha) * img[m] + alpha * np.asarray(colour, np.float32)
    for mm, col in ((m, colour), (outline, (0.1, 1.0, 0.2))):
        if mm is None:
            continue
        cs, _ = cv2.findContours(np.asarray(mm, np.uint8), cv2.RETR_EXTERNAL,
                                 cv2.CHAIN_APPROX_NONE)
        cv2.drawContours(img, cs, -1, tuple(float(c) for c in col), 1)
    return img


def key_view_maps(pm: PartitionModel, views: list[KeyView],
                  before_gate: float | None = None) -> list[dict]:
    """Change probabilities at every key pose: per view a dict ``prob_t0``, ``prob_t1`` and
    ``prob`` (their union: :func:`render_change_map` with ``before_gate``, None = the model's),
    float32 [H, W] at the view's camera."""
    out = []
    for v in progress(views, desc="partition maps"):
        r = render_change_map(pm, v.camera, None, before_gate=before_gate)
        out.append({k: r[k] for k in ("prob_t0", "prob_t1", "prob")})
    return out


# thresholds tried by choose_threshold: every hundredth in (0, 1)
THRESHOLDS = np.round(np.arange(0.01, 1.0, 0.01), 2)


def choose_threshold(probs, masks, thresholds=THRESHOLDS) -> dict:
    """The probability threshold that best reproduces the training masks.

    Pools the pixels of every key view: ``probs`` (iterable of [H, W] change probabilities,
    e.g. the union maps of :func:`key_view_maps`) against ``masks`` (bool [H, W], e.g. the
    compare stage's union masks), and takes the threshold of largest F1 (``prob > th`` is
    changed); ties go to the one nearest 0.5.

    Returns dict ``threshold`` (None when the masks have no changed or no unchanged pixel: F1
    says nothing then), ``f1`` (at it) and ``curve`` (DataFrame: threshold, P, R, F1, IoU).
    """
    pos, neg = [], []
    for p, m in zip(probs, masks):
        p, m = np.asarray(p, np.float32).ravel(), np.asarray(m, bool).ravel()
        pos.append(p[m])
        neg.append(p[~m])
    pos, neg = np.sort(np.concatenate(pos)), np.sort(np.concatenate(neg))
    th = np.asarray(thresholds, np.float64)
    tp = len(pos) - np.searchsorted(pos, th, side="right")   # prob > th
    fp = len(neg) - np.searchsorted(neg, th, side="right")
    fn = len(pos) - tp
    rows = [{"threshold": float(t), **scores_from_counts(a, b, c)}
            for t, a, b, c in zip(th, tp, fp, fn)]
    curve = pd.DataFrame(rows)
    if len(pos) == 0 or len(neg) == 0:
        return {"threshold": None, "f1": float("nan"), "curve": curve}
    f1 = curve["F1"].fillna(0.0).to_numpy()
    best = np.flatnonzero(f1 == f1.max())
    i = best[np.argmin(np.abs(th[best] - 0.5))]
    return {"threshold": float(th[i]), "f1": float(f1[i]), "curve": curve}


def write_key_maps(pm: PartitionModel, views: list[KeyView], maps_dir,
                   maps: list[dict] | None = None):
    """Render change maps at every key pose and score them against the compare-stage masks.

    Writes, per key view ``<name>`` (``<path>_<frame>``): ``maps/{t0,t1,union}/<name>.png``
    (binary masks at ``pm.threshold``, 255 = changed), ``maps/{t0,t1,union}_prob/<name>.png``
    (probability x 255) and ``maps/overlay/<name>.png`` (the photo with the union map in red
    and the compare stage's union mask outlined in green). ``maps``: the views'
    :func:`key_view_maps` when already rendered. Returns a DataFrame with one row per view:
    name, time, IoU of the map at the photo's time vs its target (``iou_own_time``) and of the
    union map vs ``mask_union`` (``iou_union``), plus pixel F1 of the union.
    """
    maps_dir = Path(maps_dir)
    maps = key_view_maps(pm, views) if maps is None else maps
    rows = []
    th = pm.threshold
    for v, r in zip(views, maps):
        union = r["prob"] > th
        for key, p in (("t0", r["prob_t0"]), ("t1", r["prob_t1"]), ("union", r["prob"])):
            write_mask(maps_dir / key / f"{v.name}.png", p > th)
            write_image(maps_dir / f"{key}_prob" / f"{v.name}.png",
                        np.repeat(p[..., None], 3, axis=2))
        own = _load_mask(v.target, v.camera) > 0.5
        union_t = _load_mask(v.masks["union"], v.camera) > 0.5
        photo = _load_image(v.image, v.camera)
        write_image(maps_dir / "overlay" / f"{v.name}.png",
                    overlay(photo, union, outline=union_t))
        own_pred = r[f"prob_t{int(v.time)}"] > th
        s_own, s_union = pixel_scores(own_pred, own), pixel_scores(union, union_t)
        rows.append({"name": v.name, "image": str(v.image), "time": v.time,
                     "iou_own_time": s_own["IoU"], "iou_union": s_union["IoU"],
                     "f1_union": s_union["F1"]})
    return pd.DataFrame(rows)
