"""Change maps from frames stored with each EXR codec, against the synthetic ground truth.

Renders ``--poses`` ground-truth frames of a built-in synthetic scene (before orbit, both
times, at ``--size``), stores each frame with each codec through :func:`gdiff.exr.write_frame`
and reads it back (:func:`gdiff.exr.read_frame`), then runs segmentation, tracking and the ID
comparison (:func:`gdiff.segment.track_paths`, :func:`gdiff.compare.compare_paths`, config
defaults) on the read-back frames. Prints per codec: bytes per frame, colour error, changed
IDs, and the Dice of the union change masks with the ground-truth changed pixels and with the
masks of the unstored (float32) frames.

    python benchmarks/exr_codecs.py [--preset demo] [--seed 2] [--size 320x240] [--poses 8]
        [--codecs zip,piz,dwaa,dwab] [--dwa-level 45] [--threads 2]
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def _dice(a: np.ndarray, b: np.ndarray) -> float:
    s = a.sum() + b.sum()
    return 1.0 if s == 0 else float(2 * (a & b).sum() / s)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--preset", default="demo")
    p.add_argument("--seed", type=int, default=2)
    p.add_argument("--size", default="320x240")
    p.add_argument("--poses", type=int, default=8)
    p.add_argument("--codecs", default="zip,piz,dwaa,dwab")
    p.add_argument("--dwa-level", type=float, default=45.0)
    p.add_argument("--threads", type=int, default=2)
    args = p.parse_args(argv)

    import yaml

    from gdiff import synth
    from gdiff.compare import CompareOptions
    from gdiff.device import set_threads
    from gdiff.exr import read_frame, write_frame
    from gdiff.options import from_config
    from gdiff.compare import compare_paths
    from gdiff.segment import SegmentOptions, make_segmenter, track_paths
    from gdiff.track import TrackOptions

    set_threads(args.threads)
    cfg = yaml.safe_load((Path(__file__).resolve().parents[1] / "config/config.yaml").read_text())
    seg = make_segmenter(from_config(SegmentOptions, cfg["segment"], "segment"))
    trk = from_config(TrackOptions, cfg["track"], "track")
    cmp = from_config(CompareOptions, cfg["compare"], "compare")
    w, h = (int(v) for v in args.size.split("x"))
    preset = dataclasses.replace(synth.get_preset(args.preset), width=w, height=h)
    scene = synth.build_scene(preset, args.seed)
    frames, gt = {}, {}
    for i, cam in enumerate(synth.orbit_path(scene, "before", args.poses)):
        for t, st in (("t0", "before"), ("t1", "after")):
            r = scene.render(cam, st)
            frames[("p1", t, i)] = dict(rgb=r["rgb"].astype(np.float32),
                                        depth=r["depth"].astype(np.float32),
                                        alpha=np.ones(r["depth"].shape, np.float32), camera=cam)
            gt[("p1", t, i)] = r["changed"]
    gt_union = {i: gt[("p1", "t0", i)] | gt[("p1", "t1", i)] for i in range(args.poses)}
    print(f"{args.preset} seed {args.seed}: {args.poses} poses x 2 times at {w}x{h}")

    def run(name, fr, size=None, err=None):
        ids, _ = track_paths(fr, seg, trk)
        masks, df = compare_paths(ids, fr, cmp)
        union = {i: m0 | m1 for (_, i), (m0, m1) in masks.items()}
        d_gt = np.mean([_dice(union[i], gt_union[i]) for i in union])
        line = (f"  {name:6s} changed IDs {int(df['changed'].sum()):2d}, Dice vs ground truth "
                f"{d_gt:.3f}")
        if ref:
            line += f", vs float32 frames {np.mean([_dice(union[i], ref[i]) for i in union]):.3f}"
        if size is not None:
            line += f"; {size / 1e3:.0f} kB/frame, colour error mean {255 * err[0]:.2f}, " \
                    f"max {255 * err[1]:.1f} (8-bit steps)"
        print(line, flush=True)
        return union

    ref: dict = {}
    ref.update(run("float32", frames))
    with tempfile.TemporaryDirectory() as tmp:
        for codec in [c for c in args.codecs.split(",") if c]:
            back, size, e_mean, e_max = {}, 0, [], 0.0
            for k, f in frames.items():
                path = Path(tmp) / f"{codec}_{k[1]}_{k[2]}.exr"
                write_frame(path, f["rgb"], f["alpha"], f["depth"], compression=codec,
                            dwa_level=args.dwa_level)
                size += path.stat().st_size
                rgb, alpha, depth = read_frame(path)
                assert np.array_equal(depth, f["depth"]) and np.array_equal(alpha, f["alpha"])
                e = np.abs(np.clip(rgb, 0, 1) - np.clip(f["rgb"], 0, 1))
                e_mean.append(e.mean())
                e_max = max(e_max, float(e.max()))
                back[k] = dict(f, rgb=rgb, depth=depth, alpha=alpha)
            run(codec, back, size / len(frames), (float(np.mean(e_mean)), e_max))
    return 0


if __name__ == "__main__":
    sys.exit(main())
