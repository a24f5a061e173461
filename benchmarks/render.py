"""Benchmark the render stage on a finished scene: time, CPU time, bytes per frame and codec.

Renders ``RESULTS/fit/model.pt`` along ``RESULTS/sequence/poses.json`` (a ``results/<scene>/``
folder of a run that got past ``interpolate``) with :func:`gdiff.sequence.render_sequences`
into ``--out`` and prints wall and CPU seconds (this process, user + system), the split into
model evaluation / rasterisation / file writing, frames per second and the size of the
``render/`` folder by file kind.

With ``--codecs zip,piz,dwaa`` every written frame is then re-encoded with each OpenEXR
compression (:func:`gdiff.exr.write_frame`) and read back: per codec the total size, the
encode and decode CPU time per frame, and the largest error per channel against the frame as
rendered (colour in sRGB 8-bit steps, alpha, depth relative). Lossless codecs must print 0.

With ``--segment`` the ``segment`` and ``compare`` stages are also run on the frames of each
codec (defaults of config/config.yaml) and the change masks are compared with those of the
first codec: per codec the changed IDs and the IoU of the union change masks over all poses.

    python benchmarks/render.py results/demo --out /tmp/render_bench [--threads 2]
        [--codecs zip,piz,dwaa] [--segment] [--previews] [--batch 8]
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def _cpu() -> float:
    t = os.times()
    return t.user + t.system


def _du(folder: Path) -> dict[str, int]:
    sizes: dict[str, int] = {}
    for f in folder.rglob("*"):
        if f.is_file():
            kind = "sheet" if f.name.endswith("_sheet.png") else f.suffix.lstrip(".")
            sizes[kind] = sizes.get(kind, 0) + f.stat().st_size
    return sizes


def _mb(n: float) -> str:
    return f"{n / 1e6:.1f} MB"


def render_once(results: Path, out: Path, options) -> dict:
    from gdiff.sequence import render_sequences

    if out.exists():
        shutil.rmtree(out)
    w0, c0 = time.perf_counter(), _cpu()
    summary = render_sequences(results / "fit" / "model.pt", results / "sequence" / "poses.json",
                               out, options, device="cpu")
    wall, cpu = time.perf_counter() - w0, _cpu() - c0
    n = 2 * sum(summary["frames"].values())
    sizes = _du(out)
    print(f"render: {n} frames {summary['width']}x{summary['height']}, compression "
          f"{options.compression}, previews {options.previews}: wall {wall:.1f} s, CPU "
          f"{cpu:.1f} s ({n / wall:.1f} frames/s)"
          + ("; model {seconds_model:.1f} s, rasterise {seconds_raster:.1f} s, write "
             "{seconds_write:.1f} s".format(**summary) if "seconds_write" in summary else ""))
    print("  size: " + ", ".join(f"{k} {_mb(v)}" for k, v in sorted(sizes.items()))
          + f"; total {_mb(sum(sizes.values()))} ({sum(sizes.values()) / n / 1e3:.0f} kB/frame)")
    return summary


def codecs(frames_dir: Path, names: list[str], work: Path, dwa_level: float) -> dict[str, Path]:
    """Re-encode every frame of ``frames_dir`` (a render folder) with each codec into
    ``work/<codec>/`` (same layout, frames.json copied); print size, time and error."""
    from gdiff.exr import read_exr, read_frame, write_frame
    from gdiff.io import linear_to_srgb

    files = sorted(frames_dir.rglob("*.exr"))
    ref = [read_exr(f) for f in files]
    out = {}
    for name in names:
        dst = work / name
        if dst.exists():
            shutil.rmtree(dst)
        shutil.copytree(frames_dir, dst, ignore=shutil.ignore_patterns("*.exr", "*.png"))
        for f in frames_dir.glob("*/*_sheet.png"):
            shutil.copy(f, dst / f.relative_to(frames_dir))
        enc = dec = 0.0
        err_rgb = err_a = err_z = 0.0
        for f, ch in zip(files, ref):
            lin = np.stack([ch[c].astype(np.float32) for c in "RGB"], -1)
            srgb = linear_to_srgb(lin).astype(np.float32)
            g = dst / f.relative_to(frames_dir)
            c0 = _cpu()
            write_frame(g, srgb, ch["A"].astype(np.float32), ch["Z"], compression=name,
                        dwa_level=dwa_level)
            c1 = _cpu()
            rgb2, a2, z2 = read_frame(g)
            dec += _cpu() - c1
            enc += c1 - c0
            err_rgb = max(err_rgb, float(np.abs(np.clip(rgb2, 0, 1) - np.clip(srgb, 0, 1)).max()))
            err_a = max(err_a, float(np.abs(a2 - ch["A"].astype(np.float32)).max()))
            z = ch["Z"]
            err_z = max(err_z, float((np.abs(z2 - z) / np.maximum(np.abs(z), 1e-6)).max()))
        size = sum(f.stat().st_size for f in dst.rglob("*.exr"))
        print(f"  {name:5s}: {_mb(size):>9s} ({size / len(files) / 1e3:.0f} kB/frame), encode "
              f"{1e3 * enc / len(files):.1f} ms, decode {1e3 * dec / len(files):.1f} ms CPU per "
              f"frame; max error: colour {255 * err_rgb:.2f}/255, alpha {err_a:.2g}, depth "
              f"{err_z:.2g} relative")
        out[name] = dst
    return out


def segment_compare(render_dirs: dict[str, Path], poses_json: Path, work: Path) -> None:
    """Run segment + compare on each codec's frames; compare the change masks with the first."""
    import yaml

    from gdiff.compare import CompareOptions
    from gdiff.io import read_mask
    from gdiff.options import from_config
    from gdiff.compare import compare
    from gdiff.segment import SegmentOptions, segment_and_track
    from gdiff.track import TrackOptions

    cfg = yaml.safe_load((Path(__file__).resolve().parents[1] / "config/config.yaml").read_text())
    seg = from_config(SegmentOptions, cfg["segment"], "segment")
    trk = from_config(TrackOptions, cfg["track"], "track")
    cmp = from_config(CompareOptions, cfg["compare"], "compare")
    first = None
    for name, rdir in render_dirs.items():
        inst, change = work / f"instances_{name}", work / f"change_{name}"
        c0 = _cpu()
        segment_and_track(rdir, poses_json, inst, seg, trk)
        res = compare(inst, poses_json, change, cmp)
        cpu = _cpu() - c0
        masks = {f.relative_to(change): read_mask(f) for f in change.glob("*/union/*.png")}
        changed = sum(int(m.sum()) for m in masks.values())
        line = (f"  {name:5s}: segment+compare CPU {cpu:.0f} s, changed IDs {res['changed']}, "
                f"instances {res['instances']}, changed pixels {changed}")
        if first is None:
            first = masks
        else:
            inter = sum((masks[k] & first[k]).sum() for k in first)
            union = sum((masks[k] | first[k]).sum() for k in first)
            line += f", union-mask IoU vs {next(iter(render_dirs))} {inter / max(union, 1):.3f}"
        print(line)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("results", type=Path, help="results/<scene>/ with fit/model.pt and "
                   "sequence/poses.json")
    p.add_argument("--out", type=Path, required=True, help="scratch folder (replaced)")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--batch", type=int, default=8)
    p.add_argument("--compression", default=None,
                   help="compression of the timed render (default: the render stage's)")
    p.add_argument("--previews", action="store_true", help="also write PNG previews")
    p.add_argument("--codecs", default="", help="comma-separated codecs to compare")
    p.add_argument("--dwa-level", type=float, default=45.0)
    p.add_argument("--segment", action="store_true",
                   help="run segment + compare on each codec's frames (slow)")
    args = p.parse_args(argv)

    from gdiff.device import set_threads
    from gdiff.log import setup_logging
    from gdiff.sequence import RenderOptions

    setup_logging(None)
    set_threads(args.threads)
    args.out.mkdir(parents=True, exist_ok=True)
    extra = {"compression": args.compression} if args.compression else {}
    render_once(args.results, args.out / "render",
                RenderOptions(batch=args.batch, previews=args.previews,
                              dwa_level=args.dwa_level, **extra))
    names = [c for c in args.codecs.split(",") if c]
    if names:
        dirs = codecs(args.out / "render", names, args.out / "codecs", args.dwa_level)
        if args.segment:
            segment_compare(dirs, args.results / "sequence" / "poses.json", args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
