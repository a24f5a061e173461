"""Cost against the number of photos: one synthetic scene at several photo counts, the workflow
on each, and per rule the wall seconds side by side with their growth per step.

Usage::

    nice -n 15 python benchmarks/scaling.py --photos 15,30,60 --results results_scaling \
        [--preset demo] [--seed 0] [--eval 10] [--width 320 --height 240] \
        [--configfile extra.yaml]
    python benchmarks/scaling.py --photos 15,30,60 --results results_scaling --no-run

Makes ``<results>/scenes/<preset>_p<N>`` with ``gdiff synth`` (same preset and seed, N before and
N after photos, the same eval views; kept when they exist), runs ``benchmarks/bench.py`` on that
folder (working directory ``<results>/bench``, default configuration plus ``--configfile``, one
job at a time) and prints :func:`gdiff.bench.scaling_table`: per rule and in total the wall
seconds at each photo count and the growth factor of each step next to the photos' (a rule
whose factor stays at or below the photos' grows at most linearly), then the partition's F1 and
the fit's eval-view PSNR of each scene. Written to ``<results>/scaling.md`` and ``scaling.csv``;
the full bench table (CPU, memory, disk per rule) is in ``<results>/bench/results/bench.md``.
Times are only comparable on an otherwise quiet machine (see ``benchmarks/bench.py``).
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from gdiff.bench import format_scaling, read_results, scaling_table  # noqa: E402
from gdiff.errors import GdiffError  # noqa: E402
from gdiff.io import atomic_path, write_csv  # noqa: E402
from gdiff.log import setup_logging  # noqa: E402
from gdiff.synth import SynthOptions, make_scene  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--photos", default="15,30,60", help="photos per set (before = after), "
                    "comma-separated")
    ap.add_argument("--results", default="results_scaling", help="working directory")
    ap.add_argument("--preset", default="demo", help="gdiff synth preset")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--eval", type=int, default=10, help="eval views of every scene")
    ap.add_argument("--width", type=int, default=320)
    ap.add_argument("--height", type=int, default=240)
    ap.add_argument("--configfile", help="extra configuration over the defaults")
    ap.add_argument("--no-run", action="store_true", help="only read the results and print")
    args = ap.parse_args(argv)
    setup_logging()
    try:
        counts = sorted({int(x) for x in args.photos.split(",") if x.strip()})
    except ValueError:
        counts = []
    if not counts or min(counts) < 2:
        sys.exit(f"scaling: --photos {args.photos!r}: give whole numbers of at least 2 photos "
                 "per set, comma-separated (e.g. 15,30,60)")
    work = Path(args.results).resolve()
    scenes = work / "scenes"
    photos = {f"{args.preset}_p{n}": n for n in counts}
    if not args.no_run:
        for name, n in photos.items():
            if not (scenes / name / "meta.json").is_file():
                try:
                    preset = SynthOptions(preset=args.preset, n_before=n, n_after=n,
                                          n_eval=args.eval, width=args.width,
                                          height=args.height).to_preset()
                    make_scene(scenes / name, preset, args.seed, overwrite=True)
                except GdiffError as e:
                    sys.exit(f"scaling: scene {scenes / name}: {e}")
        cmd = [sys.executable, str(ROOT / "benchmarks" / "bench.py"), str(scenes),
               "--results", str(work / "bench")]
        if args.configfile:
            cmd += ["--configfile", str(Path(args.configfile).resolve())]
        rc = subprocess.call(cmd)
        if rc != 0:
            print(f"scaling: the bench exited with {rc}; the table covers what finished",
                  file=sys.stderr)
    results = work / "bench" / "results"
    if not results.is_dir():
        sys.exit(f"scaling: {results} does not exist; run without --no-run first")
    table = scaling_table(read_results(results, list(photos)), photos)
    write_csv(work / "scaling.csv", table)
    text = format_scaling(table)
    with atomic_path(work / "scaling.md") as tmp:
        Path(tmp).write_text(f"# scaling: {results}\n\n{text}")
    print(text, end="")
    print(f"scaling: table written to {work / 'scaling.md'} and {work / 'scaling.csv'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
