"""Stages ``segment`` and ``compare``: rendered paths -> tracked instance IDs -> change masks.

In-memory core (used by the stages, the benchmark and the tests):

* :func:`track_paths` segments every frame of the four sequences (p1/p2 x t0/t1) and tracks them
  in one ID space (chain order of :func:`gdiff.track.chain_order`);
* :func:`compare_paths` compares the IDs of every pose at t0 and t1 and returns the per-pose
  masks and the per-ID decisions (:mod:`gdiff.change`).

Frames are keyed ``(path, t, i)`` with ``t`` in ``{"t0", "t1"}`` and ``i`` the frame number.

Files (results/<scene>/):

* in: ``render/<path>/<t>/NNNNN.exr`` (R, G, B linear, A, Z depth) + ``render/frames.json``,
  ``sequence/poses.json`` (cameras, key frames);
* ``segment`` writes ``instances/<path>/<t>/NNNNN.png`` (uint16 IDs), ``instances/tracks.csv``
  and, last, ``instances/index.json`` (with ``segment.overlays`` also
  ``instances/overlay/<path>/<t>/NNNNN.jpg``);
* ``compare`` writes ``change/<path>/<t0|t1|union>/NNNNN.png`` (255 = changed),
  ``change/changes.csv`` and, last, ``change/keyframes.csv``.
"""

from __future__ import annotations

import logging
import os
import shutil
from collections import OrderedDict
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pandas as pd

from .cameras import Camera
from .change import CompareOptions, change_masks, decide, pose_stats
from .coverage import DepthView, observed
from .errors import SceneError
from .io import read_ids, read_json, write_csv, write_ids, write_image, write_json, write_mask
from .log import progress
from .segment import SegmentOptions, Segmenter, make_segmenter
from .track import TrackFrame, TrackOptions, chain_order, labels_from_instances, track_sequence

log = logging.getLogger("gdiff.segtrack")

TIMES = ("t0", "t1")
Key = tuple  # (path, "t0" | "t1", frame index)


# ------------------------------------------------------------------------------------------
# in-memory core
# ------------------------------------------------------------------------------------------

class _Chain(Sequence):
    """:class:`TrackFrame` s of the chain order, loaded and segmented on demand.

    Each frame is segmented once, when first read (the tracker reads frames in chain order);
    its labels are kept, the images only for the last ``keep`` frames read, so memory does not
    grow with the number of frames. A frame read again after that (a same-pose partner far
    back in the chain) is loaded again.
    """

    def __init__(self, order: list[Key], get, segmenter: Segmenter, keep: int):
        self.order, self.get, self.segmenter, self.keep = order, get, segmenter, max(2, keep)
        self.labels: dict[int, np.ndarray] = {}
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
        f = self.get(key)
        if not f:
            raise SceneError(f"rendered frame {key} missing (every path needs the same frames "
                             "at t0 and t1); re-run the render stage")
        cam = f.get("camera")
        if k not in self.labels:
            self.labels[k] = segment_labels(self.segmenter, f["rgb"], f.get("depth"),
                                            f.get("alpha"), cam.K if cam is not None else None)
        tf = TrackFrame(labels=self.labels[k], rgb=f["rgb"], depth=f.get("depth"), camera=cam,
                        pose_key=(key[0], key[2]), name=key, time=TIMES.index(key[1]))
        self.cache[k] = tf
        while len(self.cache) > self.keep:
            self.cache.popitem(last=False)
        return tf


def segment_labels(segmenter: Segmenter, rgb: np.ndarray, depth=None, alpha=None,
                   K=None) -> np.ndarray:
    """Segment labels int32 [H, W] of one frame (0 = none; 1.. in the segmenter's order):
    the segmenter's own ``label`` map when it has one (the same labels without building one
    full-size mask per instance), else its instances painted in order."""
    if hasattr(segmenter, "label"):
        return np.asarray(segmenter.label(rgb, depth, alpha, K), np.int32)
    return labels_from_instances(segmenter.segment(rgb, depth, alpha, K), rgb.shape[:2])


def track_paths(frames, segmenter: Segmenter,
                track_options: TrackOptions | None = None) -> tuple[dict[Key, np.ndarray], pd.DataFrame]:
    """Segment and track all frames in one ID space.

    ``frames[(path, t, i)]`` is a dict with ``rgb`` (float32 [H, W, 3] sRGB), optional
    ``depth`` (float32 [H, W] z-depth), ``alpha`` (float32 [H, W]) and ``camera``
    (:class:`Camera`). Every path must have the same frames at t0 and t1 (same poses).
    ``frames`` may also be ``(keys, load)``: the frame keys and a callable key -> frame dict,
    to read frames on demand (then only a few frames are held in memory at a time).
    Returns (ID map int32 [H, W] per key, tracks table with id, first, last, n_frames,
    mean_area; first/last as "path/t/NNNNN").
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
    chain = _Chain(order, get, segmenter, keep=o.max_missed + 3)
    res = track_sequence(chain, o)
    ids = {key: m for key, m in zip(order, res.ids)}
    tracks = res.tracks.copy()
    fmt = lambda k: f"{order[k][0]}/{order[k][1]}/{order[k][2]:05d}"  # noqa: E731
    tracks["first"] = [fmt(k) for k in tracks["first"]]
    tracks["last"] = [fmt(k) for k in tracks["last"]]
    return ids, tracks


def key_views(frames, keys: dict[tuple[str, int], int] | None) -> dict[int, list[DepthView]]:
    """Key views per time for :mod:`gdiff.coverage`: ``keys[(path, i)] = time`` (0 or 1) names
    the path frames that are training cameras of that time; each contributes its camera and
    its depth rendered at that time (``frames``: dict or callable key -> frame dict). Frames
    without depth or camera are skipped."""
    get = frames if callable(frames) else (lambda k: (frames or {}).get(k, {}))
    out: dict[int, list[DepthView]] = {0: [], 1: []}
    for (p, i), time in sorted((keys or {}).items()):
        f = get((p, TIMES[int(time)], i))
        if f.get("depth") is not None and f.get("camera") is not None:
            out[int(time)].append(DepthView(f["camera"], f["depth"]))
    return out


def compare_paths(ids: dict[Key, np.ndarray], frames: dict[Key, dict] | None,
                  options: CompareOptions | None = None,
                  keys: dict[tuple[str, int], int] | None = None
                  ) -> tuple[dict[tuple[str, int], tuple[np.ndarray, np.ndarray]], pd.DataFrame]:
    """Change masks per pose from the tracked ID maps.

    ``ids[(path, t, i)]``: int [H, W]; ``frames`` (optional, same keys) gives ``rgb``/``depth``/
    ``camera`` (and optional ``alpha``) for the evidence check (see :mod:`gdiff.change`); it
    may also be a callable key -> frame dict (to load lazily). ``keys`` (optional):
    ``{(path, i): time}`` of the path frames that are training cameras (key frames) of that
    time; with them only pixels a training photo of each time saw are compared
    (:mod:`gdiff.coverage`). Returns ({(path, i): (mask_t0, mask_t1)}, changes table: id,
    changed, type, partner, n_t0, n_t1, n_confirmed, first, last, area, instance).
    """
    o = options or CompareOptions()
    get = frames if callable(frames) else (lambda k: (frames or {}).get(k, {}))
    poses = sorted({(p, i) for p, _, i in ids})
    views = key_views(get, keys) if keys else None
    stats = []
    for p, i in progress(poses, desc="compare"):
        f0, f1 = get((p, "t0", i)), get((p, "t1", i))
        cam = f0.get("camera")
        seen = [None, None]
        if views is not None and cam is not None:
            for time, f in enumerate((f0, f1)):
                if f.get("depth") is not None and views[time]:
                    seen[time] = observed(f["depth"], cam, views[time], o.observed_depth_tol,
                                          o.observed_min_views, f.get("alpha"),
                                          min_parallax=o.observed_min_parallax,
                                          max_views=o.observed_max_views)
        stats.append((f"{p}/{i:05d}", pose_stats(
            ids[(p, "t0", i)], ids[(p, "t1", i)], o, f0.get("rgb"), f1.get("rgb"),
            f0.get("depth"), f1.get("depth"), focal=cam.fx if cam is not None else None,
            camera=cam, observed0=seen[0], observed1=seen[1])))
    df = decide(stats, o)
    changed = df.loc[df["changed"], "id"].tolist()
    masks = {(p, i): change_masks(ids[(p, "t0", i)], ids[(p, "t1", i)], changed)
             for p, i in poses}
    log.info("compared %d poses: %d of %d IDs changed (%s)", len(poses), len(changed), len(df),
             ", ".join(f"{t}: {(df['type'] == t).sum()}" for t in ("added", "removed", "moved")))
    return masks, df


# ------------------------------------------------------------------------------------------
# files
# ------------------------------------------------------------------------------------------

def _poses(poses_json) -> tuple[dict[str, list[Camera]], dict[str, list[dict]]]:
    data = read_json(poses_json)
    try:
        paths = data["paths"]
        shared = {k: data[k] for k in ("width", "height", "fx", "fy", "cx", "cy")}
    except KeyError as e:
        raise SceneError(f"{poses_json}: key {e} missing; see sequence/poses.json in "
                         "docs/design.md, re-run the interpolate stage") from None
    cams, meta = {}, {}
    for p, entry in paths.items():
        cams[p] = [Camera(**{k: fr.get(k, v) for k, v in shared.items()}, c2w=fr["c2w"])
                   for fr in entry["frames"]]
        meta[p] = [dict(fr, set=entry.get("set")) for fr in entry["frames"]]
    return cams, meta


def _read_exr(path: Path):
    """(rgb sRGB float32 [H, W, 3], alpha [H, W] | None, depth [H, W] | None) of a frame."""
    try:
        from .exr import read_frame
    except ImportError:  # the exr module is optional for reading; OpenEXR directly otherwise
        read_frame = _read_exr_openexr
    return read_frame(path)


def _read_exr_openexr(path):
    import OpenEXR

    from .io import linear_to_srgb

    with OpenEXR.File(str(path)) as f:
        ch = f.channels()  # OpenEXR groups R, G, B(, A) into "RGB" / "RGBA"
        alpha = None
        if "RGBA" in ch:
            px = np.asarray(ch["RGBA"].pixels, np.float32)
            lin, alpha = px[..., :3], px[..., 3]
        elif "RGB" in ch:
            lin = np.asarray(ch["RGB"].pixels, np.float32)
        elif all(c in ch for c in "RGB"):
            lin = np.stack([np.asarray(ch[c].pixels, np.float32) for c in "RGB"], -1)
        else:
            raise SceneError(f"{path}: no R, G, B channels (has {', '.join(ch)}); re-run render")
        if alpha is None and "A" in ch:
            alpha = np.asarray(ch["A"].pixels, np.float32)
        depth = np.asarray(ch["Z"].pixels, np.float32) if "Z" in ch else None
    return linear_to_srgb(lin).astype(np.float32), alpha, depth


def _render_files(render_dir: Path, cams: dict[str, list[Camera]]) -> dict[Key, Path]:
    files = {}
    for p, cl in cams.items():
        for t in TIMES:
            for i in range(len(cl)):
                f = render_dir / p / t / f"{i:05d}.exr"
                if not f.exists():
                    raise SceneError(f"{f}: rendered frame missing (sequence/poses.json has "
                                     f"{len(cl)} frames on path {p}); re-run the render stage")
                files[(p, t, i)] = f
    return files


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


def key_frames(meta: dict[str, list[dict]]) -> dict[tuple[str, int], int]:
    """``{(path, i): time}`` of the key frames (training cameras) of sequence/poses.json
    (``meta`` from :func:`_poses`): time 1 for an ``after`` set, else 0."""
    return {(p, i): (1 if (fr.get("set") or "").endswith("after") else 0)
            for p, frs in meta.items() for i, fr in enumerate(frs) if fr.get("key")}


def segment_and_track(render_dir, poses_json, out_dir, options: SegmentOptions | None = None,
                      track_options: TrackOptions | None = None) -> dict:
    """Stage ``segment``: ID maps of every rendered frame in one ID space.

    Reads ``render_dir/<path>/<t0|t1>/NNNNN.exr`` for every pose of ``poses_json``; writes
    ``out_dir/<path>/<t>/NNNNN.png`` (uint16 IDs), ``out_dir/tracks.csv`` and last
    ``out_dir/index.json`` (render_dir, frames, files); with ``options.overlays`` also
    ``out_dir/overlay/<path>/<t>/NNNNN.jpg`` (stale overlays are removed otherwise).
    Returns a summary dict (frames, tracks).
    """
    render_dir, out_dir = Path(render_dir), Path(out_dir)
    cams, _ = _poses(poses_json)
    files = _render_files(render_dir, cams)
    options = options or SegmentOptions()
    seg = make_segmenter(options)

    def load(key):
        rgb, alpha, depth = _read_exr(files[key])
        return dict(rgb=rgb, alpha=alpha, depth=depth, camera=cams[key[0]][key[2]])

    # frames are read on demand (all of them at once would not fit in memory on long paths)
    ids, tracks = track_paths((list(files), load), seg, track_options)
    index = {"render_dir": os.path.relpath(render_dir, out_dir), "frames": []}
    if not options.overlays and (out_dir / "overlay").is_dir():
        shutil.rmtree(out_dir / "overlay")  # from an earlier run with overlays on
    for (p, t, i), m in progress(sorted(ids.items()), desc="write IDs"):
        rel = f"{p}/{t}/{i:05d}.png"
        write_ids(out_dir / rel, m)
        if options.overlays:
            rgb = _read_exr(files[(p, t, i)])[0]
            write_image(out_dir / "overlay" / p / t / f"{i:05d}.jpg", _overlay(rgb, m))
        index["frames"].append({"path": p, "t": t, "frame": i, "ids": rel,
                                "render": os.path.relpath(files[(p, t, i)], out_dir)})
    write_csv(out_dir / "tracks.csv", tracks)
    write_json(out_dir / "index.json", index)
    return {"frames": len(ids), "tracks": len(tracks)}


def compare(instances_dir, poses_json, out_dir, options: CompareOptions | None = None) -> dict:
    """Stage ``compare``: change masks of every pose from the tracked IDs.

    Reads ``instances_dir/index.json`` (and through it the ID maps and the rendered EXR frames,
    for the depth evidence) and the key frames of ``poses_json`` (the training cameras: only
    pixels a photo of each time saw are compared, :mod:`gdiff.coverage`); writes ``out_dir/<path>/<t0|t1|union>/NNNNN.png``,
    ``out_dir/changes.csv`` (id, type, partner, first/last pose, area, instance: the object a
    changed ID is a piece of, ...) and last
    ``out_dir/keyframes.csv`` (path, frame, image, set, time, mask_t0, mask_t1, mask_union;
    mask paths relative to the parent of ``out_dir``, i.e. results/<scene>/).
    """
    instances_dir, out_dir = Path(instances_dir), Path(out_dir)
    index = read_json(instances_dir / "index.json")
    cams, meta = _poses(poses_json)
    ids, renders = {}, {}
    for fr in index.get("frames", []):
        key = (fr["path"], fr["t"], int(fr["frame"]))
        ids[key] = read_ids(instances_dir / fr["ids"])
        renders[key] = instances_dir / fr["render"]
    if not ids:
        raise SceneError(f"{instances_dir / 'index.json'}: no frames listed; re-run segment")

    def read(key):
        if key not in renders or not renders[key].exists():
            return {}
        rgb, alpha, depth = _read_exr(renders[key])
        return dict(rgb=rgb, alpha=alpha, depth=depth, camera=cams[key[0]][key[2]])

    keys = key_frames(meta)
    # key frames are read once: for the coverage views and again at their own pose
    keyed = {(p, TIMES[t], i): read((p, TIMES[t], i)) for (p, i), t in keys.items()}

    def load(key):
        return keyed[key] if key in keyed else read(key)

    masks, df = compare_paths(ids, load, options, keys=keys)
    root = out_dir.parent
    rows = []
    for (p, i), (m0, m1) in sorted(masks.items()):
        rel = {}
        for name, m in (("t0", m0), ("t1", m1), ("union", m0 | m1)):
            f = out_dir / p / name / f"{i:05d}.png"
            write_mask(f, m)
            rel[name] = os.path.relpath(f, root)
        if (p, i) in keys:
            fr = meta[p][i]
            rows.append(dict(path=p, frame=i, image=fr.get("image", ""), set=fr.get("set") or "",
                             time=keys[(p, i)], mask_t0=rel["t0"], mask_t1=rel["t1"],
                             mask_union=rel["union"]))
    write_csv(out_dir / "changes.csv", df[df["changed"]].drop(columns=["changed"]))
    write_csv(out_dir / "keyframes.csv", pd.DataFrame(rows, columns=[
        "path", "frame", "image", "set", "time", "mask_t0", "mask_t1", "mask_union"]))
    counts = df.loc[df["changed"], "type"].value_counts().to_dict()
    return {"poses": len(masks), "changed": int(df["changed"].sum()),
            "instances": int(df.loc[df["changed"], "instance"].nunique()), **counts}
