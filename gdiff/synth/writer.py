"""Writing a rendered scene folder (the layout of the shared scenes) and the CLI."""

from __future__ import annotations

import argparse
import dataclasses
import logging
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from ..errors import GdiffError
from ..io import write_image, write_json, write_mask
from ..log import progress
from .build import build_scene
from .model import STATES
from .presets import PRESETS, SynthOptions, SynthPreset, get_preset
from .scene import SynthScene

log = logging.getLogger("gdiff.synth")

CONVENTION = (
    "c2w is the 4x4 camera-to-world matrix in the OpenCV camera convention (camera x right, "
    "y down, z forward/viewing direction). World frame: z up, metres, floor at z=0. Pixel "
    "coordinates (u right, v down) have their origin at the top-left CORNER of the image, i.e. "
    "the centre of pixel (col i, row j) is (i+0.5, j+0.5) (COLMAP/NeRF convention). No lens "
    "distortion.")

MASK_DEFINITION = (
    "union of the visible pixels of all changed objects (removed/moved/replaced objects in the "
    "BEFORE render, added/moved/replacement objects in the AFTER render) at the eval "
    "viewpoint, one ray through each pixel centre; occlusion by other geometry is respected; "
    "shadows of changed objects are NOT included; lighting differences are NOT changes")


def _gt_cameras(scene: SynthScene, name: str) -> dict:
    intr = scene.intrinsics()
    K = [[intr["fx"], 0.0, intr["cx"]], [0.0, intr["fy"], intr["cy"]], [0.0, 0.0, 1.0]]
    frames = []
    for st in STATES:
        for i, cam in enumerate(scene.cameras(st)):
            frames.append({"file": cam.image, "split": "train", "state": st, "index": i,
                           "c2w": cam.c2w.tolist()})
    views = []
    for i, cam in enumerate(scene.cameras("eval")):
        mask = f"eval/masks/{i:03d}.png"
        for st in STATES:
            frames.append({"file": f"eval/{st}/{i:03d}.png", "split": "eval", "state": st,
                           "index": i, "c2w": cam.c2w.tolist(), "mask": mask})
        views.append({"index": i, "before": f"eval/before/{i:03d}.png",
                      "after": f"eval/after/{i:03d}.png", "mask": mask,
                      "c2w": cam.c2w.tolist()})
    return {"scene": name, "convention": CONVENTION,
            "intrinsics": {"model": "PINHOLE", **intr, "K": K},
            "frames": frames, "eval_views": views}


def _check_target(out: Path, overwrite: bool) -> None:
    if out.exists() and not out.is_dir():
        raise GdiffError(f"{out}: exists and is not a folder; choose another output path")
    if out.is_dir() and any(out.iterdir()) and not overwrite:
        raise GdiffError(f"{out}: folder exists and is not empty; choose another path or pass "
                         "overwrite=True (--overwrite) to replace it")


def make_scene(out_dir: str | os.PathLike, preset: str | SynthPreset = "tiny", seed: int = 0,
               overwrite: bool = False) -> Path:
    """Render the scene of ``preset``/``seed`` into the gdiff scene folder ``out_dir``.

    The folder is rendered into a temporary sibling and renamed into place when complete, so
    ``out_dir`` is either absent/unchanged or complete. An existing non-empty ``out_dir`` is a
    :class:`GdiffError` unless ``overwrite`` is true. Returns the folder path.
    """
    p = get_preset(preset)
    out = Path(out_dir)
    _check_target(out, overwrite)
    out.parent.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    scene = build_scene(p, seed)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.tmp-", dir=out.parent))
    try:
        times = _render_folder(scene, tmp)
        meta = {"scene": out.name, "seed": int(seed), "preset": p.name,
                "description": p.description, "generator": "gdiff.synth",
                "preset_settings": dataclasses.asdict(p), **scene.meta(),
                "render": {"engine": "gdiff.synth ray tracer (numpy)",
                           "resolution": [p.width, p.height],
                           "supersample": p.supersample,
                           "shading": "Lambertian albedo x (hemispherical ambient + sun with "
                                      "cast shadows, soft sun sampled over its disc); "
                                      "tone curve 1-exp(-x); sRGB 8-bit",
                           "mask_render": "1 ray per pixel centre, object ids"},
                "gt_mask": {"definition": MASK_DEFINITION, "per_view": times.pop("per_view")}}
        write_json(tmp / "gt_cameras.json", _gt_cameras(scene, out.name))
        write_json(tmp / "meta.json", meta)
        total = time.perf_counter() - t_start
        write_json(tmp / "timing.json", {"scene": out.name, "preset": p.name,
                                         "total_seconds": round(total, 3), **times})
        _check_target(out, overwrite)
        if out.exists():
            old = Path(tempfile.mkdtemp(prefix=f".{out.name}.old-", dir=out.parent))
            os.replace(out, old / out.name)
            os.replace(tmp, out)
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.replace(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    log.info("wrote synthetic scene %s (preset %s, seed %d) in %.1f s", out, p.name, seed,
             time.perf_counter() - t_start)
    return out


def _render_folder(scene: SynthScene, root: Path) -> dict:
    """Render every image and mask of ``scene`` into ``root``; returns timing + mask counts."""
    p = scene.preset
    jobs = [(st, cam) for st in STATES for cam in scene.cameras(st)]
    n_total = len(jobs) + 2 * p.n_eval
    rgb_times = []
    per_view = []
    bar = progress(total=n_total, desc=f"synth {p.name}")
    try:
        for st, cam in jobs:
            t0 = time.perf_counter()
            write_image(root / cam.image, scene.render(cam, st)["rgb"])
            rgb_times.append(time.perf_counter() - t0)
            bar.update(1)
        for i, cam in enumerate(scene.cameras("eval")):
            masks = {}
            for st in STATES:
                t0 = time.perf_counter()
                r = scene.render(cam, st)
                write_image(root / "eval" / st / f"{i:03d}.png", r["rgb"])
                rgb_times.append(time.perf_counter() - t0)
                masks[st] = r["changed"]
                bar.update(1)
            union = masks["before"] | masks["after"]
            write_mask(root / "eval" / "masks" / f"{i:03d}.png", union)
            write_mask(root / "eval" / "mask_before" / f"{i:03d}.png", masks["before"])
            write_mask(root / "eval" / "mask_after" / f"{i:03d}.png", masks["after"])
            per_view.append({"index": i, "changed_pixels": int(union.sum()),
                             "before_pixels": int(masks["before"].sum()),
                             "after_pixels": int(masks["after"].sum()),
                             "fraction": round(float(union.mean()), 5)})
    finally:
        bar.close()
    rt = np.asarray(rgb_times)
    return {"n_rgb_images": len(rt), "rgb_mean_seconds": round(float(rt.mean()), 4),
            "rgb_min_seconds": round(float(rt.min()), 4),
            "rgb_max_seconds": round(float(rt.max()), 4),
            "resolution": [p.width, p.height], "supersample": p.supersample,
            "per_view": per_view}


def main(argv: list[str] | None = None) -> int:
    """``gdiff synth OUT --preset NAME [--seed N] [--n-before N] [--n-after N] [--n-eval N]
    [--width W --height H] [--overwrite]``; returns the exit code."""
    ap = argparse.ArgumentParser(
        prog="gdiff synth",
        description="Render a procedural before/after scene with ground-truth change masks "
                    "into a gdiff scene folder.")
    ap.add_argument("out", help="output scene folder")
    ap.add_argument("--preset", default="tiny", choices=sorted(PRESETS),
                    help="scene preset (default: tiny)")
    ap.add_argument("--seed", type=int, default=0, help="random seed (default: 0)")
    for name, what in (("n_before", "before photos"), ("n_after", "after photos"),
                       ("n_eval", "eval views"), ("width", "image width in pixels"),
                       ("height", "image height in pixels")):
        ap.add_argument("--" + name.replace("_", "-"), type=int, default=None,
                        help=f"{what} (default: the preset's)")
    ap.add_argument("--overwrite", action="store_true",
                    help="replace the output folder if it exists and is not empty")
    args = ap.parse_args(argv)
    try:
        preset = SynthOptions(preset=args.preset, n_before=args.n_before, n_after=args.n_after,
                              n_eval=args.n_eval, width=args.width,
                              height=args.height).to_preset()
        out = make_scene(args.out, preset, args.seed, args.overwrite)
    except GdiffError as e:
        print(f"gdiff synth: error: {e}", file=sys.stderr)
        return 1
    print(out)
    return 0
