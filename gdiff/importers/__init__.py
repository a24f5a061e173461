"""Import public change-detection datasets as gdiff scene folders.

``gdiff import FORMAT SRC DST [--copy]`` (or :func:`import_scene`) reads one scene of a
dataset in its published layout and writes a gdiff scene folder at ``DST``::

    before/  after/                   training images (symlinks to SRC, or copies)
    eval/{before,after,masks}/        eval views matched by file stem (masks: 8-bit, 255 =
                                      changed); a view may lack eval/before when the dataset
                                      has no pre-change image at its viewpoint
    eval/{mask_before,mask_after}/    when the dataset separates them
    cameras.json                      known poses (OpenCV c2w) when the dataset has them for
                                      every image
    import.json                       provenance: format, source, counts, mapping notes

The folder is built next to ``DST`` and renamed into place, so an interrupted import leaves
nothing half-written; ``DST`` must not exist (or be empty). Formats (one module each; their
docstrings give the exact layout and how eval views are mapped, see also docs/datasets.md):
"""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

from ..errors import ConfigError, SceneError
from . import ccs3d, cnerf, gscd, paslcd, tfyaml
from ._common import SceneWriter

log = logging.getLogger("gdiff.importers")

FORMATS = {m.FORMAT: m for m in (cnerf, gscd, paslcd, ccs3d, tfyaml)}
ALIASES = {"tf": "tf-yaml", "tfyaml": "tf-yaml", "c-nerf": "cnerf", "3dgs-cd": "3dgscd", "3dgs_cd": "3dgscd", "gscd": "3dgscd"}

__doc__ += "\n".join(f"\n* ``{m.FORMAT}`` — {m.SUMMARY}" for m in FORMATS.values())


def resolve_format(fmt: str) -> str:
    """Canonical format name (case-insensitive, aliases such as ``3DGS-CD``)."""
    key = str(fmt).strip().lower()
    key = ALIASES.get(key, key)
    if key not in FORMATS:
        raise ConfigError(f"unknown dataset format {fmt!r}; known formats: "
                          f"{', '.join(FORMATS)}")
    return key


def detect_format(src: str | Path) -> str | None:
    """Guess the format of a dataset folder from its layout (None if none fits)."""
    src = Path(src)
    if (src / "rgb_new").is_dir() and (src / "rgb").is_dir():
        return gscd.FORMAT
    if (src / "train-pre").is_dir() and (src / "train-post").is_dir():
        return ccs3d.FORMAT
    if (src / "gt_mask").is_dir() and any((src / n).is_dir()
                                          for n in ("input_orig_test", "images_test")):
        return paslcd.FORMAT
    if list(src.glob("*transformations.y*ml")) or list(src.glob("robot/*transformations.y*ml")):
        return tfyaml.FORMAT
    if list(src.glob("*/poses_bounds.npy")):
        return cnerf.FORMAT
    return None


def import_scene(fmt: str, src: str | Path, dst: str | Path, copy: bool = False) -> Path:
    """Convert one dataset scene at ``src`` (layout ``fmt``) into a gdiff scene at ``dst``.

    Images are symlinked (absolute targets) unless ``copy``. Raises :class:`SceneError`
    naming the missing file/folder when ``src`` does not match the layout. Returns ``dst``.
    """
    key = resolve_format(fmt)
    src = Path(src)
    if not src.is_dir():
        raise SceneError(f"{src}: source folder not found")
    writer = SceneWriter(dst, key, src, copy=copy)
    try:
        FORMATS[key].build(src, writer)
        out = writer.commit()
    except BaseException:
        writer.abort()
        raise
    log.info("imported %s scene %s -> %s (%s)", key, src, out,
             ", ".join(f"{k}: {v}" for k, v in writer.counts.items()))
    return out


def main(argv=None) -> int:
    """``gdiff import FORMAT SRC DST [--copy]``."""
    p = argparse.ArgumentParser(
        prog="gdiff import", formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Convert one scene of a public change-detection dataset into a gdiff "
                    "scene folder.",
        epilog="formats:\n" + "\n".join(f"  {m.SUMMARY}" for m in FORMATS.values())
        + "\n\nSee docs/datasets.md for how each dataset's masks map to eval views.")
    p.add_argument("format", help="cnerf | 3dgscd | paslcd | ccs3d | tf-yaml | auto (guess from layout)")
    p.add_argument("src", type=Path, help="the dataset's scene folder")
    p.add_argument("dst", type=Path, help="the gdiff scene folder to create")
    p.add_argument("--copy", action="store_true", help="copy images instead of symlinking")
    args = p.parse_args(argv)
    fmt = args.format
    if fmt.lower() == "auto":
        fmt = detect_format(args.src)
        if fmt is None:
            raise SceneError(f"{args.src}: layout matches none of {', '.join(FORMATS)}; give "
                             "the format explicitly")
    out = import_scene(fmt, args.src, args.dst, copy=args.copy)
    meta = json.loads((out / "import.json").read_text())
    print(f"{out}: imported ({resolve_format(fmt)})")
    print("  " + ", ".join(f"{k}: {v}" for k, v in meta["counts"].items())
          + f"; known poses: {'yes' if meta['known_poses'] else 'no'}")
    for n in meta["notes"]:
        print(f"  note: {n}")
    return 0
