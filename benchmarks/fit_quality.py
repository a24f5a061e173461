"""Quality and wall time of the fit stage on scenes with ground truth.

For each scene (a gdiff scene folder with ``gt_cameras.json``, e.g. ../shared/scenes/*, or
``synth:<preset>`` to generate one): known poses are imported as they are (not refined) and
points triangulated by the poses stage (``gdiff.sfm.run_poses``, source known), the 4D model is
fitted with ``FitOptions`` (defaults, or ``--set key=value`` overrides), then

* training views: PSNR / SSIM from ``fit/quality.csv`` (each image at its own time);
* wall and CPU time of the fit and the machine's load average at its start and end (on a
  shared machine the CPU time is the steadier measure of cost);
* eval views (novel, never trained on): render t=0 and t=1 at full size and compare with
  ``eval/before`` and ``eval/after``; also PSNR outside the ground-truth change mask (the
  unchanged background must look like the real image of that time, lighting included) and
  the mean |render(t1) - render(t0)| inside vs outside the mask; and PSNR split by whether a
  pixel's surface point (from the rendered depth) lies in the view of some training camera of
  that time (``psnr_covered``) or of none (``psnr_uncovered``, ``uncovered`` = its share):
  before and after captures taken from other places leave parts seen at one time only.

Usage::

    nice python benchmarks/fit_quality.py synth:demo ../shared/scenes/bench_desk \
        --out /tmp/fitbench [--set fine_iters=3000 ...] [--threads 2]

Writes ``<out>/<scene>/fit/...``, ``<out>/<scene>/eval_views.csv`` and ``<out>/summary.csv``.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import resource
import shutil
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # gdiff from this checkout

from gdiff.cameras import load_cameras
from gdiff.io import read_image, read_mask
from gdiff.splat.losses import psnr, ssim
from gdiff.splat.model import load_model
from gdiff.splat.render import render
from gdiff.splat.train import FitOptions, fit_scene


def prepare(spec: str, out: Path) -> tuple[str, Path]:
    """Scene folder with a cameras.json (copied from gt_cameras.json) -> (name, folder)."""
    if spec.startswith("synth:"):
        from gdiff.synth import make_scene

        preset = spec.split(":", 1)[1]
        src = out / f"synth_{preset}" / "source"
        if not src.is_dir():
            make_scene(src, preset, 0)
        name = f"synth_{preset}"
    else:
        src = Path(spec)
        name = src.name
    work = out / name / "scene"
    if not work.is_dir():
        work.mkdir(parents=True)
        for sub in ("before", "after", "eval"):
            (work / sub).symlink_to((src / sub).resolve())
        shutil.copy(src / "gt_cameras.json", work / "cameras.json")
    return name, work


def poses(work: Path, out: Path) -> Path:
    from gdiff.sfm import PosesOptions, run_poses

    pdir = out / "poses"
    if not (pdir / "cameras.json").is_file():
        # the true poses as they are: this measures the fit, not pose refinement
        run_poses(work, pdir, PosesOptions(source="known", refine_known=False))
    return pdir


def covered(cam, depth: np.ndarray, train: list) -> np.ndarray:
    """[H, W] bool: the pixel's surface point (camera-frame z ``depth`` [H, W]) projects inside
    at least one camera of ``train`` (in front of it; occlusion not tested)."""
    j, i = np.mgrid[:cam.height, :cam.width]
    x = (i + 0.5 - cam.cx) / cam.fx * depth
    y = (j + 0.5 - cam.cy) / cam.fy * depth
    p = np.stack([x, y, depth, np.ones_like(depth)], -1).reshape(-1, 4) @ cam.c2w.T
    hit = np.zeros(len(p), bool)
    for c in train:
        q = p @ c.w2c.T
        z = np.where(q[:, 2] > 1e-6, q[:, 2], np.nan)
        u, v = c.fx * q[:, 0] / z + c.cx, c.fy * q[:, 1] / z + c.cy
        hit |= (u >= 0) & (u < c.width) & (v >= 0) & (v < c.height)
    return hit.reshape(depth.shape)


@torch.no_grad()
def eval_views(model, cams_json: Path, scene: Path) -> pd.DataFrame:
    cams = load_cameras(cams_json)
    train = {0: [c for c in cams if c.set == "before"], 1: [c for c in cams if c.set == "after"]}
    rows = []
    ev = {c.image.split("/")[-1]: c for c in cams if c.set == "eval_before"}
    for name, cam in sorted(ev.items()):
        mask_path = scene / "eval" / "masks" / name
        mask = read_mask(mask_path) if mask_path.is_file() else None
        r = {}
        for t, st in ((0, "before"), (1, "after")):
            gt = torch.from_numpy(read_image(scene / "eval" / st / name))
            out = render(model, [cam], float(t), render_mode="RGB+ED")
            pred = out["rgb"][0].clamp(0, 1)
            r[t] = pred
            row = {"view": name, "time": t, "psnr": float(psnr(pred, gt)),
                   "ssim": float(ssim(pred, gt))}
            cov = torch.from_numpy(covered(cam, out["depth"][0, ..., 0].numpy(), train[t]))
            row["uncovered"] = float((~cov).float().mean())
            for key, sel in (("psnr_covered", cov), ("psnr_uncovered", ~cov)):
                row[key] = float(psnr(pred[sel], gt[sel])) if sel.any() else float("nan")
            if mask is not None and (~mask).any():
                keep = torch.from_numpy(~mask)
                row["psnr_unchanged"] = float(psnr(pred[keep], gt[keep]))
            rows.append(row)
        if mask is not None and mask.any():
            diff = (r[1] - r[0]).abs().mean(-1).numpy()
            rows[-1]["diff_in"] = float(diff[mask].mean())
            rows[-1]["diff_out"] = float(diff[~mask].mean())
    return pd.DataFrame(rows)


def fitted_summary(fit_dir: Path) -> dict:
    """The summary fields of :func:`fit_scene` for an existing fit (``--eval-only``)."""
    model = load_model(fit_dir / "model.pt", "cpu")
    q = pd.read_csv(fit_dir / "quality.csv")
    w, h = model.meta["working_size"]
    s = {"iterations": model.meta["iterations"], "n_gaussians": len(model), "width": w,
         "height": h}
    for t in (0, 1):
        s[f"psnr_t{t}"] = float(q[q["time"] == t]["psnr"].mean())
        s[f"ssim_t{t}"] = float(q[q["time"] == t]["ssim"].mean())
    return s


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("scenes", nargs="+")
    p.add_argument("--out", required=True)
    p.add_argument("--set", action="append", default=[], help="FitOptions override key=value")
    p.add_argument("--threads", type=int, default=0)
    p.add_argument("--eval-only", action="store_true",
                   help="score the existing <out>/<scene>/fit/model.pt instead of fitting")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    if args.threads:
        torch.set_num_threads(args.threads)
    over = {}
    for kv in args.set:
        k, v = kv.split("=", 1)
        over[k] = json.loads(v)
    opts = FitOptions(**over)
    out = Path(args.out)
    summary = []
    for spec in args.scenes:
        name, work = prepare(spec, out)
        sdir = out / name
        pdir = poses(work, sdir)
        t0, c0, load0 = time.time(), resource.getrusage(resource.RUSAGE_SELF), os.getloadavg()[0]
        if args.eval_only:
            s = fitted_summary(sdir / "fit")
        else:
            s = fit_scene(work, pdir / "cameras.json", pdir / "points.ply", sdir / "fit", opts,
                          "cpu")
        wall = time.time() - t0
        c1 = resource.getrusage(resource.RUSAGE_SELF)
        cpu = (c1.ru_utime + c1.ru_stime) - (c0.ru_utime + c0.ru_stime)
        if args.eval_only:
            wall = cpu = float("nan")
        model = load_model(sdir / "fit" / "model.pt", "cpu")
        ev = eval_views(model, pdir / "cameras.json", work)
        ev.to_csv(sdir / "eval_views.csv", index=False)
        row = {"scene": name, "fit_seconds": round(wall, 1), "fit_cpu_seconds": round(cpu, 1),
               "load_start": round(load0, 1), "load_end": round(os.getloadavg()[0], 1),
               "threads": torch.get_num_threads(),
               **{k: s[k] for k in ("iterations", "n_gaussians", "width", "height",
                                    "psnr_t0", "ssim_t0", "psnr_t1", "ssim_t1")}}
        for t in (0, 1):
            e = ev[ev["time"] == t]
            row[f"eval_psnr_t{t}"] = float(e["psnr"].mean())
            row[f"eval_ssim_t{t}"] = float(e["ssim"].mean())
            if "psnr_unchanged" in e:
                row[f"eval_psnr_unchanged_t{t}"] = float(e["psnr_unchanged"].mean())
            row[f"eval_uncovered_t{t}"] = float(e["uncovered"].mean())
            row[f"eval_psnr_uncovered_t{t}"] = float(e["psnr_uncovered"].mean())
        if "diff_in" in ev:
            row["diff_in"] = float(ev["diff_in"].mean())
            row["diff_out"] = float(ev["diff_out"].mean())
        summary.append(row)
        print(json.dumps(row), flush=True)
    pd.DataFrame(summary).to_csv(out / "summary.csv", index=False)
    return 0


if __name__ == "__main__":
    sys.exit(main())
