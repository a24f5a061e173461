"""Image lists of a scene: the set (before, after, eval_before, eval_after) of each image,
their sizes, and the per-set bookkeeping of registered images."""

from __future__ import annotations

import logging
import os
from pathlib import Path

from ..cameras import SETS
from ..errors import PosesError, SceneError
from ..io import IMAGE_EXTENSIONS, exif_orientation

log = logging.getLogger("gdiff.sfm")

# Scene sub-folders searched when no image list is given, with the set they hold.
SET_FOLDERS = {"before": "before", "after": "after", "eval_before": "eval/before",
               "eval_after": "eval/after"}


def set_from_path(rel: str) -> str | None:
    """The image set of a scene-relative path (``before/x.png`` -> ``before``,
    ``eval/after/x.png`` -> ``eval_after``), or None if the folder is not a set folder."""
    parts = Path(rel).parts
    if len(parts) >= 2 and parts[0] in ("before", "after"):
        return parts[0]
    if len(parts) >= 3 and parts[0] == "eval" and parts[1] in ("before", "after"):
        return f"eval_{parts[1]}"
    return None


def discover_images(scene_dir: str | os.PathLike) -> list[tuple[str, str]]:
    """(relative path, set) of every image in before/, after/, eval/before/, eval/after/,
    sorted by name within each set (the capture order for sequential matching)."""
    root = Path(scene_dir)
    out = []
    for st, folder in SET_FOLDERS.items():
        d = root / folder
        if d.is_dir():
            files = sorted(p for p in d.iterdir() if p.is_file() and p.suffix in IMAGE_EXTENSIONS
                           and not p.name.startswith("."))
            out += [(p.relative_to(root).as_posix(), st) for p in files]
    if not any(s == "before" for _, s in out) or not any(s == "after" for _, s in out):
        raise SceneError(f"{root}: needs images in before/ and after/")
    return out


def _image_sizes(scene_dir: Path, names: list[str],
                 orientations: dict[str, int] | None = None) -> dict[str, tuple[int, int]]:
    """(width, height) per image as displayed (EXIF orientation 5..8 swaps the stored size),
    the stored size read from the file headers; ``orientations`` (name -> EXIF tag, e.g. from
    :func:`gdiff.sfm.upright.orientations`) saves reading the tags again."""
    from PIL import Image

    sizes = {}
    for n in names:
        try:
            with Image.open(scene_dir / n) as im:
                w, h = im.size
        except (OSError, ValueError):
            raise SceneError(f"{scene_dir / n}: cannot be read as an image") from None
        o = orientations[n] if orientations is not None else exif_orientation(scene_dir / n)
        sizes[n] = (h, w) if o >= 5 else (w, h)
    return sizes


def _check_unregistered(images: list[tuple[str, str]], registered: set[str], max_frac: float,
                        what: str) -> list[str]:
    """Raise PosesError if a set lost more than ``max_frac`` of its images; else return the
    names of the lost images (to be dropped)."""
    lost = [(n, s) for n, s in images if n not in registered]
    bad = []
    for st in SETS:
        n_set = sum(1 for _, s in images if s == st)
        lost_set = [n for n, s in lost if s == st]
        if n_set and len(lost_set) / n_set > max_frac:
            bad.append(f"{st}: {len(lost_set)} of {n_set} ({', '.join(lost_set)})")
    if bad:
        raise PosesError(
            f"{what}: too many images could not be posed (more than "
            f"{max_frac:.0%} of a set, see poses.max_unregistered_fraction): "
            + "; ".join(bad) + ". Causes: these photos overlap too little with the others, "
            "are blurred or show untextured surfaces. Fixes: add overlapping photos between "
            "them and the rest, remove them from the scene, or give known poses "
            "(cameras.json).")
    if lost:
        log.warning("dropping %d image(s) that could not be posed: %s", len(lost),
                    ", ".join(n for n, _ in lost))
    return [n for n, _ in lost]


def _count(images, names=None) -> dict[str, int]:
    return {st: sum(1 for n, s in images if s == st and (names is None or n in names))
            for st in SETS if any(s == st for _, s in images)}
