"""Benchmark: ID-compare change masks vs ground truth on synthetic paths, next to a pixel-diff
baseline (absolute colour difference + Otsu, ``gdiff.baselines.pixel_diff``).

For each preset/seed: ground-truth renders (colour, depth) along the before and after orbits
(paths p1, p2) in both states, segment + track + compare (``gdiff.segtrack``), and per-frame
F1/IoU of the union change map against the ground-truth union (changed objects visible at t0 or
t1); also of mask_t0/mask_t1 against the per-time ground truth. Prints a table and writes
``--out`` (CSV, one row per frame and method).

    python benchmarks/change_synth.py --presets demo lightchange --seeds 0 1 2 --frames 10
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import pandas as pd

from gdiff import synth
from gdiff.baselines import pixel_diff
from gdiff.change import CompareOptions
from gdiff.metrics import pixel_scores
from gdiff.segment import SegmentOptions, make_segmenter
from gdiff.segtrack import compare_paths, track_paths
from gdiff.track import TrackOptions


def render_paths(scene, n: int, supersample: int | None = None):
    """frames[(path, t, i)] (rgb, depth, camera) and ground truth gt[(path, t, i)] (changed)."""
    frames, gt = {}, {}
    for p, orbit_state in (("p1", "before"), ("p2", "after")):
        for i, cam in enumerate(synth.orbit_path(scene, orbit_state, n)):
            for t, state in (("t0", "before"), ("t1", "after")):
                r = scene.render(cam, state, supersample=supersample)
                frames[(p, t, i)] = dict(rgb=r["rgb"], depth=r["depth"], camera=cam)
                gt[(p, t, i)] = r
    return frames, gt


def evaluate(frames, gt, masks, use_depth=True):
    rows = []
    for (p, i), (m0, m1) in sorted(masks.items()):
        g0, g1 = gt[(p, "t0", i)]["changed"], gt[(p, "t1", i)]["changed"]
        s = pixel_scores(m0 | m1, g0 | g1)
        s0, s1 = pixel_scores(m0, g0), pixel_scores(m1, g1)
        rows.append(dict(path=p, frame=i, method="gdiff", F1=s["F1"], IoU=s["IoU"],
                         F1_t0=s0["F1"], F1_t1=s1["F1"]))
        pd_ = pixel_diff(frames[(p, "t0", i)]["rgb"], frames[(p, "t1", i)]["rgb"])
        sb = pixel_scores(pd_.mask, g0 | g1)
        rows.append(dict(path=p, frame=i, method="pixel_diff", F1=sb["F1"], IoU=sb["IoU"]))
    return rows


def type_accuracy(scene, ids, gt, df):
    """Per GT changed object: the types of the changed IDs covering most of it (any frame);
    and the GT unchanged objects that a changed ID covers (false changes)."""
    found, false = {}, set()
    changed = set(df.loc[df["changed"], "id"])
    typ = dict(zip(df["id"], df["type"]))
    for key, m in ids.items():
        g = gt[key]["ids"]
        for oid in np.unique(g):
            sel = g == oid
            if oid == 0 or sel.sum() < 40:
                continue
            v, c = np.unique(m[sel], return_counts=True)
            d = int(v[np.argmax(c)])
            if d in changed:
                if oid in scene.change_types:
                    found.setdefault(int(oid), set()).add(typ[d])
                else:
                    false.add(int(oid))
    ok = sum(t in found.get(o, set()) for o, t in scene.change_types.items())
    return ok, len(scene.change_types), found, false


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--presets", nargs="+", default=["demo", "lightchange"])
    ap.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    ap.add_argument("--frames", type=int, default=10, help="frames per path")
    ap.add_argument("--supersample", type=int, default=None)
    ap.add_argument("--no-depth", action="store_true", help="segment/compare without depth")
    ap.add_argument("--out", default="change_synth.csv")
    a = ap.parse_args(argv)
    seg = make_segmenter(SegmentOptions())
    all_rows, types = [], []
    for preset in a.presets:
        for seed in a.seeds:
            scene = synth.build_scene(preset, seed)
            t = time.time()
            frames, gt = render_paths(scene, a.frames, a.supersample)
            t_render = time.time() - t
            if a.no_depth:
                frames = {k: dict(rgb=f["rgb"]) for k, f in frames.items()}
            t = time.time()
            ids, tracks = track_paths(frames, seg, TrackOptions())
            masks, df = compare_paths(ids, frames, CompareOptions())
            t_run = time.time() - t
            rows = evaluate(frames, gt, masks)
            for r in rows:
                r.update(preset=preset, seed=seed)
            all_rows += rows
            ok, n_gt, found, false = type_accuracy(scene, ids, gt, df)
            types.append(dict(preset=preset, seed=seed, gt=str(scene.change_types),
                              found=str(found), types_ok=f"{ok}/{n_gt}",
                              false_objects=str(sorted(false)),
                              render_s=round(t_render, 1), run_s=round(t_run, 1)))
            res = pd.DataFrame(rows).groupby("method")[["F1", "IoU"]].mean()
            print(f"{preset} seed {seed}: " + "; ".join(
                f"{m} F1 {r.F1:.3f} IoU {r.IoU:.3f}" for m, r in res.iterrows())
                  + f"  (render {t_render:.0f}s, gdiff {t_run:.0f}s)", flush=True)
    df = pd.DataFrame(all_rows)
    df.to_csv(a.out, index=False)
    print("\nper-frame means (NaN frames, no change and no prediction, skipped):")
    print(df.groupby(["preset", "method"])[["F1", "IoU"]].mean().round(3).to_string())
    print("\nchange types:")
    print(pd.DataFrame(types).to_string(index=False))


if __name__ == "__main__":
    main()
