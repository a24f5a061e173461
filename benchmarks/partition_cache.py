"""Partition stage: size and CPU time of the frozen phase's cached blend weights.

For a results folder (``fit/model.pt``, ``poses/cameras.json``) the script computes the blend
weights of every ``--step``-th training view (before at t=0, after at t=1) three ways:

* ``exact``: full training size, all pairs, float32 weights, sized as the former layout
  (pixel + Gaussian index + weight: 12 bytes a pair);
* ``scaled``: at ``--scale`` of the training size, float32, all pairs (8 bytes a pair + 4 a
  pixel);
* ``stage``: what the partition stage caches (``partition.frozen_scale``, float16 weights, a
  pixel's faintest pairs dropped up to ``CACHE_TOLERANCE``).

It prints per view the pairs per pixel, MB and CPU seconds, and the totals extrapolated to all
training views (the cache holds every key view at once), plus the largest difference of a
blended random change logit (|z| ~ 3) between the stage's cache and the exact weights.

    python benchmarks/partition_cache.py results/bench_desk --step 10
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from gdiff.cameras import load_cameras  # noqa: E402
from gdiff.partition import blend_weights, render_blended  # noqa: E402
from gdiff.partition.train import CACHE_TOLERANCE  # noqa: E402
from gdiff.splat.model import load_model  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("results", type=Path, help="results/<scene> with fit/ and poses/")
    ap.add_argument("--step", type=int, default=10, help="every step-th training view")
    ap.add_argument("--scale", type=float, default=1.0,
                    help="cache scale (default: the training size, which the stage keeps while "
                         "its cache fits in partition.cache_max_mb)")
    ap.add_argument("--max-side", type=int, default=None,
                    help="training size (default: the fit's working size)")
    args = ap.parse_args(argv)
    torch.manual_seed(0)
    model = load_model(args.results / "fit" / "model.pt", "cpu")
    max_side = args.max_side or (model.meta.get("options") or {}).get("max_side", 320)
    cams = [c for c in load_cameras(args.results / "poses" / "cameras.json")
            if c.set in ("before", "after")]
    cams = [c.scaled(max_side / max(c.width, c.height))
            if max_side and max(c.width, c.height) > max_side else c for c in cams]
    with torch.no_grad():
        gs = {t: model.at_time(t) for t in (0.0, 1.0)}
    z = 3.0 * torch.randn(len(model))
    print(f"{len(model)} Gaussians, {len(cams)} training views at {cams[0].width}x"
          f"{cams[0].height}; stage cache at scale {args.scale}, tolerance {CACHE_TOLERANCE}")
    tot = {"exact": [0.0, 0.0], "scaled": [0.0, 0.0], "stage": [0.0, 0.0]}
    picked = cams[:: args.step]
    for c in picked:
        g = gs[float(c.time)]
        small = c.scaled(args.scale) if args.scale != 1.0 else c
        row = []
        for name, cam, kw in (("exact", c, {}), ("scaled", small, {}),
                              ("stage", small, {"tolerance": CACHE_TOLERANCE,
                                                "dtype": torch.float16})):
            t0 = time.process_time()
            bw = blend_weights(g, cam, **kw)
            dt = time.process_time() - t0
            mb = (12 * len(bw.gid) if name == "exact" else bw.nbytes) / 2**20
            tot[name][0] += mb
            tot[name][1] += dt
            row.append(f"{name} {len(bw.gid) / (cam.width * cam.height):.1f}/px {mb:.1f} MB "
                       f"{dt:.2f} s")
            if name == "exact":
                exact = render_blended(bw, z)
            elif name == "stage" and args.scale == 1.0:
                row.append(f"max |dz| {float((render_blended(bw, z) - exact).abs().max()):.4f}")
        print(f"{c.image}: " + "; ".join(row), flush=True)
    k = len(cams) / len(picked)
    print("all views (extrapolated): " + "; ".join(
        f"{n} {v[0] * k:.0f} MB {v[1] * k:.0f} s CPU" for n, v in tot.items()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
