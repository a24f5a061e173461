"""Stage ``segment``: every rendered frame of the four sequences (p1/p2 x t0/t1) segmented
and tracked in one ID space (chain order of :func:`gdiff.track.chain_order`).

Files (results/<scene>/): reads ``render/<path>/<t>/NNNNN.exr`` and ``sequence/poses.json``
(:mod:`gdiff.frames`); writes ``instances/<path>/<t>/NNNNN.png`` (uint16 IDs),
``instances/tracks.csv`` and, last, ``instances/index.json`` (with ``segment.overlays`` also
``instances/overlay/<path>/<t>/NNNNN.jpg``).
"""

from __future__ import annotations

import logging
import os
import shutil
from collections import OrderedDict
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np
import pandas as pd

from ..errors import SceneError
from ..frames import TIMES, Key, key_frames, read_frame, read_sequence, render_files
from ..io import MAX_ID, write_csv, write_ids, write_image, write_json
from ..log import progress
from ..parallel import ordered_map
from ..track import (TrackFrame, TrackOptions, chain_order, labels_from_instances, narrow_ids,
                     track_sequence)
from .base import Segmenter, SegmentOptions, make_segmenter
from .pair import shared_pose

log = logging.getLogger("gdiff.segment")


class _Chain(Sequence):
    """:class:`TrackFrame` s of the chain order, loaded and segmented on demand.

    Each frame is segmented once: taken from ``ahead`` (labels segmented elsewhere, in chain
    order) up to that frame, or segmented here when first read (the tracker reads frames in
    chain order); its labels are kept, the images only for the last ``keep`` frames read, so memory does not
    grow with the number of frames. A frame read again after that (a same-pose partner far
    back in the chain) is loaded again.
    """

    def __init__(self, order: list[Key], get, segment: "_SegmentKey", keep: int,
                 key_poses: dict[tuple[str, int], int] | None = None,
                 ahead: Iterator[tuple[np.ndarray, bool]] | None = None):
        self.order, self.get, self.segment, self.keep = order, get, segment, max(2, keep)
        self.key_poses = key_poses or {}
        self.labels: dict[int, tuple[np.ndarray, bool]] = {}  # (labels, shared partition)
        self.ahead = ahead  # labels of the frames in chain order, segmented elsewhere
        self.cache: OrderedDict[int, TrackFrame] = OrderedDict()

    def __len__(self):
        return len(self.order)

    def __getitem__(self, k: int) -> TrackFrame:
        if not 0 <= k < len(self.order):
            raise IndexError(k)
        if k in self.cache:
            self.cache.move_to_end(k)
            return self.cache[k]
        key = self.order[k]
        f = _frame(self.get, key)
        cam = f.get("camera")
        if self.ahead is not None:  # taken as they come, up to this frame
            while k not in self.labels:
                labels, shared = next(self.ahead)
                self.labels[len(self.labels)] = (narrow_ids(labels), shared)
        if k not in self.labels:
            labels, shared = self.segment(key, f)
            self.labels[k] = (narrow_ids(labels), shared)
        labels, shared = self.labels[k]
        tf = TrackFrame(labels=labels, rgb=f["rgb"], depth=f.get("depth"), camera=cam,
                        pose_key=(key[0], key[2]), name=key, time=TIMES.index(key[1]),
                        key=(key[0], key[2]) in self.key_poses, shared=shared)
        self.cache[k] = tf
        while len(self.cache) > self.keep:
            self.cache.popitem(last=False)
        return tf


def _frame(get, key: Key) -> dict:
    f = get(key)
    if not f:
        raise SceneError(f"rendered frame {key} missing (every path needs the same frames "
                         "at t0 and t1); re-run the render stage")
    return f


class _SegmentKey:
    """Segment labels of one frame key, read through ``get`` (also run in worker processes):
    ``(labels int32 [H, W], shared)``. ``shared``: the frame was segmented together with the
    other time's render of its pose (:mod:`gdiff.segment.pair`), by ``shared_partition``
    (``auto``: where the two rendered depths agree within ``depth_tol_rel`` on less than half
    of the frame). Backends without a ``label`` that takes the other time never share."""

    def __init__(self, get, segmenter: Segmenter, shared_partition: str = "never",
                 depth_tol_rel: float = 0.05, alpha_min: float = 0.0):
        self.get, self.segmenter = get, segmenter
        self.mode = shared_partition if getattr(segmenter, "pairs_times", False) else "never"
        self.depth_tol_rel, self.alpha_min = depth_tol_rel, alpha_min

    def __call__(self, key: Key, f: dict | None = None) -> tuple[np.ndarray, bool]:
        f = _frame(self.get, key) if f is None else f
        other = None
        if self.mode != "never":
            p, t, i = key
            g = _frame(self.get, (p, TIMES[1 - TIMES.index(t)], i))
            if self.mode == "always" or shared_pose(f, g, self.depth_tol_rel, self.alpha_min):
                other = (g["rgb"], g.get("depth"), g.get("alpha"))
        cam = f.get("camera")
        labels = segment_labels(self.segmenter, f["rgb"], f.get("depth"), f.get("alpha"),
                                cam.K if cam is not None else None, other=other)
        return labels, other is not None


def segment_labels(segmenter: Segmenter, rgb: np.ndarray, depth=None, alpha=None,
                   K=None, other=None) -> np.ndarray:
    """Segment labels int32 [H, W] of one frame (0 = none; 1.. in the segmenter's order):
    the segmenter's own ``label`` map when it has one (the same labels without building one
    full-size mask per instance), else its instances painted in order. ``other``: the
    ``(rgb, depth, alpha)`` of the pose's other time to segment together with (only for a
    segmenter with ``pairs_times``, see :class:`_SegmentKey`)."""
    if other is not None:
        return np.asarray(segmenter.label(rgb, depth, alpha, K, other=other), np.int32)
    if hasattr(segmenter, "label"):
        return np.asarray(segmenter.label(rgb, depth, alpha, K), np.int32)
    return labels_from_instances(segmenter.segment(rgb, depth, alpha, K), rgb.shape[:2])


def track_paths(frames, segmenter: Segmenter, track_options: TrackOptions | None = None,
                key_poses: dict[tuple[str, int], int] | None = None, workers: int = 1,
                shared_partition: str = "never", alpha_min: float = 0.0
                ) -> tuple[dict[Key, np.ndarray], pd.DataFrame]:
    """Segment and track all frames in one ID space.

    ``frames[(path, t, i)]`` is a dict with ``rgb`` (float32 [H, W, 3] sRGB), optional
    ``depth`` (float32 [H, W] z-depth), ``alpha`` (float32 [H, W]) and ``camera``
    (:class:`Camera`). Every path must have the same frames at t0 and t1 (same poses).
    ``frames`` may also be ``(keys, load)``: the frame keys and a callable key -> frame dict,
    to read frames on demand (then only a few frames are held in memory at a time).
    ``key_poses`` (optional, :func:`gdiff.frames.key_frames`): ``{(path, i): time}`` of the poses of
    the training photos; the frames of such a pose (at both times) are key frames of the tracker
    (:attr:`gdiff.track.TrackFrame.key`). ``workers`` > 1: the frames are segmented on that
    many processes (:func:`gdiff.parallel.ordered_map`; only segmenters with ``parallel_safe``)
    while this process tracks them in order, each as soon as its labels are there; the result
    does not depend on it. ``shared_partition`` (``auto``, ``always``, ``never``) and
    ``alpha_min``: where the two times of a pose are segmented together (:class:`_SegmentKey`;
    the tracker then links them by appearance, :attr:`gdiff.track.TrackFrame.shared`).
    Returns (ID map int32 [H, W] per key, tracks table with id, first, last, n_frames,
    mean_area; first/last as "path/t/NNNNN"). ``tracks.attrs["shared"]``: the keys segmented
    together with their other time.
    """
    if isinstance(frames, tuple):
        keys, get = frames
    else:
        keys, get = list(frames), (lambda k: frames.get(k, {}))
    n_frames: dict[str, int] = {}
    for p, t, i in keys:
        n_frames[p] = max(n_frames.get(p, 0), i + 1)
    paths = sorted(n_frames)
    order = chain_order(n_frames, paths)
    have = set(keys)
    missing = [k for k in order if k not in have]
    if missing:
        raise SceneError(f"rendered frames missing for {missing[:3]} (every path needs the same "
                         "frames at t0 and t1); re-run the render stage")
    o = track_options or TrackOptions()
    segment = _SegmentKey(get, segmenter, shared_partition, o.depth_tol_rel, alpha_min)
    ahead = None
    if workers > 1 and getattr(segmenter, "parallel_safe", False):
        # the workers segment the frames in chain order while the tracker follows them here
        # (it takes each frame's labels as they come); the workers read each frame for its
        # labels only, the tracker reads it again when it gets there (holding every frame's
        # images until then would not fit on long paths)
        ahead = ordered_map(segment, order, workers, chunksize=4)
    chain = _Chain(order, get, segment, keep=o.max_missed + 3,
                   key_poses=key_poses, ahead=ahead)
    try:
        res = track_sequence(chain, o)
    finally:
        if ahead is not None:
            ahead.close()  # stops the workers if the tracker stopped early
    ids = {key: m for key, m in zip(order, res.ids)}
    tracks = res.tracks.copy()
    fmt = lambda k: f"{order[k][0]}/{order[k][1]}/{order[k][2]:05d}"  # noqa: E731
    tracks["first"] = [fmt(k) for k in tracks["first"]]
    tracks["last"] = [fmt(k) for k in tracks["last"]]
    tracks.attrs["shared"] = sorted(order[k] for k, (_, sh) in chain.labels.items() if sh)
    return ids, tracks


def _overlay(rgb: np.ndarray, ids: np.ndarray) -> np.ndarray:
    """Colour overlay: each ID a fixed pseudo-random colour blended at 50 %, edges darkened."""
    import cv2

    rng = np.random.default_rng(12345)
    pal = rng.uniform(0.2, 1.0, (int(ids.max()) + 1, 3)).astype(np.float32)
    col = pal[ids]
    out = np.where(ids[..., None] > 0, 0.5 * rgb + 0.5 * col, rgb)
    edge = cv2.morphologyEx(ids.astype(np.float32), cv2.MORPH_GRADIENT, np.ones((3, 3))) > 0
    out[edge] *= 0.3
    return out


def segment_and_track(render_dir, poses_json, out_dir, options: SegmentOptions | None = None,
                      track_options: TrackOptions | None = None, workers: int = 1) -> dict:
    """Stage ``segment``: ID maps of every rendered frame in one ID space.

    Reads ``render_dir/<path>/<t0|t1>/NNNNN.exr`` for every pose of ``poses_json``; writes
    ``out_dir/<path>/<t>/NNNNN.png`` (uint16 IDs), ``out_dir/tracks.csv`` and last
    ``out_dir/index.json`` (render_dir, alpha_min: the opacity below which a pixel got no ID,
    frames, files); with ``options.overlays`` also
    ``out_dir/overlay/<path>/<t>/NNNNN.jpg`` (stale overlays are removed otherwise).
    ``workers``: processes the frames are segmented on (:func:`track_paths`; the files do not
    depend on it). Returns a summary dict (frames, tracks).
    """
    render_dir, out_dir = Path(render_dir), Path(out_dir)
    cams, meta = read_sequence(poses_json)
    files = render_files(render_dir, cams)
    options = options or SegmentOptions()
    seg = make_segmenter(options)

    def load(key):
        rgb, alpha, depth = read_frame(files[key])
        return dict(rgb=rgb, alpha=alpha, depth=depth, camera=cams[key[0]][key[2]])

    # frames are read on demand (all of them at once would not fit in memory on long paths)
    ids, tracks = track_paths((list(files), load), seg, track_options,
                              key_poses=key_frames(meta), workers=workers,
                              shared_partition=options.shared_partition,
                              alpha_min=options.alpha_min)
    shared = set(tracks.attrs.get("shared", []))
    n_poses = len({(p, i) for p, _, i in ids})
    n_shared = len({(p, i) for p, _, i in shared})
    if n_shared:
        log.info("segmented the two times together at %d of %d poses (segment.shared_partition "
                 "%s: their rendered depths agree within track.depth_tol_rel on less than half "
                 "of the frame, so the times are linked by appearance there)", n_shared, n_poses,
                 options.shared_partition)
    if len(tracks) > MAX_ID:  # checked before anything is written
        raise SceneError(
            f"{render_dir}: {len(tracks)} instance tracks over {len(ids)} frames, more than the "
            f"{MAX_ID} IDs a 16-bit ID map holds. Render fewer frames (larger "
            "interpolate.max_angle_deg and interpolate.max_step) or raise "
            "segment.min_region_area so fewer small segments are kept.")
    index = {"render_dir": os.path.relpath(render_dir, out_dir),
             "alpha_min": options.alpha_min, "frames": []}
    if not options.overlays and (out_dir / "overlay").is_dir():
        shutil.rmtree(out_dir / "overlay")  # from an earlier run with overlays on
    for (p, t, i), m in progress(sorted(ids.items()), desc="write IDs"):
        rel = f"{p}/{t}/{i:05d}.png"
        write_ids(out_dir / rel, m)
        if options.overlays:
            rgb = read_frame(files[(p, t, i)])[0]
            write_image(out_dir / "overlay" / p / t / f"{i:05d}.jpg", _overlay(rgb, m))
        index["frames"].append({"path": p, "t": t, "frame": i, "ids": rel,
                                "render": os.path.relpath(files[(p, t, i)], out_dir),
                                "shared": (p, t, i) in shared})
    write_csv(out_dir / "tracks.csv", tracks)
    write_json(out_dir / "index.json", index)
    return {"frames": len(ids), "tracks": len(tracks), "shared_poses": n_shared}
