"""Stage ``compare``: change masks of every pose of the rendered paths from the tracked IDs.

:func:`compare_paths` compares the IDs of every pose at t0 and t1 (per-pose evidence and the
per-ID decision: :mod:`gdiff.compare.change`; which pixels the photos of each time saw:
:mod:`gdiff.compare.coverage`) and returns the per-pose masks and the per-ID decisions;
:func:`compare` is the stage on files.

Files (results/<scene>/): reads ``instances/index.json`` (the ID maps and, through it, the
rendered EXR frames) and ``sequence/poses.json`` (:mod:`gdiff.frames`); writes
``change/<path>/<t0|t1|union>/NNNNN.png`` (255 = changed), ``change/changes.csv``,
``change/candidates.csv`` (every changed object of the ID comparison that the 3D evidence and
colour test judged, kept or dropped, with the figures it was judged by),
``change/evidence3d.npz`` (the changed voxels of the 3D evidence), ``change/coverage.csv`` and
``change/<path>/judged/NNNNN.png`` (where the photos let each pose be judged:
:func:`gdiff.compare.coverage.judged_map`) and, last, ``change/keyframes.csv``.
"""

from __future__ import annotations

import logging
import os
from functools import partial
from pathlib import Path

import cv2
import numpy as np
import pandas as pd

from ..errors import SceneError
from ..frames import TIMES, Key, key_frames, read_frame, read_sequence
from ..io import read_ids, read_json, srgb_to_linear, write_csv, write_image, write_mask
from ..log import progress
from ..parallel import ordered_map
from ..segment.base import ALPHA_MIN
from ..track import world_points
from .agree import agreeing
from .change import (HIDDEN_SHARE, CompareOptions, appearance_change, change_masks, decide,
                     pose_stats, replaced, unpair)
from .complete import complete_key_masks, key_differences
from .coverage import (JUDGED_DEPTH, JUDGED_SEEN, DepthView, judged_counts, judged_map, observed,
                       surface)
from .geometry import (GeometryEvidence, flat_flags, pixel_scale, pose_flags, pose_record,
                       write_evidence)
from .lineup import in_place_px, poorly_lined_up, render_lineup
from .photos import (KeyPhoto, alike_components, load_photo, point_photo_counts,
                     region_photos_differ, visit_exposure)
from .spread import count_voxels, object_voxels, spread_masks, voxel_keys

log = logging.getLogger("gdiff.compare")


def key_views(frames, keys: dict[tuple[str, int], int] | None, window: float = 0.0
              ) -> dict[int, list[DepthView]]:
    """Key views per time for :mod:`gdiff.compare.coverage`: ``keys[(path, i)] = time`` (0 or 1) names
    the path frames that are training cameras of that time; each contributes its camera and
    its depth rendered at that time (``frames``: dict or callable key -> frame dict). Frames
    without depth or camera are skipped. ``window``: the visibility test's window
    (:class:`DepthView`) as a fraction of the frame's longer side (``compare.observed_window``)."""
    get = frames if callable(frames) else (lambda k: (frames or {}).get(k, {}))
    out: dict[int, list[DepthView]] = {0: [], 1: []}
    for (p, i), time in sorted((keys or {}).items()):
        f = get((p, TIMES[int(time)], i))
        if f.get("depth") is not None and f.get("camera") is not None:
            px = int(round(window * max(np.shape(f["depth"]))))
            out[int(time)].append(DepthView(f["camera"], f["depth"], px))
    return out


def _key_photos(get, keys: dict[tuple[str, int], int], photos: dict) -> list[KeyPhoto]:
    """The key frames that have a photo (``photos[(path, i)]``) and a rendered depth and camera
    at their own time (``get``: key -> frame dict), as :class:`KeyPhoto`."""
    out = []
    for (p, i), t in sorted(keys.items()):
        f = get((p, TIMES[int(t)], i)) if (p, i) in photos else {}
        if f.get("depth") is not None and f.get("camera") is not None:
            out.append(KeyPhoto(int(t), f["camera"], f["depth"], photos[(p, i)], (p, i)))
    return out


class _JudgePose:
    """The per-pose part of :func:`compare_paths` (depends on that pose alone, so poses can be
    judged in parallel): called with ``(path, i)``, returns ``(stats entry, judged map (uint8
    [H, W], :func:`judged_map`) or None, geometry record or None, flat record or None)``.
    ``key_photos`` (list of
    :class:`KeyPhoto`, optional): the training photos, asked whether the two times differ on
    a region only seen (:func:`gdiff.compare.change.pose_stats`)."""

    def __init__(self, ids, get, o: CompareOptions, views, geo_stride: int | None,
                 flat_stride: int | None, alpha_min: float, key_photos=None):
        self.ids, self.get, self.o, self.views = ids, get, o, views
        self.key_photos = key_photos
        self.geo_stride, self.flat_stride = geo_stride, flat_stride
        self.alpha_min = alpha_min

    def __call__(self, pose):
        p, i = pose
        o, get, views = self.o, self.get, self.views
        f0, f1 = get((p, "t0", i)), get((p, "t1", i))
        cam = f0.get("camera")
        z0, z1 = f0.get("depth"), f1.get("depth")
        have_depth = cam is not None and z0 is not None and z1 is not None
        evidence = have_depth and (self.geo_stride is not None or self.flat_stride is not None)
        # world points of each time's depth, computed once for the coverage, the ID tests
        # and the evidence (when one of the first and the last needs them)
        need = cam is not None and (views is not None or evidence)
        pts = [world_points(z, cam) if need and z is not None else None for z in (z0, z1)]
        seen = [None, None]  # per time: depth determined there (observed), shown by a photo
        if views is not None and cam is not None:
            for time, f in enumerate((f0, f1)):
                if f.get("depth") is not None and views[time]:
                    seen[time] = observed(f["depth"], cam, views[time], o.observed_depth_tol,
                                          o.observed_min_views, f.get("alpha"),
                                          alpha_min=self.alpha_min,
                                          min_parallax=o.observed_min_parallax,
                                          max_views=o.observed_max_views, seen=True,
                                          step=o.observed_step(*f["depth"].shape),
                                          points=pts[time])
        obs = [s[0] if s is not None else None for s in seen]
        shown = [s[1] if s is not None else None for s in seen]
        # a photo of each time shows the surface (the coverage, and at a key pose the ID
        # comparison's photo test)
        shown_both = (shown[0] & shown[1] if shown[0] is not None and shown[1] is not None
                      else None)
        judged = None
        if all(m is not None for m in obs + shown):
            both = (surface(f0["depth"], f0.get("alpha"), self.alpha_min)
                    & surface(f1["depth"], f1.get("alpha"), self.alpha_min))
            judged = judged_map(both, shown_both, obs[0] & obs[1])
        differ = None  # the pose's appearance change: the evidence needs it, the IDs may
        if evidence and f0.get("rgb") is not None and f1.get("rgb") is not None:
            differ = appearance_change(f0["rgb"], f1["rgb"], o.chroma_tol, o.ncc_min)
        photo_check = None  # do the photos of the two times differ on a region?
        if self.key_photos and have_depth and need:
            photo_check = partial(region_photos_differ, points=tuple(pts), depths=(z0, z1),
                                  photos=self.key_photos, depth_tol=o.observed_depth_tol,
                                  contrast=o.flat_photo_contrast)
        stats = (pose_name(p, i), pose_stats(
            self.ids[(p, "t0", i)], self.ids[(p, "t1", i)], o, f0.get("rgb"), f1.get("rgb"),
            z0, z1, focal=cam.fx if cam is not None else None,
            camera=cam, observed0=obs[0], observed1=obs[1], seen0=shown[0], seen1=shown[1],
            appearance=differ, points=tuple(pts) if have_depth and need else None,
            photos_differ=photo_check))
        g_rec = f_rec = None
        # the depth of both times observed: the evidence's pixels (at the key poses also in
        # the judged map, where the completion leaves them alone)
        known = obs[0] & obs[1] if obs[0] is not None and obs[1] is not None else None
        if evidence:
            if self.geo_stride is not None:
                g_rec = pose_record(z0, z1, cam, *pose_flags(z0, z1, o.depth_change_rel,
                                                             o.evidence_open, known, differ),
                                    points=tuple(pts), stride=self.geo_stride)
            if self.flat_stride is not None and differ is not None:
                f_rec = pose_record(z0, z1, cam, *flat_flags(z0, z1, o.depth_change_rel,
                                                             o.evidence_open, known, differ),
                                    points=tuple(pts), stride=self.flat_stride)
        return stats, judged, g_rec, f_rec


def pose_name(path: str, frame: int) -> str:
    """A pose's name in the changes table (``first``, ``last``) and the logs: ``path/NNNNN``."""
    return f"{path}/{int(frame):05d}"


def compare_paths(ids: dict[Key, np.ndarray], frames: dict[Key, dict] | None,
                  options: CompareOptions | None = None,
                  keys: dict[tuple[str, int], int] | None = None, workers: int = 1,
                  photos: dict[tuple[str, int], np.ndarray] | None = None,
                  alpha_min: float = ALPHA_MIN, unlined: set[str] | None = None
                  ) -> tuple[dict[tuple[str, int], tuple[np.ndarray, np.ndarray]], pd.DataFrame]:
    """Change masks per pose from the tracked ID maps.

    ``ids[(path, t, i)]``: int [H, W]; ``frames`` (optional, same keys) gives ``rgb``/``depth``/
    ``camera`` (and optional ``alpha``) for the evidence check (see :mod:`gdiff.compare.change`); it
    may also be a callable key -> frame dict (to load lazily). ``keys`` (optional):
    ``{(path, i): time}`` of the path frames that are training cameras (key frames) of that
    time; with them only pixels a training photo of each time saw are compared
    (:mod:`gdiff.compare.coverage`). ``workers``: processes the poses are judged on
    (:func:`gdiff.parallel.ordered_map`; the result does not depend on it). ``photos``
    (optional): ``{(path, i): linear RGB float32 [H, W, 3]}``, the training photo of each key
    frame at the frame's size; with them the flat evidence keeps only what the photos of the
    two times show differently (``flat_photo_contrast``, :mod:`gdiff.compare.photos`), and so
    does the ID comparison for a region whose depth is not trusted at a pose of a sparse
    capture and that only its colours would confirm; the key frames' masks are completed where
    the photo differs from the other time's render next to a change (``complete_reach``,
    :mod:`gdiff.compare.complete`), and an object of the ID comparison that neither depth nor
    colour confirms is kept when the photos of both times show it changed (``confirm_photo``,
    :func:`_photo_support`); last, a key frame's mask of its own time loses what a photo of
    the other visit shows alike (``photo_agree``, :mod:`gdiff.compare.agree`).
    ``alpha_min``: a pixel whose rendered opacity (the frames' ``alpha``) is below this shows no
    surface and is not judged (the segmenter's ``alpha_min``: it gave such pixels no ID).
    ``unlined``: the key poses (``path/NNNNN``) whose t0 and t1 renders do not line up
    (:func:`unlined_poses`); an object found at one of them only is not kept by its colour
    (``confirm_colour_lined_up``). Returns
    ({(path, i): (mask_t0, mask_t1)}, changes table: id,
    changed, type, partner, n_t0, n_t1, n_confirmed, first, last, area, instance, x, y, z,
    size; see :func:`gdiff.compare.change.decide`). The table's
    ``attrs["evidence3d"]`` holds the changed voxels of the 3D evidence, ``{"geometry" | "flat":
    (voxel side, keys at t0, keys at t1)}`` (see :func:`gdiff.compare.geometry.write_evidence`).
    """
    o = options or CompareOptions()
    get = frames if callable(frames) else (lambda k: (frames or {}).get(k, {}))
    poses = sorted({(p, i) for p, _, i in ids})
    views = key_views(get, keys, o.observed_window) if keys else None
    stats = []
    judged = {}  # pose -> uint8 [H, W] judged map (coverage.judged_map)
    geo = (GeometryEvidence(o.geometry_voxel_px, o.geometry_vote, o.geometry_min_poses,
                            o.geometry_min_object) if o.geometry else None)
    flat = (GeometryEvidence(o.geometry_voxel_px, o.geometry_vote, o.geometry_min_poses,
                             o.geometry_min_object) if o.flat else None)
    key_photos = _key_photos(get, keys, photos) if photos and keys else None
    judge = _JudgePose(ids, get, o, views, geo.stride if geo is not None else None,
                       flat.stride if flat is not None else None, alpha_min,
                       key_photos=key_photos if o.flat_photo_contrast > 0 else None)
    results = ordered_map(judge, poses, workers)
    for pose, (st, jd, g_rec, f_rec) in zip(poses, progress(results, desc="compare",
                                                          total=len(poses))):
        stats.append(st)
        if jd is not None:
            judged[pose] = jd
        if g_rec is not None:
            geo.put(pose, g_rec)
        if f_rec is not None:
            flat.put(pose, f_rec)
    # at the key poses: the depth of both times observed there (the completion leaves it
    # alone), a photo of each time shows the surface (the photo test counts only that)
    known = {k: m == JUDGED_DEPTH for k, m in judged.items() if keys and k in keys}
    shown = {k: m >= JUDGED_SEEN for k, m in judged.items() if keys and k in keys}
    coverage = coverage_table(judged, keys)
    total = coverage[["surface", "seen", "depth"]].sum()
    if total["surface"]:
        log.info("coverage: a photo of each time shows %.1f %% of the rendered surface (judged "
                 "by ID and appearance); its depth is observed (>= %d key views per time, "
                 "%.0f deg apart) on %.1f %% (judged also by depth); the other %.1f %% is not "
                 "judged", 100 * total["seen"] / total["surface"], o.observed_min_views,
                 o.observed_min_parallax, 100 * total["depth"] / total["surface"],
                 100 - 100 * total["seen"] / total["surface"])
    df = decide(stats, o)
    g_geo = geo.finish() if geo is not None else None
    g_flat = flat.finish(max_rate=o.flat_max_rate) if flat is not None else None
    band = max(1, int(round(2 * o.geometry_voxel_px)))
    light_changed = g_flat is not None and g_flat["rejected"]
    alike = np.zeros(0, np.int64)
    if g_flat is not None and not light_changed and g_flat["objects"] and photos and keys \
            and o.flat_photo_contrast > 0:
        alike, n_judged = alike_components(
            flat.changed, flat.component, flat.voxel, flat.centres,
            key_photos,
            o.flat_photo_contrast)
        flat.drop(alike)
        log.info("flat changes: the photos of the two times judged %d of %d components and show "
                 "%d of them alike (within compare.flat_photo_contrast = %g times their spread "
                 "within a time): left out", n_judged, g_flat["objects"], len(alike),
                 o.flat_photo_contrast)
    if light_changed:  # said first: the rules below depend on it
        log.info("flat changes: appearance changed on %.1f %% of the surfaces judged (more "
                 "than compare.flat_max_rate = %.1f %%): taken as a change of light, nothing "
                 "marked", 100 * g_flat["rate"], 100 * o.flat_max_rate)
    # the training photos against the other time's renders at the key poses, once: for the
    # confirmation of the ID comparison's objects and for the completion of the key masks
    diffs = (key_differences(get, keys, photos) if photos and keys and not light_changed and (
        o.confirm_photo > 0 or o.complete_reach > 0) else {})
    if geo is not None:
        _support_3d(df, ids, [geo] + ([flat] if flat is not None and not light_changed else []),
                    band)
        if o.confirm_photo > 0:
            _photo_support(df, ids, keys, diffs, o.confirm_photo, o.min_area, shown)
        if o.confirm_colour_points > 0 and key_photos and not light_changed:
            _photo_points(df, ids, key_photos, o)
        _own_view(df, ids, keys, shown)
        if o.confirm_support > 0:
            _confirm_by_evidence(df, o, band, light_changed, unlined)
    else:
        df["support"] = np.nan
    for c in ("photo", "photo_other", "photo_points", "own_px"):  # the same columns always
        if c not in df:
            df[c] = np.nan
    _replaced(df, o)
    changed = df.loc[df["changed"], "id"].tolist()
    masks = {(p, i): change_masks(ids[(p, "t0", i)], ids[(p, "t1", i)], changed)
             for p, i in poses}
    evidence = {}
    if geo is not None:
        evidence["geometry"] = (geo.voxel, geo.changed[0], geo.changed[1])
        added = _add_evidence(masks, geo)
        log.info("geometry: voxel %.4g scene units, %d changed voxels in %d objects; %d pixels "
                 "added to the ID masks over %d poses", g_geo["voxel"] or 0,
                 g_geo["changed_voxels"], g_geo["objects"], added, len(masks))
    if flat is not None:
        g = g_flat
        rims = _rims(flat, masks, g["objects"], band)
        evidence["flat"] = (flat.voxel, *(k[~np.isin(c, rims)]
                                          for k, c in zip(flat.changed, flat.component)))
        added = _add_evidence(masks, flat, leave_out=rims)
        if not g["rejected"]:
            log.info("flat changes: appearance changed on %.1f %% of the surfaces judged; %d "
                     "changed voxels in %d objects, %d of them alike in the photos and %d "
                     "the rims or shadows of other changes (left out); %d pixels added over "
                     "%d poses", 100 * g["rate"], g["changed_voxels"], g["objects"],
                     len(alike), len(rims), added, len(masks))
    if o.spread_vote > 0 and changed and keys:  # last: the rules above judge the ID masks
        voxel = geo.voxel if geo is not None and geo.voxel else _key_voxel(get, keys, o)
        if voxel:
            _spread(masks, ids, get, keys, changed, voxel, o, workers)
    if o.complete_reach > 0 and photos and keys:  # after the spread: it grows what it marked
        if light_changed:
            log.info("key views: not completed from the photos: the light changed, and a photo "
                     "differs from the other time's render wherever it did")
        else:
            n, pieces, added = complete_key_masks(masks, get, keys, diffs, o.complete_reach,
                                                  alpha_min, known)
            log.info("key views: %d pieces of changes grown by %d pixels over %d key frames, "
                     "where the training photo differs from the other time's render next to "
                     "them (compare.complete_reach = %g)", pieces, added, n, o.complete_reach)
    if o.photo_agree > 0 and key_photos:  # last: it judges the key masks as they stand
        _leave_out_agreeing(masks, key_photos, o.photo_agree, known, o.observed_depth_tol,
                            workers)
    log.info("compared %d poses: %d of %d IDs changed (%s)", len(poses), len(changed), len(df),
             ", ".join(f"{t}: {(df['type'] == t).sum()}" for t in ("added", "removed", "moved")))
    df.attrs["evidence3d"] = evidence
    df.attrs["judged"] = judged
    df.attrs["coverage"] = coverage
    df.attrs["light_changed"] = bool(light_changed)
    return masks, df


class _Agreeing:
    """:func:`gdiff.compare.agree.agreeing` for one key photo (by its index in
    ``key_photos``) against the other visit's, so that the key photos can be judged in
    parallel (forked workers see the photos; only the index and the map are sent)."""

    def __init__(self, key_photos: list[KeyPhoto], contrast: float, trusted: dict,
                 depth_tol: float):
        self.key_photos, self.contrast = key_photos, contrast
        self.trusted, self.depth_tol = trusted, depth_tol

    def __call__(self, index: int) -> np.ndarray:
        own = self.key_photos[index]
        return agreeing(own, [k for k in self.key_photos if k.time != own.time], self.contrast,
                        trusted=self.trusted.get(own.pose), depth_tol=self.depth_tol)


def _leave_out_agreeing(masks, key_photos: list[KeyPhoto], contrast: float,
                        trusted: dict | None = None, depth_tol: float = 0.05,
                        workers: int = 1) -> None:
    """At each key pose (in place in ``masks``, ``{(path, i): (mask_t0, mask_t1)}``), the
    mask of the photo's own time loses the pixels whose surface a photo of the other visit
    shows alike (:mod:`gdiff.compare.agree`): what the photo shows there did not change. The
    other time's mask is left: it marks what that time's model draws at this pose, which the
    photo may not show. ``trusted[(path, i)]`` (bool [H, W], optional): where the depth of
    both times is observed at that key pose; there a match must lie within ``depth_tol``
    (relative) of the rendered depth."""
    n, removed = 0, 0
    agree_one = _Agreeing(key_photos, contrast, trusted or {}, depth_tol)
    for kp, agree in zip(key_photos, ordered_map(agree_one, range(len(key_photos)), workers)):
        ms = list(masks.get(kp.pose, ()))
        if len(ms) != 2 or ms[kp.time].shape != agree.shape:
            continue
        n += 1
        removed += int((ms[kp.time] & agree).sum())
        ms[kp.time] = ms[kp.time] & ~agree
        masks[kp.pose] = tuple(ms)
    log.info("key views: %d changed pixels over %d key frames left out where a photo of the "
             "other visit shows the surface alike (flow matched both ways and on the pixel's "
             "ray; compare.photo_agree = %g)", removed, n, contrast)


#: how well the t0 and t1 renders line up at a key pose (:func:`lineup_table`)
LINEUP_COLUMNS = ["lineup_matches", "lineup_in_place", "lined_up"]
COVERAGE_COLUMNS = ["path", "frame", "key", "surface", "seen", "depth", "seen_frac",
                    "depth_frac", "not_judged_frac", *LINEUP_COLUMNS]


def coverage_table(judged: dict[tuple[str, int], np.ndarray],
                   keys: dict[tuple[str, int], int] | None = None) -> pd.DataFrame:
    """One row per pose of the judged maps ``judged`` ({(path, i): uint8 [H, W],
    :func:`gdiff.compare.coverage.judged_map`}): ``path``, ``frame``, ``key`` (the time of the
    training photo taken there, 0 or 1, or empty), the pixel counts ``surface`` (a surface at
    both times), ``seen`` (judged: shown by a photo of each time) and ``depth`` (judged also by
    depth), and ``seen_frac``, ``depth_frac`` and ``not_judged_frac`` (shares of ``surface``;
    empty when it is 0); ``lineup_matches``, ``lineup_in_place`` and ``lined_up`` are left
    empty (:func:`lineup_table` fills them at the key poses). Columns
    :data:`COVERAGE_COLUMNS`."""
    rows = []
    for (p, i), jd in sorted(judged.items()):
        c = judged_counts(jd)
        n = c["surface"]
        rows.append(dict(path=p, frame=int(i), key=(keys or {}).get((p, i)), **c,
                         seen_frac=c["seen"] / n if n else None,
                         depth_frac=c["depth"] / n if n else None,
                         not_judged_frac=1 - c["seen"] / n if n else None))
    df = pd.DataFrame(rows, columns=COVERAGE_COLUMNS)
    df["key"] = df["key"].astype("Int64")
    for c in ("surface", "seen", "depth"):
        df[c] = df[c].astype(np.int64)
    return _with_lineup(df)


def _with_lineup(coverage: pd.DataFrame, lined: pd.DataFrame | None = None) -> pd.DataFrame:
    """``coverage`` (:func:`coverage_table`) with the columns :data:`LINEUP_COLUMNS` of
    ``lined`` (:func:`lineup_table`) at its poses (empty where ``lined`` has none, or is None),
    typed once here: counts ``Int64``, the flag ``boolean``."""
    cov = coverage.drop(columns=LINEUP_COLUMNS, errors="ignore")
    if lined is not None and len(lined) and len(cov):
        cov = cov.merge(lined[["path", "frame", *LINEUP_COLUMNS]], on=["path", "frame"],
                        how="left")
    else:
        cov = cov.assign(**{c: None for c in LINEUP_COLUMNS})
    cov["lineup_matches"] = cov["lineup_matches"].astype("Int64")
    cov["lineup_in_place"] = cov["lineup_in_place"].astype(float)
    cov["lined_up"] = cov["lined_up"].astype("boolean")
    return cov[COVERAGE_COLUMNS]


def lineup_table(load, keys: dict[tuple[str, int], int], meta: dict, share: float
                 ) -> pd.DataFrame:
    """Per key pose (``keys``: {(path, i): time}), how well its t0 and t1 renders line up
    (:func:`gdiff.compare.lineup.render_lineup`; ``load(key)`` returns a frame's dict with
    ``rgb``): columns ``path``, ``frame``, ``image`` (the training photo's name from ``meta``),
    ``lineup_matches``, ``lineup_in_place`` and ``lined_up`` (False below ``share`` of the
    scene's median, :func:`gdiff.compare.lineup.poorly_lined_up`; NA when ``share`` is 0).
    ``attrs["in_place_px"]``: the distance a match counts as in place within. Measured before
    the ID comparison (:func:`unlined_poses`), reported after it (:func:`report_lineup`)."""
    rows, tol = [], float("nan")
    for p, i in sorted(keys):
        rgb0, rgb1 = load((p, "t0", i)).get("rgb"), load((p, "t1", i)).get("rgb")
        if rgb0 is None or rgb1 is None:
            continue
        lu = render_lineup(rgb0, rgb1)
        tol = in_place_px(rgb0.shape)
        rows.append(dict(path=p, frame=int(i), image=meta[p][i].get("image") or pose_name(p, i),
                         lineup_matches=lu.matches, lineup_in_place=lu.in_place))
    df = pd.DataFrame(rows, columns=["path", "frame", "image", "lineup_matches",
                                     "lineup_in_place", "lined_up"])
    df.attrs["in_place_px"] = tol
    if df.empty:
        return df
    bad = poorly_lined_up(df["lineup_in_place"].to_numpy(float), share)
    df["lined_up"] = pd.array(~bad, dtype="boolean") if share > 0 else pd.NA
    return df


def _not_lined_up(lined: pd.DataFrame) -> pd.DataFrame:
    """The rows of a :func:`lineup_table` whose renders do not line up (NA: not judged)."""
    return lined[~lined["lined_up"].fillna(True).astype(bool)]


def unlined_poses(lined: pd.DataFrame | None) -> set[str]:
    """The key poses of a :func:`lineup_table` whose renders do not line up, named as the
    changes table names poses (``path/NNNNN``)."""
    if lined is None or lined.empty:
        return set()
    return {pose_name(r.path, int(r.frame)) for r in _not_lined_up(lined).itertuples()}


def report_lineup(lined: pd.DataFrame, share: float, light_changed: bool = False) -> None:
    """Log how well the key poses' renders line up (``lined``: :func:`lineup_table`): the
    scene's median and, as a warning, the poses that do not (``light_changed``: the stage took
    the scene for a change of light, whose moved shadows move features too; the log says
    so)."""
    if lined.empty:
        return
    if lined["lineup_in_place"].isna().all():
        log.info("the t0 and t1 renders of the key poses share no feature match: how well they "
                 "line up is not measured")
        return
    med = float(np.nanmedian(lined["lineup_in_place"]))
    log.info("the t0 and t1 renders of the key poses line up on %.0f %% of their feature "
             "matches (median over %d poses; a match in place: its features within %.1f px)",
             100 * med, len(lined), lined.attrs.get("in_place_px", float("nan")))
    bad = _not_lined_up(lined)
    if len(bad):
        why = ("the light changed between the visits, and moved shadows and highlights move "
               "features too; or the models of the two visits disagree there on where things "
               "are" if light_changed else "the models of the two visits disagree there on "
               "where things are (check the poses of those photos)")
        log.warning("at %d key poses the t0 and t1 renders do not line up (below %.0f %% of the "
                    "median): %s. %s, and the changes marked there are uncertain",
                    len(bad), 100 * share,
                    ", ".join(f"{r.image} ({r.lineup_in_place:.0%} of {r.lineup_matches} "
                              "matches)" if r.lineup_matches else f"{r.image} (no match)"
                              for r in bad.itertuples()), why[0].upper() + why[1:])


def _key_voxel(get, keys: dict[tuple[str, int], int], o: CompareOptions) -> float | None:
    """Voxel side (world units) of ``o.geometry_voxel_px`` pixels at the median depth of the
    key frames (as :class:`GeometryEvidence` sets it over all poses), when the geometry
    evidence is off; None without depth."""
    scales = []
    for (p, i), _ in sorted(keys.items()):
        for t in TIMES:
            f = get((p, t, i))
            if f.get("depth") is not None and f.get("camera") is not None:
                scales.append(pixel_scale(f["depth"], f["camera"]))
    scales = [s for s in scales if s is not None]
    return o.geometry_voxel_px * float(np.median(scales)) if scales else None


class _SpreadPose:
    """Per pose (``(path, i)``), the pixels each time's mask (``masks[pose]``) gains from the
    changed objects' voxels ``voxels[t]`` (:func:`gdiff.compare.spread.spread_masks`, depth
    edges left out): those that also look different at the two times
    (:func:`gdiff.compare.change.appearance_change`, when both renders have colour). None
    without depth."""

    def __init__(self, get, masks, voxels: list[np.ndarray], voxel: float, o: CompareOptions):
        self.get, self.masks, self.voxels, self.voxel, self.o = get, masks, voxels, voxel, o

    def __call__(self, pose):
        p, i = pose
        frames = [self.get((p, name, i)) for name in TIMES]
        if any(f.get("depth") is None or f.get("camera") is None for f in frames):
            return None
        out = [spread_masks(voxel_keys(f["depth"], f["camera"], self.voxel,
                                       self.o.depth_change_rel), v) & ~m
               for f, v, m in zip(frames, self.voxels, self.masks[pose])]
        if any(m.any() for m in out) and all(f.get("rgb") is not None for f in frames):
            differ = appearance_change(frames[0]["rgb"], frames[1]["rgb"], self.o.chroma_tol,
                                       self.o.ncc_min)
            out = [m & differ for m in out]
        return out


def _spread(masks, ids: dict[Key, np.ndarray], get, keys: dict[tuple[str, int], int],
            changed: list, voxel: float, o: CompareOptions, workers: int) -> None:
    """Carry the changed IDs' surfaces to the poses where other IDs cover them (``masks`` in
    place; :mod:`gdiff.compare.spread`): the voxels of each time that at least
    ``o.spread_vote`` of the key frames looking at them show as a changed ID's pixels, and
    that the same key poses at the other time mostly see empty, join that time's mask at
    every pose with depth, where the two renders also look different (:class:`_SpreadPose`).
    """
    def views(t):
        for (p, i), _ in sorted(keys.items()):
            f = get((p, t, i))
            if f.get("depth") is not None and f.get("camera") is not None:
                yield (voxel_keys(f["depth"], f["camera"], voxel, o.depth_change_rel),
                       np.isin(ids[(p, t, i)], changed))

    counts = [count_voxels(views(t)) for t in TIMES]
    voxels = [object_voxels(counts[k], counts[1 - k], o.spread_vote) for k in range(2)]
    poses = sorted(masks)
    added = 0
    extras = ordered_map(_SpreadPose(get, masks, voxels, voxel, o), poses, workers)
    for pose, extra in zip(poses, progress(extras, desc="compare: spread", total=len(poses))):
        if extra is None:
            continue
        m0, m1 = masks[pose]
        added += int(extra[0].sum() + extra[1].sum())
        masks[pose] = (m0 | extra[0], m1 | extra[1])
    log.info("spread: %d voxels at t0 and %d at t1 that >= %.0f %% of the key frames seeing them "
             "show as changed IDs and that the other time left empty; %d pixels of other IDs "
             "in them that look different at the two times added over %d poses",
             len(voxels[0]), len(voxels[1]), 100 * o.spread_vote, added, len(poses))


def _id_counts(ids: dict[Key, np.ndarray], n: int = 2) -> list[np.ndarray]:
    """``n`` zeroed int64 counters indexed by ID value (every ID of ``ids``): pixels of an ID,
    and those of them that pass a test."""
    size = int(max(int(m.max()) for m in ids.values())) + 1
    return [np.zeros(size, np.int64) for _ in range(n)]


def _place_sums(df: pd.DataFrame, counts: np.ndarray) -> pd.Series:
    """Per changed row of ``df`` (indexed like it), the sum of ``counts`` (int, indexed by ID
    value) over every ID of its ``place`` (the pieces of its object at one place,
    :func:`gdiff.compare.change._group_instances`): the unit a change is confirmed by."""
    ch = df.index[df["changed"]]
    per_id = pd.Series(counts[df.loc[ch, "id"].to_numpy(np.int64)], index=ch)
    return per_id.groupby(df.loc[ch, "place"].to_numpy()).transform("sum")


def _pool_places(df: pd.DataFrame, column: str, total: np.ndarray, hits: np.ndarray,
                    min_px: int = 0) -> None:
    """Column ``column`` of the changed rows of ``df`` (in place): per ``place``, the hits
    of all its IDs over their pixels (``total``, ``hits``: counts per ID value). Left as it is
    for a place with fewer than ``min_px`` pixels (at least one counts as one)."""
    n, h = _place_sums(df, total), _place_sums(df, hits)
    ok = n >= min_px
    df.loc[ok.index[ok], column] = h[ok] / np.maximum(n[ok], 1)


def _support_3d(df: pd.DataFrame, ids: dict[Key, np.ndarray], evidence: list[GeometryEvidence],
                band: int) -> None:
    """Column ``support`` (in place): per changed object at one place (a ``place`` of the
    table, all its IDs together), the share of its pixels, at the poses and times where its
    IDs are visible, within ``band`` pixels of the change pixels of that time of any of ``evidence``
    (:class:`gdiff.compare.geometry.GeometryEvidence` objects, after ``finish``; the first
    decides which poses were judged in 3D): how much of it changed in 3D. NaN for unchanged
    IDs."""
    df["support"] = np.nan
    ch = df.index[df["changed"]]
    if len(ch) == 0:
        return
    total, near = _id_counts(ids)
    size = len(total)
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * band + 1, 2 * band + 1))
    for p, i in sorted({(p, i) for p, _, i in ids}):
        if (p, i) not in evidence[0]:
            continue  # no depth at this pose: not judged in 3D
        labels = [ev.labels((p, i)) for ev in evidence if (p, i) in ev]
        for k, t in enumerate(TIMES):
            m = ids[(p, t, i)].ravel()
            total += np.bincount(m, minlength=size)
            hit = np.any([lab[k] >= 0 for lab in labels], axis=0)
            if hit.any():
                g = (cv2.dilate(hit.astype(np.uint8), kernel) > 0).ravel()
                near += np.bincount(m[g], minlength=size)
    _pool_places(df, "support", total, near)


def _shown_ids(ids: dict[Key, np.ndarray], key: Key, shown: dict | None) -> np.ndarray | None:
    """The ID map ``ids[key]`` (``key`` = (path, time, frame) of a key pose) with 0 (counted
    for no object) where ``shown[(path, frame)]`` (bool [H, W], optional) says no photo of one
    of the times shows the surface; None when there is no such map."""
    m = ids.get(key)
    mask = None if m is None or shown is None else shown.get((key[0], key[2]))
    return m if mask is None else np.where(mask, m, 0)


def _photo_support(df: pd.DataFrame, ids: dict[Key, np.ndarray], keys: dict[tuple[str, int], int],
                   diffs: dict, margin: float, min_px: int, shown: dict | None = None) -> None:
    """Columns ``photo`` and ``photo_other`` (in place): per changed object at one place (a
    ``place``, all its IDs together), the share of its pixels at the key poses where the
    training photo differs from the render of the time it was not taken at by more than
    ``margin`` times the photo's noise floor (``diffs``:
    :func:`gdiff.compare.complete.key_differences`).
    ``photo``: at the key poses of the time its IDs show there (the ID map of the key frame's
    own time: an added object at the after visit's poses, where the photos show it and the
    before render what stood there). ``photo_other``: at the key poses of the other time, in
    the other time's ID map (an added object at the before visit's poses, drawn by the after
    render, where the photos show what stood there before). A real change shows both ways; a
    surface one time's model renders poorly from the other time's poses (it never saw it from
    there) only in ``photo``. ``shown[(path, i)]`` (optional, bool [H, W]): the pixels of the
    key pose whose surface a photo of each time shows
    (:func:`gdiff.compare.coverage.observed`); only those count. Where the other time's photos
    did not see the surface, its render there is a guess, and a photo differs from it on any
    surface. NaN for unchanged IDs, and for objects with fewer than ``min_px`` such pixels."""
    df["photo"] = np.nan
    df["photo_other"] = np.nan
    ch = df.index[df["changed"]]
    if len(ch) == 0 or not diffs:
        return
    total, above, total_o, above_o = _id_counts(ids, 4)
    size = len(total)
    for (p, i), (d, floor) in sorted(diffs.items()):
        t = int(keys[(p, i)])
        hit = (d > margin * floor).ravel()
        for k, (tot, ab) in ((t, (total, above)), (1 - t, (total_o, above_o))):
            m = _shown_ids(ids, (p, TIMES[k], i), shown)
            if m is None or m.shape != d.shape:
                continue
            m = m.ravel()
            tot += np.bincount(m, minlength=size)
            ab += np.bincount(m[hit], minlength=size)
    _pool_places(df, "photo", total, above, min_px)
    _pool_places(df, "photo_other", total_o, above_o, min_px)


def _own_view(df: pd.DataFrame, ids: dict[Key, np.ndarray], keys: dict[tuple[str, int], int],
              shown: dict | None = None) -> None:
    """Column ``own_px`` (in place): per changed object at one place (a ``place``, all its
    IDs together), its pixels at the key poses of its own time: in the ID map of the time the
    key frame's photo was taken at (an added object at the after visit's poses), where its render
    reproduces a photo. ``shown[(path, i)]`` (optional, bool [H, W]): the pixels of the key pose
    whose surface a photo of each time shows (:func:`gdiff.compare.coverage.observed`); only
    those count. 0 for an object that shows only from the other visit's poses; NaN for
    unchanged IDs."""
    df["own_px"] = np.nan
    if not len(df.index[df["changed"]]) or not keys:
        return
    (total,) = _id_counts(ids, 1)
    for (p, i), t in sorted(keys.items()):
        m = _shown_ids(ids, (p, TIMES[int(t)], i), shown)
        if m is not None:
            total += np.bincount(m.ravel(), minlength=len(total))
    own = _place_sums(df, total)
    df.loc[own.index, "own_px"] = own.astype(float)


def _photo_points(df: pd.DataFrame, ids: dict[Key, np.ndarray], key_photos: list[KeyPhoto],
                  o: CompareOptions) -> None:
    """Column ``photo_points`` (in place): per changed object at one place (a ``place``, all
    its IDs together), the share of its surface points at the key poses of its own time that
    the other time's photos show differently from the key photo, more than nine in ten points of
    the unchanged surface of the same pair of photos are
    (:func:`gdiff.compare.photos.point_photo_counts`). The same 3D points in the photos of
    both visits: an object still standing shows there as itself, however poorly the other
    time's model renders it from this pose; one added or removed shows what it stands in
    front of or what it covered. NaN for unchanged IDs and for objects with fewer than
    ``o.min_area`` such points. ``key_photos``: the key frames' photos (:func:`_key_photos`)."""
    df["photo_points"] = np.nan
    ch = df.index[df["changed"]]
    if len(ch) == 0:
        return
    total, above = _id_counts(ids)
    changed = np.zeros(len(total), bool)
    changed[df.loc[ch, "id"].to_numpy(np.int64)] = True
    by_time = {t: [k for k in key_photos if k.time == t] for t in (0, 1)}
    for own in key_photos:
        p, i = own.pose
        m = ids.get((p, TIMES[own.time], i))
        if m is None:
            continue
        tot, ab = point_photo_counts(own, m, changed, by_time[1 - own.time],
                                     o.observed_depth_tol, len(total))
        total += tot
        above += ab
    _pool_places(df, "photo_points", total, above, o.min_area)


#: an object's photos show it changed when at least this share of its pixels differ from the
#: other time's render (``photo`` / ``photo_other``, :func:`_photo_support`)
PHOTO_SHARE = 0.5

CANDIDATE_COLUMNS = ["instance", "place", "ids", "types", "n_t0", "n_t1", "n_confirmed", "area",
                     "x", "y", "z", "size", "support", "colour", "photo", "photo_other",
                     "photo_points", "own_px", "verdict"]


def _candidate_row(instance: int, place: int, members: pd.DataFrame, support: float,
                   colour: float, verdict: str, photo: float = float("nan"),
                   photo_other: float = float("nan"), photo_points: float = float("nan"),
                   own_px: float = float("nan")) -> dict:
    """One row of ``candidates.csv`` (:data:`CANDIDATE_COLUMNS`) for a changed object at one
    place, made of the table rows ``members``: its counts, area, position and size are its
    largest member's."""
    head = members.loc[members["area"].idxmax()]
    return dict(instance=instance, place=place, ids=" ".join(str(int(i)) for i in members["id"]),
                types=" ".join(sorted(set(members["type"]))), n_t0=int(head["n_t0"]),
                n_t1=int(head["n_t1"]), n_confirmed=int(head["n_confirmed"]),
                area=float(head["area"]), **{c: float(head[c]) for c in ("x", "y", "z", "size")},
                support=support, colour=colour, photo=photo, photo_other=photo_other,
                photo_points=photo_points, own_px=own_px, verdict=verdict)


def _confirm_by_evidence(df: pd.DataFrame, o: CompareOptions, band: int,
                         light_changed: bool = False, unlined: set[str] | None = None) -> None:
    """Keep only the changed objects of the ID comparison that the 3D evidence or their own
    colour confirms (in place: ``changed`` set False for the others, with their ``type``,
    ``partner``, ``instance`` and ``place``).

    An ID missing at one time is a change only if the object is: the segmenter also cuts an
    unchanged surface differently at the two renders (a textured floor or wall far away, in
    pieces that differ between the times), and under a change of light the tracker cannot match
    an unchanged object's two looks (a shadow now crosses it, a warmer sun lights it), so it
    shows up as removed and added. Neither changes the surface in 3D, nor its colour relative
    to the surface next to it, which the same light falls on. A changed object at one place
    (a ``place`` of the table, all its IDs there together) is kept when its ``support``
    (:func:`_support_3d`: near the geometry evidence, and with unchanged light the flat
    evidence) is at least ``o.confirm_support``, or when its ``colour`` relative to its
    surroundings changed by at least ``o.confirm_colour`` (per ID,
    :func:`gdiff.compare.change.surround_colour_change`; pooled over the place weighted by
    ``n_colour``): an object swapped for one of the same shape and size changes no depth, but
    its own colour, unless the photos of both visits show its surface points alike
    (``photo_points`` below ``o.confirm_colour_points``, :func:`_photo_points`): the other
    time's rendered colours at a pose its photos did not see are a guess; nor when it shows at
    no key pose of its own time (``own_px`` below ``o.min_area``, :func:`_own_view`;
    ``o.confirm_colour_own_view``): then its own colours are that time's guess; nor, with the
    light unchanged, when the ID comparison found it at one pose only and that is a key
    pose whose two renders do not line up (in ``unlined``, :func:`unlined_poses`;
    ``o.confirm_colour_lined_up``) and the photos of its own time do not show it changed
    (``photo`` below one half): the two models disagree there on where things are, and its
    colour is compared with another surface's, while the photo is measured against its own
    view's noise floor. With the light unchanged, it is also kept when the training photos show
    it changed both ways (``photo`` and ``photo_other``, :func:`_photo_support`, each at least
    one half; ``o.confirm_photo`` > 0) and the ID comparison confirmed it at two poses or more:
    on a sparse capture neither the depth nor the rendered colours may tell a grey mug on a
    white table, the photos do; an unchanged surface the segmenter cut differently looks in
    the photos as the other time renders it, and one the other time's model renders poorly
    from this time's poses looks in the other time's photos as this time renders it.

    The two places of an object that moved are judged apart: each changed, and the evidence of
    the one does not vouch for the other (on a sparse capture the segmenter's pieces of an
    unchanged surface pair up as moved with real changes and with each other). When one of
    them is dropped, the other is what it was before the pairing (``added`` or ``removed``,
    no ``partner``, its ``place`` its ``instance``).

    Every place judged, with its figures and verdict (``kept: 3D``, ``kept: colour``,
    ``kept: photo`` or ``dropped``), goes to ``df.attrs["candidates"]`` (columns
    :data:`CANDIDATE_COLUMNS`; ``instance`` the object it is part of; ``n_t0``, ``n_t1``,
    ``n_confirmed``, ``area``, ``x``, ``y``, ``z`` and ``size`` are those of its largest
    member).
    """
    ch = df.index[df["changed"]]
    df.attrs["candidates"] = pd.DataFrame(columns=CANDIDATE_COLUMNS)
    if len(ch) == 0:
        return
    places = df.loc[ch, "place"].to_numpy()
    colour = np.nan_to_num(df.loc[ch, "colour"].to_numpy(float))  # NaN only where n_colour 0
    weight = df.loc[ch, "n_colour"].to_numpy(float)
    # per changed ID, its place's photo shares and own-view pixels (NaN where not measured)
    photo = df.reindex(columns=["photo", "photo_other", "photo_points", "own_px"]
                       ).loc[ch].to_numpy(float)
    by_photo = o.confirm_photo > 0 and not light_changed
    drop, rows = [], []
    # objects whose colour changed but were dropped, by the first reason colour did not count
    vetoed = dict.fromkeys(("alike", "unseen", "unlined"), 0)
    by_lineup = o.confirm_colour_lined_up and bool(unlined) and not light_changed
    for v in np.unique(places):
        sel = places == v
        support = float(df.loc[ch[sel], "support"].iloc[0])
        w = weight[sel]
        col = float((colour[sel] * w).sum() / w.sum()) if w.sum() else np.nan
        pho, phx, pts, own = photo[sel][0]
        # its colour counts unless the photos of both visits show its points alike
        alike = o.confirm_colour_points > 0 and pts < o.confirm_colour_points
        # ... and unless it shows only where its time's photos were not taken (NaN: not
        # counted, it counts)
        unseen = o.confirm_colour_own_view and own < o.min_area
        # ... and unless one pose alone shows it (all its IDs there, nowhere else), where the
        # two models do not line up, and the photo taken there does not show it changed either
        seen_at = (set(df.loc[ch[sel], "first"]) | set(df.loc[ch[sel], "last"])
                   if by_lineup else set())
        unlined_only = (len(seen_at) == 1 and seen_at <= unlined
                        and not pho >= PHOTO_SHARE)  # NaN (no photo measure): not shown
        # the photo's word counts for an object confirmed at more than one pose: one pose's
        # render, against the photo next to it, may differ where the fit is poor
        several = int(df.loc[ch[sel], "n_confirmed"].max()) >= 2
        veto = ("alike" if alike else "unseen" if unseen else "unlined" if unlined_only
                else None)
        verdict = ("kept: 3D" if support >= o.confirm_support else
                   "kept: colour" if col >= o.confirm_colour and veto is None else
                   "kept: photo" if (by_photo and several and pho >= PHOTO_SHARE
                                     and phx >= PHOTO_SHARE)
                   else "dropped")
        if verdict == "dropped" and col >= o.confirm_colour:
            vetoed[veto] += 1
        log.debug("place %d: %.2f of its pixels near a change in 3D, colour change %.2f, "
                  "%.2f / %.2f shown changed by the photos of its own / the other time, %.2f of "
                  "its points by the other time's photos: %s", v, support, col, pho, phx, pts,
                  verdict)
        if verdict == "dropped":
            drop.extend(ch[sel])
        rows.append(_candidate_row(int(df.loc[ch[sel], "instance"].iloc[0]), int(v),
                                   df.loc[ch[sel]], support, col, verdict, pho, phx, pts, own))
    df.attrs["candidates"] = pd.DataFrame(rows, columns=CANDIDATE_COLUMNS)
    n = len(np.unique(places))
    n_photo = sum(r["verdict"] == "kept: photo" for r in rows)
    log.info("%s%d of %d changed objects of the ID comparison (a moved one at each of its two "
             "places apart) changed in 3D (>= %.0f %% of their pixels within %d px of the 3D "
             "evidence), in colour (by >= %.2f, relative to their surroundings)%s and are "
             "kept; %d IDs dropped",
             "change of light: " if light_changed else "",
             n - len(np.unique(df.loc[drop, "place"])), n, 100 * o.confirm_support, band,
             o.confirm_colour,
             f" or in the training photos ({n_photo}: >= half of their pixels differ from "
             f"the other time's render by >= {o.confirm_photo:g} x the photo's noise floor, "
             f"at the key poses of both times)"
             if by_photo else "", len(drop))
    if vetoed["alike"]:
        log.info("%d objects whose colour changed were dropped: fewer than %.0f %% of their "
                 "surface points look different in the photos of the other visit "
                 "(compare.confirm_colour_points)", vetoed["alike"],
                 100 * o.confirm_colour_points)
    if vetoed["unseen"]:
        log.info("%d objects whose colour changed were dropped: they show at no key pose of "
                 "their own time (on fewer than %d pixels), only in that time's render from the "
                 "other visit's poses, where none of its photos was taken "
                 "(compare.confirm_colour_own_view)", vetoed["unseen"], o.min_area)
    if vetoed["unlined"]:
        log.info("%d objects whose colour changed were dropped: the ID comparison found them at "
                 "one pose only, a key pose whose t0 and t1 renders do not line up, and the "
                 "photo taken there does not show them changed "
                 "(compare.confirm_colour_lined_up)", vetoed["unlined"])
    df.loc[drop, "changed"] = False
    df.loc[drop, "type"] = ""
    df.loc[drop, ["partner", "instance", "place"]] = 0
    unpair(df)


def _replaced(df: pd.DataFrame, o: CompareOptions) -> None:
    """Mark the objects replaced in place by a change (:func:`gdiff.compare.change.replaced`),
    log them and list them in ``df.attrs["candidates"]`` with the verdict ``kept: replaced by
    <ID>``."""
    marked = df[df["id"].isin(replaced(df, o))]
    if marked.empty:
        return
    rows = [_candidate_row(int(r["id"]), int(r["id"]), marked.loc[[i]], float(r["support"]),
                           float(r["colour"]), f"kept: replaced by {int(r['partner'])}")
            for i, r in marked.iterrows()]
    cand = df.attrs.get("candidates")
    new = pd.DataFrame(rows, columns=CANDIDATE_COLUMNS)
    df.attrs["candidates"] = new if cand is None or cand.empty else pd.concat(
        [cand, new], ignore_index=True)
    log.info("replaced: %d IDs never seen at the other time, where a change present at that "
             "time hides at least %.0f %% of them and the rest shows a farther surface at >= "
             "%.0f %% of their poses, are changes too (%s)",
             len(marked), 100 * HIDDEN_SHARE, 100 * o.vote_frac,
             ", ".join(f"{int(r['id'])} by {int(r['partner'])}" for _, r in marked.iterrows()))


def _add_evidence(masks, ev: GeometryEvidence, leave_out: np.ndarray | None = None) -> int:
    """OR the change pixels of ``ev`` into ``masks`` (in place), except those of the components
    ``leave_out``; returns the number of pixels added."""
    added = 0
    for pose, (m0, m1) in masks.items():
        if pose not in ev:
            continue
        g0, g1 = ((lab >= 0) & ~np.isin(lab, leave_out) if leave_out is not None else lab >= 0
                  for lab in ev.labels(pose))
        added += int((g0 & ~m0).sum() + (g1 & ~m1).sum())
        masks[pose] = (m0 | g0, m1 | g1)
    return added


def _rims(flat: GeometryEvidence, masks, n: int, band: int) -> np.ndarray:
    """Components of the flat evidence that are the rims or shadows of other changes: at the
    poses that show them, at least 9/10 of the pixels they would add to ``masks`` (the ID
    comparison's and the geometry's changes) lie within ``band`` pixels of those changes. A
    changed object darkens the surface it stands on and blurs into it at its outline; those
    pixels keep their depth and change appearance, like a flat object, but hug the object. A
    flat object the ID comparison found in part, or the lowest part of an object standing on
    its support (too near the support for its depth to tell them apart), reaches beyond that
    band and is kept, even when most of it lies within the band."""
    if n == 0:
        return np.zeros(0, np.int64)
    new = np.zeros(n, np.int64)
    near = np.zeros(n, np.int64)
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * band + 1, 2 * band + 1))
    for pose, (m0, m1) in masks.items():
        if pose not in flat:
            continue
        other = m0 | m1
        ring = (cv2.dilate(other.astype(np.uint8), kernel) > 0) & ~other
        for lab in flat.labels(pose):
            sel = (lab >= 0) & ~other
            new += np.bincount(lab[sel], minlength=n)
            near += np.bincount(lab[sel & ring], minlength=n)
    return np.flatnonzero(near >= 0.9 * np.maximum(new, 1))


def _key_photos_at_one_exposure(keys: dict[tuple[str, int], int], meta: dict, photo_root: Path,
                                get, alpha_min: float) -> dict[tuple[str, int], np.ndarray]:
    """The key frames' photos (linear RGB float32 at their frame's size, read from
    ``photo_root`` / the frame's ``image``), each brought to the exposure both visits are
    compared at by the renders of both times at its camera
    (:func:`gdiff.compare.photos.visit_exposure`; only pixels with opacity >= ``alpha_min``
    at both times): auto exposure differs between visits. ``get``: key -> frame dict."""
    photos = {}
    for (p, i), t in sorted(keys.items()):
        own = get((p, TIMES[t], i))
        image, depth = meta[p][i].get("image"), own.get("depth")
        if not image or depth is None:
            continue
        photo = load_photo(photo_root / image, depth.shape[1], depth.shape[0])
        frames = [own, get((p, TIMES[1 - t], i))]
        drawn = [srgb_to_linear(f["rgb"]) for f in frames
                 if f.get("rgb") is not None and f["rgb"].shape == photo.shape]
        valid = [f["alpha"] >= alpha_min for f in frames
                 if f.get("alpha") is not None and f["alpha"].shape == depth.shape]
        photos[(p, i)] = visit_exposure(photo, drawn,
                                        np.logical_and.reduce(valid) if valid else None)
    return photos


def compare(instances_dir, poses_json, out_dir, options: CompareOptions | None = None,
            workers: int = 1, photo_root=None) -> dict:
    """Stage ``compare``: change masks of every pose from the tracked IDs.

    Reads ``instances_dir/index.json`` (and through it the ID maps and the rendered EXR frames,
    for the depth evidence) and the key frames of ``poses_json`` (the training cameras: only
    pixels a photo of each time saw are compared, :mod:`gdiff.compare.coverage`); writes ``out_dir/<path>/<t0|t1|union>/NNNNN.png``,
    ``out_dir/changes.csv`` (id, type, partner, first/last pose, area, instance: the object a
    changed ID is a piece of, place: its pieces at one place, x, y, z, size: where it is in
    the cameras' world frame, ...),
    ``out_dir/coverage.csv`` (per pose, how much of it the photos of both times let be judged:
    :func:`coverage_table`) with ``out_dir/<path>/judged/NNNNN.png``
    (:func:`gdiff.compare.coverage.judged_map`; both only when the key frames hold photos of
    both times) and, last, ``out_dir/keyframes.csv`` (path, frame, image, set, time, mask_t0,
    mask_t1, mask_union, judged: the pose's judged map or empty; paths relative to the parent
    of ``out_dir``, i.e. results/<scene>/; light_changed: whether the stage took the scene for
    a change of light, the same on every row). ``workers``:
    processes the poses are judged on (the files do not depend on it). ``photo_root``: the
    folder the key frames' ``image`` names are relative to (:func:`gdiff.cameras.image_root`);
    with it the training photos, brought to one exposure for both visits
    (:func:`_key_photos_at_one_exposure`), check the flat evidence, confirm objects, complete
    the key frames' masks and clear in them what both visits' photos show alike
    (``compare_paths``' ``photos``).
    Pixels whose rendered opacity is below the segmenter's ``alpha_min`` (recorded in
    ``index.json``; :data:`gdiff.segment.base.ALPHA_MIN` when an older index lacks it) show no
    surface and are not judged (``compare_paths``' ``alpha_min``).
    """
    instances_dir, out_dir = Path(instances_dir), Path(out_dir)
    index = read_json(instances_dir / "index.json")
    cams, meta = read_sequence(poses_json)
    ids, renders = {}, {}
    for fr in index.get("frames", []):
        key = (fr["path"], fr["t"], int(fr["frame"]))
        ids[key] = read_ids(instances_dir / fr["ids"])
        renders[key] = instances_dir / fr["render"]
    if not ids:
        raise SceneError(f"{instances_dir / 'index.json'}: no frames listed; re-run segment")

    missing = [f for f in renders.values() if not f.exists()]
    if missing:
        raise SceneError(f"{missing[0]}: rendered frame not found ({len(missing)} of "
                         f"{len(renders)} frames that {instances_dir / 'index.json'} lists are "
                         "missing); re-run render (the workflow deletes the frames once segment "
                         "and compare have read them, unless render.keep_frames is true)")

    def read(key):
        if key not in renders:
            return {}
        rgb, alpha, depth = read_frame(renders[key])
        return dict(rgb=rgb, alpha=alpha, depth=depth, camera=cams[key[0]][key[2]])

    keys = key_frames(meta)
    # key frames are read once: for the coverage views and again at their own pose
    keyed = {(p, TIMES[t], i): read((p, TIMES[t], i)) for (p, i), t in keys.items()}

    def load(key):
        return keyed[key] if key in keyed else read(key)

    photos = None
    o = options or CompareOptions()
    if photo_root is not None and (o.flat_photo_contrast > 0 or o.complete_reach > 0
                                   or o.confirm_photo > 0 or o.photo_agree > 0):
        photos = _key_photos_at_one_exposure(keys, meta, Path(photo_root), load,
                                             index.get("alpha_min", ALPHA_MIN))
    # how well the two times' renders line up at the key poses: before the ID comparison, whose
    # colour test does not trust a pose that does not (compare.confirm_colour_lined_up)
    lined = lineup_table(load, keys, meta, o.lineup_share) if o.lineup_share > 0 else None
    masks, df = compare_paths(ids, load, options, keys=keys, workers=workers, photos=photos,
                              alpha_min=index.get("alpha_min", ALPHA_MIN),
                              unlined=unlined_poses(lined))
    root = out_dir.parent
    judged = df.attrs.get("judged", {})
    rows = []
    for (p, i), (m0, m1) in sorted(masks.items()):
        rel = {}
        for name, m in (("t0", m0), ("t1", m1), ("union", m0 | m1)):
            f = out_dir / p / name / f"{i:05d}.png"
            write_mask(f, m)
            rel[name] = os.path.relpath(f, root)
        rel["judged"] = ""
        if (p, i) in judged:
            f = out_dir / p / "judged" / f"{i:05d}.png"
            write_image(f, judged[(p, i)])
            rel["judged"] = os.path.relpath(f, root)
        if (p, i) in keys:
            fr = meta[p][i]
            rows.append(dict(path=p, frame=i, image=fr.get("image", ""), set=fr.get("set") or "",
                             time=keys[(p, i)], mask_t0=rel["t0"], mask_t1=rel["t1"],
                             mask_union=rel["union"], judged=rel["judged"],
                             light_changed=bool(df.attrs.get("light_changed"))))
    coverage = df.attrs.get("coverage", pd.DataFrame(columns=COVERAGE_COLUMNS))
    if lined is not None:
        report_lineup(lined, o.lineup_share, bool(df.attrs.get("light_changed")))
        coverage = _with_lineup(coverage, lined)
    write_csv(out_dir / "coverage.csv", coverage)
    keyed = coverage.dropna(subset=["key", "not_judged_frac"])
    if len(keyed):
        log.info("where the photos let each pose be judged: %s (per pose; at the key poses %.1f "
                 "%% of the surface not judged on average, %.1f %% at most) and %s (0: no "
                 "surface, 64: not judged, 128: judged by ID and appearance, 255: also by "
                 "depth)", out_dir / "coverage.csv",
                 100 * keyed["not_judged_frac"].mean(), 100 * keyed["not_judged_frac"].max(),
                 out_dir / "<path>" / "judged")
    write_evidence(out_dir / "evidence3d.npz", df.attrs.get("evidence3d", {}))
    write_csv(out_dir / "candidates.csv",
              df.attrs.get("candidates", pd.DataFrame(columns=CANDIDATE_COLUMNS)))
    write_csv(out_dir / "changes.csv", df[df["changed"]].drop(columns=["changed"]))
    write_csv(out_dir / "keyframes.csv", pd.DataFrame(rows, columns=[
        "path", "frame", "image", "set", "time", "mask_t0", "mask_t1", "mask_union", "judged",
        "light_changed"]))
    counts = df.loc[df["changed"], "type"].value_counts().to_dict()
    return {"poses": len(masks), "changed": int(df["changed"].sum()),
            "instances": int(df.loc[df["changed"], "instance"].nunique()), **counts}
