"""Training data of the partition stage: key views (photo, camera, compare-stage masks) from
``change/keyframes.csv`` and ``poses/cameras.json``.

Conventions: see :mod:`gdiff.partition`.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pandas as pd

from ..cameras import load_cameras
from ..errors import SceneError
from ..io import read_image_sized, read_mask


@dataclass
class KeyView:
    """One key pose used for training: a source photo and the compare stage's masks there.

    ``camera`` is at training resolution; ``time`` the photo's time (0 before, 1 after);
    ``image`` the photo; ``masks`` maps "t0", "t1", "union" to mask files (absolute paths);
    the training target of the photo is ``masks[f"t{time}"]``.
    """

    name: str
    camera: object
    time: float
    image: object
    masks: dict

    @property
    def target(self):
        return self.masks[f"t{int(round(self.time))}"]

    @property
    def other(self):
        """The mask of the other time (what changed but is drawn at 1 - time)."""
        return self.masks[f"t{1 - int(round(self.time))}"]


KEYFRAME_COLUMNS = ("path", "frame", "image", "set", "time", "mask_t0", "mask_t1", "mask_union")


def read_key_views(keyframes_csv, cameras_json, scene_dir, max_side: int = 0) -> list[KeyView]:
    """Join ``change/keyframes.csv`` with ``poses/cameras.json``.

    Mask paths in the CSV are relative to ``results/<scene>/`` (the CSV's grandparent folder);
    image paths are relative to ``scene_dir``. Cameras are scaled so that max(width, height)
    <= ``max_side`` (0 = full size). Raises :class:`gdiff.errors.SceneError` naming the file and
    row for missing columns, unknown images or missing files.
    """
    keyframes_csv, scene_dir = Path(keyframes_csv), Path(scene_dir)
    try:
        df = pd.read_csv(keyframes_csv)
    except FileNotFoundError:
        raise SceneError(f"{keyframes_csv}: not found; run the compare stage first") from None
    missing = [c for c in KEYFRAME_COLUMNS if c not in df.columns]
    if missing:
        raise SceneError(f"{keyframes_csv}: missing column(s) {', '.join(missing)}; rerun the "
                         "compare stage")
    if df.empty:
        raise SceneError(f"{keyframes_csv}: no key poses; the compare stage found no key frames")
    cams = {Path(c.image).as_posix(): c for c in load_cameras(cameras_json) if c.image}
    root = keyframes_csv.parent.parent
    views = []
    for i, row in df.iterrows():
        img = Path(str(row["image"])).as_posix()
        cam = cams.get(img)
        if cam is None:
            raise SceneError(f"{keyframes_csv}: row {i}: image {img!r} has no camera in "
                             f"{cameras_json}; rerun the poses stage (or the compare stage)")
        t = float(row["time"])
        if t not in (0.0, 1.0):
            raise SceneError(f"{keyframes_csv}: row {i}: time must be 0 or 1, got {row['time']}")
        masks = {k: root / str(row[f"mask_{k}"]) for k in ("t0", "t1", "union")}
        for k, p in masks.items():
            if not p.is_file():
                raise SceneError(f"{keyframes_csv}: row {i}: mask_{k} file {p} not found; "
                                 "rerun the compare stage")
        if max_side and max(cam.width, cam.height) > max_side:
            cam = cam.scaled(max_side / max(cam.width, cam.height))
        views.append(KeyView(f"{row['path']}_{int(row['frame']):05d}", cam, t,
                             scene_dir / img, masks))
    return views


def light_changed(keyframes_csv) -> bool:
    """Whether the compare stage took the scene for a change of light (the ``light_changed``
    column of ``change/keyframes.csv``; False when the file predates it). Raises
    :class:`gdiff.errors.SceneError` naming the file when the column holds anything but
    True / False."""
    df = pd.read_csv(keyframes_csv)
    if "light_changed" not in df.columns:
        return False
    col = df["light_changed"]
    if col.dtype != bool:
        raise SceneError(f"{keyframes_csv}: column light_changed must hold True or False on "
                         f"every row, got {sorted(set(map(str, col)))[:5]}; rerun the compare "
                         "stage")
    return bool(col.any())


def _load_image(path, camera) -> np.ndarray:
    """Photo as float32 [H, W, 3] sRGB in [0, 1], resized (area) to the camera's size."""
    return read_image_sized(path, camera.width, camera.height)


def _load_mask(path, camera) -> np.ndarray:
    """Mask as float32 [H, W] in [0, 1] at the camera's size (area resampling: soft edges)."""
    m = read_mask(path).astype(np.float32)
    if m.shape != (camera.height, camera.width):
        m = cv2.resize(m, (camera.width, camera.height), interpolation=cv2.INTER_AREA)
    return m
