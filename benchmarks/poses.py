"""Pose registration accuracy on a scene with ground-truth cameras.

Usage::

    python benchmarks/poses.py SCENE_DIR [--matcher auto|exhaustive|retrieval|sequential]
        [--out DIR]
        [--camera-model PINHOLE|SIMPLE_PINHOLE] [--refine-principal-point] [--csv FILE]
        [--max-reproj-error PX] [--refine-iterations N] [--mapper-attempts N] [--threads N]
        [--repeatable|--no-repeatable]
        [--dsp|--no-dsp]

SCENE_DIR must hold ``gt_cameras.json`` (e.g. the shared test scenes). Runs the poses stage
with COLMAP (ignoring any known poses), aligns the estimated camera centres to the ground truth
with a Sim3 and prints: % of images registered, median rotation error (deg), median centre
error (% of the GT orbit radius, the median distance of GT centres from their centroid), the
estimated focal length against the true one, time and the 1-minute load average at start and end
(timings on a shared machine are only comparable at similar load).
Targets: >= 95 % registered, median rotation < 1 deg, median centre error < 2 %.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # gdiff from this checkout

from gdiff.align import pose_errors
from gdiff.cameras import load_cameras
from gdiff.log import setup_logging
from gdiff.sfm import PosesOptions, read_cameras_file, run_poses
from gdiff.sfm.options import MATCHERS


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene")
    ap.add_argument("--matcher", default="auto", choices=MATCHERS)
    ap.add_argument("--camera-model", default="PINHOLE", choices=["PINHOLE", "SIMPLE_PINHOLE"])
    ap.add_argument("--refine-principal-point", action="store_true")
    d = PosesOptions()
    ap.add_argument("--max-reproj-error", type=float, default=d.max_reproj_error)
    ap.add_argument("--refine-iterations", type=int, default=d.refine_iterations)
    ap.add_argument("--mapper-attempts", type=int, default=d.mapper_attempts)
    ap.add_argument("--threads", type=int, default=d.num_threads)
    ap.add_argument("--repeatable", action=argparse.BooleanOptionalAction,
                    default=d.repeatable, help="all of COLMAP on one thread")
    ap.add_argument("--dsp", action=argparse.BooleanOptionalAction,
                    default=d.domain_size_pooling, help="DSP-SIFT descriptors")
    ap.add_argument("--out", help="keep the poses outputs here (default: a temporary folder)")
    ap.add_argument("--csv", help="write the per-image errors to this CSV")
    args = ap.parse_args(argv)
    setup_logging(level=logging.INFO)
    scene = Path(args.scene)
    gt_file = scene / "gt_cameras.json"
    if not gt_file.is_file():
        print(f"{gt_file}: not found; this benchmark needs ground-truth cameras", file=sys.stderr)
        return 2
    gt = read_cameras_file(gt_file)
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(args.out) if args.out else Path(tmp)
        t0 = time.time()
        load0 = os.getloadavg()[0]
        summary = run_poses(scene, out, PosesOptions(
            source="colmap", matcher=args.matcher, camera_model=args.camera_model,
            refine_principal_point=args.refine_principal_point,
            max_reproj_error=args.max_reproj_error, refine_iterations=args.refine_iterations,
            mapper_attempts=args.mapper_attempts, num_threads=args.threads,
            repeatable=args.repeatable, domain_size_pooling=args.dsp))
        seconds = time.time() - t0
        load1 = os.getloadavg()[0]
        est = load_cameras(out / "cameras.json")
    df = pose_errors(est, gt)
    if args.csv:
        df.to_csv(args.csv, index=False)
    n_img = sum(summary["images"].values())
    n_reg = sum(summary["registered"].values())
    print(f"scene               {scene.name}")
    print(f"matcher             {summary['matcher']}")
    print(f"registered          {n_reg}/{n_img} = {100.0 * n_reg / n_img:.1f} %  "
          f"(per set {summary['registered']})")
    print(f"median rotation     {df.rot_err_deg.median():.3f} deg  "
          f"(max {df.rot_err_deg.max():.3f})")
    print(f"median centre error {100 * df.center_err_frac.median():.3f} % of orbit radius  "
          f"(max {100 * df.center_err_frac.max():.3f} %, radius "
          f"{df.attrs['orbit_radius']:.3f})")
    print(f"mean reproj. error  {summary['mean_reprojection_error']:.3f} px, "
          f"{summary['num_points']} points")
    g = gt[0]
    print(f"focal length        {est[0].fx:.2f}, {est[0].fy:.2f} px (true {g.fx:.2f}, "
          f"{g.fy:.2f}); principal point {est[0].cx:.2f}, {est[0].cy:.2f}")
    print(f"mapping runs        {summary.get('mapper_attempts', 1)}, refinement "
          f"{summary.get('refinement')}")
    print(f"time                {seconds:.1f} s (load average {load0:.1f} at start, "
          f"{load1:.1f} at end, {os.cpu_count()} CPUs)")
    ok = (n_reg / n_img >= 0.95 and df.rot_err_deg.median() < 1.0
          and df.center_err_frac.median() < 0.02)
    print("targets            ", "met" if ok else "NOT met")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
