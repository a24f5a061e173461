"""Benchmark: can COLMAP register the synthetic scenes, and how accurately?

For each preset/seed: render the scene folder (``gdiff.synth.make_scene``, into ``--work``,
reused when present), then SIFT extraction (one shared PINHOLE camera), exhaustive matching and
incremental mapping with pycolmap on all images (before, after, eval before/after) in a
temporary database. Reports the registered fraction per image set, the number of 3D points,
the mean reprojection error and the camera-centre error against ``gt_cameras.json`` after a
similarity alignment (Umeyama), plus render/SfM times. One JSON line per scene; ``--out``
also writes them as CSV.

    python benchmarks/synth_colmap.py --presets tiny demo lightchange --seeds 0 1
"""

from __future__ import annotations

import argparse
import sys
import json
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pycolmap

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # gdiff from this checkout

from gdiff import synth
from gdiff.io import read_json

SETS = ("before", "after", "eval/before", "eval/after")


def similarity_residuals(est: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """Distances [N] between ``ref`` [N, 3] and ``est`` [N, 3] after the least-squares
    similarity transform (rotation, translation, scale) mapping est onto ref."""
    me, mr = est.mean(0), ref.mean(0)
    E, R0 = est - me, ref - mr
    U, S, Vt = np.linalg.svd(R0.T @ E)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    rot = U @ D @ Vt
    scale = (S * np.diag(D)).sum() / (E ** 2).sum()
    return np.linalg.norm(scale * E @ rot.T + mr - ref, axis=1)


def run_sfm(scene_dir: Path, threads: int) -> dict:
    """SIFT + exhaustive matching + incremental mapping on every image of ``scene_dir``."""
    work = Path(tempfile.mkdtemp(prefix="synth_colmap_"))
    try:
        images = work / "images"
        names = []
        for sub in SETS:
            for p in sorted((scene_dir / sub).glob("*.png")):
                dst = images / sub / p.name
                dst.parent.mkdir(parents=True, exist_ok=True)
                shutil.copy(p, dst)
                names.append(f"{sub}/{p.name}")
        db = work / "database.db"
        reader = pycolmap.ImageReaderOptions()
        reader.camera_model = "PINHOLE"
        extract = pycolmap.FeatureExtractionOptions()
        extract.num_threads = threads
        t0 = time.perf_counter()
        pycolmap.extract_features(db, images, camera_mode=pycolmap.CameraMode.SINGLE,
                                  reader_options=reader, extraction_options=extract)
        pycolmap.match_exhaustive(db)
        recs = pycolmap.incremental_mapping(db, images, work / "sparse")
        sfm_s = time.perf_counter() - t0
        best = max(recs.values(), key=lambda r: r.num_reg_images()) if recs else None
        centres = {im.name: np.asarray(im.projection_center())
                   for im in (best.images.values() if best else [])}
        return {"names": names, "centres": centres, "n_models": len(recs),
                "points": best.num_points3D() if best else 0,
                "reproj_px": best.compute_mean_reprojection_error() if best else float("nan"),
                "sfm_seconds": sfm_s}
    finally:
        shutil.rmtree(work, ignore_errors=True)


def evaluate(preset: str, seed: int, work: Path, threads: int) -> dict:
    scene_dir = work / f"{preset}_{seed}"
    t0 = time.perf_counter()
    if not (scene_dir / "meta.json").is_file():
        synth.make_scene(scene_dir, preset, seed, overwrite=True)
    render_s = time.perf_counter() - t0
    sfm = run_sfm(scene_dir, threads)
    gt = read_json(scene_dir / "gt_cameras.json")
    gt_centre = {fr["file"]: np.asarray(fr["c2w"])[:3, 3] for fr in gt["frames"]}
    reg = sfm["centres"]
    row = {"preset": preset, "seed": seed, "images": len(sfm["names"]),
           "registered": len(reg), "fraction": len(reg) / len(sfm["names"]),
           "models": sfm["n_models"], "points": sfm["points"],
           "reproj_px": round(sfm["reproj_px"], 3)}
    for sub in SETS:
        subset = [n for n in sfm["names"] if n.startswith(sub + "/")]
        row[f"reg_{sub.replace('/', '_')}"] = f"{sum(n in reg for n in subset)}/{len(subset)}"
    if len(reg) >= 3:
        names = sorted(reg)
        res = similarity_residuals(np.array([reg[n] for n in names]),
                                   np.array([gt_centre[n] for n in names]))
        row["centre_err_median_m"] = round(float(np.median(res)), 4)
        row["centre_err_max_m"] = round(float(res.max()), 4)
    row["render_seconds"] = round(render_s, 1)
    row["sfm_seconds"] = round(sfm["sfm_seconds"], 1)
    return row


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--presets", nargs="+", default=["tiny", "demo", "lightchange"])
    ap.add_argument("--seeds", nargs="+", type=int, default=[0])
    ap.add_argument("--work", type=Path, default=Path("benchmarks/out/synth_colmap"))
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--out", type=Path, default=None, help="CSV of the results")
    args = ap.parse_args(argv)
    rows = []
    for preset in args.presets:
        for seed in args.seeds:
            row = evaluate(preset, seed, args.work, args.threads)
            print(json.dumps(row), flush=True)
            rows.append(row)
    if args.out:
        pd.DataFrame(rows).to_csv(args.out, index=False)


if __name__ == "__main__":
    main()
