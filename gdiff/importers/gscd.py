"""3DGS-CD layout (Lu et al., "3DGS-CD: 3D Gaussian Splatting-based Change Detection for
Physical Object Rearrangement"), as described in the dataset's README::

    SRC/rgb/*.png            pre-change images
    SRC/rgb_new/*.png        post-change images; indices 0, 2, 4, ... are for change detection,
                             1, 3, 5, ... for evaluation
    SRC/masks_gt/*.png       ground-truth change masks of the evaluation images
    SRC/transforms.json      pre- and post-change camera poses (nerfstudio format, OpenGL axes)
    (nerfstudio_models/, config.yml, configs.json: the authors' model files, ignored)

Mapping to a gdiff scene:

* ``before/`` = all of ``rgb/``; ``after/`` = the post-change images without a mask;
* each mask is paired with its post-change image by file stem, else by the number in the name
  (``mask_00003.png`` <-> ``frame_00003.png``); if neither matches, and there are as many masks
  as odd-indexed ``rgb_new`` images, they are paired in sorted order (the README's split; a
  guess about the file naming, recorded in ``import.json``);
* those views become ``eval/after/NAME`` + ``eval/masks/NAME``. 3DGS-CD has *no pre-change
  image at the evaluation viewpoints*, so there is no ``eval/before``: methods that compare
  two images use the fitted model's render at t = 0 there. The masks mark the rearranged
  objects as seen from the post-change view (their new and, where visible, old location),
  which is gdiff's ground-truth convention.
* ``cameras.json`` from ``transforms.json`` (converted to OpenCV axes, intrinsics scaled to the
  image files) when every image has a frame there.
"""

from __future__ import annotations

from pathlib import Path

from ..cameras import Camera, cameras_from_transforms
from ..errors import SceneError
from ..io import read_json
from ._common import SceneWriter, list_images, need_dir, trailing_index

FORMAT = "3dgscd"
SUMMARY = "3DGS-CD: SRC/{rgb/, rgb_new/, masks_gt/, transforms.json}"


def _key(path: str | Path) -> str:
    p = Path(str(path).replace("\\", "/"))
    return f"{p.parent.name}/{p.stem}"


def pair_masks(images: list[Path], masks: list[Path], where: Path) -> tuple[dict[Path, Path], str]:
    """Map eval image -> mask: by file stem; else by the number in the names when that picks
    the odd-indexed images (the README's split); else the odd-indexed images in sorted order
    when the counts agree; else by number alone."""
    img_stems = {i.stem: i for i in images}
    if all(m.stem in img_stems for m in masks):
        return {img_stems[m.stem]: m for m in masks}, "file stem"
    odd = images[1::2]
    idx_img = {trailing_index(i.name): i for i in images}
    idx_mask = {trailing_index(m.name): m for m in masks}
    by_number = None
    if None not in idx_mask and len(idx_img) == len(images) and set(idx_mask) <= set(idx_img):
        by_number = {idx_img[k]: m for k, m in idx_mask.items()}
        if set(by_number) == set(odd):
            return by_number, "number in the file name"
    if len(odd) == len(masks):
        return dict(zip(odd, sorted(masks))), "odd-indexed post-change images, in sorted order"
    if by_number is not None:
        return by_number, "number in the file name (not the README's odd-index split)"
    raise SceneError(f"{where}: cannot pair the {len(masks)} masks with the post-change images "
                     "(no common file stems or numbers, and not one mask per odd-indexed image)")


def build(src: Path, w: SceneWriter) -> None:
    rgb = list_images(need_dir(src / "rgb", "the pre-change images", FORMAT))
    new = list_images(need_dir(src / "rgb_new", "the post-change images", FORMAT))
    masks = list_images(need_dir(src / "masks_gt", "the ground-truth change masks", FORMAT))
    tpath = src / "transforms.json"
    cams: dict[str, Camera] = {}
    if tpath.is_file():
        for c in cameras_from_transforms(read_json(tpath), str(tpath)):
            cams[_key(c.image)] = c
    else:
        w.note(f"{tpath.name} not found: no known poses")
    pairs, how = pair_masks(new, masks, src / "masks_gt")
    w.note(f"masks_gt paired with rgb_new by {how}")
    for p in rgb:
        w.add_image("before", p, cams.get(_key(p)))
    for p in new:
        cam = cams.get(_key(p))
        if p in pairs:
            w.add_image("eval_after", p, cam)
            w.add_mask("masks", p.stem, pairs[p])
        else:
            w.add_image("after", p, cam)
    w.note("eval views are post-change only (no eval/before): 3DGS-CD has no pre-change image "
           "at the evaluation viewpoints")
