"""Upright copies of EXIF-rotated photos for COLMAP.

Phones and many cameras store a portrait photo as landscape pixels plus an EXIF orientation tag
(1..8). Every gdiff stage reads photos upright (:data:`gdiff.io.IMREAD_UPRIGHT`, the tag
applied), and the manifest records upright sizes; pycolmap's feature extraction reads the stored
pixels and ignores the tag (checked with pycolmap 4.x: a tag-6 JPEG of 400x300 stored pixels
gives a 400x300 camera). So when any photo of a scene carries a tag other than 1, the poses
stage registers *upright copies*: a folder that mirrors the scene's images under the same
relative paths, tagged files decoded upright and re-encoded without the tag, the other files
hard-linked. Eval masks of the eval views are included, so the folder is a complete image root
(it becomes ``poses/images/`` when no resampling follows, see :mod:`gdiff.sfm.run`).
"""

from __future__ import annotations

import logging
from pathlib import Path

import cv2

from ..errors import SceneError
from ..io import atomic_path, exif_orientation, imread_upright, link_or_copy
from .undistort import MASK_FOLDERS

log = logging.getLogger("gdiff.sfm")

JPEG_QUALITY = 100  # re-encoded copies are read by every later stage: keep the loss small


def orientations(photos: Path, names: list[str]) -> dict[str, int]:
    """The EXIF orientation tag (1..8, 1 = upright) of each image (relative to ``photos``)."""
    return {n: exif_orientation(photos / n) for n in names}


def _eval_masks(photos: Path, images: list[tuple[str, str]]) -> list[str]:
    """The eval masks (relative paths) of the eval views among ``images``."""
    stems = {Path(n).stem for n, s in images if s in ("eval_before", "eval_after")}
    out = []
    for folder in MASK_FOLDERS:
        d = photos / folder
        if d.is_dir():
            out += [f"{folder}/{p.name}" for p in sorted(d.iterdir())
                    if p.is_file() and p.stem in stems]
    return out


def _write_upright(src: Path, dst: Path) -> None:
    img = imread_upright(src)
    if img is None:
        raise SceneError(f"{src}: cannot be decoded as an image (corrupt or unsupported "
                         "format); replace or remove the file")
    jpeg = dst.suffix.lower() in (".jpg", ".jpeg")
    params = [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY] if jpeg else []
    with atomic_path(dst) as tmp:
        if not cv2.imwrite(str(tmp), img, params):
            raise OSError(f"could not write {dst}")


def write_upright_copies(photos: str | Path, out_dir: str | Path,
                         images: list[tuple[str, str]],
                         tags: dict[str, int] | None = None) -> int:
    """Mirror the photos ``images`` (``(relative path, set)``) and the masks of their eval
    views from ``photos`` into ``out_dir``: EXIF-tagged files upright without the tag, the rest
    hard-linked (copied where links are impossible). ``tags`` (name -> EXIF orientation, from
    :func:`orientations`) saves reading the tags of files already read. Returns the number of
    files re-encoded."""
    photos, out = Path(photos), Path(out_dir)
    names = [n for n, _ in images] + _eval_masks(photos, images)
    known = tags or {}
    tags = {**orientations(photos, [n for n in names if n not in known]), **known}
    tagged = {n for n in names if tags[n] != 1}
    for n in names:
        if n in tagged:
            _write_upright(photos / n, out / n)
        else:
            link_or_copy(photos / n, out / n)
    if tagged:
        log.info("%d photo(s) carry an EXIF orientation tag (e.g. %s): registered from upright "
                 "copies, as every stage reads them", len(tagged), sorted(tagged)[0])
    return len(tagged)
