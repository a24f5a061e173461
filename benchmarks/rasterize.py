"""Benchmark the Gaussian rasterizer on CPU: gdiff backends vs a plain packed torch baseline.

For each size (default 160x120 with 20k Gaussians and 320x240 with 100k) it prints, per method,
forward and forward+backward wall time (best of ``--repeats``: on a shared machine other
processes only ever add time), Gaussian-pixel pairs per
second (candidate pairs = pixels inside the visible Gaussians' 3-sigma boxes, the same count
for every method) and the peak resident memory the call added (VmHWM after a peak reset). The images of every method are
compared with the baseline's (max abs difference).

Methods:
* ``gdiff-cpp``: ``rasterize(backend="cpp")`` (compiled kernel, tiles, early termination).
* ``gdiff-torch``: ``rasterize(backend="torch")`` (the pure torch backend).
* ``baseline``: the same projection, then every candidate pair is kept, sorted by pixel,
  transmittance by cumulative sum, scatter with ``index_add``; no pair filtering and no early
  stop (the alpha and transmittance rules only zero the weights, so the image is the same).

Timings run in one subprocess per size with the methods alternating; peak memory
(VmHWM growth during one forward+backward) in a fresh subprocess per method.

    python benchmarks/rasterize.py [--threads 2] [--repeats 3] [--sizes 160x120:20000,...]
"""

from __future__ import annotations

import argparse
import json
import math
import multiprocessing as mp
import os
import resource
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # gdiff from this checkout


def make_scene(n: int, width: int, height: int, seed: int = 0):
    """Random Gaussians in a 2 m cube 3 m in front of one camera (60 degree horizontal FOV).

    Scales are log-uniform in [0.004, 0.04] m (1-10 px std at 320 px), opacities in [0.05, 1],
    RGB colours uniform: a cloud with a few hundred overlapping layers at the centre.
    """
    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=g) - 0.5) * 2.0
    means[:, 2] += 3.0
    quats = torch.randn(n, 4, generator=g)
    scales = torch.exp(torch.rand(n, 3, generator=g) * math.log(10.0) + math.log(0.004))
    opacities = torch.rand(n, generator=g) * 0.95 + 0.05
    colors = torch.rand(n, 3, generator=g)
    f = 0.5 * width / math.tan(math.radians(30))
    Ks = torch.tensor([[[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]]])
    return means, quats, scales, opacities, colors, torch.eye(4)[None], Ks


def baseline_composite(means2d, conics, colors, opacities, extents, visible, depths, W, H):
    """Plain packed compositing: all candidate pairs, sort by (pixel, depth), log-cumsum
    transmittance, index_add. The 3DGS rules (ellipse, alpha >= 1/255, T cutoff) zero weights
    but never shrink the work."""
    from gdiff.splat.rasterize import _pixel_pairs, _sigma

    C, N, D = colors.shape
    outs, alphas = [], []
    for ci in range(C):
        vis = visible[ci].nonzero(as_tuple=True)[0]
        gids = vis[torch.argsort(depths[ci, vis].detach(), stable=True)]
        src, px, py = _pixel_pairs(means2d[ci, gids].detach(), extents[ci, gids], W, H)
        pix = py * W + px
        key, perm = torch.sort(pix * max(len(gids), 1) + src)
        src, pix, px, py = src[perm], pix[perm], px[perm], py[perm]
        g = gids[src]
        sig = _sigma(means2d[ci, g], conics[ci, g], px, py)
        alpha = torch.clamp_max(opacities[ci, g] * torch.exp(-sig), 0.99)
        alpha = torch.where((sig <= 4.5) & (sig >= 0) & (alpha >= 1 / 255), alpha,
                            torch.zeros_like(alpha))
        logt = torch.log1p(-alpha.double())
        csum = torch.cumsum(logt, 0)
        excl = csum - logt
        _, counts = torch.unique_consecutive(pix, return_counts=True)
        start = torch.cumsum(counts, 0) - counts
        T = torch.exp(excl - torch.repeat_interleave(excl[start], counts, output_size=len(pix)))
        live = (T * (1 - alpha.double())) > 1e-4
        w = torch.where(live, alpha * T.to(alpha.dtype), torch.zeros_like(alpha))
        outs.append(colors.new_zeros(H * W, D).index_add(0, pix, colors[ci, g] * w[:, None])
                    .reshape(H, W, D))
        alphas.append(w.new_zeros(H * W).index_add(0, pix, w).reshape(H, W, 1))
    return torch.stack(outs), torch.stack(alphas)


def render(method, scene, W, H):
    """One call of ``method`` -> (image, alpha) with autograd graph."""
    from gdiff.splat import rasterize as R

    means, quats, scales, opac, colors, vm, Ks = scene
    if method == "gdiff-cpp":
        out, alpha, _ = R.rasterize(means, quats, scales, opac, colors, vm, Ks, W, H,
                                    backend="cpp")
        return out, alpha
    if method == "gdiff-torch":
        out, alpha, _ = R.rasterize(means, quats, scales, opac, colors, vm, Ks, W, H,
                                    backend="torch")
        return out, alpha
    proj = R.project_gaussians(means, R.covariance_3d(quats, scales), vm, Ks, W, H)
    feats = colors[None].expand(1, *colors.shape)
    return baseline_composite(proj["means2d"], proj["conics"], feats,
                              opac[None].expand(1, -1), proj["extents"], proj["visible"],
                              proj["depths"], W, H)


def count_pairs(scene, W, H):
    """(candidate pairs in 3-sigma boxes, pairs that contribute to the image)."""
    from gdiff.splat import rasterize as R

    means, quats, scales, opac, colors, vm, Ks = scene
    with torch.no_grad():
        proj = R.project_gaussians(means, R.covariance_3d(quats, scales), vm, Ks, W, H)
        vis = proj["visible"][0]
        m, e = proj["means2d"][0, vis], proj["extents"][0, vis]
        src, px, py = R._pixel_pairs(m, e, W, H)
        sig = R._sigma(m[src], proj["conics"][0, vis][src], px, py)
        alpha = torch.clamp_max(opac[vis][src] * torch.exp(-sig), 0.99)
        useful = int(((sig <= 4.5) & (alpha >= 1 / 255)).sum())
    return len(src), useful


def _timings(methods, W, H, n, repeats, threads, q):
    """Best-of-``repeats`` fwd and fwd+bwd times; methods alternate round-robin so that a
    burst of load from other processes hits all of them alike."""
    torch.set_num_threads(threads)
    scene = make_scene(n, W, H)
    params = [t.clone().requires_grad_(True) for t in scene[:5]]
    scene = (*params, *scene[5:])
    if "gdiff-cpp" in methods:
        from gdiff.splat import csrc
        csrc.load(required=True)
    weights = torch.rand(1, H, W, 3, generator=torch.Generator().manual_seed(1))
    fwd = {m: [] for m in methods}
    both = {m: [] for m in methods}
    images = {}
    for m in methods:
        with torch.no_grad():
            images[m] = render(m, scene, W, H)[0]  # warm-up
    for _ in range(repeats):
        for m in methods:
            t0 = time.perf_counter()
            with torch.no_grad():
                render(m, scene, W, H)
            fwd[m].append(time.perf_counter() - t0)
            for p in params:
                p.grad = None
            t0 = time.perf_counter()
            out, a = render(m, scene, W, H)
            ((out * weights).sum() + a.sum()).backward()
            both[m].append(time.perf_counter() - t0)
    ref = images.get("baseline")
    q.put({m: dict(fwd=min(fwd[m]), both=min(both[m]),
                   diff=float((images[m] - ref).abs().max()) if ref is not None else float("nan"))
           for m in methods})


def _peak(method, W, H, n, threads, q):
    """Peak resident memory added by one forward+backward call (MiB)."""
    torch.set_num_threads(threads)
    scene = make_scene(n, W, H)
    params = [t.clone().requires_grad_(True) for t in scene[:5]]
    scene = (*params, *scene[5:])
    if method == "gdiff-cpp":
        from gdiff.splat import csrc
        csrc.load(required=True)
    rss0 = _status_kib("VmRSS")
    try:  # reset the peak (VmHWM) to the current RSS so imports do not count (Linux >= 4.0)
        with open("/proc/self/clear_refs", "w") as fh:
            fh.write("5")
    except OSError:
        pass
    out, a = render(method, scene, W, H)
    (out.sum() + a.sum()).backward()
    q.put((_status_kib("VmHWM") - rss0) / 1024.0)


def _status_kib(key):
    """A memory figure (KiB) from /proc/self/status, e.g. VmRSS or VmHWM (peak)."""
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith(key + ":"):
                return int(line.split()[1])
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss


def in_subprocess(fn, *args):
    ctx = mp.get_context("spawn")
    q = ctx.Queue()
    p = ctx.Process(target=fn, args=(*args, q))
    p.start()
    res = q.get()
    p.join()
    return res


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--sizes", default="160x120:20000,320x240:100000",
                    help="comma-separated WxH:N")
    ap.add_argument("--methods", default="gdiff-cpp,gdiff-torch,baseline")
    ap.add_argument("--json", help="also write the results to this JSON file")
    args = ap.parse_args(argv)
    methods = args.methods.split(",")
    print(f"torch {torch.__version__}, {args.threads} threads, {os.cpu_count()} CPUs, "
          f"load average {os.getloadavg()[0]:.1f}, best of {args.repeats}")
    rows = []
    for spec in args.sizes.split(","):
        wh, n = spec.split(":")
        W, H = (int(v) for v in wh.split("x"))
        n = int(n)
        cand, useful = count_pairs(make_scene(n, W, H), W, H)
        print(f"\n{W}x{H}, {n} Gaussians: {cand / 1e6:.2f} M candidate pairs, "
              f"{useful / 1e6:.2f} M inside the ellipse with alpha >= 1/255")
        print(f"{'method':<12} {'fwd s':>8} {'fwd+bwd s':>10} {'fwd Mpair/s':>12} "
              f"{'f+b Mpair/s':>12} {'peak MiB':>9} {'max |diff|':>11} {'f+b speedup':>12}")
        res = in_subprocess(_timings, methods, W, H, n, args.repeats, args.threads)
        for m in methods:
            r = res[m]
            r["peak_mib"] = in_subprocess(_peak, m, W, H, n, args.threads)
            diff = r["diff"]
            speed = res["baseline"]["both"] / r["both"] if "baseline" in res else float("nan")
            print(f"{m:<12} {r['fwd']:8.3f} {r['both']:10.3f} {cand / r['fwd'] / 1e6:12.2f} "
                  f"{cand / r['both'] / 1e6:12.2f} {r['peak_mib']:9.0f} {diff:11.2e} "
                  f"{speed:11.1f}x")
            rows.append(dict(width=W, height=H, n=n, method=m, fwd_s=r["fwd"],
                             fwd_bwd_s=r["both"], pairs=cand, useful_pairs=useful,
                             peak_mib=r["peak_mib"], max_abs_diff_vs_baseline=diff,
                             fwd_bwd_speedup_vs_baseline=speed))
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(rows, fh, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
