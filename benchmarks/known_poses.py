"""The poses stage on real captures with known poses (robot tf + CameraInfo, or any scene
folder with a cameras.json / transforms.json): how many points are triangulated with the
given poses and how many seeded in the camera frusta, the reprojection error, whether the
photos were undistorted, and (``--colmap``) whether COLMAP alone registers the photos (and
how far its poses are from the given ones after a Sim3 alignment).

Usage::

    nice python benchmarks/known_poses.py ../shared/real/obchange_livingarea \
        ../shared/real/obchange_kitchen --out /tmp/known_bench [--colmap] \
        [--set max_reproj_error=4 ...]

A source folder in the ``tf-yaml`` layout is imported first (``gdiff import tf-yaml``); a
gdiff scene folder is used as it is. Prints one row per scene and writes
``<out>/summary.csv``.
"""

from __future__ import annotations

import argparse
import logging
import shutil
import sys
import time
from pathlib import Path

import pandas as pd
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from gdiff.align import pose_errors  # noqa: E402
from gdiff.cameras import load_cameras  # noqa: E402
from gdiff.errors import GdiffError  # noqa: E402
from gdiff.importers import detect_format, import_scene  # noqa: E402
from gdiff.options import from_config  # noqa: E402
from gdiff.sfm import PosesOptions, load_known_cameras, run_poses  # noqa: E402


def _value(v: str):
    return yaml.safe_load(v)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("sources", nargs="+", type=Path)
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--colmap", action="store_true", help="also try COLMAP registration")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="PosesOptions override (repeatable)")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    over = {k: _value(v) for k, v in (s.split("=", 1) for s in args.set)}
    rows = []
    for src in args.sources:
        name = src.name
        scene = src
        if detect_format(src) == "tf-yaml":
            scene = args.out / name / "scene"
            shutil.rmtree(scene, ignore_errors=True)
            import_scene("tf-yaml", src, scene)
        row = {"scene": name}
        opts = from_config(PosesOptions, {"source": "known", **over}, "poses")
        t0 = time.process_time()
        s = run_poses(scene, args.out / name / "poses", opts)
        row.update(images=sum(s["images"].values()), registered=sum(s["registered"].values()),
                   triangulated=s["num_points_triangulated"], seeded=s["num_points_seeded"],
                   reproj_px=round(s["mean_reprojection_error"], 3),
                   undistorted=s["undistorted"], cpu_s=round(time.process_time() - t0, 1))
        if args.colmap:
            copts = from_config(PosesOptions, {**over, "source": "colmap"}, "poses")
            try:
                c = run_poses(scene, args.out / name / "colmap", copts)
                row["colmap_registered"] = sum(c["registered"].values())
                known = load_known_cameras(scene)[0]
                err = pose_errors(load_cameras(args.out / name / "colmap" / "cameras.json"),
                                  known)
                row["colmap_vs_given_rot_deg"] = round(float(err.rot_err_deg.median()), 2)
            except GdiffError as e:
                row["colmap_registered"] = f"failed: {str(e)[:80]}"
        rows.append(row)
        print(row, flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    df = pd.DataFrame(rows)
    df.to_csv(args.out / "summary.csv", index=False)
    print(df.to_string(index=False))
    return 0


if __name__ == "__main__":
    sys.exit(main())
