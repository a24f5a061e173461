"""Instance tracking with one shared ID space, in the spirit of DEVA's decoupled design.

Segmentation is done per frame (any :class:`gdiff.segment.Segmenter`); this module only
associates. For every frame in chain order:

1. *Propagate*: the ID map of the previous frame (and, for tracks missed there, of the frame
   they were last seen in) is carried to the current frame. With rendered depth and known
   cameras this is a reprojection: each current pixel is back-projected with the current depth,
   projected into the source camera and given the source ID when the source depth agrees
   (``depth_tol_rel``), so occluded/disoccluded and changed surfaces get no ID. Without depth,
   OpenCV DIS optical flow (current -> source) with a forward-backward check is used; between
   two frames of the same pose (``pose_key``) without depth, the identity map is used.
2. *Same-pose link* (``link_same_pose``): when the frame of the same pose at the other time has
   already been tracked, its ID map is a second source. This is what makes the t0/t1 comparison
   work at every pose, not only at the join of the chain. A link between the two times must
   also pass an appearance test (:mod:`gdiff.appearance`): the track's mask at the other time
   and the segment, compared pixel for pixel (same pose), must show correlated log-colour
   texture (``link_min_similarity``). This breaks the link when an object was *replaced* by
   another of similar size at the same spot (the depth check alone lets it pass), and is not
   fooled by a lighting change. Sources at the other time and another pose are not used when
   the frames carry their time (IDs cross times only where the two times are pixel-aligned).
   Where the two times of a pose were segmented together (``TrackFrame.shared``, a sparse
   capture whose two rendered depths disagree: :mod:`gdiff.segment.pair`), the IDs are carried
   pixel for pixel without the depth test, and the link must also keep its colours: the
   chromaticity histograms of the linked pixels at the two times (exposure and white balance
   matched, :func:`gdiff.appearance.matched_chroma`) must agree
   (``link_min_color_similarity``), as a coloured object put on a surface of another colour
   changes them while the texture test may pass on two smooth surfaces.
3. *Merge*: predicted masks and current segments are paired by mask IoU with the Hungarian
   algorithm (gate ``iou_gate``); unmatched segments start new tracks (IDs are never reused;
   the tracks that remain at the end are renumbered 1..K);
   tracks unseen for more than ``max_missed`` frames are dropped (they may still be re-found by
   the same-pose link, which is re-identification of the same object).
4. *Vote* (``vote_window``): tracks seen in fewer than half of the first ``vote_window`` frames
   after their birth are flicker; their pixels are set to 0 (no instance). A track seen at a
   *key* frame (``TrackFrame.key``: the pose of a training photo, rendered at that photo's
   time) is kept whatever the vote: there the render reproduces a photo, so its segments are
   as reliable as the segmenter, while a sparse capture's renders between photos can be too
   blurred to carry an object to the next frames.
5. *Merge by 3D position* (``merge_3d``, frames with depth, cameras and time): two tracks
   that never share a frame, are seen at the same times and sit at the same place in the world
   (their median 3D points closer than ``merge_dist_frac`` x their size at every time both are
   seen) are one object and get one ID; e.g. a removed object seen on both paths, whose track
   cannot cross the after-time frames between them.

Chain order (see :func:`chain_order`): path p1 at t0 forward, then p1 at t1 backward (the join
is the same pose at the other time), then p2 at t1 forward and p2 at t0 backward.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from typing import Hashable

import cv2
import numpy as np
import pandas as pd
from scipy.optimize import linear_sum_assignment
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from .appearance import (Texture, bhattacharyya, chroma_hist, matched_chroma,
                         region_similarity, texture as image_texture)
from .cameras import Camera
from .errors import ConfigError
from .log import progress

log = logging.getLogger("gdiff.track")

WARP_MODES = ("auto", "reproject", "flow")


@dataclass
class TrackOptions:
    """Options of the ``track`` config section.

    warp: how IDs are carried between frames: ``reproject`` (rendered depth + cameras),
        ``flow`` (OpenCV DIS optical flow), ``auto`` (reproject when depth and cameras exist).
    iou_gate: minimum mask IoU between a propagated track and a segment to continue the track.
    max_missed: a track unseen in more than this many consecutive frames is dropped.
    depth_tol_rel: reprojection visibility test: |z_projected - z_source| / z_source must be
        below this for a pixel to inherit an ID.
    link_same_pose: also propagate from the frame of the same pose at the other time.
    vote_window: tracks seen in fewer than ceil(vote_window / 2) of their first vote_window
        frames are removed (0 disables voting).
    flow_fb_tol: optical-flow forward-backward consistency tolerance, pixels.
    link_min_similarity: a link between the two times at one pose needs at least this
        correlation of the log-colour texture of the two masks (see :mod:`gdiff.appearance`);
        masks with too little texture (``min_texture``) keep the link. -1 disables the test.
    min_texture: RMS log-colour gradient (per pixel, after removing shading) below which a
        region counts as untextured and its appearance is not compared.
    link_min_color_similarity: where the two times of a pose were segmented together
        (``TrackFrame.shared``), a link between them also needs at least this Bhattacharyya
        coefficient between the chromaticity histograms of the linked pixels at the two times
        (:func:`gdiff.appearance.chroma_hist`); pixels too dark for a chromaticity keep the
        link. 0 disables the test.
    merge_3d: merge tracks of one object by 3D position (needs depth, cameras, times).
    merge_dist_frac: two tracks are at the same place when their median 3D points are closer
        than this fraction of the object's size (square root of its metric area).
    """

    warp: str = "auto"
    iou_gate: float = 0.5
    max_missed: int = 5
    depth_tol_rel: float = 0.05
    link_same_pose: bool = True
    vote_window: int = 5
    flow_fb_tol: float = 1.5
    link_min_similarity: float = 0.35
    min_texture: float = 0.03
    link_min_color_similarity: float = 0.85
    merge_3d: bool = True
    merge_dist_frac: float = 0.5

    def __post_init__(self):
        if self.warp not in WARP_MODES:
            raise ConfigError(f"config key 'track.warp': unknown value {self.warp!r}; use one of "
                              f"{', '.join(WARP_MODES)}")
        if not 0.0 < self.iou_gate <= 1.0:
            raise ConfigError("config key 'track.iou_gate' must lie in (0, 1]")
        if self.max_missed < 0 or self.vote_window < 0:
            raise ConfigError("config keys 'track.max_missed' and 'track.vote_window' must be >= 0")
        if not -1.0 <= self.link_min_similarity <= 1.0:
            raise ConfigError("config key 'track.link_min_similarity' must lie in [-1, 1]")
        if not 0.0 <= self.link_min_color_similarity <= 1.0:
            raise ConfigError("config key 'track.link_min_color_similarity' must lie in [0, 1]")
        if self.min_texture < 0 or self.merge_dist_frac < 0:
            raise ConfigError("config keys 'track.min_texture' and 'track.merge_dist_frac' "
                              "must be >= 0")


@dataclass
class TrackFrame:
    """One frame to track.

    labels: int [H, W] segment labels of this frame, 0 = no segment (non-overlapping masks).
    rgb: float32 [H, W, 3] sRGB in [0, 1] (used for optical flow).
    depth: float32 [H, W] z-depth (scene units) or None.
    camera: the frame's :class:`Camera` (OpenCV axes) or None.
    pose_key: hashable naming the pose (e.g. ("p1", 7)); frames of the same pose at the two
        times share it. None = no same-pose partner.
    name: free label for logs and tables (e.g. ("p1", "t0", 7)).
    time: 0 (before) or 1 (after), or None when unknown.
    key: the frame is the pose of a training photo of its own time (its tracks skip the vote).
    shared: the frame was segmented together with the other time's frame of its pose
        (:mod:`gdiff.segment.pair`); when both are, IDs cross between them pixel for pixel,
        checked by appearance (texture and colour) instead of depth.
    cache: what is computed once per frame and used by every propagation into it.
    """

    labels: np.ndarray
    rgb: np.ndarray | None = None
    depth: np.ndarray | None = None
    camera: Camera | None = None
    pose_key: Hashable | None = None
    name: Hashable | None = None
    time: float | None = None
    key: bool = False
    shared: bool = False
    cache: dict = field(default_factory=dict, repr=False, compare=False)


@dataclass
class TrackResult:
    """ids: one int32 [H, W] ID map per input frame (0 = no instance), in input order.
    tracks: DataFrame with columns id, first, last (chain indices), n_frames, mean_area."""

    ids: list[np.ndarray]
    tracks: pd.DataFrame = field(default_factory=pd.DataFrame)


def labels_from_instances(instances, shape: tuple[int, int]) -> np.ndarray:
    """Paint instances (list of :class:`gdiff.segment.Instance`) into int32 labels [H, W].

    Labels are 1..n in list order; where masks overlap the earlier (higher-score) one wins.
    """
    labels = np.zeros(shape, np.int32)
    for i, inst in enumerate(instances, start=1):
        labels[inst.mask & (labels == 0)] = i
    return labels


def chain_order(n_frames: dict[str, int], paths=("p1", "p2")) -> list[tuple[str, str, int]]:
    """Chain (path, time, frame) carrying IDs from t0 to t1 at the same pose.

    p1: t0 forward, t1 backward; p2: t1 forward, t0 backward (each path joins the other time at
    the same pose; consecutive paths join through reprojection between their end poses).
    ``n_frames``: frames per path.
    """
    order = []
    for k, p in enumerate(paths):
        if p not in n_frames:
            continue
        n = n_frames[p]
        first, second = ("t0", "t1") if k % 2 == 0 else ("t1", "t0")
        order += [(p, first, i) for i in range(n)]
        order += [(p, second, i) for i in reversed(range(n))]
    return order


def _same_pose(a: TrackFrame, b: TrackFrame) -> bool:
    if a.pose_key is not None and a.pose_key == b.pose_key:
        return True
    if a.camera is not None and b.camera is not None:
        return bool(np.allclose(a.camera.c2w, b.camera.c2w, atol=1e-9))
    return False


def _camera_points(f: TrackFrame) -> tuple[np.ndarray, np.ndarray]:
    """Homogeneous points [H * W, 4] float64 of ``f``'s depth at its pixel centres, in its
    camera frame (OpenCV axes), and bool [H * W] where the depth is a surface (finite, > 0).
    Computed once per frame (``f.cache``): a frame is propagated into from several others."""
    if "points" not in f.cache:
        cd = f.camera
        z = f.depth.astype(np.float64)
        H, W = z.shape
        jj, ii = np.mgrid[0:H, 0:W]
        x = (ii + 0.5 - cd.cx) / cd.fx * z
        y = (jj + 0.5 - cd.cy) / cd.fy * z
        P = np.stack([x, y, z, np.ones_like(z)], -1).reshape(-1, 4)
        f.cache["points"] = (P, np.isfinite(z.ravel()) & (z.ravel() > 0))
    return f.cache["points"]


def reproject_ids(ids_src: np.ndarray, src: TrackFrame, dst: TrackFrame,
                  depth_tol_rel: float) -> np.ndarray:
    """Carry ``ids_src`` [Hs, Ws] of ``src`` onto the pixel grid of ``dst`` by reprojection.

    Each dst pixel centre (i+0.5, j+0.5) is back-projected with dst depth, transformed to the src
    camera (OpenCV axes) and looked up at the nearest src pixel; it inherits the ID only if the
    src depth there agrees within ``depth_tol_rel`` (visibility / no change). Returns int32
    [Hd, Wd], 0 where no ID is carried.
    """
    cd, cs = dst.camera, src.camera
    H, W = dst.depth.shape
    P, valid = _camera_points(dst)
    T = cs.w2c @ cd.c2w  # dst camera -> src camera
    Q = P @ T.T
    zs = Q[:, 2]
    ok = valid & (zs > 1e-9)
    u = np.where(ok, cs.fx * Q[:, 0] / np.where(ok, zs, 1) + cs.cx, -1)
    v = np.where(ok, cs.fy * Q[:, 1] / np.where(ok, zs, 1) + cs.cy, -1)
    Hs, Ws = ids_src.shape
    ui = np.floor(u).astype(np.int64)
    vi = np.floor(v).astype(np.int64)
    ok &= (ui >= 0) & (ui < Ws) & (vi >= 0) & (vi < Hs)
    out = np.zeros(H * W, np.int32)
    idx = np.flatnonzero(ok)
    zsrc = src.depth[vi[idx], ui[idx]].astype(np.float64)
    agree = np.abs(zs[idx] - zsrc) <= depth_tol_rel * np.maximum(zsrc, 1e-9)
    idx = idx[agree]
    out[idx] = ids_src[vi[idx], ui[idx]]
    return out.reshape(H, W)


_DIS = None


def _grey(rgb: np.ndarray) -> np.ndarray:
    """uint8 [H, W] luma of a float RGB image [H, W, 3] in [0, 1]."""
    return cv2.cvtColor((np.clip(rgb, 0, 1) * 255).astype(np.uint8), cv2.COLOR_RGB2GRAY)


def flow_matches(grey_a: np.ndarray, grey_b: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Dense optical flow (OpenCV DIS) from ``grey_a`` to ``grey_b`` (uint8 [H, W] each, the
    same size), checked back: ``(mx, my, err)``, float32 [H, W] each, where pixel (x, y) of
    ``a`` matches pixel (mx, my) of ``b`` (pixel indices, a(x) ~ b(x + flow)) and ``err`` is
    how far the flow back from there misses it, in pixels (huge where the match leaves
    ``b``): an occluded or changed pixel has no match to return to."""
    global _DIS
    if _DIS is None:
        _DIS = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    fwd = _DIS.calc(grey_a, grey_b, None)
    bwd = _DIS.calc(grey_b, grey_a, None)
    H, W = grey_a.shape
    jj, ii = np.mgrid[0:H, 0:W].astype(np.float32)
    mx, my = ii + fwd[..., 0], jj + fwd[..., 1]
    back = cv2.remap(bwd, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                     borderValue=(1e6, 1e6))
    err = np.hypot(fwd[..., 0] + back[..., 0], fwd[..., 1] + back[..., 1])
    return mx, my, err


def flow_ids(ids_src: np.ndarray, src: TrackFrame, dst: TrackFrame, fb_tol: float) -> np.ndarray:
    """Carry ``ids_src`` onto ``dst`` with optical flow dst -> src and a forward-backward check
    (:func:`flow_matches`).

    Returns int32 [H, W], 0 where the flow is inconsistent (occlusion) or leaves the image.
    """
    mx, my, err = flow_matches(_grey(dst.rgb), _grey(src.rgb))
    out = cv2.remap(ids_src.astype(np.float32), mx, my, cv2.INTER_NEAREST,
                    borderMode=cv2.BORDER_CONSTANT, borderValue=0).astype(np.int32)
    out[err > fb_tol] = 0
    return out


def propagate(ids_src: np.ndarray, src: TrackFrame, dst: TrackFrame, o: TrackOptions) -> np.ndarray:
    """Predicted ID map int32 [H, W] of ``dst`` from the ID map of ``src`` (see module doc)."""
    can_reproject = (src.depth is not None and dst.depth is not None
                     and src.camera is not None and dst.camera is not None)
    if o.warp == "reproject" and not can_reproject:
        raise ConfigError("track.warp is 'reproject' but frames lack depth or cameras; "
                          "use warp: auto or flow")
    if o.warp in ("auto", "reproject") and can_reproject:
        return reproject_ids(ids_src, src, dst, o.depth_tol_rel)
    if _same_pose(src, dst) or src.rgb is None or dst.rgb is None:
        if ids_src.shape != dst.labels.shape:
            raise ValueError("frames of the same pose must have the same size")
        return ids_src.astype(np.int32)
    return flow_ids(ids_src, src, dst, o.flow_fb_tol)


def id_dtype(max_id: int) -> type:
    """The narrowest type for ID maps with IDs up to ``max_id``: uint16 (as ID maps are
    written), else int32. A chain's ID maps are all held until it ends."""
    return np.uint16 if max_id <= np.iinfo(np.uint16).max else np.int32


def narrow_ids(a: np.ndarray) -> np.ndarray:
    """``a`` (non-negative integer labels or IDs) in :func:`id_dtype` of its largest value."""
    return a.astype(id_dtype(int(a.max(initial=0))), copy=False)


def unique_ids(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``np.unique(a.ravel(), return_inverse=True)`` for an ID map (non-negative integers): the
    sorted IDs present and each pixel's index into them, by counting instead of sorting."""
    flat = a.ravel()
    if flat.size == 0 or flat.dtype.kind not in "iu" or flat.min() < 0:
        return np.unique(flat, return_inverse=True)
    present = np.bincount(flat) > 0
    ids = np.flatnonzero(present).astype(flat.dtype)
    index = np.cumsum(present) - 1
    return ids, index[flat]


def _iou_table(pred: np.ndarray, segments: tuple[np.ndarray, np.ndarray]
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """IoU between every predicted track mask and every segment; ``segments`` is
    :func:`unique_ids` of the frame's segment labels (computed once per frame).

    Returns (track_ids [T], segment labels [S], iou [T, S]).
    """
    tids, pinv = unique_ids(pred)
    sids, sinv = segments
    inter = np.bincount(pinv.ravel() * len(sids) + sinv.ravel(),
                        minlength=len(tids) * len(sids)).reshape(len(tids), len(sids))
    pa = inter.sum(1)
    sa = inter.sum(0)
    iou = inter / np.maximum(pa[:, None] + sa[None, :] - inter, 1)
    tmask, smask = tids != 0, sids != 0
    return tids[tmask], sids[smask], iou[np.ix_(tmask, smask)]


def _time_of(fr: TrackFrame) -> float | None:
    return None if fr.time is None else float(fr.time)


def track_sequence(frames: list[TrackFrame], options: TrackOptions | None = None
                   ) -> TrackResult:
    """Track ``frames`` (in chain order) and return one shared-ID map per frame.

    See the module docstring for the algorithm. The tracks that survive voting and merging
    are numbered 1..K in the order they first appeared (0 = no instance).
    """
    o = options or TrackOptions()
    out: list[np.ndarray] = []
    next_id = 1
    last_seen: dict[int, int] = {}  # track id -> chain index of its last observation
    seen_at: dict[int, list[int]] = {}  # track id -> chain indices where observed
    at_key: set[int] = set()  # tracks seen at a key frame (kept whatever the vote)
    areas: dict[int, int] = {}
    done_by_pose: dict[Hashable, int] = {}
    grads: dict[int, Texture] = {}
    positions: dict[int, dict[float, list]] = {}  # track -> time -> [(median point, size)]
    n_broken = 0

    def texture(k: int) -> Texture:
        if k not in grads:
            grads[k] = image_texture(frames[k].rgb, o.min_texture)
        return grads[k]

    for k, fr in enumerate(progress(frames, desc="track", total=len(frames))):
        labels = np.asarray(fr.labels)
        seg_sids, seg_index = unique_ids(labels)
        sources: list[tuple[int, np.ndarray]] = []
        if k > 0:
            sources.append((k - 1, out[k - 1]))
            # tracks alive but missed in the previous frame: propagate from where last seen
            alive_missed = [t for t, f in last_seen.items()
                            if f < k - 1 and k - 1 - f <= o.max_missed]
            for f in sorted({last_seen[t] for t in alive_missed}):
                keep = [t for t in alive_missed if last_seen[t] == f]
                sources.append((f, np.where(np.isin(out[f], keep), out[f], 0)))
        if o.link_same_pose and fr.pose_key is not None and fr.pose_key in done_by_pose:
            f = done_by_pose[fr.pose_key]
            if f != k - 1:
                sources.append((f, out[f]))
        best: dict[tuple[int, int], float] = {}
        for f, ids_src in sources:
            src = frames[f]
            cross_time = (_time_of(src) is not None and _time_of(fr) is not None
                          and _time_of(src) != _time_of(fr))
            same_pose = _same_pose(src, fr)
            if cross_time and not same_pose:
                continue  # IDs cross times only where the two times are pixel-aligned
            check = (cross_time or (same_pose and src.time is None)) and \
                o.link_min_similarity > -1 and src.rgb is not None and fr.rgb is not None
            # the two times cut together (a sparse capture): pixel for pixel, no depth test
            shared = cross_time and same_pose and src.shared and fr.shared
            colour = shared and o.link_min_color_similarity > 0 and src.rgb is not None \
                and fr.rgb is not None
            pred = ids_src.astype(np.int32) if shared else propagate(ids_src, src, fr, o)
            chroma = None  # the pair's matched_chroma, once per source, when a link needs it
            tids, sids, iou = _iou_table(pred, (seg_sids, seg_index))
            for a, b in zip(*np.nonzero(iou > 0)):
                t, s = tids[a], sids[b]
                if (check or colour) and iou[a, b] >= o.iou_gate:
                    both = (ids_src == t) & (labels == s)
                    sim = (region_similarity(texture(f), texture(k), both, o.min_texture)
                           if check else float("nan"))
                    if sim < o.link_min_similarity:  # NaN (untextured) keeps the link
                        n_broken += 1
                        log.debug("frame %s: link of track %d to segment %d broken "
                                  "(texture similarity %.2f)", fr.name, t, s, sim)
                        continue
                    if colour:
                        if chroma is None:
                            chroma = matched_chroma(src.rgb, fr.rgb)
                        h0, h1 = chroma_hist(chroma[0], both), chroma_hist(chroma[1], both)
                        csim = bhattacharyya(h0, h1) if h0.sum() and h1.sum() else 1.0
                        if csim < o.link_min_color_similarity:  # too dark: keeps the link
                            n_broken += 1
                            log.debug("frame %s: link of track %d to segment %d broken "
                                      "(colour similarity %.2f)", fr.name, t, s, csim)
                            continue
                key = (int(t), int(s))
                best[key] = max(best.get(key, 0.0), float(iou[a, b]))
        seg_area = np.bincount(seg_index.ravel(), minlength=len(seg_sids))
        area_of = {int(s): int(a) for s, a in zip(seg_sids, seg_area) if s != 0}
        seg_ids = list(area_of)
        assign: dict[int, int] = {}
        if best and seg_ids:
            trk = sorted({t for t, _ in best})
            ti = {t: i for i, t in enumerate(trk)}
            si = {s: j for j, s in enumerate(seg_ids)}
            M = np.zeros((len(trk), len(seg_ids)))
            for (t, s), v in best.items():
                if s in si:
                    M[ti[t], si[s]] = v
            rows, cols = linear_sum_assignment(-M)
            for r, c in zip(rows, cols):
                if M[r, c] >= o.iou_gate:
                    assign[seg_ids[c]] = trk[r]
        for s in seg_ids:
            if s not in assign:
                assign[s] = next_id
                next_id += 1
        # the ID maps of the whole chain stay in memory until the end: the narrowest type
        lut = np.zeros(int(labels.max(initial=0)) + 1, id_dtype(next_id - 1))
        for s in seg_ids:
            lut[s] = assign[s]
        ids = lut[labels]
        out.append(ids)
        for s, t in assign.items():
            last_seen[t] = k
            seen_at.setdefault(t, []).append(k)
            if fr.key:
                at_key.add(t)
            areas[t] = areas.get(t, 0) + area_of[s]
        if fr.pose_key is not None:
            done_by_pose[fr.pose_key] = k
        # keep memory bounded on long chains: textures of frames out of the propagation
        # window (also those of same-pose partners far back) are dropped
        for j in [j for j in grads if j <= k - 2 * (o.max_missed + 2)]:
            del grads[j]
        if o.merge_3d and fr.depth is not None and fr.camera is not None and fr.time is not None:
            for t, rec in frame_positions(ids, fr).items():
                positions.setdefault(t, {}).setdefault(float(fr.time), []).append(rec)
    n = len(frames)
    # raw ID -> final ID: voting, merging and renumbering are composed here and the ID maps
    # are relabelled once, at the end
    lut = np.arange(max(next_id, 1), dtype=np.int32)
    removed = set()
    if o.vote_window > 0:
        for t, ks in seen_at.items():
            window = min(o.vote_window, n - ks[0])
            need = math.ceil(window / 2)
            if t not in at_key and sum(1 for x in ks if x < ks[0] + o.vote_window) < need:
                removed.add(t)
        lut[sorted(removed)] = 0
    merged = {}
    if o.merge_3d:
        # positions were gathered frame by frame during tracking (frames need not stay in
        # memory); voting only removed whole tracks, the others kept their pixels
        pos = _summarise_positions({t: v for t, v in positions.items() if t not in removed})
        merged = merge_positions(pos, {t: set(ks) for t, ks in seen_at.items()
                                       if t not in removed}, o.merge_dist_frac)
        if merged:
            for a, b in merged.items():
                lut[a] = b
            for a, b in merged.items():
                if a in seen_at:
                    seen_at[b] = sorted(seen_at.get(b, []) + seen_at.pop(a))
                    areas[b] = areas.get(b, 0) + areas.pop(a, 0)
    # surviving tracks renumbered 1..K in their order (the tracker hands out a new ID to every
    # unmatched segment, so on long sequences raw IDs run far beyond the tracks that remain)
    keep = sorted(t for t in seen_at if t not in removed)
    number = np.zeros(len(lut), dtype=id_dtype(len(keep)))
    number[keep] = np.arange(1, len(keep) + 1)
    lut = number[lut]
    for k, m in enumerate(out):  # in place: one chain of ID maps in memory, not two
        out[k] = lut[m]
    rows = [dict(id=int(number[t]), first=seen_at[t][0], last=seen_at[t][-1],
                 n_frames=len(seen_at[t]), mean_area=areas[t] / len(seen_at[t])) for t in keep]
    log.info("tracked %d frames: %d tracks (%d removed by voting, %d merged by 3D position, "
             "%d cross-time links broken by appearance)", n, len(rows), len(removed),
             len(merged), n_broken)
    return TrackResult(ids=out, tracks=pd.DataFrame(
        rows, columns=["id", "first", "last", "n_frames", "mean_area"]))


def world_points(depth: np.ndarray, camera: Camera) -> np.ndarray:
    """World points [H, W, 3] of a z-depth map [H, W] seen by ``camera`` (pixel centres +0.5,
    OpenCV axes); NaN where the depth is not finite and positive."""
    z = np.asarray(depth, np.float64)
    z = np.where(np.isfinite(z) & (z > 0), z, np.nan)
    H, W = z.shape
    u = (np.arange(W) + 0.5 - camera.cx) / camera.fx
    v = (np.arange(H) + 0.5 - camera.cy) / camera.fy
    P = np.stack([u[None, :] * z, v[:, None] * z, z], -1)
    return P @ camera.c2w[:3, :3].T + camera.c2w[:3, 3]


def frame_positions(ids: np.ndarray, frame: TrackFrame) -> dict[int, tuple[np.ndarray, float]]:
    """Per track in one frame's ID map ``ids`` int [H, W]: (median world point [3], metric
    size), for tracks with at least 4 finite points. The size is sqrt(area) x median depth /
    focal length (scene units). ``frame`` needs depth and camera."""
    m = np.asarray(ids).ravel()
    order = np.argsort(m, kind="stable")
    tids, starts, counts = np.unique(m[order], return_index=True, return_counts=True)
    if not (tids != 0).any():
        return {}
    P = world_points(frame.depth, frame.camera).reshape(-1, 3)
    z = np.asarray(frame.depth).ravel()
    out = {}
    for t, a, c in zip(tids, starts, counts):
        if t == 0:
            continue
        idx = order[a:a + c]
        pts = P[idx]
        pts = pts[np.isfinite(pts).all(1)]
        if len(pts) < 4:
            continue
        size = np.sqrt(c) * np.median(z[idx]) / frame.camera.fx
        out[int(t)] = (np.median(pts, 0), size)
    return out


def _summarise_positions(acc: dict[int, dict[float, list]]
                         ) -> dict[int, dict[float, tuple[np.ndarray, float]]]:
    """Per track and time: medians over frames of the :func:`frame_positions` records."""
    out = {}
    for t, per_time in acc.items():
        out[t] = {tm: (np.median(np.stack([p for p, _ in v]), 0), float(np.median([s for _, s in v])))
                  for tm, v in per_time.items()}
    return out


def track_positions(ids: list[np.ndarray], frames: list[TrackFrame]
                    ) -> dict[int, dict[float, tuple[np.ndarray, float]]]:
    """Per track and time: (median world point [3], metric size) over all its observations.

    The size is the median over frames of sqrt(area) x median depth / focal length (scene
    units). Frames without depth, camera or time are skipped.
    """
    acc: dict[int, dict[float, list]] = {}
    for m, fr in zip(ids, frames):
        if fr.depth is None or fr.camera is None or fr.time is None:
            continue
        for t, rec in frame_positions(m, fr).items():
            acc.setdefault(t, {}).setdefault(float(fr.time), []).append(rec)
    return _summarise_positions(acc)


def link_groups(n: int, links: list[tuple[int, int]]) -> np.ndarray:
    """Group label int [n] of items 0..n-1 joined (transitively) by the undirected ``links``
    [(i, j), ...]: the connected components of the link graph (scipy)."""
    i, j = (np.array(links, np.int64).reshape(-1, 2).T if links
            else (np.zeros(0, np.int64), np.zeros(0, np.int64)))
    graph = coo_matrix((np.ones(len(i)), (i, j)), shape=(n, n))
    return connected_components(graph, directed=False)[1]


#: tracks compared at once with all others in :func:`merge_positions` (bounds its memory)
_MERGE_BLOCK = 256


def merge_by_position(ids: list[np.ndarray], frames: list[TrackFrame],
                      dist_frac: float) -> dict[int, int]:
    """Tracks of one object by 3D position (see the module docstring, step 5).

    Returns {track id: id it merges into} (the smaller ID of a group is kept).
    """
    frames_of: dict[int, set[int]] = {}
    for k, m in enumerate(ids):
        for t in unique_ids(m)[0]:
            if t:
                frames_of.setdefault(int(t), set()).add(k)
    return merge_positions(track_positions(ids, frames), frames_of, dist_frac)


def merge_positions(pos: dict[int, dict[float, tuple[np.ndarray, float]]],
                    frames_of: dict[int, set[int]], dist_frac: float) -> dict[int, int]:
    """:func:`merge_by_position` from the tracks' positions (:func:`track_positions`) and the
    frames each track is seen in (``frames_of``: track id -> set of frame indices)."""
    if len(pos) < 2:
        return {}
    tr = sorted(pos)
    # tracks seen at the same times are the same object when, at every one of them, their
    # median points are closer than dist_frac x the smaller size and the sizes agree within 1.5x
    by_times: dict[tuple, list[int]] = {}
    for i, a in enumerate(tr):
        by_times.setdefault(tuple(sorted(pos[a])), []).append(i)
    links = []
    for times, members in by_times.items():
        m = len(members)
        if m < 2:
            continue
        pts = {tm: np.stack([pos[tr[i]][tm][0] for i in members]).astype(np.float64)
               for tm in times}
        size = {tm: np.array([pos[tr[i]][tm][1] for i in members], np.float64) for tm in times}
        for r0 in range(0, m, _MERGE_BLOCK):  # rows in blocks: memory of a block x m pairs
            r1 = min(m, r0 + _MERGE_BLOCK)
            same = np.arange(m)[None, :] > np.arange(r0, r1)[:, None]  # each pair once
            for tm in times:
                p, sz = pts[tm], size[tm]
                small = np.minimum(sz[r0:r1, None], sz[None, :])
                dist = np.sqrt(((p[r0:r1, None, :] - p[None, :, :]) ** 2).sum(-1))
                same &= (dist <= dist_frac * small) & (np.maximum(sz[r0:r1, None], sz[None, :])
                                                       <= 1.5 * small)
            for u, v in zip(*np.nonzero(same)):
                i, j = members[r0 + u], members[v]
                if not frames_of.get(tr[i], set()) & frames_of.get(tr[j], set()):
                    links.append((i, j))
    if not links:
        return {}
    label = link_groups(len(tr), links)
    # a group may merge only tracks that never share a frame
    out = {}
    groups: dict[int, list[int]] = {}
    for t, g in zip(tr, label):
        groups.setdefault(int(g), []).append(t)
    for members in groups.values():
        r = members[0]  # the smallest ID of the group (tr is sorted)
        used: set[int] = set()
        for t in members:
            if frames_of.get(t, set()) & used:
                continue
            used |= frames_of.get(t, set())
            if t != r:
                out[t] = r
    return out
