"""CCS3D layout (synthetic Blender scenes of SCaR-3D, Zhou et al.), as in its README::

    SRC = <dataset>/<scene>/
        images/                all images (the COLMAP model's image folder)
        train-pre/             pre-change training images
        train-post/            post-change training images
        test-pre/              pre-change test images
        test-post/             post-change test images
        gt-pre-mask/           ground-truth change masks of the pre-change test images
        gt-post-mask/          ground-truth change masks of the post-change test images
        sparse/0/ (or sparse/) COLMAP model of all images (known poses)
        <scene>.db             COLMAP database (ignored)

Masks are paired with test images by file stem, else by the last number in the name (the
authors' evaluation reads ``gt_<n>.png`` and matches it to the image numbered ``n``).

Mapping to gdiff eval views (the GT convention is the union of changed objects visible before
*or* after at one viewpoint):

* a pre and a post test image with the same number whose cameras coincide (same centre within
  1e-4 of the scene size, rotation within 0.1 degree; needs ``sparse/``) form one eval view
  ``NAME``: ``eval/before``, ``eval/after``, ``eval/mask_before`` (= gt-pre-mask),
  ``eval/mask_after`` (= gt-post-mask) and ``eval/masks`` = their union;
* otherwise each test image is a single-sided view, ``post_NAME`` (``eval/after`` + its
  gt-post-mask) or ``pre_NAME`` (``eval/before`` + its gt-pre-mask). Its mask is the dataset's
  mask for that image, which may mark only the objects present in that state (a guess: the
  README does not say), so such scores are comparable with the dataset's own protocol (it
  scores ``test-post`` against ``gt-post-mask``) rather than with paired views.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..cameras import Camera
from ..io import read_mask
from ._common import (SceneWriter, first_dir, list_images, need_dir, read_colmap,
                      trailing_index)
from .paslcd import pair_by_name

FORMAT = "ccs3d"
SUMMARY = ("CCS3D: SRC/{train-pre/, train-post/, test-pre/, test-post/, gt-pre-mask/, "
           "gt-post-mask/, sparse/[0/]}")


def _same_view(a: Camera | None, b: Camera | None, scale: float) -> bool:
    if a is None or b is None:
        return False
    if np.linalg.norm(a.center - b.center) > 1e-4 * scale:
        return False
    R = a.c2w[:3, :3].T @ b.c2w[:3, :3]
    angle = np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1.0, 1.0)))
    return angle < 0.1 and abs(a.fx - b.fx) < 1e-3 * a.fx


def build(src: Path, w: SceneWriter) -> None:
    d = {k: need_dir(src / k, what, FORMAT) for k, what in (
        ("train-pre", "the pre-change training images"),
        ("train-post", "the post-change training images"))}
    cams: dict[str, Camera] = {}
    sparse = first_dir(src, ("sparse/0", "sparse"), "", FORMAT, required=False)
    if sparse is not None and any(sparse.glob("images.*")):
        cams = read_colmap(sparse)
    else:
        w.note("no sparse/ COLMAP model: no known poses")
    for p in list_images(d["train-pre"]):
        w.add_image("before", p, cams.get(p.name))
    for p in list_images(d["train-post"]):
        w.add_image("after", p, cams.get(p.name))

    sides = {}
    for side, tdir, mdir in (("pre", "test-pre", "gt-pre-mask"),
                             ("post", "test-post", "gt-post-mask")):
        if (src / tdir).is_dir() and (src / mdir).is_dir():
            imgs = list_images(need_dir(src / tdir, f"the {side}-change test images", FORMAT))
            masks = list_images(need_dir(src / mdir, f"the {side}-change test masks", FORMAT))
            sides[side] = pair_by_name(imgs, masks, src / tdir)
        elif (src / tdir).is_dir() or (src / mdir).is_dir():
            w.note(f"{tdir}/ and {mdir}/ must both exist to make eval views; skipped")
    if not sides:
        w.note("no test images with masks: no eval/ folder")
        return
    centres = np.array([c.center for c in cams.values()]) if cams else np.zeros((1, 3))
    scale = float(np.linalg.norm(centres.max(0) - centres.min(0))) or 1.0
    pre = {trailing_index(p.name): (p, m) for p, m in sides.get("pre", {}).items()}
    paired = 0
    for img, mask in sorted(sides.get("post", {}).items()):
        k = trailing_index(img.name)
        if k in pre and _same_view(cams.get(pre[k][0].name), cams.get(img.name), scale):
            pimg, pmask = pre.pop(k)
            name = img.stem
            w.add_image("eval_before", pimg, cams.get(pimg.name), name=name)
            w.add_image("eval_after", img, cams.get(img.name), name=name)
            mb, ma = read_mask(pmask), read_mask(mask)
            w.add_mask("mask_before", name, mb)
            w.add_mask("mask_after", name, ma)
            w.add_mask("masks", name, mb | ma)
            paired += 1
        else:
            name = f"post_{img.stem}"
            w.add_image("eval_after", img, cams.get(img.name), name=name)
            w.add_mask("masks", name, mask)
    for img, mask in pre.values():
        name = f"pre_{img.stem}"
        w.add_image("eval_before", img, cams.get(img.name), name=name)
        w.add_mask("masks", name, mask)
    n_single = sum(len(s) for s in sides.values()) - 2 * paired
    w.note(f"{paired} paired eval view(s) (same camera before and after, mask = union of "
           f"gt-pre-mask and gt-post-mask) and {n_single} single-sided view(s)")
