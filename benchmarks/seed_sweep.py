"""How well the poses stage's plane sweep (gdiff.sfm.seed.sweep_depths) finds depths: at every
triangulated point of a finished poses stage, the sweep's depth for the point's pixel in each
photo it projects into, against the point's own depth there.

Usage::

    python benchmarks/seed_sweep.py results/living/poses [results/kitchen/poses ...] \
        [--scene scenes/living]   # where the photos are, when poses/images/ does not hold them

Prints per poses folder: the number of projections swept, the share the sweep gave a depth,
the median |log(depth ratio)| and the shares within 5 % / 15 % and off by more than 30 %, and
the time taken. Projections include photos in which the point is hidden behind something
nearer, so the last share also counts occlusions, not only wrong matches.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from gdiff.cameras import image_root, load_cameras  # noqa: E402
from gdiff.io import read_image  # noqa: E402
from gdiff.sfm.seed import _grey, _project, depth_range, sweep_depths  # noqa: E402


def measure(poses_dir: Path, scene: Path | None = None) -> dict:
    import pycolmap

    cams = load_cameras(poses_dir / "cameras.json")
    models = sorted((poses_dir / "sparse").glob("*/points3D.bin"))
    if not models:
        raise SystemExit(f"{poses_dir}: no sparse/*/points3D.bin (run the poses stage first)")
    rec = pycolmap.Reconstruction(str(models[0].parent))
    X = np.array([p.xyz for p in rec.points3D.values()]).reshape(-1, 3)
    near, far, _ = depth_range(cams, X)
    if (poses_dir / "images").is_dir():
        root = poses_dir / "images"
    elif scene is not None:
        root = Path(image_root(scene, poses_dir / "cameras.json"))
    else:
        raise SystemExit(f"{poses_dir}: no images/ folder; give the scene folder with --scene")
    greys = [_grey(read_image(root / c.image)) for c in cams]
    t = time.perf_counter()
    errs, n = [], 0
    for i, c in enumerate(cams):
        uv, z = _project(c, X)  # the points in front of the camera
        u, v = uv[:, 0], uv[:, 1]
        m = (u > 10) & (u < c.width - 10) & (v > 10) & (v < c.height - 10)
        d = sweep_depths(cams, greys, i, u[m], v[m], near, far)
        ok = np.isfinite(d)
        n += int(m.sum())
        errs.append(np.abs(np.log(d[ok] / z[m][ok])))
    e = np.concatenate(errs) if errs else np.zeros(0)
    return dict(poses=str(poses_dir), points=len(X), projections=n,
                swept=100 * len(e) / max(n, 1), median_log=float(np.median(e)) if e.size else np.nan,
                within5=100 * float(np.mean(e < 0.05)) if e.size else np.nan,
                within15=100 * float(np.mean(e < 0.15)) if e.size else np.nan,
                off30=100 * float(np.mean(e > 0.3)) if e.size else np.nan,
                seconds=time.perf_counter() - t)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("poses", nargs="+", type=Path, help="results/<scene>/poses folders")
    ap.add_argument("--scene", type=Path, help="the scene folder (photos), when the poses "
                    "folder has no images/")
    args = ap.parse_args(argv)
    for d in args.poses:
        r = measure(d, args.scene)
        print(f"{r['poses']}: {r['points']} points, {r['projections']} projections, "
              f"{r['swept']:.0f} % given a depth; |log ratio| median {r['median_log']:.3f}, "
              f"within 5 % {r['within5']:.0f} %, within 15 % {r['within15']:.0f} %, "
              f"off > 30 % {r['off30']:.0f} %; {r['seconds']:.1f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
