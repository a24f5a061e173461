"""Partition-stage quality: change maps rendered at a scene's eval views vs ground-truth masks.

For each scene the script runs the stages the partition needs, with small budgets, in a work
folder, then trains the partition and scores its change maps at the eval viewpoints (which are
in neither training set) against ``eval/masks``:

1. poses: the scene's ``gt_cameras.json`` as known poses (as they are, not refined), sparse
   points triangulated by the poses stage (``gdiff.sfm.run_poses``, source ``known``);
2. fit: ``gdiff.splat.train.fit_scene`` with the budget given on the command line;
3. key-pose targets (``change/keyframes.csv``), either
   * ``oracle`` (synthetic scenes only): the exact changed-object masks at every training pose
     from ``gdiff.synth`` - isolates the partition stage from segmentation errors; or
   * ``pair``: the fitted model rendered at every training pose at t=0 and t=1 (colour +
     depth) and compared by ``gdiff.compare.detect_changes_pair`` (segment, carry IDs, compare)
     - the compare stage without the interpolated sequences;
4. partition: ``gdiff.partition.train_partition``;
5. scoring: ``render_change_map(pm, eval camera, t=None)`` (union of t=0 and t=1) vs the GT
   mask: pooled and per-view mean P/R/F1/IoU (``gdiff.metrics``), plus a threshold
   sweep of the probability map (the 0.5 default vs the best threshold, to check the claim
   that no per-scene threshold is needed).

``--geometry-lr-scale``, ``--frozen-iterations`` and ``--plain-bce`` select the partition's
training mode (frozen / two-phase / joint geometry, unweighted BCE) to compare with the
defaults. Measured with exact masks (fit 500+1000 iterations at 192 px, partition 600 steps,
1 thread on 2 shared cores), union map at the eval views, pooled F1 / IoU at 0.5:

==========================================  ===============  ===============
partition                                   synth demo       synth lightchange
==========================================  ===============  ===============
before (joint, own-time masks as targets)   0.760 / 0.613    0.990 / 0.980
frozen throughout, other-time ignored       0.948 / 0.901    0.972 / 0.945
joint throughout, other-time ignored        0.982 / 0.964    0.990 / 0.980
two-phase 400 + 200 (default)               0.978 / 0.958    0.987 / 0.975
==========================================  ===============  ===============

Usage::

    python benchmarks/partition_quality.py --scene synth:demo --targets oracle --work /tmp/pq
    python benchmarks/partition_quality.py --scene ../shared/scenes/bench_desk \
        --targets pair --work /tmp/pq

Writes ``<work>/<name>/quality_<targets><tag>.json`` and prints it. Timings are wall-clock seconds.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from gdiff.cameras import load_cameras  # noqa: E402
from gdiff.io import read_mask, write_csv, write_json, write_mask  # noqa: E402
from gdiff.metrics import confusion, pixel_scores, scores_from_counts  # noqa: E402


def prepare_scene(spec: str, work: Path) -> tuple[str, Path, str | None]:
    """A scene folder with the GT poses as ``cameras.json`` (known poses); returns
    (name, folder, synth preset or None)."""
    if spec.startswith("synth:"):
        from gdiff.synth import make_scene

        preset = spec.split(":", 1)[1]
        name = f"synth_{preset}"
        scene = work / name / "scene"
        if not scene.is_dir():
            make_scene(scene, preset, 0)
    else:
        src = Path(spec)
        preset, name = None, src.name
        scene = work / name / "scene"
        scene.mkdir(parents=True, exist_ok=True)
        for sub in ("before", "after", "eval"):
            if not (scene / sub).exists():
                (scene / sub).symlink_to(src / sub)
    if not (scene / "cameras.json").is_file():
        shutil.copy(scene / "gt_cameras.json" if (scene / "gt_cameras.json").is_file()
                    else Path(spec) / "gt_cameras.json", scene / "cameras.json")
    return name, scene, preset


def oracle_targets(preset: str, cams, res: Path) -> None:
    """Exact changed-object masks at the training poses (synthetic scenes)."""
    from gdiff.synth import build_scene

    sc = build_scene(preset, 0)
    _write_targets(cams, res, lambda cam: (sc.render(cam, "before", supersample=1)["changed"],
                                           sc.render(cam, "after", supersample=1)["changed"]))


def pair_targets(model_path: Path, cams, res: Path) -> None:
    """Render the fit at each training pose at t=0/1 and compare the pair (ID compare)."""
    from gdiff.compare import detect_changes_pair
    from gdiff.splat.model import load_model
    from gdiff.splat.render import render

    model = load_model(model_path, "cpu")

    def masks(cam):
        with torch.no_grad():
            r = [render(model, [cam], t, render_mode="RGB+ED") for t in (0.0, 1.0)]
        rgb = [np.clip(x["rgb"][0].numpy(), 0, 1).astype(np.float32) for x in r]
        dep = [x["depth"][0, ..., 0].numpy().astype(np.float32) for x in r]
        return detect_changes_pair(rgb[0], rgb[1], dep[0], dep[1], K=cam.K)

    _write_targets(cams, res, masks)


def _write_targets(cams, res: Path, fn) -> None:
    rows = []
    for path, st in (("p1", "before"), ("p2", "after")):
        for i, cam in enumerate(c for c in cams if c.set == st):
            m0, m1 = fn(cam)
            m = {"t0": m0, "t1": m1, "union": np.asarray(m0) | np.asarray(m1)}
            rel = {k: f"change/{path}/{k}/{i:05d}.png" for k in m}
            for k in m:
                write_mask(res / rel[k], m[k])
            rows.append({"path": path, "frame": i, "image": cam.image, "set": st,
                         "time": cam.time, **{f"mask_{k}": rel[k] for k in m}})
    write_csv(res / "change" / "keyframes.csv", pd.DataFrame(rows))


def score_eval_views(pm, scene: Path, cams) -> dict:
    """Pooled and mean pixel scores of the union change map at every eval view."""
    from gdiff.partition import render_change_map

    by_stem = {}
    for c in cams:
        if c.set in ("eval_before", "eval_after"):
            by_stem.setdefault(Path(c.image).stem, c)
    counts, per_view, probs, gts = np.zeros(3), [], [], []
    for mpath in sorted((scene / "eval" / "masks").glob("*.png")):
        gt = read_mask(mpath)
        cam = by_stem[mpath.stem]
        if (cam.width, cam.height) != (gt.shape[1], gt.shape[0]):
            cam = cam.scaled(gt.shape[1] / cam.width)
        r = render_change_map(pm, cam, None)
        counts += confusion(r["mask"], gt)
        per_view.append(pixel_scores(r["mask"], gt))
        probs.append(r["prob"].ravel())
        gts.append(gt.ravel())
    pooled = scores_from_counts(*counts)
    p, g = np.concatenate(probs), np.concatenate(gts)
    sweep = {}
    for th in np.round(np.arange(0.1, 0.95, 0.1), 2):
        sweep[float(th)] = scores_from_counts(*confusion(p > th, g))["F1"]
    return {"pooled": {k: pooled[k] for k in ("P", "R", "F1", "IoU")},
            "mean": {k: float(np.nanmean([v[k] for v in per_view])) for k in ("P", "R", "F1",
                                                                              "IoU")},
            "views": len(per_view), "f1_by_threshold": sweep}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scene", required=True, help="synth:<preset> or a scene folder")
    ap.add_argument("--work", required=True, type=Path)
    ap.add_argument("--targets", choices=("oracle", "pair"), default="pair")
    ap.add_argument("--fit-coarse", type=int, default=500)
    ap.add_argument("--fit-fine", type=int, default=1000)
    ap.add_argument("--max-side", type=int, default=192)
    ap.add_argument("--max-gaussians", type=int, default=30000)
    ap.add_argument("--iterations", type=int, default=600)
    ap.add_argument("--lambda-3d", type=float, default=None)
    ap.add_argument("--geometry-lr-scale", type=float, default=None,
                    help="partition geometry_lr_scale (0 = geometry frozen throughout)")
    ap.add_argument("--frozen-iterations", type=int, default=None,
                    help="partition frozen_iterations (0 = joint fine-tuning from the start)")
    ap.add_argument("--plain-bce", action="store_true",
                    help="partition balance_classes=False (the unweighted mean BCE)")
    ap.add_argument("--tag", default="", help="suffix of the quality_<targets><tag>.json file")
    ap.add_argument("--device", default="cpu")
    args = ap.parse_args(argv)

    from gdiff.partition import PartitionOptions, load_partition_model, train_partition
    from gdiff.sfm import PosesOptions, run_poses
    from gdiff.splat.train import FitOptions, fit_scene

    name, scene, preset = prepare_scene(args.scene, args.work)
    res = args.work / name / "results"
    timing = {}
    t = time.perf_counter()
    if not (res / "poses" / "cameras.json").is_file():
        run_poses(scene, res / "poses", PosesOptions(source="known", refine_known=False))
    timing["poses"] = time.perf_counter() - t
    cams = load_cameras(res / "poses" / "cameras.json")
    t = time.perf_counter()
    if not (res / "fit" / "model.pt").is_file():
        fit = fit_scene(scene, res / "poses" / "cameras.json", res / "poses" / "points.ply",
                        res / "fit", FitOptions(coarse_iters=args.fit_coarse,
                                                fine_iters=args.fit_fine, max_side=args.max_side,
                                                densify_until=args.fit_coarse + args.fit_fine // 2,
                                                max_gaussians=args.max_gaussians,
                                                checkpoint_every=250), device=args.device)
    else:
        fit = json.loads((args.work / name / "fit.json").read_text())
    write_json(args.work / name / "fit.json", fit)
    timing["fit"] = time.perf_counter() - t
    t = time.perf_counter()
    if not (res / "change" / "keyframes.csv").is_file():
        if args.targets == "oracle":
            if preset is None:
                raise SystemExit("--targets oracle needs a synth:<preset> scene")
            oracle_targets(preset, cams, res)
        else:
            pair_targets(res / "fit" / "model.pt", cams, res)
    timing["targets"] = time.perf_counter() - t
    opts = {"iterations": args.iterations}
    if args.lambda_3d is not None:
        opts["lambda_3d"] = args.lambda_3d
    if args.geometry_lr_scale is not None:
        opts["geometry_lr_scale"] = args.geometry_lr_scale
    if args.frozen_iterations is not None:
        opts["frozen_iterations"] = args.frozen_iterations
    if args.plain_bce:
        opts["balance_classes"] = False
    shutil.rmtree(res / "partition", ignore_errors=True)
    t = time.perf_counter()
    summary = train_partition(res / "fit" / "model.pt", res / "poses" / "cameras.json",
                              res / "change" / "keyframes.csv", scene, res / "partition",
                              PartitionOptions(**opts), device=args.device)
    timing["partition"] = time.perf_counter() - t
    pm = load_partition_model(res / "partition" / "model.pt", args.device)
    t = time.perf_counter()
    scores = score_eval_views(pm, scene, cams)
    timing["eval_render"] = time.perf_counter() - t
    out = {"scene": name, "targets": args.targets, "fit": fit, "partition": summary,
           "eval": scores, "seconds": timing, "args": {k: str(v) for k, v in vars(args).items()},
           "torch_threads": torch.get_num_threads()}
    write_json(args.work / name / f"quality_{args.targets}{args.tag}.json", out)
    print(json.dumps({"scene": name, "targets": args.targets, "eval": scores,
                      "seconds": timing}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
