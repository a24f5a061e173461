"""The bench: run the workflow on a set of scenes and print one table of quality and cost.

Usage::

    nice -n 15 python benchmarks/bench.py ../shared/scenes --synth demo,lightchange \
        --seeds 0,1,2 --results results_bench [--cores 2] [--jobs 1] [--configfile extra.yaml] \
        [--fit-seeds 0,1,2]
    python benchmarks/bench.py --no-run --results results --out /tmp/bench_base

Scenes: every scene folder of ``DIR`` (or the rows of a scenes sheet, overrides kept) plus the
synthetic presets ``--synth`` at each of ``--seeds`` (scenes ``<preset>_s<seed>``, made by the
workflow itself from ``synth:<preset>:<seed>``). They are written into one sheet,
``<results>/scenes.tsv``, and the workflow runs once over it with the default configuration
(plus ``--configfile``) in its own working directory ``<results>``
(``snakemake --directory``): outputs in ``<results>/results/``, logs in ``<results>/logs/``,
synthetic scenes in ``<results>/resources/synth/``. A rerun continues where the last stopped.
``--fit-seeds`` runs every scene once per fit seed (``<scene>_f<seed>``, config ``fit.seed``):
two fits of the same photos differ by more than many changes to the code do, so judge a change
on the per-scene means this adds (and the spread of their rows), not on one fit.
``--jobs`` caps how many jobs run at once (default 1, so rules do not share the cores and their
times are comparable) within ``--cores``.

Times are only comparable on an otherwise quiet machine. ``nice`` on other work is not enough
where the kernel groups processes by session (``/proc/sys/kernel/sched_autogroup_enabled`` = 1,
the default on many Linux systems): a niced job started from another terminal then still gets
an equal share of the cores, and a 2-core fit runs up to twice as slow.

``--no-run`` only reads: ``--results`` is then either such a working directory or a
``results/`` folder itself (e.g. results).

Prints the table of :mod:`gdiff.bench` (scene x method pooled P / R / F1 / IoU / object recall,
box recall and the far-from-box fraction where a scene has boxes, means over the seeds of each
preset, then per scene the wall / CPU seconds and peak MB per rule and in total, the size on
disk and the fit's PSNR) and writes it as ``bench.csv`` and ``bench.md`` into ``--out`` (default:
the results folder), with ``bench_run.json`` (command, wall and CPU time of the whole run) after
a run. For scenes whose folder lists its objects (``meta.json`` with boxes, and
``gt_cameras.json``: the shared test scenes, ``gdiff synth``) it also prints what the compare
stage made of each changed object (kept, dropped under its thresholds, or not judged) and the
false changes it kept (:func:`gdiff.bench.compare_objects`), and writes them as
``compare_objects.csv``. It prints figures and never judges them.
"""

from __future__ import annotations

import argparse
import json
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import pandas as pd  # noqa: E402

from gdiff.bench import (format_compare_objects, format_table, read_compare_objects,  # noqa: E402
                         read_results, with_fit_seeds)
from gdiff.io import atomic_path, write_csv, write_json  # noqa: E402
from gdiff.scene import discover_scenes, synth_folder_name  # noqa: E402


def _csv_list(text: str) -> list[str]:
    return [x.strip() for x in text.split(",") if x.strip()]


def _int_list(text: str, option: str) -> list[int]:
    """Comma-separated integers of ``option``; a clear exit on anything else."""
    try:
        return [int(x) for x in _csv_list(text)]
    except ValueError:
        sys.exit(f"bench: {option} takes comma-separated integers (e.g. 0,1,2), got {text!r}")


def write_sheet(path: Path, source: str | None, presets: list[str], seeds: list[int],
                fit_seeds: list[int] | None = None) -> list[str]:
    """One scenes sheet for the whole bench (scene folder paths made absolute); returns the
    scene names in order. With ``fit_seeds`` every scene is run once per fit seed, as
    ``<scene>_f<seed>`` with config ``fit.seed`` set."""
    rows: list[dict] = []
    if source:
        for name, s in discover_scenes(source).items():
            row = {"name": name}
            if s.synth_preset is not None:
                seed = "" if s.synth_seed is None else f":{s.synth_seed}"
                row["path"] = f"synth:{s.synth_preset}{seed}"
            else:
                row["path"] = str(s.path.resolve())
            for section, kv in s.overrides.items():
                for k, v in kv.items():
                    row[f"{section}.{k}"] = v
            rows.append(row)
    for preset in presets:
        for seed in seeds:
            rows.append({"name": synth_folder_name(preset, seed), "path": f"synth:{preset}:{seed}"})
    rows = with_fit_seeds(rows, fit_seeds or [])
    names = [r["name"] for r in rows]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        sys.exit(f"bench: scene name(s) {', '.join(dup)} appear twice (a scene folder named like "
                 "a synthetic scene?); rename the folder or drop the preset")
    if not rows:
        sys.exit("bench: no scenes; give a folder of scenes or a sheet, and/or --synth")
    df = pd.DataFrame(rows, dtype=object).fillna("")  # ints stay ints where a column has gaps
    with atomic_path(path) as tmp:
        df.to_csv(tmp, sep="\t", index=False)
    return names


def run_workflow(work: Path, sheet: Path, cores: int, jobs: int, configfile: str | None) -> dict:
    """Run Snakemake once over the sheet in ``work``; wall and CPU seconds of the whole run."""
    snakemake = shutil.which("snakemake") or str(Path(sys.executable).parent / "snakemake")
    cmd = [snakemake, "-s", str(ROOT / "Snakefile"), "--directory", str(work),
           "--cores", str(cores), "--rerun-incomplete", "--nolock", "--keep-going",
           "--resources", f"bench_jobs={jobs}", "--default-resources", "bench_jobs=1"]
    if configfile:
        cmd += ["--configfile", str(Path(configfile).resolve())]
    cmd += ["--config", f"scenes={sheet}"]
    print("bench:", " ".join(cmd), flush=True)
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0, started = time.monotonic(), time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
    rc = subprocess.call(cmd, cwd=work)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return {"command": cmd, "started": started, "wall_s": round(time.monotonic() - t0, 1),
            "cpu_s": round(cpu, 1), "returncode": rc}


def results_folder(path: Path) -> Path:
    """A bench working directory (has results/) or a results folder itself."""
    return path / "results" if (path / "results").is_dir() else path


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scenes", nargs="?", help="folder of scene folders (or one scene folder), or "
                    "a scenes sheet; optional with --synth or --no-run")
    ap.add_argument("--synth", default="", help="synthetic presets, comma-separated "
                    "(e.g. demo,lightchange)")
    ap.add_argument("--seeds", default="0", help="seeds of the synthetic presets (e.g. 0,1,2)")
    ap.add_argument("--results", default="results_bench", help="the bench's working directory "
                    "(outputs in <results>/results/); with --no-run also a results folder")
    ap.add_argument("--fit-seeds", default="", help="run every scene once per fit seed "
                    "(config fit.seed; runs <scene>_f<seed>, with mean rows per scene), e.g. "
                    "0,1,2: one fit differs from another of the same photos, so compare means")
    ap.add_argument("--cores", type=int, default=2)
    ap.add_argument("--jobs", type=int, default=1, help="jobs at once (default 1)")
    ap.add_argument("--configfile", help="extra configuration over the defaults")
    ap.add_argument("--no-run", action="store_true", help="only read the results and print")
    ap.add_argument("--out", help="where to write bench.csv / bench.md (default: the results "
                    "folder)")
    args = ap.parse_args(argv)
    presets, seeds = _csv_list(args.synth), _int_list(args.seeds, "--seeds")
    fit_seeds = _int_list(args.fit_seeds, "--fit-seeds")
    work = Path(args.results).resolve()
    run = None
    if args.no_run:
        results = results_folder(work)
        if not results.is_dir():
            sys.exit(f"bench: {results} does not exist; nothing to read")
        names = None
        if args.scenes or presets:
            names = [n for n in (discover_scenes(args.scenes) if args.scenes else {})]
            names += [synth_folder_name(p, s) for p in presets for s in seeds]
            names = [r["name"] for r in with_fit_seeds([{"name": n} for n in names], fit_seeds)]
        run_json = results.parent / "bench_run.json"
        if run_json.is_file():
            run = json.loads(run_json.read_text())
    else:
        work.mkdir(parents=True, exist_ok=True)
        sheet = work / "scenes.tsv"
        names = write_sheet(sheet, args.scenes, presets, seeds, fit_seeds)
        run = run_workflow(work, sheet, args.cores, args.jobs, args.configfile)
        run["scenes"] = names
        write_json(work / "bench_run.json", run)
        results = work / "results"
    table = read_results(results, names, presets, fit_seeds)
    out = Path(args.out) if args.out else results
    write_csv(out / "bench.csv", table)
    text = format_table(table)
    footer = ""
    if run is not None:
        footer = (f"whole run: {run['wall_s']:.0f} s wall, {run['cpu_s']:.0f} s CPU "
                  f"(started {run['started']}, exit code {run['returncode']})\n")
    with atomic_path(out / "bench.md") as tmp:
        Path(tmp).write_text(f"# bench: {results}\n\n" + format_table(table, markdown=True)
                             + ("\n" + footer if footer else ""))
    print(text + footer, end="")
    print(f"bench: table written to {out / 'bench.csv'} and {out / 'bench.md'}")
    objects = read_compare_objects(results, names)
    if len(objects):
        write_csv(out / "compare_objects.csv", objects)
        print("compare stage, per object of the scenes' ground truth (meta.json):\n"
              + format_compare_objects(objects), end="")
        print(f"bench: objects written to {out / 'compare_objects.csv'}")
    return 0 if run is None else int(run["returncode"] != 0)


if __name__ == "__main__":
    sys.exit(main())
