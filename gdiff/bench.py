"""The bench table: quality and cost of a workflow run, one row per scene and method.

Read by ``benchmarks/bench.py`` (which runs the workflow first unless ``--no-run``); pure
functions on the files of a results folder (``results/``), so a finished or half-finished run
can be tabulated at any time.

Per scene and method (from ``<scene>/eval/metrics.csv``, aggregated as the summary rule does with
:func:`gdiff.summary.summarize_metrics`): pooled ``P, R, F1, IoU``, object recall ``obj_R`` and,
for scenes with box ground truth, box recall ``gtbox_R`` and ``far_frac`` (share of the image
flagged farther than the margin from every box).

Per scene (the same value on each of its rows):

* per rule ``wall_<rule>`` (s), ``cpu_<rule>`` (user + system s), ``mb_<rule>`` (peak
  MB), from Snakemake's benchmark files ``<scene>/benchmarks/<rule>.tsv`` (the figures the summary
  rule copies into ``timings.csv``; read from the TSVs so a run still in progress is covered,
  else from ``timings.csv``);
* ``wall_s`` and ``cpu_s``: the sums over the scene's rules (its stages run one after another,
  so ``wall_s`` is the scene's whole-workflow wall time when it runs alone), ``peak_mb`` the
  largest rule peak; a rule's memory (``mb_<rule>``) is its peak PSS where Snakemake measured
  one (pages shared by a rule's forked workers counted once), else its peak RSS sum;
* ``disk_mb``: size of the files under ``<scene>/`` (MB = 10^6 bytes);
* ``psnr_t0``, ``psnr_t1``: the fit's PSNR (dB) per time, mean over the eval views from
  ``eval/fit_quality.csv`` (the evaluate rule renders the fitted model there), else over the
  training views from ``fit/quality.csv`` (``psnr_views`` says which: ``eval`` or ``train``).

Synthetic scenes run at several seeds (``<preset>_s<seed>``) get extra rows ``<preset> (mean of
N)``: every number averaged over the seeds. A scene fitted at several fit seeds (rows
``<scene>_f<seed>``, the bench's ``--fit-seeds``) gets a row ``<scene> (mean of N fit seeds)``:
one fit of a scene differs from another of the same photos by more than many changes do, so a
change is judged on those means and the spread of their rows.
"""

from __future__ import annotations

import math
import os
import re
from pathlib import Path
from typing import Iterable, Mapping

import numpy as np
import pandas as pd

from .io import read_json
from .summary import collect_metrics, collect_timings, find_benchmarks, summarize_metrics

QUALITY = {"P_pooled": "P", "R_pooled": "R", "F1_pooled": "F1", "IoU_pooled": "IoU",
           "obj_R_pooled": "obj_R", "gtbox_R_pooled": "box_R", "far_frac_pooled": "far_frac"}
SCENE_COLUMNS = ["wall_s", "cpu_s", "peak_mb", "disk_mb", "psnr_t0", "psnr_t1", "psnr_views"]
# the workflow's rules in run order (others found in a results folder are appended)
RULE_ORDER = ["manifest", "poses", "fit", "interpolate", "render", "segment", "compare",
              "partition", "evaluate"]


def scene_folders(results: str | Path) -> list[str]:
    """The scene folders of a results folder (those with ``input/``, ``benchmarks/`` or
    ``eval/``), sorted."""
    results = Path(results)
    if not results.is_dir():
        return []
    return sorted(p.name for p in results.iterdir() if p.is_dir() and any(
        (p / d).is_dir() for d in ("input", "benchmarks", "eval")))


def disk_mb(folder: str | Path) -> float:
    """Total size of the files under ``folder`` in MB (10^6 bytes); symlinks not followed."""
    total = 0
    for root, _, files in os.walk(folder):
        for f in files:
            try:
                total += os.lstat(os.path.join(root, f)).st_size
            except OSError:  # removed while walking (a run in progress)
                pass
    return total / 1e6


def fit_psnr(scene_results: str | Path) -> dict:
    """``{"psnr_t0", "psnr_t1", "psnr_views"}`` of ``results/<scene>/`` from
    ``eval/fit_quality.csv``, else ``fit/quality.csv`` (module docstring); NaN and ``""`` when
    neither has rows."""
    out = {"psnr_t0": math.nan, "psnr_t1": math.nan, "psnr_views": ""}
    root = Path(scene_results)
    q = None
    for rel, kind in (("eval/fit_quality.csv", "eval"), ("fit/quality.csv", "train")):
        if (root / rel).is_file():
            q = pd.read_csv(root / rel)
            if len(q) and {"time", "psnr"} <= set(q.columns):
                out["psnr_views"] = kind
                break
    if not out["psnr_views"]:
        return out
    for t in (0, 1):
        v = pd.to_numeric(q.loc[np.isclose(q["time"].astype(float), t), "psnr"], errors="coerce")
        out[f"psnr_t{t}"] = float(v.mean()) if v.notna().any() else math.nan
    return out


def scene_timings(results: str | Path, scenes: Iterable[str]) -> pd.DataFrame:
    """``scene, rule, seconds, cpu_seconds, max_rss_mb, max_pss_mb`` per scene and rule: from the
    benchmark TSVs, else from ``results/timings.csv`` (module docstring)."""
    results = Path(results)
    t = collect_timings(find_benchmarks({s: results / s / "benchmarks" for s in scenes}))
    have = set(t["scene"])
    missing = [s for s in scenes if s not in have]
    if missing and (results / "timings.csv").is_file():
        old = pd.read_csv(results / "timings.csv")
        t = pd.concat([t, old[old["scene"].isin(missing)]], ignore_index=True)
    return t


def fit_seed_name(scene: str, seed: int) -> str:
    """Name of the run of ``scene`` with fit seed ``seed`` (config ``fit.seed``)."""
    return f"{scene}_f{seed}"


def with_fit_seeds(rows: list[dict], fit_seeds: Iterable[int]) -> list[dict]:
    """Rows of a scenes sheet (``name``, ``path``, ``<section>.<key>`` overrides), each
    repeated per fit seed as ``<name>_f<seed>`` (:func:`fit_seed_name`) with ``fit.seed`` set;
    the rows unchanged when ``fit_seeds`` is empty."""
    seeds = [int(k) for k in fit_seeds]
    if not seeds:
        return list(rows)
    return [{**r, "name": fit_seed_name(r["name"], k), "fit.seed": k} for r in rows for k in seeds]


def fit_seed_groups(scenes: Iterable[str], fit_seeds: Iterable[int]) -> dict[str, list[str]]:
    """``{scene: [run names]}`` for runs named ``<scene>_f<seed>`` (:func:`fit_seed_name`) with
    a seed of ``fit_seeds``, seeds in numeric order. (The seeds must be named: a scene folder
    may be called like ``desk_f1`` too.)"""
    seeds = {int(x) for x in fit_seeds}
    groups: dict[str, list[tuple[int, str]]] = {}
    for s in scenes:
        m = re.fullmatch(r"(.+)_f(\d+)", s)
        if m and int(m.group(2)) in seeds:
            groups.setdefault(m.group(1), []).append((int(m.group(2)), s))
    return {k: [s for _, s in sorted(v)] for k, v in groups.items()}


def synth_groups(scenes: Iterable[str], presets: Iterable[str],
                 fit_seeds: Iterable[int] = ()) -> dict[str, list[str]]:
    """``{preset: [scene names]}`` for scenes named ``<preset>_s<seed>`` (the workflow's name for
    ``synth:<preset>:<seed>``), or ``<preset>_s<seed>_f<fit seed>`` with a seed of
    ``fit_seeds``, of the given presets, in numeric order. (Presets must be named: a scene
    folder may be called like ``desk_s1`` too.)"""
    presets, seeds = set(presets), {int(x) for x in fit_seeds}
    groups: dict[str, list[tuple[int, int, str]]] = {}
    for s in scenes:
        m = re.fullmatch(r"(.+)_s(\d+)(?:_f(\d+))?", s)
        if m and m.group(1) in presets and (m.group(3) is None or int(m.group(3)) in seeds):
            groups.setdefault(m.group(1), []).append((int(m.group(2)), int(m.group(3) or 0), s))
    return {k: [s for *_, s in sorted(v)] for k, v in sorted(groups.items())}


def build_table(summary: pd.DataFrame, timings: pd.DataFrame, scene_info: Mapping[str, dict],
                groups: Mapping[str, list[str]] | None = None,
                fit_groups: Mapping[str, list[str]] | None = None) -> pd.DataFrame:
    """The bench table (module docstring) from its parts.

    ``summary``: per (scene, method) rows of :func:`gdiff.summary.summarize_metrics` (rows of
    scene ``ALL`` are ignored); ``timings``: ``scene, rule, seconds, cpu_seconds, max_rss_mb``
    (and ``max_pss_mb`` when present);
    ``scene_info``: per scene ``disk_mb``, ``psnr_t0``, ``psnr_t1``, ``psnr_views``;
    ``groups``: ``{preset: [scenes]}`` whose means are appended as ``<preset> (mean of N)``;
    ``fit_groups``: ``{scene: [runs]}`` whose means are appended as ``<scene> (mean of N fit
    seeds)`` (before the preset means).
    Scenes without metrics (no eval views, or evaluate not run yet) get one row with an empty
    method. Columns: ``scene, method, n_views`` + quality + :data:`SCENE_COLUMNS` + per rule
    ``wall_/cpu_/mb_<rule>``.
    """
    summary = summary[summary["scene"] != "ALL"] if len(summary) else summary
    scenes = list(dict.fromkeys(list(summary["scene"]) if len(summary) else []))
    scenes = list(dict.fromkeys(scenes + list(scene_info) + list(timings["scene"])))
    rules = [r for r in RULE_ORDER if r in set(timings["rule"])]
    rules += sorted(set(timings["rule"]) - set(rules))
    per_scene = {}
    timings = timings.copy()
    if "max_pss_mb" in timings.columns:  # timings.csv of older runs have RSS only
        timings["mb"] = timings["max_pss_mb"].combine_first(timings["max_rss_mb"])
    else:
        timings["mb"] = timings["max_rss_mb"]
    for s in scenes:
        t = timings[timings["scene"] == s].set_index("rule")
        row: dict = {}
        for r in rules:
            have = r in t.index
            row[f"wall_{r}"] = float(t.loc[r, "seconds"]) if have else math.nan
            row[f"cpu_{r}"] = float(t.loc[r, "cpu_seconds"]) if have else math.nan
            row[f"mb_{r}"] = float(t.loc[r, "mb"]) if have else math.nan
        row["wall_s"] = float(t["seconds"].sum(min_count=1)) if len(t) else math.nan
        row["cpu_s"] = float(t["cpu_seconds"].sum(min_count=1)) if len(t) else math.nan
        row["peak_mb"] = float(t["mb"].max()) if len(t) else math.nan
        info = scene_info.get(s, {})
        for c in ("disk_mb", "psnr_t0", "psnr_t1"):
            row[c] = float(info.get(c, math.nan))
        row["psnr_views"] = info.get("psnr_views", "")
        per_scene[s] = row
    rows = []
    for s in scenes:
        sel = summary[summary["scene"] == s] if len(summary) else summary
        methods = list(sel.iterrows()) if len(sel) else [(None, None)]
        for _, r in methods:
            row = {"scene": s, "method": "" if r is None else r["method"],
                   "n_views": math.nan if r is None else r.get("n_views", math.nan)}
            for src, dst in QUALITY.items():
                row[dst] = math.nan if r is None else float(r.get(src, math.nan))
            row.update(per_scene[s])
            rows.append(row)
    cols = (["scene", "method", "n_views"] + list(QUALITY.values()) + SCENE_COLUMNS
            + [f"{k}_{r}" for r in rules for k in ("wall", "cpu", "mb")])
    table = pd.DataFrame(rows, columns=cols)
    means = [(f"{k} (mean of {{n}} fit seeds)", v) for k, v in (fit_groups or {}).items()]
    means += [(f"{k} (mean of {{n}})", v) for k, v in (groups or {}).items()]
    for label, members in means:
        g = table[table["scene"].isin(members)]
        if g.empty:
            continue
        num = [c for c in cols if c not in ("scene", "method", "psnr_views")]
        mean = g.groupby("method", sort=False)[num].mean().reset_index()
        mean.insert(0, "scene", label.format(n=g["scene"].nunique()))
        mean["psnr_views"] = ",".join(sorted(set(g["psnr_views"]) - {""}))
        table = pd.concat([table, mean[cols]], ignore_index=True)
    return table


def _fmt(v, digits: int) -> str:
    if isinstance(v, str):
        return v
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return "-"
    return f"{v:.{digits}f}"


def format_table(table: pd.DataFrame, markdown: bool = False) -> str:
    """The table as text: quality per row, the scene's cost columns on its first row only, per
    rule one cell ``wall/cpu/MB``. Plain aligned text, or a markdown table."""
    rules = [c[5:] for c in table.columns if c.startswith("wall_") and c != "wall_s"]
    show_box = table[["box_R", "far_frac"]].notna().any().any()
    head = ["scene", "method", "views", "P", "R", "F1", "IoU", "obj_R"]
    head += ["box_R", "far"] if show_box else []
    head += ["PSNR t0/t1", "wall s", "CPU s", "peak MB", "disk MB"]
    head += [f"{r} s/cpu/MB" for r in rules]
    lines, last = [], None
    for _, r in table.iterrows():
        cells = [r["scene"] if r["scene"] != last else "", r["method"] or "-",
                 _fmt(r["n_views"], 0)]
        cells += [_fmt(r[c], 3) for c in ("P", "R", "F1", "IoU", "obj_R")]
        cells += [_fmt(r["box_R"], 3), _fmt(r["far_frac"], 3)] if show_box else []
        if r["scene"] != last:
            views = f" ({r['psnr_views']})" if r["psnr_views"] else ""
            cells += [f"{_fmt(r['psnr_t0'], 1)}/{_fmt(r['psnr_t1'], 1)}{views}",
                      _fmt(r["wall_s"], 0), _fmt(r["cpu_s"], 0), _fmt(r["peak_mb"], 0),
                      _fmt(r["disk_mb"], 1)]
            cells += [f"{_fmt(r[f'wall_{x}'], 0)}/{_fmt(r[f'cpu_{x}'], 0)}/"
                      f"{_fmt(r[f'mb_{x}'], 0)}" for x in rules]
        else:
            cells += [""] * (5 + len(rules))
        lines.append(cells)
        last = r["scene"]
    if markdown:
        out = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
        out += ["| " + " | ".join(c for c in cells) + " |" for cells in lines]
        return "\n".join(out) + "\n"
    widths = [max(len(h), *(len(c[i]) for c in lines)) if lines else len(h)
              for i, h in enumerate(head)]
    fmt = lambda cells: "  ".join(c.ljust(w) for c, w in zip(cells, widths)).rstrip()  # noqa: E731
    return "\n".join([fmt(head), fmt(["-" * w for w in widths])] + [fmt(c) for c in lines]) + "\n"


def scaling_table(table: pd.DataFrame, photos: Mapping[str, int],
                  method: str = "partition") -> pd.DataFrame:
    """Cost against the number of photos: one row per rule (in run order) and ``total``, one
    column per scene of ``photos`` (``scene -> photos per set``, in increasing order) with
    its wall seconds, then per step between consecutive counts ``a -> b`` the growth factor
    ``wall(b) / wall(a)`` next to the photos' ``b / a`` (cost grows at most linearly where
    the first is no larger than the second); rows ``F1 (<method>)`` and ``PSNR t0`` /
    ``PSNR t1`` carry each scene's quality (no growth factor).

    ``table`` is a bench table (:func:`build_table`); a rule a scene did not run is NaN."""
    order = sorted(photos, key=lambda s: photos[s])
    secs = {s: f"{photos[s]} s" for s in order}
    steps = {f"x {photos[a]}->{photos[b]}": (a, b) for a, b in zip(order, order[1:])}
    first = table.drop_duplicates("scene").set_index("scene")
    qual = table[table["method"] == method].drop_duplicates("scene").set_index("scene")
    rules = [c[5:] for c in table.columns if c.startswith("wall_") and c != "wall_s"]
    rows = []
    for label, frame, col in ([(r, first, f"wall_{r}") for r in rules]
                              + [("total", first, "wall_s"), (f"F1 ({method})", qual, "F1"),
                                 ("PSNR t0", first, "psnr_t0"), ("PSNR t1", first, "psnr_t1")]):
        v = {s: float(frame.loc[s, col]) if s in frame.index else math.nan for s in order}
        if label in rules and all(math.isnan(x) for x in v.values()):
            continue
        row = {"row": label, **{secs[s]: v[s] for s in order}}
        if label in rules or label == "total":  # quality rows get no growth factor
            row.update({k: v[b] / v[a] if v[a] > 0 else math.nan
                        for k, (a, b) in steps.items()})
        rows.append(row)
    out = pd.DataFrame(rows, columns=["row"] + list(secs.values()) + list(steps))
    out.attrs["photo_ratio"] = {k: photos[b] / photos[a] for k, (a, b) in steps.items()}
    return out


def format_scaling(scaling: pd.DataFrame) -> str:
    """:func:`scaling_table` as a markdown table: seconds with one decimal, growth factors
    with two and the photo ratio in the header (``x 15->30 (photos x2.00)``)."""
    ratio = scaling.attrs.get("photo_ratio", {})
    head = ["rule"] + [f"{c} (photos x{ratio[c]:.2f})" if c in ratio else
                       "{0}+{0} photos: s".format(c.removesuffix(" s"))
                       for c in scaling.columns[1:]]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for _, r in scaling.iterrows():
        cells = [r["row"]]
        for c in scaling.columns[1:]:
            if r["row"].startswith("F1"):
                digits = 3
            elif r["row"].startswith("PSNR") or c in ratio:
                digits = 2
            else:
                digits = 1
            cells.append(_fmt(r[c], digits))
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def read_results(results: str | Path, scenes: Iterable[str] | None = None,
                 presets: Iterable[str] = (), fit_seeds: Iterable[int] = ()) -> pd.DataFrame:
    """The bench table of a results folder (every scene folder in it, or ``scenes``), with the
    mean rows of the synthetic presets ``presets`` (over their ``<preset>_s<seed>`` scenes) and
    of each scene run at the fit seeds ``fit_seeds`` (over its ``<scene>_f<seed>`` runs)."""
    results = Path(results)
    scenes = list(scenes) if scenes is not None else scene_folders(results)
    metrics_csvs = [results / s / "eval" / "metrics.csv" for s in scenes]
    metrics_csvs = [p for p in metrics_csvs if p.is_file()]
    summary = pd.DataFrame(columns=["scene", "method"])
    if metrics_csvs:
        metrics, boxes = collect_metrics(metrics_csvs)
        if len(metrics):
            summary = summarize_metrics(metrics, boxes)
    info = {s: {"disk_mb": disk_mb(results / s) if (results / s).is_dir() else math.nan,
                **fit_psnr(results / s)} for s in scenes}
    timings = scene_timings(results, scenes)
    return build_table(summary, timings, info, synth_groups(scenes, presets, fit_seeds),
                       fit_seed_groups(scenes, fit_seeds))


# ------------------------------------------------------------------------------------------
# the compare stage judged per object, where a scene lists its objects
# ------------------------------------------------------------------------------------------

OBJECT_COLUMNS = ["object", "changed", "verdict", "instances", "support", "colour"]


def _scene_objects(scene_dir: Path) -> list[tuple[str, bool, int, np.ndarray]] | None:
    """(name, changed, time, box [2, 3]) per object and time it is present, from the scene's
    ``meta.json`` (``objects``: ``name``, ``changed``, ``before`` / ``after`` with ``present``
    and ``bbox_world``, as the shared test scenes and ``gdiff synth`` write it); None without."""
    meta = scene_dir / "meta.json"
    if not meta.is_file() or not (scene_dir / "gt_cameras.json").is_file():
        return None
    objects = read_json(meta).get("objects")
    if not objects:
        return None
    out = []
    for o in objects:
        for time, state in enumerate(("before", "after")):
            s = o.get(state) or {}
            if s.get("present") and s.get("bbox_world") is not None:
                out.append((str(o["name"]), bool(o.get("changed")), time,
                            np.asarray(s["bbox_world"], float)))
    return out


def compare_objects(scene_results: str | Path) -> pd.DataFrame | None:
    """The compare stage's verdicts per object of the scene's ground truth, or None when the
    scene folder (``input/manifest.json``'s ``scene``) does not list its objects (``meta.json``
    with ``objects`` and boxes, and ``gt_cameras.json``), compare has not run, or its files
    carry no positions (written by an older version).

    The registered cameras (``poses/cameras.json``) are aligned to ``gt_cameras.json`` (the
    similarity of :func:`gdiff.align.pose_errors`, on the centres of the images both hold).
    Every changed ID the stage kept (``change/changes.csv``) and every object it judged and
    dropped (``change/candidates.csv``, placed by its largest ID) is put, by its world position
    (``x, y, z``), on the object whose box at the time it was seen (t0 for ``removed``, t1 for
    ``added``, either for ``moved``) is nearest, when it lies within a quarter of that box's
    diagonal of it. One row per changed object of the scene: ``verdict`` ``kept`` (a kept ID
    lies on it), ``dropped`` (only dropped ones), ``not judged`` (none: the ID comparison did
    not find it, or only the 3D evidence did), with the instances on it and the ``support``
    and ``colour`` of the largest; then one row per kept instance none of whose IDs lies on a
    changed object (``changed`` False, ``object`` the unchanged object its largest ID lies
    on, or empty): verdict ``kept`` too, a false change."""
    from .align import pose_errors
    from .sfm import read_cameras_file

    res = Path(scene_results)
    change, manifest = res / "change", res / "input" / "manifest.json"
    if not (change / "candidates.csv").is_file() or not (change / "changes.csv").is_file() \
            or not manifest.is_file():
        return None
    scene_dir = Path(read_json(manifest)["scene"])
    if not scene_dir.is_absolute():  # relative to the workflow's directory, above results/
        scene_dir = res.parent.parent / scene_dir
    boxes = _scene_objects(scene_dir)
    if boxes is None:
        return None
    kept = pd.read_csv(change / "changes.csv")
    cand = pd.read_csv(change / "candidates.csv")
    if not ({"x", "y", "z"} <= set(kept.columns) and {"x", "y", "z"} <= set(cand.columns)):
        return None  # written before compare recorded positions
    try:
        sim = pose_errors(read_cameras_file(res / "poses" / "cameras.json"),
                          read_cameras_file(scene_dir / "gt_cameras.json")).attrs
    except ValueError:  # fewer than 3 images in common: no alignment
        return None
    s, R, t = sim["scale"], sim["R"], sim["t"]

    def place(df: pd.DataFrame, type_column: str) -> None:
        on = []
        for _, c in df.iterrows():
            x = np.array([c["x"], c["y"], c["z"]], float)
            types = str(c[type_column]).split()
            times = {0} if types == ["removed"] else {1} if types == ["added"] else {0, 1}
            best = (np.inf, "", False)
            if np.isfinite(x).all():
                p = s * R @ x + t
                for name, changed, time, (lo, hi) in boxes:
                    d = float(np.linalg.norm(np.maximum(0, np.maximum(lo - p, p - hi))))
                    if time in times and d <= 0.25 * np.linalg.norm(hi - lo) and d < best[0]:
                        best = (d, name, changed)
            on.append(best[1:])
        df["object"] = [o for o, _ in on]
        df["on_changed"] = [c for _, c in on]

    place(kept, "type")
    dropped = cand[cand["verdict"] == "dropped"].copy()
    place(dropped, "types")
    rows = []
    for name in dict.fromkeys(n for n, changed, _, _ in boxes if changed):
        k = kept[kept["object"] == name].sort_values("area", ascending=False)
        d = dropped[dropped["object"] == name].sort_values("area", ascending=False)
        mine = k if len(k) else d
        verdict = "kept" if len(k) else "dropped" if len(d) else "not judged"
        rows.append(dict(object=name, changed=True, verdict=verdict,
                         instances=" ".join(str(int(i)) for i in dict.fromkeys(mine["instance"])),
                         support=float(mine["support"].iloc[0]) if len(mine) else np.nan,
                         colour=float(mine["colour"].iloc[0]) if len(mine) else np.nan))
    for inst, k in kept.groupby("instance", sort=True):
        if k["on_changed"].any():
            continue
        head = k.sort_values("area", ascending=False).iloc[0]
        rows.append(dict(object=head["object"], changed=False, verdict="kept",
                         instances=str(int(inst)), support=float(head["support"]),
                         colour=float(head["colour"])))
    return pd.DataFrame(rows, columns=OBJECT_COLUMNS)


def compare_object_counts(objects: pd.DataFrame) -> dict:
    """Counts of a :func:`compare_objects` table: changed objects, how many were kept,
    dropped and not judged, and how many false changes were kept."""
    ch = objects[objects["changed"].astype(bool)]
    return {"changed": len(ch), "kept": int((ch["verdict"] == "kept").sum()),
            "dropped": int((ch["verdict"] == "dropped").sum()),
            "not_judged": int((ch["verdict"] == "not judged").sum()),
            "false_kept": int((~objects["changed"].astype(bool)).sum())}


def read_compare_objects(results: str | Path, scenes: Iterable[str] | None = None
                         ) -> pd.DataFrame:
    """:func:`compare_objects` of every scene of a results folder (or ``scenes``) that lists its
    objects, one table with a first column ``scene``; empty when none does."""
    results = Path(results)
    scenes = list(scenes) if scenes is not None else scene_folders(results)
    parts = []
    for s in scenes:
        t = compare_objects(results / s)
        if t is not None:
            parts.append(t.assign(scene=s))
    if not parts:
        return pd.DataFrame(columns=["scene"] + OBJECT_COLUMNS)
    return pd.concat(parts, ignore_index=True)[["scene"] + OBJECT_COLUMNS]


def format_compare_objects(objects: pd.DataFrame) -> str:
    """One line per scene of a :func:`read_compare_objects` table: its changed objects kept,
    dropped and not judged by the compare stage (with the dropped ones' support and colour, the
    figures their verdict turned on), and the false changes it kept."""
    lines = []
    for scene, t in objects.groupby("scene", sort=False):
        n = compare_object_counts(t)
        dropped = t[t["changed"].astype(bool) & (t["verdict"] == "dropped")]
        why = "".join(f"; dropped {r.object} (support {r.support:.2f}, colour {r.colour:.2f})"
                      for r in dropped.itertuples())
        lines.append(f"{scene}: {n['kept']} of {n['changed']} changed objects kept, "
                     f"{n['dropped']} dropped, {n['not_judged']} not judged; "
                     f"{n['false_kept']} false changes kept{why}")
    return "\n".join(lines) + ("\n" if lines else "")
