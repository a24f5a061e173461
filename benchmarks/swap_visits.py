"""A capture's two visits swapped: what was added becomes removed, on the same real photos.

Usage::

    python benchmarks/swap_visits.py scenes/living scenes/living_removed
    snakemake --cores 2 --config scenes=scenes/living_removed

Real captures with a known change are rare, and those at hand (``../shared/real``) only add
objects. Exchanging ``before/`` and ``after/`` turns every added object into a removed one,
with everything else (photos, poses, exposure, the robot's pose errors) as it was: a check of the
removal direction (the change shows in the t=0 map: the object rendered from the after poses)
on real photos.

The new scene holds symbolic links to the photos (``before/`` <- the old ``after/`` and back),
``cameras.json`` with each frame's ``set`` and ``time`` exchanged (the intrinsics, distortion
and poses as given), and ``eval/boxes.json`` if the scene has one: the boxes drawn on an after
photo (where the objects stand) carried to the before photo of the same name, the same waypoint
of the other visit (now the after photo, where the objects are gone), by the homography of the
two photos' SIFT matches (OpenCV, RANSAC). Photos of one place are not pixel-aligned on a
robot's two visits (tens of pixels); the homography takes the turn and leaves the parallax, so
the boxes stay as approximate as they were. A view whose photos give no homography is left
out, with a message.
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np

from gdiff.compare.lineup import sift_matches
from gdiff.errors import SceneError
from gdiff.evaluate import box_image, read_boxes
from gdiff.io import read_json, write_json

SETS = {"before": "after", "after": "before"}
#: matches (Lowe's ratio test) and RANSAC inliers a homography needs
MIN_INLIERS = 12


def carry_boxes(boxes: np.ndarray, src: np.ndarray, dst: np.ndarray) -> np.ndarray | None:
    """Boxes [K, 4] (x0, y0, x1, y1, pixels) of image ``src`` carried into image ``dst`` (grey
    uint8 [H, W] each) by the homography of their SIFT matches: the bounding box of each box's
    carried corners. None when the images give no homography (fewer than :data:`MIN_INLIERS`
    inliers)."""
    pa, pb = sift_matches(src, dst, n_features=4000, ratio=0.75)
    if len(pa) < MIN_INLIERS:
        return None
    cv2.setRNGSeed(0)
    H, inl = cv2.findHomography(pa, pb, cv2.RANSAC, 4.0)
    if H is None or int(inl.sum()) < MIN_INLIERS:
        return None
    x0, y0, x1, y1 = (boxes[:, i] for i in range(4))
    corners = np.stack([np.c_[x0, y0], np.c_[x1, y0], np.c_[x1, y1], np.c_[x0, y1]], 1)
    c = cv2.perspectiveTransform(corners.reshape(-1, 1, 2).astype(np.float64), H)
    c = c.reshape(-1, 4, 2)
    return np.c_[c[..., 0].min(1), c[..., 1].min(1), c[..., 0].max(1), c[..., 1].max(1)]


def swap_visits(scene: Path, out: Path) -> dict:
    """Write ``out`` as ``scene`` with its visits exchanged (module docstring). Returns
    ``{"photos": n, "boxes_carried": [view, ...], "boxes_dropped": [view, ...]}``."""
    scene, out = Path(scene), Path(out)
    for s in SETS:
        if not (scene / s).is_dir():
            raise SystemExit(f"{scene}: no {s}/ folder; a scene folder has before/ and after/")
    if (scene / "transforms.json").exists() and not (scene / "cameras.json").exists():
        raise SystemExit(f"{scene}: poses in transforms.json; swap_visits reads cameras.json "
                         "(gdiff import writes it) or no poses at all")
    if out.exists():
        raise SystemExit(f"{out} exists; give a new folder")
    cams, box_file = scene / "cameras.json", scene / "eval" / "boxes.json"
    try:  # read everything before writing anything
        data = read_json(cams) if cams.exists() else None
        boxes = read_boxes(box_file) if box_file.exists() else None
    except SceneError as e:
        raise SystemExit(str(e)) from None
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
    try:
        info = _write_swapped(scene, tmp, data, boxes)
        os.replace(tmp, out)  # the whole folder appears at once
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return info


def _write_swapped(scene: Path, out: Path, data: dict | None, boxes: dict | None) -> dict:
    """The body of :func:`swap_visits`, into the existing empty folder ``out``; ``data``: the
    scene's cameras.json (or None), ``boxes``: its :func:`read_boxes` (or None)."""
    n = 0
    for s, other in SETS.items():
        (out / other).mkdir(parents=True)
        for p in sorted((scene / s).iterdir()):
            if p.is_file():
                os.symlink(p.resolve(), out / other / p.name)
                n += 1
    if data is not None:
        for fr in data.get("frames", []):
            top, _, rest = str(fr.get("image", "")).partition("/")
            if top in SETS:
                fr["image"] = f"{SETS[top]}/{rest}"
                fr["set"] = SETS[top]
                fr["time"] = 1 if SETS[top] == "after" else 0
        write_json(out / "cameras.json", data)
    info = {"photos": n, "boxes_carried": [], "boxes_dropped": []}
    if boxes is not None:
        carried = {}
        for name, b in boxes.items():
            found = box_image(scene, name, ())  # the scene's photo the entry names
            src = scene / found[1] if found else None
            if src is None or src.parent.name != "after":
                info["boxes_dropped"].append(name)
                continue
            key = f"after/{src.name}"
            if len(b) == 0:
                carried[key] = []
                continue
            dst = scene / "before" / src.name
            moved = None
            if dst.is_file():
                moved = carry_boxes(b, cv2.imread(str(src), cv2.IMREAD_GRAYSCALE),
                                    cv2.imread(str(dst), cv2.IMREAD_GRAYSCALE))
            if moved is None:
                info["boxes_dropped"].append(name)
                continue
            carried[key] = [[round(float(v), 1) for v in row] for row in moved]
            info["boxes_carried"].append(key)
        (out / "eval").mkdir(exist_ok=True)
        write_json(out / "eval" / "boxes.json", carried)
    return info


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scene", type=Path, help="scene folder (before/, after/, cameras.json, "
                    "eval/boxes.json)")
    ap.add_argument("out", type=Path, help="new scene folder")
    a = ap.parse_args(argv)
    info = swap_visits(a.scene, a.out)
    print(f"{a.out}: {info['photos']} photos linked with the visits exchanged; boxes carried "
          f"at {len(info['boxes_carried'])} views" + (
              f"; left out (no after photo or no homography): {', '.join(info['boxes_dropped'])}"
              if info["boxes_dropped"] else ""))
    return 0


if __name__ == "__main__":
    sys.exit(main())
