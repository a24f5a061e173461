"""Render a fitted 4D Gaussian model at any camera pose and time.

Library::

    from gdiff.splat.model import load_model
    from gdiff.splat.render import render
    model = load_model("results/<scene>/fit/model.pt", device)
    out = render(model, cameras, t=1.0)       # cameras: list[gdiff.cameras.Camera], same size
    out["rgb"]    # [C, H, W, 3] sRGB-encoded values (not clipped; clip to [0, 1] to save)
    out["alpha"]  # [C, H, W, 1] accumulated opacity
    out["depth"]  # [C, H, W, 1] expected camera-frame z (world units) for "RGB+ED"

Cameras use OpenCV axes and pixel centres at +0.5 (:mod:`gdiff.cameras`); every camera is
rendered at its own width/height (cameras in one call must share the size).

Command line (``gdiff render``)::

    gdiff render --model fit/model.pt --cameras poses/cameras.json [--set eval_before] \
                 --t 0 [--t 1] --out DIR [--max-side 640] [--depth]
    gdiff render --model fit/model.pt --c2w pose.json|pose.npy|pose.txt --t 0.5 --out DIR

writes ``DIR/t<t>/NNNNN.png`` (and ``NNNNN_depth.npy`` with ``--depth``) plus
``DIR/index.json`` listing each frame's camera. With ``--c2w`` the intrinsics are the model's
training camera (``model.meta["camera"]``).
"""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

import numpy as np
import torch

from ..cameras import Camera, cameras_to_json, load_cameras, stack_for_render
from ..errors import GdiffError, SceneError
from ..io import atomic_path, write_image, write_json
from .gaussians import Gaussians
from .model import GaussianModel4D, load_model
from .rasterize import _pick_backend, camera_centers, rasterize
from .reflection import shade

log = logging.getLogger("gdiff.splat.render")


def _backgrounds(background, n: int, device, dtype) -> torch.Tensor | None:
    if background is None:
        return None
    bg = torch.as_tensor(background, device=device, dtype=dtype)
    if bg.dim() == 1:
        bg = bg[None].expand(n, bg.shape[0])
    return bg


def rasterize_gaussians(g: Gaussians, viewmats: torch.Tensor, Ks: torch.Tensor, width: int,
                        height: int, background=None, render_mode: str = "RGB",
                        backend: str = "auto", absgrad: bool = False):
    """Rasterise activated Gaussians into C cameras (thin wrapper over
    :func:`gdiff.splat.rasterize.rasterize` with SH colours, plus the mirror-direction term of
    :mod:`gdiff.splat.reflection` when ``g`` has one). ``viewmats`` [C,4,4] world-to-camera.
    Returns ``(colors [C,H,W,X], alphas [C,H,W,1], meta)``."""
    bg = _backgrounds(background, viewmats.shape[0], g.means.device, g.means.dtype)
    colors, degree = g.sh, g.sh_degree
    if g.environment is not None and render_mode not in ("D", "ED"):
        fused = _pick_backend(backend, g.means.device) == "cpp"
        colors, degree = shade(g, camera_centers(viewmats), fused=fused), None
    return rasterize(g.means, g.quats, g.scales, g.opacities, colors, viewmats, Ks, width, height,
                     sh_degree=degree, backgrounds=bg, render_mode=render_mode,
                     backend=backend, absgrad=absgrad)


def render(model: GaussianModel4D, cameras: list[Camera], t: float, background=None,
           render_mode: str = "RGB+ED", gaussians: Gaussians | None = None,
           chunk: int = 8, backend: str = "auto") -> dict[str, torch.Tensor]:
    """Render ``cameras`` at time ``t`` (see module docstring).

    Args:
        model: the 4D model (its device is used).
        cameras: cameras of one size (width, height).
        t: time in [0, 1] (0 = before, 1 = after).
        background: colour [3] in [0, 1] behind the Gaussians (None = black).
        render_mode: "RGB", "RGB+D" or "RGB+ED" (expected depth), or "D"/"ED" (depth only).
        gaussians: already evaluated ``model.at_time(t)`` to reuse (e.g. for many calls).
        chunk: cameras rasterised per call (bounds memory).
    Returns:
        dict with ``rgb`` [C,H,W,3] (unless depth-only), ``alpha`` [C,H,W,1] and, for depth
        modes, ``depth`` [C,H,W,1] (camera-frame z, world units). Differentiable when grad is on.
    """
    if not cameras:
        raise ValueError("render: no cameras given")
    sizes = {(c.width, c.height) for c in cameras}
    if len(sizes) != 1:
        raise ValueError(f"render: cameras in one call must share width/height, got {sizes}")
    width, height = sizes.pop()
    g = gaussians if gaussians is not None else model.at_time(t)
    viewmats, Ks = stack_for_render(cameras, device=g.means.device, dtype=g.means.dtype)
    colors, alphas = [], []
    for i in range(0, len(cameras), chunk):
        c, a, _ = rasterize_gaussians(g, viewmats[i:i + chunk], Ks[i:i + chunk], width, height,
                                      background, render_mode, backend)
        colors.append(c)
        alphas.append(a)
    colors = torch.cat(colors)
    out = {"alpha": torch.cat(alphas)}
    if render_mode in ("D", "ED"):
        out["depth"] = colors
    elif render_mode in ("RGB+D", "RGB+ED"):
        out["rgb"], out["depth"] = colors[..., :3], colors[..., 3:]
    else:
        out["rgb"] = colors
    return out


# -------------------------------------------------------------------- command line


def _read_poses(path: Path) -> np.ndarray:
    """4x4 camera-to-world matrices [M, 4, 4] from .json / .npy / text."""
    try:
        if path.suffix == ".npy":
            a = np.load(path)
        elif path.suffix == ".json":
            d = json.loads(path.read_text())
            if isinstance(d, dict):
                d = d.get("c2w", d.get("poses", d.get("frames")))
                if isinstance(d, list) and d and isinstance(d[0], dict):
                    d = [f["c2w"] for f in d]
            a = np.asarray(d, dtype=np.float64)
        else:
            a = np.loadtxt(path)
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise SceneError(f"{path}: cannot read camera-to-world matrices ({e})") from None
    a = np.asarray(a, dtype=np.float64)
    if a.ndim == 2 and a.shape[1] == 4 and a.shape[0] % 4 == 0:
        a = a.reshape(-1, 4, 4)
    elif a.ndim == 2 and a.shape == (3, 4):
        a = np.vstack([a, [0, 0, 0, 1]])[None]
    if a.ndim != 3 or a.shape[1:] != (4, 4) or not np.isfinite(a).all():
        raise SceneError(f"{path}: expected one or more finite 4x4 camera-to-world matrices "
                         "(OpenCV axes), as JSON, .npy or text rows")
    return a


def _t_name(t: float) -> str:
    return f"t{t:g}".replace(".", "p")


def render_main(argv=None) -> int:
    """``gdiff render``: render a fitted 4D model at given cameras and times."""
    from ..device import resolve_device

    p = argparse.ArgumentParser(prog="gdiff render", description=render_main.__doc__)
    p.add_argument("--model", required=True, help="fit/model.pt")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--cameras", help="a cameras.json (every frame, or those of --set)")
    src.add_argument("--c2w", help="camera-to-world matrices: .json, .npy or text (4 rows each)")
    p.add_argument("--set", action="append", default=None,
                   help="with --cameras: only frames of this set (repeatable)")
    p.add_argument("--t", type=float, action="append", required=True,
                   help="time in [0, 1] (repeatable); 0 = before, 1 = after")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--max-side", type=int, default=0,
                   help="downscale cameras so the longest side is at most this (0 = as given)")
    p.add_argument("--depth", action="store_true", help="also save depth maps (.npy, z)")
    p.add_argument("--device", default="auto")
    args = p.parse_args(argv)

    device = resolve_device(args.device)
    model = load_model(args.model, device)
    if args.cameras:
        cams = load_cameras(args.cameras)
        if args.set:
            cams = [c for c in cams if c.set in args.set]
            if not cams:
                raise GdiffError(f"{args.cameras}: no frames in set(s) {args.set}")
    else:
        ref = model.meta.get("camera")
        if not ref:
            raise GdiffError(f"{args.model}: has no training camera in its meta; "
                             "use --cameras with a cameras.json instead of --c2w")
        cams = [Camera(**ref, c2w=m) for m in _read_poses(Path(args.c2w))]
    if args.max_side:
        cams = [c.scaled(args.max_side / max(c.width, c.height))
                if max(c.width, c.height) > args.max_side else c for c in cams]
    for t in args.t:
        if not 0.0 <= t <= 1.0:
            raise GdiffError(f"--t {t}: time must lie in [0, 1]")
    out = Path(args.out)
    index = {"model": str(args.model), "times": args.t, "cameras": cameras_to_json(cams)}
    with torch.no_grad():
        for t in args.t:
            g = model.at_time(t)
            folder = out / _t_name(t)
            for i, cam in enumerate(cams):
                r = render(model, [cam], t, gaussians=g,
                           render_mode="RGB+ED" if args.depth else "RGB")
                write_image(folder / f"{i:05d}.png", r["rgb"][0].clamp(0, 1).cpu().numpy())
                if args.depth:
                    with atomic_path(folder / f"{i:05d}_depth.npy") as tmp:
                        np.save(tmp, r["depth"][0, ..., 0].cpu().numpy())
            log.info("rendered %d views at t=%g into %s", len(cams), t, folder)
    write_json(out / "index.json", index)
    print(f"rendered {len(cams)} view(s) x {len(args.t)} time(s) into {out}")
    return 0
