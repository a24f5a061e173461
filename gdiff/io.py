"""File input/output helpers: atomic writes, images, JSON.

All stage outputs are written through :func:`atomic_path` (write to a temporary file in the same
folder, then ``os.replace``), so a reader never sees a half-written file, even if the process is
killed mid-write.

Photos and masks are read *upright*: a file's EXIF orientation tag (phones store portrait
photos as landscape pixels plus a tag) is applied on reading (:data:`IMREAD_UPRIGHT`), so every
stage sees the image as a viewer shows it and sizes are the upright sizes. COLMAP ignores the
tag; the poses stage gives it upright copies (see :mod:`gdiff.sfm.upright`).
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import shutil
import tempfile
from pathlib import Path
from typing import Any, Iterator

import cv2
import numpy as np

from .errors import SceneError

log = logging.getLogger("gdiff.io")

# marks the temporary files of atomic_path: ".<stem>.<random>.tmp<ext>" next to the target
_TMP = ".tmp"

IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".PNG", ".JPG", ".JPEG")

# cv2.imread flags for photos and masks: bit depth and channel count as stored (grey stays grey,
# 16 bit stays 16 bit, an alpha channel is dropped) with the EXIF orientation applied.
# cv2.IMREAD_UNCHANGED would ignore the orientation tag.
IMREAD_UPRIGHT = cv2.IMREAD_ANYDEPTH | cv2.IMREAD_ANYCOLOR
EXIF_ORIENTATION_TAG = 0x0112


def imread_upright(path: str | os.PathLike) -> np.ndarray | None:
    """``cv2.imread`` of ``path`` with :data:`IMREAD_UPRIGHT`: BGR or grey [H, W(, 3)] as
    displayed (EXIF orientation applied); None when the file cannot be decoded."""
    return cv2.imread(str(path), IMREAD_UPRIGHT)


def exif_orientation(path: str | os.PathLike) -> int:
    """The EXIF orientation tag of an image file (1..8; 1 = stored upright, also when the file
    has no tag or no EXIF block). 5..8 swap width and height."""
    from PIL import Image

    try:
        with Image.open(path) as im:
            value = im.getexif().get(EXIF_ORIENTATION_TAG, 1)
    except (OSError, ValueError, SyntaxError):
        return 1
    return int(value) if value in range(1, 9) else 1


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, suffix: str | None = None) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; on success move it onto ``path`` atomically.

    The temporary file keeps the target's extension (libraries such as OpenCV or OpenEXR pick
    the format from it). On an exception the temporary file is removed and ``path`` is left as
    it was.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    suffix = suffix if suffix is not None else "".join(path.suffixes[-1:])
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=_TMP + suffix, dir=path.parent)
    os.close(fd)
    tmp = Path(tmp)
    try:
        yield tmp
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        raise


def remove_stale_temporaries(folder: str | os.PathLike) -> list[Path]:
    """Delete (and log) the temporary files that ``atomic_path`` left in ``folder`` when its
    process was killed mid-write (SIGKILL, power loss: no ``except`` ran). Call it where a stage
    reopens a folder it owns, such as its checkpoint folder on resume. Returns the removed
    paths."""
    folder = Path(folder)
    if not folder.is_dir():
        return []
    stale = sorted(p for p in folder.glob(f".*{_TMP}*") if p.is_file())
    for p in stale:
        p.unlink(missing_ok=True)
        log.info("removed %s, left by an interrupted write", p)
    return stale


def save_torch(obj, path: str | os.PathLike) -> None:
    """``torch.save`` of ``obj`` to ``path``, atomically. The archive is written through a file
    object, so its inner folder name is torch's fixed default, not the temporary file's name:
    saving the same object twice gives the same bytes."""
    import torch

    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        torch.save(obj, f)


def link_or_copy(src: str | os.PathLike, dst: str | os.PathLike) -> None:
    """Make ``dst`` the same file as ``src``: a hard link, else a copy (replacing ``dst``
    atomically)."""
    src, dst = Path(src), Path(dst)
    dst.parent.mkdir(parents=True, exist_ok=True)
    tmp = dst.with_name(f".{dst.name}.tmp")
    tmp.unlink(missing_ok=True)
    try:
        os.link(src, tmp)
    except OSError:
        shutil.copyfile(src, tmp)
    os.replace(tmp, dst)


def write_text(path: str | os.PathLike, text: str) -> None:
    """Write ``text`` to ``path`` atomically."""
    with atomic_path(path) as tmp:
        tmp.write_text(text)


def write_json(path: str | os.PathLike, obj: Any, indent: int = 1) -> None:
    """Write ``obj`` as JSON to ``path`` atomically (numpy arrays become lists)."""

    def default(o):
        if isinstance(o, np.ndarray):
            return o.tolist()
        if isinstance(o, (np.floating, np.integer)):
            return o.item()
        if isinstance(o, Path):
            return str(o)
        raise TypeError(f"not JSON serialisable: {type(o)}")

    write_text(path, json.dumps(obj, indent=indent, default=default) + "\n")


def read_json(path: str | os.PathLike) -> Any:
    """Read JSON, with an error naming the file if it is missing or malformed."""
    path = Path(path)
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        raise SceneError(f"{path}: file not found") from None
    except json.JSONDecodeError as e:
        raise SceneError(f"{path}: not valid JSON ({e}); fix or remove the file") from None


def write_csv(path: str | os.PathLike, df) -> None:
    """Write a pandas DataFrame as CSV atomically (no index column)."""
    with atomic_path(path) as tmp:
        df.to_csv(tmp, index=False)


def read_image(path: str | os.PathLike) -> np.ndarray:
    """Read an 8- or 16-bit PNG/JPEG as float32 RGB in [0, 1], shape [H, W, 3].

    Values are the file's encoded (sRGB) values scaled to [0, 1]; an alpha channel is dropped,
    a grey image is repeated to three channels, the EXIF orientation is applied (the image as
    displayed). Raises :class:`SceneError` naming the file if it cannot be decoded.
    """
    path = Path(path)
    img = imread_upright(path)
    if img is None:
        if not path.exists():
            raise SceneError(f"{path}: image file not found")
        raise SceneError(
            f"{path}: cannot be decoded as an image (corrupt or unsupported format); "
            "replace or remove the file"
        )
    scale = 65535.0 if img.dtype == np.uint16 else 255.0
    img = img.astype(np.float32) / scale
    if img.ndim == 2:
        img = np.repeat(img[:, :, None], 3, axis=2)
    return np.ascontiguousarray(img[:, :, ::-1])


def read_image_sized(path: str | os.PathLike, width: int, height: int) -> np.ndarray:
    """:func:`read_image` resized (area-averaged) to ``width`` x ``height`` when its size
    differs: float32 sRGB [height, width, 3] in [0, 1]."""
    img = read_image(path)
    if img.shape[:2] != (height, width):
        img = cv2.resize(img, (width, height), interpolation=cv2.INTER_AREA)
    return img


def write_image(path: str | os.PathLike, img: np.ndarray) -> None:
    """Write float RGB in [0, 1] ([H, W, 3]) or uint8 as an 8-bit PNG/JPEG, atomically."""
    img = np.asarray(img)
    if img.dtype != np.uint8:
        img = (np.clip(img, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    if img.ndim == 3:
        img = img[:, :, ::-1]
    with atomic_path(path) as tmp:
        if not cv2.imwrite(str(tmp), np.ascontiguousarray(img)):
            raise OSError(f"could not write image {path}")


def read_mask(path: str | os.PathLike) -> np.ndarray:
    """Read a mask PNG as bool [H, W] (any non-zero colour value = True; an alpha channel is
    ignored; EXIF orientation applied as for photos)."""
    path = Path(path)
    m = imread_upright(path)
    if m is None:
        raise SceneError(f"{path}: mask cannot be read (missing or corrupt)")
    if m.ndim == 3:
        m = m.max(axis=2)
    return m > 0


def write_mask(path: str | os.PathLike, mask: np.ndarray) -> None:
    """Write a bool/0-1 mask [H, W] as an 8-bit PNG (255 = True), atomically."""
    write_image(path, (np.asarray(mask) > 0).astype(np.uint8) * 255)


def read_ids(path: str | os.PathLike) -> np.ndarray:
    """Read an instance-ID map (uint16 PNG, 0 = no instance) as int64 [H, W]."""
    path = Path(path)
    m = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if m is None:
        raise SceneError(f"{path}: ID map cannot be read (missing or corrupt)")
    return m.astype(np.int64)


#: the largest instance ID an ID map (16-bit PNG) holds
MAX_ID = 65535


def write_ids(path: str | os.PathLike, ids: np.ndarray) -> None:
    """Write an instance-ID map [H, W] as a 16-bit PNG (0 = no instance), atomically."""
    ids = np.asarray(ids)
    if ids.max(initial=0) > MAX_ID or ids.min(initial=0) < 0:
        raise ValueError(f"instance IDs must lie in [0, {MAX_ID}]")
    with atomic_path(path) as tmp:
        if not cv2.imwrite(str(tmp), ids.astype(np.uint16)):
            raise OSError(f"could not write ID map {path}")


def srgb_to_linear(x: np.ndarray) -> np.ndarray:
    """sRGB-encoded values in [0, 1] -> linear (IEC 61966-2-1)."""
    x = np.asarray(x, dtype=np.float32)
    return np.where(x <= 0.04045, x / 12.92, ((np.clip(x, 0, None) + 0.055) / 1.055) ** 2.4)


def linear_to_srgb(x: np.ndarray) -> np.ndarray:
    """Linear values -> sRGB-encoded (IEC 61966-2-1); negative values clip to 0."""
    x = np.clip(np.asarray(x, dtype=np.float32), 0.0, None)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1 / 2.4) - 0.055)
