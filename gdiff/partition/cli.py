"""Command line ``gdiff change-map``: render a change map from a partition model at any pose.

Conventions: see :mod:`gdiff.partition`.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from ..cameras import Camera, load_cameras
from ..errors import GdiffError
from ..io import atomic_path, write_image, write_mask
from .export import overlay
from .model import load_partition_model, render_change_map


def _read_c2w(path) -> np.ndarray:
    """A 4x4 (or 3x4) camera-to-world matrix from ..npy, .json (a matrix, or an object with
    ``c2w`` / ``transform_matrix``) or a text file of 12/16 numbers."""
    path = Path(path)
    try:
        if path.suffix == ".npy":
            a = np.load(path)
        elif path.suffix == ".json":
            d = json.loads(path.read_text())
            a = d.get("c2w", d.get("transform_matrix")) if isinstance(d, dict) else d
            a = np.asarray(a, dtype=np.float64)
        else:
            a = np.loadtxt(path, dtype=np.float64)
    except (OSError, ValueError, TypeError) as e:
        raise GdiffError(f"{path}: cannot read a camera-to-world matrix ({e}); give a .npy, "
                         ".json or text file with a 4x4 matrix") from None
    return _as_c2w(np.asarray(a, dtype=np.float64), str(path))


def _as_c2w(a: np.ndarray, source: str) -> np.ndarray:
    a = a.reshape(-1)
    if a.size not in (12, 16) or not np.isfinite(a).all():
        raise GdiffError(f"{source}: expected 12 or 16 finite numbers (a 3x4 or 4x4 "
                         f"camera-to-world matrix, row-major), got {a.size}")
    m = a.reshape(-1, 4)
    return np.vstack([m, [0, 0, 0, 1]]) if len(m) == 3 else m


def pose_from_values(values: list[float]) -> np.ndarray:
    """c2w [4, 4] from 7 numbers ``x y z qw qx qy qz`` (camera centre in world units and the
    camera-to-world rotation as a wxyz quaternion, OpenCV camera axes) or 12/16 numbers (a
    row-major 3x4/4x4 c2w matrix)."""
    v = np.asarray(values, dtype=np.float64)
    if v.size == 7:
        q = v[3:]
        if not np.isfinite(v).all() or np.linalg.norm(q) < 1e-12:
            raise GdiffError("--pose: the quaternion qw qx qy qz must be finite and non-zero")
        c2w = np.eye(4)
        c2w[:3, :3] = Rotation.from_quat(q, scalar_first=True).as_matrix()
        c2w[:3, 3] = v[:3]
        return c2w
    return _as_c2w(v, "--pose")


def change_map_main(argv=None) -> int:
    """``gdiff change-map``: render a change map from a partition model at any camera pose."""
    p = argparse.ArgumentParser(
        prog="gdiff change-map", description=change_map_main.__doc__,
        epilog="Camera axes are OpenCV (x right, y down, z forward); c2w is camera-to-world. "
               "Without intrinsics options the model's training intrinsics are used.")
    p.add_argument("--model", required=True, help="results/<scene>/partition/model.pt")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--c2w", metavar="FILE",
                     help="4x4 camera-to-world matrix (.npy, .json or text)")
    src.add_argument("--pose", nargs="+", type=float, metavar="V",
                     help="x y z qw qx qy qz (centre + c2w rotation), or 12/16 matrix numbers")
    src.add_argument("--cameras", metavar="JSON",
                     help="a cameras.json; with --frame, render that frame's camera")
    p.add_argument("--frame", default="0",
                   help="with --cameras: frame index or image path (default 0)")
    p.add_argument("--t", type=float, default=None,
                   help="time: 0 (before) or 1 (after); omitted = union of t=0 and t=1 (the "
                        "t=0 map where the two times render differently: "
                        "partition.before_gate)")
    p.add_argument("--out", required=True, help="binary change mask PNG (255 = changed)")
    p.add_argument("--prob-out", help="also write the change probability (PNG x255, or .npy)")
    p.add_argument("--image-out", help="also write the rendered image (PNG)")
    p.add_argument("--overlay-out", help="also write the image with the mask overlaid (PNG)")
    for k in ("width", "height"):
        p.add_argument(f"--{k}", type=int, help=f"image {k} (px)")
    for k in ("fx", "fy", "cx", "cy"):
        p.add_argument(f"--{k}", type=float, help=f"intrinsic {k} (px, pixel centres at +0.5)")
    p.add_argument("--device", default="auto", help="auto, cpu or cuda")
    args = p.parse_args(argv)

    pm = load_partition_model(args.model, args.device)
    cam = pm.camera
    if args.cameras:
        cams = load_cameras(args.cameras)
        sel = [c for c in cams if c.image == args.frame]
        if not sel:
            try:
                sel = [cams[int(args.frame)]]
            except (ValueError, IndexError):
                raise GdiffError(f"{args.cameras}: no frame {args.frame!r} (give an index "
                                 f"0..{len(cams) - 1} or an image path)") from None
        cam = sel[0]
    else:
        c2w = _read_c2w(args.c2w) if args.c2w else pose_from_values(args.pose)
        cam = cam.with_pose(c2w)
    if args.width or args.height:
        if not (args.width and args.height):
            raise GdiffError("--width and --height go together")
        s = args.width / cam.width
        cam = Camera(args.width, args.height, cam.fx * s, cam.fy * args.height / cam.height,
                     cam.cx * s, cam.cy * args.height / cam.height, cam.c2w)
    over = {k: getattr(args, k) for k in ("fx", "fy", "cx", "cy") if getattr(args, k)}
    if over:
        cam = Camera(cam.width, cam.height, **{**{k: getattr(cam, k) for k in
                                                   ("fx", "fy", "cx", "cy")}, **over},
                     c2w=cam.c2w)
    if args.t is not None and not 0.0 <= args.t <= 1.0:
        raise GdiffError(f"--t must lie in [0, 1] (0 = before, 1 = after), got {args.t}")
    want_img = bool(args.image_out or args.overlay_out)
    r = render_change_map(pm, cam, args.t, with_image=want_img)
    write_mask(args.out, r["mask"])
    if args.prob_out:
        if args.prob_out.endswith(".npy"):
            with atomic_path(args.prob_out) as tmp:
                np.save(tmp, r["prob"])
        else:
            write_image(args.prob_out, np.repeat(r["prob"][..., None], 3, axis=2))
    if args.image_out:
        write_image(args.image_out, r["image"])
    if args.overlay_out:
        write_image(args.overlay_out, overlay(r["image"], r["mask"]))
    frac = float(r["mask"].mean())
    print(f"{args.out}: {cam.width}x{cam.height}, t={'union' if args.t is None else args.t}, "
          f"{100 * frac:.2f}% changed")
    return 0
