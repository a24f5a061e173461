"""Summary stage: one table and plots across scenes and methods, and the run's timings.

Writes into ``out_dir`` (``results/``), atomically:

* ``summary.csv`` — one row per (scene, method) with the mean over views (``<m>_mean``,
  ``n_<m>`` views with a defined value) and the pooled figures (``<m>_pooled``) of
  :func:`gdiff.metrics.aggregate`, plus rows with ``scene == "ALL"``: per method, the mean
  over scenes of the per-scene means (``<m>_mean``) and figures pooled over every view of
  every scene (``<m>_pooled``; e.g. ``obj_R_pooled``, the object recall: objects found over
  objects);
* ``timings.csv`` — one row per (scene, rule) from Snakemake's ``benchmark:`` TSVs: wall
  ``seconds`` (mean over repeats), ``cpu_seconds``, ``max_rss_mb`` and ``max_pss_mb`` (largest
  over repeats; RSS summed over a rule's processes counts pages they share once per process,
  PSS splits them, so PSS is the memory a rule with forked workers really holds);
* ``plots/<metric>.png`` — grouped bars, scene x method, for F1, IoU, P, R (pooled), box F1,
  box AP and object recall (pooled); ``plots/timings.png`` — stacked seconds per rule for each
  scene.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Iterable, Mapping

import numpy as np
import pandas as pd

from .errors import SceneError
from .io import atomic_path, write_csv
from .metrics import BOX_METRICS, GTBOX_METRICS, OBJECT_METRICS, PIXEL_METRICS, aggregate

log = logging.getLogger("gdiff.summary")

PLOT_METRICS = ("F1_pooled", "IoU_pooled", "P_pooled", "R_pooled", "box_F1_pooled",
                "box_AP_pooled", "obj_R_pooled")


def _read_csv(path: Path, what: str) -> pd.DataFrame:
    if not path.is_file():
        raise SceneError(f"{path}: {what} not found (did the evaluate stage run?)")
    try:
        return pd.read_csv(path)
    except Exception as e:  # pandas parser errors
        raise SceneError(f"{path}: cannot be read as CSV ({e}); delete it and re-run") from None


def collect_metrics(metrics_csvs: Iterable[str | Path]) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Concatenate per-scene ``metrics.csv`` files and their sibling ``boxes.csv`` (if any)."""
    ms, bs = [], []
    for p in map(Path, metrics_csvs):
        df = _read_csv(p, "metrics table")
        missing = {"scene", "view", "method", "TP", "FP", "FN"} - set(df.columns)
        if missing:
            raise SceneError(f"{p}: column(s) {', '.join(sorted(missing))} missing; not a "
                             "gdiff metrics.csv")
        ms.append(df)
        if (p.parent / "boxes.csv").is_file():
            bs.append(_read_csv(p.parent / "boxes.csv", "box table"))
    metrics = pd.concat(ms, ignore_index=True) if ms else pd.DataFrame()
    boxes = pd.concat([b for b in bs if len(b)], ignore_index=True) if any(len(b) for b in bs) \
        else None
    return metrics, boxes


def summarize_metrics(metrics: pd.DataFrame, boxes: pd.DataFrame | None) -> pd.DataFrame:
    """Per (scene, method) rows plus ``scene == "ALL"`` rows per method (module docstring)."""
    if metrics.empty:
        return pd.DataFrame(columns=["scene", "method"])
    per = aggregate(metrics, boxes, by=("scene", "method"))
    views = metrics["scene"].astype(str) + "/" + metrics["view"].astype(str)
    every = metrics.assign(view=views, scene="ALL")
    overall = aggregate(every, None if boxes is None else boxes.assign(scene="ALL"),
                        by=("scene", "method"))
    # "ALL" means: mean over scenes of the per-scene means (each scene weighs the same)
    for m in PIXEL_METRICS + BOX_METRICS + OBJECT_METRICS + GTBOX_METRICS:
        col = f"{m}_mean"
        if col in per:
            overall[col] = overall["method"].map(per.groupby("method")[col].mean())
    overall["n_scenes"] = overall["method"].map(per.groupby("method")["scene"].nunique())
    per["n_scenes"] = 1
    return pd.concat([per, overall[per.columns.intersection(overall.columns)]],
                     ignore_index=True)[per.columns]


def read_benchmark(path: str | Path) -> dict[str, float]:
    """One Snakemake benchmark TSV -> ``seconds`` (mean over repeats), ``cpu_seconds``,
    ``max_rss_mb`` and ``max_pss_mb`` (max over repeats); NaN where Snakemake wrote NA or
    nothing."""
    path = Path(path)
    if not path.is_file():
        raise SceneError(f"{path}: benchmark file not found")
    try:
        df = pd.read_csv(path, sep="\t", na_values=["NA", "-", ""])
    except Exception as e:
        raise SceneError(f"{path}: cannot be read as a Snakemake benchmark TSV ({e})") from None
    if "s" not in df.columns:
        raise SceneError(f"{path}: no 's' column; not a Snakemake benchmark file")

    def col(name, fn):
        if name not in df.columns:
            return float("nan")
        v = pd.to_numeric(df[name], errors="coerce")
        return float(fn(v)) if v.notna().any() else float("nan")

    return {"seconds": col("s", np.mean), "cpu_seconds": col("cpu_time", np.mean),
            "max_rss_mb": col("max_rss", np.max), "max_pss_mb": col("max_pss", np.max),
            "repeats": int(len(df))}


def find_benchmarks(folders: Mapping[str, str | Path]) -> dict[tuple[str, str], Path]:
    """``{scene: benchmark folder}`` -> ``{(scene, rule): folder/<rule>.tsv}`` for every TSV
    present (rules that have not run yet are simply absent)."""
    out = {}
    for scene, folder in folders.items():
        for p in sorted(Path(folder).glob("*.tsv")):
            out[(scene, p.stem)] = p
    return out


def collect_timings(benchmark_tsvs: Mapping[tuple[str, str], str | Path]) -> pd.DataFrame:
    """``{(scene, rule): tsv}`` -> table ``scene, rule, seconds, cpu_seconds, max_rss_mb,
    max_pss_mb, repeats`` sorted by scene then rule."""
    rows = [{"scene": s, "rule": r, **read_benchmark(p)}
            for (s, r), p in benchmark_tsvs.items()]
    cols = ["scene", "rule", "seconds", "cpu_seconds", "max_rss_mb", "max_pss_mb", "repeats"]
    return pd.DataFrame(rows, columns=cols).sort_values(["scene", "rule"], ignore_index=True)


# ------------------------------------------------------------------------------------ plots


def _save(fig, path: Path) -> None:
    import matplotlib.pyplot as plt

    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, bbox_inches="tight")
    plt.close(fig)


def plot_metric(summary: pd.DataFrame, metric: str, path: Path) -> None:
    """Grouped bars: one group per scene (ALL last), one bar per method."""
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    table = summary.pivot_table(index="scene", columns="method", values=metric, dropna=False)
    order = [s for s in table.index if s != "ALL"] + (["ALL"] if "ALL" in table.index else [])
    table = table.loc[order]
    fig, ax = plt.subplots(figsize=(max(4.0, 1.2 * len(table) * max(1, table.shape[1]) / 2), 3.2))
    n = max(1, table.shape[1])
    width = 0.8 / n
    x = np.arange(len(table))
    for i, method in enumerate(table.columns):
        vals = table[method].to_numpy(float)
        ax.bar(x + (i - (n - 1) / 2) * width, np.nan_to_num(vals), width, label=method)
    ax.set_xticks(x, table.index, rotation=30, ha="right")
    ax.set_ylim(0, 1)
    ax.set_ylabel(metric.replace("_", " "))
    ax.set_title(f"{metric.replace('_', ' ')} by scene and method")
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.0, 1.0))
    ax.grid(axis="y", alpha=0.3)
    _save(fig, path)


def plot_timings(timings: pd.DataFrame, path: Path) -> None:
    """Stacked wall-clock seconds per rule, one bar per scene."""
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    table = timings.pivot_table(index="scene", columns="rule", values="seconds", aggfunc="sum")
    fig, ax = plt.subplots(figsize=(max(4.0, 0.9 * len(table) + 2), 3.2))
    bottom = np.zeros(len(table))
    for rule in table.columns:
        vals = np.nan_to_num(table[rule].to_numpy(float))
        ax.bar(table.index, vals, bottom=bottom, label=rule)
        bottom += vals
    ax.set_ylabel("wall-clock seconds")
    ax.set_title("time per rule")
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.0, 1.0))
    ax.tick_params(axis="x", rotation=30)
    _save(fig, path)


def summarize(metrics_csvs: list, benchmark_tsvs: Mapping[tuple[str, str], str | Path],
              out_dir: str | Path) -> dict:
    """Write ``summary.csv``, ``timings.csv`` and the plots (module docstring) into
    ``out_dir``. Returns ``{"summary": DataFrame, "timings": DataFrame, "plots": [paths]}``."""
    out_dir = Path(out_dir)
    metrics, boxes = collect_metrics(metrics_csvs)
    summary = summarize_metrics(metrics, boxes)
    timings = collect_timings(benchmark_tsvs)
    write_csv(out_dir / "summary.csv", summary)
    write_csv(out_dir / "timings.csv", timings)
    plots = []
    if len(summary):
        for m in PLOT_METRICS:
            if m in summary and summary[m].notna().any():
                plot_metric(summary, m, out_dir / "plots" / f"{m}.png")
                plots.append(out_dir / "plots" / f"{m}.png")
    if len(timings):
        plot_timings(timings, out_dir / "plots" / "timings.png")
        plots.append(out_dir / "plots" / "timings.png")
    for _, r in summary[summary["scene"] == "ALL"].iterrows() if len(summary) else []:
        log.info("ALL %s: F1 %.3f IoU %.3f (pooled over %d views)", r["method"],
                 r.get("F1_pooled", float("nan")), r.get("IoU_pooled", float("nan")),
                 r["n_views"])
    return {"summary": summary, "timings": timings, "plots": plots}
