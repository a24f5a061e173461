"""File input/output helpers: atomic writes, images, JSON.

All stage outputs are written through :func:`atomic_path` (write to a temporary file in the same
folder, then ``os.replace``), so a reader never sees a half-written file, even if the process is
killed mid-write.
"""

from __future__ import annotations

import contextlib
import json
import os
import tempfile
from pathlib import Path
from typing import Any, Iterator

import cv2
import numpy as np

from .errors import SceneError

IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".PNG", ".JPG", ".JPEG")


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
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=".tmp" + suffix, dir=path.parent)
    os.close(fd)
    tmp = Path(tmp)
    try:
        yield tmp
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        raise


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
    a grey image is repeated to three channels. Raises :class:`SceneError` naming the file if it
    cannot be decoded.
    """
    path = Path(path)
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
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
    elif img.shape[2] == 4:
        img = img[:, :, :3]
    return np.ascontiguousarray(img[:, :, ::-1])


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
    """Read a mask PNG as bool [H, W] (any non-zero value = True)."""
    path = Path(path)
    m = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
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


def write_ids(path: str | os.PathLike, ids: np.ndarray) -> None:
    """Write an instance-ID map [H, W] as a 16-bit PNG (0 = no instance), atomically."""
    ids = np.asarray(ids)
    if ids.max(initial=0) > 65535 or ids.min(initial=0) < 0:
        raise ValueError("instance IDs must lie in [0, 65535]")
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
