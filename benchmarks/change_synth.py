"""Benchmark: ID-compare change masks vs ground truth on synthetic paths, next to a pixel-diff
baseline (absolute colour difference + Otsu, ``gdiff.baselines.pixel_diff``).

For each preset/seed: ground-truth renders (colour, depth) along the before and after orbits
(paths p1, p2) in both states, segment + track + compare (``gdiff.segment``, ``gdiff.compare``), and per-frame
F1/IoU of the union change map against the ground-truth union (changed objects visible at t0 or
t1); also of mask_t0/mask_t1 against the per-time ground truth. Prints a table and writes
``--out`` (CSV, one row per frame and method).

``--degrade`` imitates renders of a fitted Gaussian model: colour blurred (sigma 0.7 px) with
noise (std 0.01), depth as an alpha-blended expectation (blurred across occlusion edges,
sigma 1 px) with smooth relative noise (1 %). ``--no-depth`` runs on colour only.
``--cache DIR`` keeps the ground-truth renders (npz per preset/seed/frame count) between runs.
``--scene-dirs DIR ...`` instead scores the eval pairs of gdiff scene folders (images only,
``eval/before``, ``eval/after``, ``eval/masks``) with ``detect_changes_pair`` without depth
(the evaluation's ID-compare baseline) next to pixel difference.

    python benchmarks/change_synth.py --presets demo lightchange --seeds 0 1 2 3 4 --frames 10
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pandas as pd

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # gdiff from this checkout

from gdiff import synth
from gdiff.baselines import pixel_diff
from gdiff.compare import CompareOptions, compare_paths
from gdiff.metrics import pixel_scores
from gdiff.segment import SegmentOptions, make_segmenter, track_paths
from gdiff.track import TrackOptions

_GT_KEYS = ("rgb", "depth", "ids", "changed")


def render_paths(scene, n: int, supersample: int | None = None, cache: Path | None = None):
    """frames[(path, t, i)] (rgb, depth, camera) and ground truth gt[(path, t, i)] (changed)."""
    f = None
    if cache is not None:
        f = cache / f"{scene.preset.name}_{scene.seed}_{n}_{supersample or 0}.npz"
    cams = {p: synth.orbit_path(scene, st, n) for p, st in (("p1", "before"), ("p2", "after"))}
    if f is not None and f.exists():
        data = np.load(f)
        frames, gt = {}, {}
        for p, cl in cams.items():
            for i, cam in enumerate(cl):
                for t in ("t0", "t1"):
                    r = {k: data[f"{p}_{t}_{i}_{k}"] for k in _GT_KEYS}
                    frames[(p, t, i)] = dict(rgb=r["rgb"], depth=r["depth"], camera=cam)
                    gt[(p, t, i)] = r
        return frames, gt
    frames, gt, store = {}, {}, {}
    for p, cl in cams.items():
        for i, cam in enumerate(cl):
            for t, state in (("t0", "before"), ("t1", "after")):
                r = scene.render(cam, state, supersample=supersample)
                frames[(p, t, i)] = dict(rgb=r["rgb"], depth=r["depth"], camera=cam)
                gt[(p, t, i)] = r
                store.update({f"{p}_{t}_{i}_{k}": r[k] for k in _GT_KEYS})
    if f is not None:
        f.parent.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(f, **store)
    return frames, gt


def degrade(frames, seed: int = 0):
    """Frames as a fitted Gaussian model might render them (see the module docstring)."""
    rng = np.random.default_rng(seed)
    out = {}
    for k, f in frames.items():
        rgb = cv2.GaussianBlur(f["rgb"], (0, 0), 0.7)
        rgb = np.clip(rgb + rng.normal(0, 0.01, rgb.shape), 0, 1).astype(np.float32)
        z = cv2.GaussianBlur(f["depth"], (0, 0), 1.0)
        noise = cv2.GaussianBlur(rng.normal(0, 1, z.shape).astype(np.float32), (0, 0), 4.0)
        noise *= 0.01 / max(float(noise.std()), 1e-9)
        out[k] = dict(f, rgb=rgb, depth=(z * (1 + noise)).astype(np.float32))
    return out


def evaluate(frames, gt, masks):
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
    the GT unchanged objects that a changed ID covers (false changes); and per GT changed
    object the set of changed IDs covering it (more than one = listed twice in changes.csv)."""
    found, false, id_sets = {}, set(), {}
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
                    id_sets.setdefault(int(oid), set()).add(d)
                else:
                    false.add(int(oid))
    ok = sum(t in found.get(o, set()) for o, t in scene.change_types.items())
    exact = sum(found.get(o, set()) == {t} for o, t in scene.change_types.items())
    return ok, exact, len(scene.change_types), found, false, id_sets


def evaluate_pairs(scene_dir) -> pd.DataFrame:
    """Per eval pair of a scene folder: P/R/F1/IoU of ID-compare (no depth) and pixel diff."""
    from gdiff.compare import detect_changes_pair
    from gdiff.io import read_image, read_mask

    d = Path(scene_dir) / "eval"
    rows = []
    for f in sorted((d / "masks").glob("*.png")):
        if not (d / "before" / f.name).exists() or not (d / "after" / f.name).exists():
            continue
        a, b = read_image(d / "before" / f.name), read_image(d / "after" / f.name)
        g = read_mask(f)
        m0, m1 = detect_changes_pair(a, b)
        for method, m in (("gdiff", m0 | m1), ("pixel_diff", pixel_diff(a, b).mask)):
            s = pixel_scores(m, g)
            rows.append(dict(scene=Path(scene_dir).name, view=f.stem, method=method,
                             P=s["P"], R=s["R"], F1=s["F1"], IoU=s["IoU"]))
    return pd.DataFrame(rows)


def _duplicates(id_sets, df) -> int:
    """GT changed objects covered by more than one changes.csv entry (a moved pair is one)."""
    partner = dict(zip(df["id"], df["partner"]))
    n = 0
    for ids in id_sets.values():
        groups = {min(i, partner.get(i, 0) or i) for i in ids}
        n += len(groups) > 1
    return n


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--presets", nargs="+", default=["demo", "lightchange"])
    ap.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    ap.add_argument("--frames", type=int, default=10, help="frames per path")
    ap.add_argument("--supersample", type=int, default=None)
    ap.add_argument("--no-depth", action="store_true", help="segment/compare without depth")
    ap.add_argument("--degrade", action="store_true",
                    help="imitate Gaussian-splat renders (blurred colour/depth, noise)")
    ap.add_argument("--cache", default=None, help="folder keeping the ground-truth renders")
    ap.add_argument("--scene-dirs", nargs="+", default=None,
                    help="score eval image pairs of these scene folders instead")
    ap.add_argument("--out", default="change_synth.csv")
    a = ap.parse_args(argv)
    if a.scene_dirs:
        df = pd.concat([evaluate_pairs(d) for d in a.scene_dirs])
        df.to_csv(a.out, index=False)
        print(df.groupby(["scene", "method"])[["P", "R", "F1", "IoU"]].mean().round(3)
              .to_string())
        return
    seg = make_segmenter(SegmentOptions())
    cache = Path(a.cache) if a.cache else None
    all_rows, types = [], []
    for preset in a.presets:
        for seed in a.seeds:
            scene = synth.build_scene(preset, seed)
            t = time.time()
            frames, gt = render_paths(scene, a.frames, a.supersample, cache)
            t_render = time.time() - t
            if a.degrade:
                frames = degrade(frames, seed)
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
            ok, exact, n_gt, found, false, id_sets = type_accuracy(scene, ids, gt, df)
            types.append(dict(preset=preset, seed=seed, gt=str(scene.change_types),
                              found=str(found), types_ok=f"{ok}/{n_gt}",
                              types_exact=f"{exact}/{n_gt}",
                              dup_ids=_duplicates(id_sets, df),
                              false_objects=str(sorted(false)),
                              render_s=round(t_render, 1), run_s=round(t_run, 1)))
            res = pd.DataFrame(rows).groupby("method")[["F1", "IoU"]].mean()
            print(f"{preset} seed {seed}: " + "; ".join(
                f"{m} F1 {r.F1:.3f} IoU {r.IoU:.3f}" for m, r in res.iterrows())
                  + f"  types {ok}/{n_gt} (exact {exact})"
                  + f"  (render {t_render:.0f}s, gdiff {t_run:.0f}s)", flush=True)
    df = pd.DataFrame(all_rows)
    df.to_csv(a.out, index=False)
    print("\nper-frame means (NaN frames, no change and no prediction, skipped):")
    print(df.groupby(["preset", "method"])[["F1", "IoU"]].mean().round(3).to_string())
    print("\nper seed (F1):")
    print(df.pivot_table(index=["preset", "seed"], columns="method", values="F1",
                         aggfunc="mean").round(3).to_string())
    print("\nchange types:")
    print(pd.DataFrame(types).to_string(index=False))


if __name__ == "__main__":
    main()
