"""Instance-level change detection by comparing tracked IDs at the same pose and two times.

For every pose of a path the ID maps at t=0 and t=1 (one shared ID space, see
:mod:`gdiff.track`) are compared:

* an ID visible at one time and absent at the other, or visible at both with drastically
  different masks (IoU < ``presence_iou``), is a *candidate* change at that pose;
* the candidate is *confirmed* by evidence inside its mask that the scene really differs there:
  the fraction of pixels whose rendered depth differs between the two times by more than
  ``depth_change_rel`` (illumination-invariant; used when depth exists), otherwise the fraction
  whose illumination-invariant appearance differs (grey-world-normalised chromaticity, local
  normalised cross-correlation of log intensity) - this rejects segments that only exist because
  a shadow or a highlight moved;
* per ID, over all poses where it is visible, the share of confirmed candidates decides
  (``vote_frac``): changed IDs are changed on every frame (temporal consistency);
* a changed ID is ``removed`` (seen at t0 only), ``added`` (t1 only) or ``moved`` (seen at both
  at different places, or a removed/added pair with the same appearance and size).

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

from .errors import ConfigError
from .io import srgb_to_linear

log = logging.getLogger("gdiff.change")

CHANGE_TYPES = ("added", "removed", "moved")


@dataclass
class CompareOptions:
    """Options of the ``compare`` config section.

    presence_iou: an ID visible at both times whose two masks at one pose overlap with IoU
        below this is "drastically different" (candidate change).
    min_area: instance masks smaller than this (pixels) are ignored at that pose.
    depth_change_rel: a pixel's depth changed when |z0 - z1| / min(z0, z1) exceeds this.
    chroma_tol: a pixel's chromaticity (grey-world normalised, L1) changed above this.
    ncc_min: local normalised cross-correlation of log intensity (7x7) below this on textured
        pixels counts as an appearance change.
    min_evidence: a candidate is confirmed at a pose when at least this fraction of its mask
        shows evidence of change (depth when available, appearance otherwise).
    vote_frac: an ID is changed when confirmed at >= this fraction of the poses where visible.
    moved_similarity: a removed and an added instance are one moved object when the
        Bhattacharyya coefficient of their chromaticity histograms is >= this and their metric
        sizes agree within a factor 1.5.
    """

    presence_iou: float = 0.3
    min_area: int = 24
    depth_change_rel: float = 0.05
    chroma_tol: float = 0.08
    ncc_min: float = 0.5
    min_evidence: float = 0.3
    vote_frac: float = 0.5
    moved_similarity: float = 0.85

    def __post_init__(self):
        for k in ("presence_iou", "min_evidence", "vote_frac", "moved_similarity"):
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


def _normalised_chroma(rgb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Grey-world-normalised chromaticity [H, W, 3] (sums to 1) and its confidence [H, W]."""
    lin = srgb_to_linear(rgb).astype(np.float64)
    lin = lin / np.maximum(lin.reshape(-1, 3).mean(0), 1e-6)  # global colour cast removed
    s = lin.sum(-1)
    return lin / np.maximum(s, 1e-6)[..., None], np.clip(s / 0.15, 0, 1)


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

def _chroma_hist(rgb: np.ndarray, mask: np.ndarray, bins: int = 8) -> np.ndarray:
    c, w = _normalised_chroma(rgb)
    sel = mask & (w > 0.3)
    if not sel.any():
        return np.zeros((bins, bins))
    h, _, _ = np.histogram2d(np.clip(c[sel, 0], 0, 0.999), np.clip(c[sel, 1], 0, 0.999),
                             bins=bins, range=[[0, 1], [0, 1]])
    return h


def pose_stats(ids0: np.ndarray, ids1: np.ndarray, o: CompareOptions,
               rgb0: np.ndarray | None = None, rgb1: np.ndarray | None = None,
               depth0: np.ndarray | None = None, depth1: np.ndarray | None = None,
               focal: float | None = None) -> dict[int, dict]:
    """Compare the ID maps int [H, W] of one pose at t0 and t1.

    Returns, per ID visible at this pose: ``area0``, ``area1`` (pixels), ``candidate`` (absent
    at one time or IoU < presence_iou), ``evidence`` (fraction of the candidate's masks showing
    change; 1.0 when there is no image/depth to check), ``confirmed``, ``hist`` (chromaticity
    histogram, for moved pairing) and ``size`` (metric size sqrt(area) * z / f when depth and
    ``focal`` are known, else sqrt(area) in pixels).
    """
    if depth0 is not None and depth1 is not None:
        ev_map = depth_change(depth0, depth1, o.depth_change_rel)
    elif rgb0 is not None and rgb1 is not None:
        ev_map = appearance_change(rgb0, rgb1, o.chroma_tol, o.ncc_min)
    else:
        ev_map = None
    out: dict[int, dict] = {}
    labels = np.union1d(np.unique(ids0), np.unique(ids1))
    for t in labels[labels != 0]:
        m0, m1 = ids0 == t, ids1 == t
        a0, a1 = int(m0.sum()), int(m1.sum())
        a0 = a0 if a0 >= o.min_area else 0
        a1 = a1 if a1 >= o.min_area else 0
        if a0 == 0 and a1 == 0:
            continue
        if a0 and a1:
            iou = (m0 & m1).sum() / (m0 | m1).sum()
            cand = iou < o.presence_iou
            region = m0 ^ m1
        else:
            cand = True
            region = m0 if a0 else m1
        evidence = 1.0
        if cand and ev_map is not None:
            evidence = float(ev_map[region].mean()) if region.any() else 0.0
        rec = dict(area0=a0, area1=a1, candidate=bool(cand), evidence=evidence,
                   confirmed=bool(cand and evidence >= o.min_evidence))
        rgb, m, z = (rgb0, m0, depth0) if a0 else (rgb1, m1, depth1)
        rec["hist"] = _chroma_hist(rgb, m) if rgb is not None else None
        size = np.sqrt(m.sum())
        if z is not None and focal:
            size = size * float(np.median(z[m])) / focal
        rec["size"] = float(size)
        out[int(t)] = rec
    return out


def decide(stats: list[tuple[object, dict[int, dict]]], o: CompareOptions) -> pd.DataFrame:
    """Per-ID decision from the per-pose stats ``[(pose_name, pose_stats(...)), ...]``.

    Returns a DataFrame with columns id, changed, type, partner, n_t0, n_t1 (poses where seen
    at each time), n_confirmed, first, last (pose names), area (mean pixels).
    """
    acc: dict[int, dict] = defaultdict(lambda: dict(n0=0, n1=0, n=0, conf=0, poses=[],
                                                    area=[], hist=None, size=[]))
    for name, st in stats:
        for t, r in st.items():
            a = acc[t]
            a["n"] += 1
            a["n0"] += r["area0"] > 0
            a["n1"] += r["area1"] > 0
            a["conf"] += r["confirmed"]
            a["poses"].append(name)
            a["area"].append(max(r["area0"], r["area1"]))
            a["size"].append(r["size"])
            if r["hist"] is not None:
                a["hist"] = r["hist"] if a["hist"] is None else a["hist"] + r["hist"]
    rows = []
    for t, a in sorted(acc.items()):
        changed = a["conf"] >= o.vote_frac * a["n"] and a["conf"] > 0
        typ = ""
        if changed:
            if a["n1"] <= 0.1 * a["n0"]:
                typ = "removed"
            elif a["n0"] <= 0.1 * a["n1"]:
                typ = "added"
            else:
                typ = "moved"
        rows.append(dict(id=t, changed=bool(changed), type=typ, partner=0, n_t0=a["n0"],
                         n_t1=a["n1"], n_confirmed=a["conf"], first=a["poses"][0],
                         last=a["poses"][-1], area=float(np.mean(a["area"])),
                         _hist=a["hist"], _size=float(np.median(a["size"]))))
    df = pd.DataFrame(rows, columns=["id", "changed", "type", "partner", "n_t0", "n_t1",
                                     "n_confirmed", "first", "last", "area", "_hist", "_size"])
    _pair_moved(df, o)
    return df.drop(columns=["_hist", "_size"])


def _bhattacharyya(h1, h2) -> float:
    if h1 is None or h2 is None or h1.sum() == 0 or h2.sum() == 0:
        return 0.0
    return float(np.sqrt(h1 / h1.sum() * h2 / h2.sum()).sum())


def _pair_moved(df: pd.DataFrame, o: CompareOptions) -> None:
    """Pair removed and added IDs of the same appearance and size into ``moved`` (in place)."""
    rem = df.index[df["type"] == "removed"].tolist()
    add = df.index[df["type"] == "added"].tolist()
    if not rem or not add:
        return
    S = np.zeros((len(rem), len(add)))
    for i, r in enumerate(rem):
        for j, a in enumerate(add):
            s0, s1 = df.at[r, "_size"], df.at[a, "_size"]
            if max(s0, s1) > 1.5 * min(s0, s1):
                continue
            S[i, j] = _bhattacharyya(df.at[r, "_hist"], df.at[a, "_hist"])
    rows, cols = linear_sum_assignment(-S)
    for i, j in zip(rows, cols):
        if S[i, j] >= o.moved_similarity:
            r, a = rem[i], add[j]
            df.at[r, "type"] = df.at[a, "type"] = "moved"
            df.at[r, "partner"] = int(df.at[a, "id"])
            df.at[a, "partner"] = int(df.at[r, "id"])


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
    from .cameras import Camera
    from .segment import SegmentOptions, make_segmenter
    from .track import TrackFrame, TrackOptions, labels_from_instances, track_sequence

    o = options or CompareOptions()
    seg = make_segmenter(segment_options or SegmentOptions())
    H, W = rgb0.shape[:2]
    cam = None
    if K is not None:
        K = np.asarray(K, float)
        cam = Camera(W, H, K[0, 0], K[1, 1], K[0, 2], K[1, 2])
    frames = []
    for rgb, z in ((rgb0, depth0), (rgb1, depth1)):
        inst = seg.segment(rgb, z, None, K)
        frames.append(TrackFrame(labels=labels_from_instances(inst, (H, W)), rgb=rgb, depth=z,
                                 camera=cam if z is not None else None, pose_key="pair"))
    to = track_options or TrackOptions()
    to = TrackOptions(**{**to.__dict__, "vote_window": 0})  # two frames: nothing to vote on
    res = track_sequence(frames, to)
    st = pose_stats(res.ids[0], res.ids[1], o, rgb0, rgb1, depth0, depth1,
                    focal=float(K[0, 0]) if K is not None else None)
    df = decide([("pair", st)], o)
    return change_masks(res.ids[0], res.ids[1], df.loc[df["changed"], "id"].tolist())
