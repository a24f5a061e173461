"""Shared pieces of the dataset importers: the scene-folder writer and pose readers."""

from __future__ import annotations

import logging
import os
import re
import shutil
import tempfile
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from ..cameras import SET_TIME, Camera, save_cameras
from ..errors import SceneError
from ..io import IMAGE_EXTENSIONS, imread_upright, read_mask, write_json, write_mask

log = logging.getLogger("gdiff.importers")

_DIR_FOR_SET = {"before": "before", "after": "after", "eval_before": "eval/before",
                "eval_after": "eval/after"}


def list_images(folder: Path) -> list[Path]:
    """Image files (png/jpg) directly in ``folder``, sorted by name; hidden files skipped."""
    return sorted(p for p in Path(folder).iterdir()
                  if p.is_file() and p.suffix in IMAGE_EXTENSIONS and not p.name.startswith("."))


def need_dir(path: Path, what: str, fmt: str) -> Path:
    """``path`` if it is a folder holding images, else a :class:`SceneError` naming it."""
    if not path.is_dir():
        raise SceneError(f"{path}: folder not found; a {fmt} scene needs {what} there "
                         f"(see `gdiff import --help` for the expected layout)")
    if not list_images(path):
        raise SceneError(f"{path}: no .png/.jpg images in the folder ({what})")
    return path


def first_dir(root: Path, names: tuple[str, ...], what: str, fmt: str,
              required: bool = True) -> Path | None:
    """The first of ``root/name`` that exists (layouts differ between dataset releases)."""
    for n in names:
        if (root / n).is_dir():
            return root / n
    if required:
        raise SceneError(f"{root}: none of the folders {', '.join(names)} exists; a {fmt} scene "
                         f"needs {what} in one of them")
    return None


_INT = re.compile(r"(\d+)(?!.*\d)")


def trailing_index(name: str) -> int | None:
    """The last run of digits in a file stem (``frame_00012`` -> 12, ``gt_3`` -> 3)."""
    m = _INT.search(Path(name).stem)
    return int(m.group(1)) if m else None


def image_size(path: Path) -> tuple[int, int]:
    """``(width, height)`` of an image file, upright (EXIF orientation applied)."""
    img = imread_upright(path)
    if img is None:
        raise SceneError(f"{path}: cannot be decoded as an image")
    return img.shape[1], img.shape[0]


def llff_to_opencv(pose_3x4: np.ndarray) -> np.ndarray:
    """LLFF ``[R | t]`` camera-to-world with rotation columns (down, right, back) -> OpenCV
    c2w 4x4 with columns (right, down, forward)."""
    P = np.asarray(pose_3x4, dtype=np.float64)[:3, :4]
    c2w = np.eye(4)
    c2w[:3, 0] = P[:, 1]   # right
    c2w[:3, 1] = P[:, 0]   # down
    c2w[:3, 2] = -P[:, 2]  # forward = -back
    c2w[:3, 3] = P[:, 3]
    return c2w


def read_colmap(sparse_dir: Path) -> dict[str, Camera]:
    """Registered images of a COLMAP model (binary or text) as cameras keyed by image *base
    name*: OpenCV c2w (COLMAP's camera axes are OpenCV's), pinhole intrinsics from the camera's
    calibration matrix (COLMAP puts pixel centres at +0.5, as gdiff does). Lens distortion is
    not applied; a warning says so when the model has any."""
    import pycolmap

    sparse_dir = Path(sparse_dir)
    if not sparse_dir.is_dir():
        raise SceneError(f"{sparse_dir}: COLMAP model folder not found")
    try:
        rec = pycolmap.Reconstruction(str(sparse_dir))
    except Exception as e:  # pycolmap raises plain RuntimeError/ValueError
        raise SceneError(f"{sparse_dir}: cannot be read as a COLMAP model ({e}); it needs "
                         "cameras, images and points3D (.bin or .txt)") from None
    out: dict[str, Camera] = {}
    distorted = set()
    for img in rec.images.values():
        if not img.has_pose:
            continue
        cam = rec.cameras[img.camera_id]
        K = cam.calibration_matrix()
        extra = np.asarray(cam.params)[list(cam.extra_params_idxs())]
        if np.any(np.abs(extra) > 1e-9):
            distorted.add(cam.model.name)
        w2c = np.eye(4)
        w2c[:3, :4] = img.cam_from_world().matrix()
        c2w = np.linalg.inv(w2c)
        out[Path(img.name).name] = Camera(int(cam.width), int(cam.height), float(K[0, 0]),
                                          float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), c2w)
    if distorted:
        log.warning("%s: camera model(s) %s carry lens distortion, which gdiff ignores; "
                    "undistort the images (colmap image_undistorter) for exact poses",
                    sparse_dir, ", ".join(sorted(distorted)))
    return out


class SceneWriter:
    """Builds a gdiff scene folder in a temporary folder next to ``dst`` and renames it into
    place on :meth:`commit` (so an interrupted import leaves no half-written scene).

    Images are symlinked (absolute targets) or copied (``copy=True``); masks are always
    re-encoded as 8-bit PNG, 255 = changed.
    """

    def __init__(self, dst: str | Path, fmt: str, src: str | Path, copy: bool = False):
        self.dst = Path(dst).absolute()
        self.fmt, self.src, self.copy = fmt, Path(src).absolute(), copy
        if self.dst.exists() and (not self.dst.is_dir() or any(self.dst.iterdir())):
            raise SceneError(f"{self.dst}: already exists; remove it or choose another "
                             "destination (imports never overwrite)")
        self.dst.parent.mkdir(parents=True, exist_ok=True)
        self.tmp = Path(tempfile.mkdtemp(prefix=f".{self.dst.name}.import-", dir=self.dst.parent))
        self.cameras: list[Camera] = []
        self.unposed: list[str] = []
        self.notes: list[str] = []
        self.counts: dict[str, int] = {}

    def add_image(self, set_name: str, src: Path, camera: Camera | None = None,
                  name: str | None = None) -> str:
        """Place ``src`` as ``<set folder>/<name or src.name>``; returns the relative path.

        ``camera`` (intrinsics + OpenCV c2w), when known, goes into ``cameras.json``.
        """
        src = Path(src)
        if not src.is_file():
            raise SceneError(f"{src}: image file not found")
        rel = f"{_DIR_FOR_SET[set_name]}/{(name or src.stem) + src.suffix}"
        target = self.tmp / rel
        if target.exists() or target.is_symlink():
            raise SceneError(f"{src}: two images map to {rel}; rename one of them")
        target.parent.mkdir(parents=True, exist_ok=True)
        if self.copy:
            shutil.copy2(src, target)
        else:
            os.symlink(src.resolve(), target)
        self.counts[set_name] = self.counts.get(set_name, 0) + 1
        if camera is None:
            self.unposed.append(rel)
        else:
            w, h = image_size(src)
            cam = camera.with_pose(camera.c2w)  # a copy: one pose may serve two sets
            if (cam.width, cam.height) != (w, h):  # poses given for another resolution
                cam = cam.scaled(w / cam.width)
                cam.width, cam.height = w, h
            cam.image, cam.set, cam.time = rel, set_name, SET_TIME[set_name]
            self.cameras.append(cam)
        return rel

    def add_mask(self, folder: str, name: str, mask: np.ndarray | Path) -> str:
        """Write ``eval/<folder>/<name>.png`` (folder: masks, mask_before, mask_after) from a
        mask array or file (any non-zero value = changed)."""
        m = read_mask(mask) if isinstance(mask, (str, Path)) else np.asarray(mask)
        rel = f"eval/{folder}/{name}.png"
        write_mask(self.tmp / rel, m)
        self.counts[folder] = self.counts.get(folder, 0) + 1
        return rel

    def note(self, text: str) -> None:
        """A remark stored in ``import.json`` and logged (e.g. how masks were mapped)."""
        self.notes.append(text)
        log.info("%s import: %s", self.fmt, text)

    def commit(self) -> Path:
        """Write ``cameras.json`` (when every image has a pose) and ``import.json``; move the
        folder into place."""
        for s in ("before", "after"):
            if not self.counts.get(s):
                raise SceneError(f"{self.src}: the {self.fmt} layout yielded no '{s}' images")
        if self.cameras and not self.unposed:
            save_cameras(self.tmp / "cameras.json", self.cameras)
        elif self.cameras:
            self.note(f"no cameras.json written: {len(self.unposed)} image(s) have no pose in "
                      f"the dataset (e.g. {self.unposed[0]}); the poses stage will register all "
                      "images with COLMAP")
        write_json(self.tmp / "import.json", {
            "format": self.fmt, "source": str(self.src),
            "mode": "copy" if self.copy else "symlink",
            "date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
            "counts": self.counts, "known_poses": bool(self.cameras and not self.unposed),
            "notes": self.notes})
        if self.dst.exists():
            self.dst.rmdir()  # empty (checked in __init__)
        os.replace(self.tmp, self.dst)
        return self.dst

    def abort(self) -> None:
        shutil.rmtree(self.tmp, ignore_errors=True)
