"""C-NeRF layout: two LLFF scenes, one before and one after the change.

Expected layout (``SRC``)::

    SRC/<before>/images/*.png|jpg     before images (LLFF: sorted by name)
    SRC/<before>/poses_bounds.npy     N x 17: [R | t | hwf] (3 x 5, row-major) + near, far
    SRC/<after>/images/*.png|jpg
    SRC/<after>/poses_bounds.npy

``<before>``/``<after>`` are ``before``/``after``, ``pre``/``post``, or two folders whose names
end in ``1`` and ``2`` (C-NeRF's own configs use ``chess1`` = pre, ``chess2`` = post). The
top-level naming is our reading of C-NeRF's configs (``datadir = ./data/chess1``,
``sequence = pre``); the per-folder layout is LLFF's.

Poses: LLFF stores camera-to-world ``[R | t]`` whose rotation columns are the camera's (down,
right, back) axes, plus ``hwf`` = (height, width, focal) of the full-resolution images; the
principal point is the image centre. They are converted to OpenCV c2w (right, down, forward)
and scaled to the actual image size. C-NeRF registers both sequences in one COLMAP run and
stores the joint poses in each folder (the before images take the first rows, the after images
the last rows); ``cameras.json`` is written only when the two files agree that way (one shared
world frame). Otherwise the poses stage registers the images itself.

Eval: C-NeRF's public data has no ground-truth change masks, so no ``eval/`` is written; add
``eval/before``, ``eval/after`` and ``eval/masks`` by hand to score a scene.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..cameras import Camera
from ..errors import SceneError
from ._common import SceneWriter, list_images, llff_to_opencv, need_dir

FORMAT = "cnerf"
SUMMARY = "C-NeRF: SRC/{before,after | pre,post | <name>1,<name>2}/{images/, poses_bounds.npy}"


def _pick_folders(src: Path) -> tuple[Path, Path]:
    for a, b in (("before", "after"), ("pre", "post")):
        if (src / a).is_dir() and (src / b).is_dir():
            return src / a, src / b
    subs = sorted(p for p in src.iterdir() if p.is_dir() and (p / "images").is_dir())
    ones = [p for p in subs if p.name.endswith("1")]
    twos = [p for p in subs if p.name.endswith("2")]
    if len(ones) == 1 and len(twos) == 1:
        return ones[0], twos[0]
    raise SceneError(f"{src}: expected two LLFF folders (before/ and after/, pre/ and post/, or "
                     "<name>1/ and <name>2/), each with images/ and poses_bounds.npy; found "
                     f"{', '.join(p.name for p in subs) or 'none'}")


def _load_poses(folder: Path) -> np.ndarray:
    path = folder / "poses_bounds.npy"
    if not path.is_file():
        raise SceneError(f"{path}: file not found; each LLFF folder needs poses_bounds.npy "
                         "(from LLFF's imgs2poses.py)")
    arr = np.load(path)
    if arr.ndim != 2 or arr.shape[1] != 17:
        raise SceneError(f"{path}: expected an N x 17 array (3x5 pose + near/far), got "
                         f"{arr.shape}")
    return arr


def _camera(row: np.ndarray) -> Camera:
    P = row[:15].reshape(3, 5)
    h, w, f = P[:, 4]
    return Camera(int(round(w)), int(round(h)), float(f), float(f), w / 2.0, h / 2.0,
                  llff_to_opencv(P[:, :4]))


def build(src: Path, w: SceneWriter) -> None:
    pre, post = _pick_folders(src)
    imgs = {s: list_images(need_dir(d / "images", f"{s}-change images", FORMAT))
            for s, d in (("before", pre), ("after", post))}
    arr = {"before": _load_poses(pre), "after": _load_poses(post)}
    n0, n1 = len(imgs["before"]), len(imgs["after"])
    for s, d in (("before", pre), ("after", post)):
        if len(arr[s]) < len(imgs[s]):
            raise SceneError(f"{d / 'poses_bounds.npy'}: {len(arr[s])} poses for "
                             f"{len(imgs[s])} images in {d / 'images'}")
    joint = (len(arr["before"]) == len(arr["after"]) == n0 + n1
             and np.allclose(arr["before"], arr["after"]))
    if joint:
        rows = {"before": arr["before"][:n0], "after": arr["after"][n0:]}
        w.note("poses_bounds.npy holds both sequences (one COLMAP run): before = first "
               f"{n0} rows, after = last {n1} rows")
    else:
        rows = None
        w.note("the before and after poses_bounds.npy are not one joint registration, so they "
               "may not share a world frame; cameras.json is not written and the poses stage "
               "registers all images together")
    for s in ("before", "after"):
        for i, p in enumerate(imgs[s]):
            w.add_image(s, p, _camera(rows[s][i]) if rows else None)
    w.note("no eval/ folder: C-NeRF's data has no ground-truth change masks")
