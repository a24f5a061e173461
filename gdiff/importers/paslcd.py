"""PASLCD layout (Galappaththige et al., "Multi-View Pose-Agnostic Change Localization with
Zero Labels"). One gdiff scene per ``<Scene>/<Instance_k>`` folder::

    SRC = <Scene>/Instance_<k>/
        input_orig/ (or images/)             reference (pre-change) images
        input_orig_test/ (or images_test/)   inference (post-change) images, 25 per scene
        gt_mask/                             ground-truth masks of the inference images
        sparse/0/                            optional COLMAP model (known poses)
        changes.txt                          list of changes (copied into import.json)

The folder names ``input_orig``, ``input_orig_test``, ``gt_mask`` and ``changes.txt`` are those of
the dataset's README; ``images``, ``images_test`` and ``sparse/0`` are accepted for the
COLMAP-processed release (their names are our guess). Instance 1 has the inference set's
lighting, Instance 2 a different lighting.

Mapping to a gdiff scene:

* ``before/`` = reference images; ``after/`` = all inference images;
* PASLCD evaluates at the inference views themselves, so each inference image with a mask
  (paired by file stem, else by the number in the name) is also an eval view:
  ``eval/after/NAME`` + ``eval/masks/NAME``, with no ``eval/before`` (there is no pre-change
  image at those viewpoints; two-image methods use the model's render at t = 0). Scores are
  therefore in-sample for the post-change state, as in the dataset's own protocol.
* ``cameras.json`` from ``sparse/0`` (matched by image file name) when it covers every image.
"""

from __future__ import annotations

from pathlib import Path

from ..errors import SceneError
from ._common import SceneWriter, first_dir, list_images, need_dir, read_colmap, trailing_index

FORMAT = "paslcd"
SUMMARY = "PASLCD: SRC=<Scene>/Instance_k/{input_orig|images/, input_orig_test/, gt_mask/, [sparse/0]}"


def pair_by_name(images: list[Path], masks: list[Path], where: Path) -> dict[Path, Path]:
    """Image -> mask by file stem, else by the last number in the name."""
    stems = {m.stem: m for m in masks}
    out = {i: stems[i.stem] for i in images if i.stem in stems}
    if len(out) == len(masks):
        return out
    idx = {trailing_index(i.name): i for i in images}
    out = {}
    for m in masks:
        k = trailing_index(m.name)
        if k is None or k not in idx:
            raise SceneError(f"{m}: no inference image with the same name or number in "
                             f"{where}; rename the mask or the image")
        out[idx[k]] = m
    return out


def build(src: Path, w: SceneWriter) -> None:
    if not any((src / n).is_dir() for n in ("input_orig", "images")):
        inst = sorted(p.name for p in src.glob("Instance_*") if p.is_dir())
        if inst:
            raise SceneError(f"{src}: is a PASLCD scene with {', '.join(inst)}; import one "
                             f"instance at a time, e.g. {src / inst[0]}")
    ref = need_dir(first_dir(src, ("input_orig", "images"), "the reference images", FORMAT),
                   "the reference (pre-change) images", FORMAT)
    test = need_dir(first_dir(src, ("input_orig_test", "images_test"), "the inference images",
                              FORMAT), "the inference (post-change) images", FORMAT)
    masks = list_images(need_dir(src / "gt_mask", "the ground-truth masks", FORMAT))
    cams = {}
    sparse = first_dir(src, ("sparse/0", "sparse"), "", FORMAT, required=False)
    if sparse is not None and any(sparse.glob("images.*")):
        cams = read_colmap(sparse)
    tests = list_images(test)
    pairs = pair_by_name(tests, masks, test)
    for p in list_images(ref):
        w.add_image("before", p, cams.get(p.name))
    for p in tests:
        w.add_image("after", p, cams.get(p.name))
        if p in pairs:
            w.add_image("eval_after", p, cams.get(p.name))
            w.add_mask("masks", p.stem, pairs[p])
    if (src / "changes.txt").is_file():
        w.note("changes.txt: " + (src / "changes.txt").read_text(errors="replace").strip())
    w.note("eval views are the inference (post-change) images with masks, also used as after "
           "images; no eval/before exists in PASLCD")
