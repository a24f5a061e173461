"""Benchmark: the compare stage on renders of a FITTED model, scored against synth ground truth.

Input: a workflow results folder of a synthetic scene (``render/``, ``sequence/poses.json``,
``poses/cameras.json``, optionally ``change/``), the scene folder (``gt_cameras.json``) and the
synth preset + seed that built it.

1. The registered cameras (COLMAP frame) are aligned to the ground-truth cameras with a Sim3
   (:func:`gdiff.align.pose_errors`: a similarity fitted to the camera centres of the same images).
2. Every path pose is mapped into the synth frame and rendered by the synth scene in both
   states (pixel-centre ground truth: ``changed`` = a changed object is visible); the truth per
   pose is ``gt_t0`` (state before), ``gt_t1`` (after) and their union.
3. ``segment`` + ``compare`` run as the workflow runs them (:func:`gdiff.segment.
   segment_and_track`, :func:`gdiff.compare.compare`) on the results folder's renders, writing
   to ``--out`` (``--reuse-ids`` keeps ``--out/instances`` from an earlier run and only
   compares again).
4. Scores per frame: F1/IoU of the union mask against the union truth (mean over frames with
   truth or prediction, and pooled over all pixels), of mask_t0/mask_t1 against gt_t0/gt_t1;
   the same at the key frames (what the partition stage trains on: a key frame of time t is
   supervised with ``mask_t<t>``, scored as ``key_sup``); the number of changed instances per
   type against the truth. The workflow's own ``change/`` masks (if present) are scored too.

    python benchmarks/compare_fitted.py /tmp/ci_clone/results/demo \
        /tmp/ci_clone/resources/synth/demo --preset demo --seed 0 --out /tmp/cmp/run
"""

from __future__ import annotations

import argparse
import sys
import json
import time
from pathlib import Path

import numpy as np
import pandas as pd

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # gdiff from this checkout

from gdiff import synth
from gdiff.align import pose_errors
from gdiff.cameras import Camera
from gdiff.compare import CompareOptions, compare
from gdiff.frames import key_frames, read_sequence
from gdiff.io import read_json, read_mask
from gdiff.metrics import pixel_scores, scores_from_counts
from gdiff.segment import SegmentOptions, segment_and_track
from gdiff.sfm import read_cameras_file
from gdiff.track import TrackOptions


def align_to_gt(registered: list[Camera], gt: list[Camera]
                ) -> tuple[float, np.ndarray, np.ndarray, float]:
    """Sim3 (s, R, t) mapping the registered frame onto the ground-truth frame
    (x_gt = s R x + t; :func:`gdiff.align.pose_errors`, from the centres of the images both
    lists hold), and the RMS centre residual after alignment (GT units)."""
    err = pose_errors(registered, gt)
    a = err.attrs
    return a["scale"], a["R"], a["t"], float(np.sqrt((err["center_err"] ** 2).mean()))


def to_gt_frame(cam: Camera, s: float, R: np.ndarray, t: np.ndarray) -> Camera:
    """``cam`` (registered frame) expressed in the ground-truth frame."""
    c2w = np.eye(4)
    c2w[:3, :3] = R @ cam.c2w[:3, :3]
    c2w[:3, 3] = s * R @ cam.c2w[:3, 3] + t
    return cam.with_pose(c2w)


def ground_truth(scene, cams: dict[str, list[Camera]], align, cache: Path | None):
    """{(path, i): (gt_t0, gt_t1)} bool [H, W] masks of the visible changed objects; and the
    GT object ids per (path, t, i) (int [H, W])."""
    if cache is not None and cache.exists():
        d = np.load(cache)
        gt = {(p, i): (d[f"{p}_{i}_0"], d[f"{p}_{i}_1"]) for p, cl in cams.items()
              for i in range(len(cl))}
        ids = {(p, t, i): d[f"{p}_{i}_ids{t[-1]}"] for p, cl in cams.items()
               for i in range(len(cl)) for t in ("t0", "t1")}
        return gt, ids
    gt, ids, store = {}, {}, {}
    for p, cl in cams.items():
        for i, cam in enumerate(cl):
            g = to_gt_frame(cam, *align[:3])
            r0 = scene.render(g, "before", supersample=1, shadows=False)
            r1 = scene.render(g, "after", supersample=1, shadows=False)
            gt[(p, i)] = (r0["changed"], r1["changed"])
            ids[(p, "t0", i)], ids[(p, "t1", i)] = r0["ids"], r1["ids"]
            store.update({f"{p}_{i}_0": r0["changed"], f"{p}_{i}_1": r1["changed"],
                          f"{p}_{i}_ids0": r0["ids"], f"{p}_{i}_ids1": r1["ids"]})
    if cache is not None:
        cache.parent.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(cache, **store)
    return gt, ids


def read_masks(change_dir: Path, cams) -> dict[tuple[str, int], tuple[np.ndarray, np.ndarray]]:
    return {(p, i): (read_mask(change_dir / p / "t0" / f"{i:05d}.png"),
                     read_mask(change_dir / p / "t1" / f"{i:05d}.png"))
            for p, cl in cams.items() for i in range(len(cl))}


def score(masks, gt, keys: dict[tuple[str, int], int]) -> pd.DataFrame:
    """One row per pose: union / t0 / t1 scores; ``key`` (time of the key frame or -1)."""
    rows = []
    for (p, i), (m0, m1) in sorted(masks.items()):
        g0, g1 = gt[(p, i)]
        su, s0, s1 = pixel_scores(m0 | m1, g0 | g1), pixel_scores(m0, g0), pixel_scores(m1, g1)
        kt = keys.get((p, i), -1)
        sup = (s0, s1)[kt] if kt >= 0 else None
        rows.append(dict(path=p, frame=i, key=kt, F1=su["F1"], IoU=su["IoU"], P=su["P"],
                         R=su["R"], TP=su["TP"], FP=su["FP"], FN=su["FN"], F1_t0=s0["F1"],
                         F1_t1=s1["F1"],
                         sup_TP=sup["TP"] if sup else 0, sup_FP=sup["FP"] if sup else 0,
                         sup_FN=sup["FN"] if sup else 0, sup_F1=sup["F1"] if sup else np.nan))
    return pd.DataFrame(rows)


def summarise(df: pd.DataFrame) -> dict:
    """Mean and pooled figures over all frames and over the key frames."""
    out = {}
    for name, d in (("all", df), ("key", df[df["key"] >= 0])):
        pooled = scores_from_counts(d["TP"].sum(), d["FP"].sum(), d["FN"].sum())
        out[f"{name}_F1"] = d["F1"].mean()
        out[f"{name}_IoU"] = d["IoU"].mean()
        out[f"{name}_F1_pooled"] = pooled["F1"]
        out[f"{name}_IoU_pooled"] = pooled["IoU"]
        out[f"{name}_P_pooled"] = pooled["P"]
        out[f"{name}_R_pooled"] = pooled["R"]
    k = df[df["key"] >= 0]
    sup = scores_from_counts(k["sup_TP"].sum(), k["sup_FP"].sum(), k["sup_FN"].sum())
    out["key_sup_F1_pooled"], out["key_sup_P_pooled"] = sup["F1"], sup["P"]
    out["key_sup_R_pooled"] = sup["R"]
    return out


def instance_counts(changes_csv: Path, scene) -> dict:
    ch = pd.read_csv(changes_csv)
    counts = ch["type"].value_counts().to_dict()
    truth = pd.Series(scene.change_types).value_counts().to_dict()
    inst = {}
    if "instance" in ch:  # one row per object: the type of its largest piece
        heads = ch[ch["id"] == ch["instance"]]
        inst = {"instances": int(ch["instance"].nunique()),
                **{f"inst_{t}": int((heads["type"] == t).sum())
                   for t in ("added", "removed", "moved")}}
    return {"changed": len(ch), **{t: counts.get(t, 0) for t in ("added", "removed", "moved")},
            **inst,
            "truth": len(scene.change_types),
            "truth_types": ",".join(f"{t}:{n}" for t, n in sorted(truth.items()))}


def changed_id_purity(change_dir: Path, inst_dir: Path, gt_ids: dict, scene) -> dict:
    """Changed IDs of changes.csv that ever cover a GT changed object (most of their pixels on
    one) vs those that never do (false instances)."""
    ch = pd.read_csv(change_dir / "changes.csv")
    changed = set(ch["id"].astype(int))
    true_ids = set()
    changed_obj = np.asarray(scene.changed_ids)
    index = read_json(inst_dir / "index.json")
    for fr in index["frames"]:
        key = (fr["path"], fr["t"], int(fr["frame"]))
        from gdiff.io import read_ids

        m = read_ids(inst_dir / fr["ids"])
        g = np.isin(gt_ids[key], changed_obj)
        for t in np.intersect1d(np.unique(m), list(changed)):
            sel = m == t
            if g[sel].mean() > 0.5:
                true_ids.add(int(t))
    return {"ids_on_true_change": len(true_ids), "ids_false": len(changed - true_ids)}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("results", help="workflow results folder of one synth scene")
    ap.add_argument("scene_dir", help="its scene folder (with gt_cameras.json)")
    ap.add_argument("--preset", required=True)
    ap.add_argument("--seed", type=int, required=True)
    ap.add_argument("--out", required=True, help="folder for instances/, change/, scores")
    ap.add_argument("--reuse-ids", action="store_true",
                    help="keep --out/instances from an earlier run (compare only)")
    ap.add_argument("--no-workflow", action="store_true",
                    help="do not score the results folder's own change/ masks")
    ap.add_argument("--compare", default="{}",
                    help="JSON dict of CompareOptions fields overriding the defaults")
    ap.add_argument("--track", default="{}",
                    help="JSON dict of TrackOptions fields overriding the defaults")
    a = ap.parse_args(argv)
    res, out = Path(a.results), Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    poses_json = res / "sequence" / "poses.json"
    cams, meta = read_sequence(poses_json)
    keys = key_frames(meta)
    scene = synth.build_scene(a.preset, a.seed)
    align = align_to_gt(read_cameras_file(res / "poses" / "cameras.json"),
                        read_cameras_file(Path(a.scene_dir) / "gt_cameras.json"))
    print(f"Sim3: scale {align[0]:.4f}, RMS centre residual {align[3]:.4f} m")
    gt, gt_ids = ground_truth(scene, cams, align, out / f"gt_{a.preset}_{a.seed}.npz")

    runs = {}
    if not a.no_workflow and (res / "change" / "changes.csv").exists():
        runs["workflow"] = (res / "change", res / "instances")
    t_seg = 0.0
    if not a.reuse_ids or not (out / "instances" / "index.json").exists():
        t = time.time()
        segment_and_track(res / "render", poses_json, out / "instances", SegmentOptions(),
                          TrackOptions(**json.loads(a.track)))
        t_seg = time.time() - t
    t = time.time()
    compare(out / "instances", poses_json, out / "change",
            CompareOptions(**json.loads(a.compare)))
    t_cmp = time.time() - t
    runs["this"] = (out / "change", out / "instances")
    print(f"segment+track {t_seg:.1f} s{' (reused)' if not t_seg else ''}, compare {t_cmp:.1f} s")

    rows, frames = [], []
    for name, (cdir, idir) in runs.items():
        df = score(read_masks(cdir, cams), gt, keys)
        df["run"] = name
        frames.append(df)
        rows.append(dict(run=name, **summarise(df), **instance_counts(cdir / "changes.csv", scene),
                         **changed_id_purity(cdir, idir, gt_ids, scene)))
    pd.concat(frames).to_csv(out / "frames.csv", index=False)
    table = pd.DataFrame(rows).set_index("run")
    table.to_csv(out / "summary.csv")
    with pd.option_context("display.width", 200):
        print(table.T.to_string(float_format=lambda v: f"{v:.3f}"))


if __name__ == "__main__":
    main()
