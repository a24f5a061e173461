"""Cameras: intrinsics + pose in one frame, and the ``cameras.json`` file format.

Conventions
-----------
* OpenCV camera axes: x right, y down, z forward (viewing direction).
* ``c2w``: 4x4 camera-to-world matrix (columns 0..2 are the camera axes in world coordinates,
  column 3 the camera centre). ``w2c`` (= gsplat's ``viewmat``) is its inverse.
* Pinhole intrinsics ``fx, fy, cx, cy`` in pixels; the centre of pixel (col i, row j) is at
  (i + 0.5, j + 0.5) (COLMAP / NeRF convention).

``cameras.json`` (written by the poses stage, read by every later stage)::

    {"width": W, "height": H, "fx": .., "fy": .., "cx": .., "cy": ..,
     "frames": [{"image": "before/000.png",            # path relative to the scene folder
                 "set": "before|after|eval_before|eval_after",
                 "time": 0 | 1,
                 "c2w": [[4x4]]}, ...]}

A frame may carry its own ``fx, fy, cx, cy, width, height`` when images differ in intrinsics
(input ``cameras.json`` only: photos from different cameras). The poses stage's output always
has one shared camera: it resamples such photos to one common pinhole camera (see
:mod:`gdiff.sfm.resample`) and names the folder of the resampled photos in ``"image_dir"``
(below), so later stages can rely on one image size and one ``K``.

Lens distortion (input ``cameras.json`` only): ``"distortion": [k1, k2, p1, p2(, k3)]`` (OpenCV
plumb-bob / Brown-Conrady coefficients, as in ROS CameraInfo ``D``; or a dict with those keys),
shared at the top level or per frame. The poses stage undistorts such images once and writes
pinhole cameras (no ``distortion``) plus ``"image_dir"``: the folder, relative to the
``cameras.json``, that holds the undistorted images under the same relative paths (see
:func:`image_root`); every later stage reads the photos from there. Beside it goes
``photo_cameras.json`` (:data:`PHOTO_CAMERAS`, same layout, per-frame sizes, intrinsics and
distortion, the registered poses): the cameras of the photos as the user gave them, so that
what is given in their pixels (box ground truth) can be carried into the images the stages
use (:func:`gdiff.sfm.undistort.boxes_to_pinhole`). It is written only when the photos were
undistorted or resampled.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Iterable

import numpy as np

from .errors import SceneError
from .io import read_json, write_json

SETS = ("before", "after", "eval_before", "eval_after")
#: file name, beside the poses stage's ``cameras.json``, of the photos' own cameras (module
#: docstring)
PHOTO_CAMERAS = "photo_cameras.json"
TRAIN_SETS = ("before", "after")  # the photos a fit (and the points it starts from) may use
SET_TIME = {"before": 0, "after": 1, "eval_before": 0, "eval_after": 1}

# OpenGL / nerfstudio camera axes (x right, y up, z backward) -> OpenCV: flip y and z.
_GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])


@dataclass
class Camera:
    """A pinhole camera. ``c2w`` is camera-to-world (OpenCV axes), float64 [4, 4]."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    c2w: np.ndarray = field(default_factory=lambda: np.eye(4))
    image: str | None = None  # path relative to the scene folder, if the camera has a photo
    set: str | None = None  # before | after | eval_before | eval_after
    time: float | None = None  # 0 (before) or 1 (after)
    # OpenCV distortion coefficients (k1, k2, p1, p2[, k3]) of the photo, or None (pinhole).
    dist: tuple[float, ...] | None = None

    def __post_init__(self):
        self.c2w = np.asarray(self.c2w, dtype=np.float64).reshape(4, 4)
        if self.dist is not None:
            self.dist = tuple(float(v) for v in self.dist)
            if not any(self.dist):
                self.dist = None

    @property
    def K(self) -> np.ndarray:
        """3x3 intrinsic matrix (pixel centres at +0.5)."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def w2c(self) -> np.ndarray:
        """4x4 world-to-camera matrix (gsplat's ``viewmat``)."""
        return invert_pose(self.c2w)

    @property
    def center(self) -> np.ndarray:
        """Camera centre in world coordinates, [3]."""
        return self.c2w[:3, 3].copy()

    def scaled(self, factor: float) -> "Camera":
        """The same camera for an image resized by ``factor`` (e.g. 0.5 halves width/height).

        Pixel corners stay aligned: with pixel centres at +0.5, cx and cy scale directly.
        """
        w = int(round(self.width * factor))
        h = int(round(self.height * factor))
        sx, sy = w / self.width, h / self.height
        return replace(self, width=w, height=h, fx=self.fx * sx, fy=self.fy * sy,
                       cx=self.cx * sx, cy=self.cy * sy, c2w=self.c2w.copy())

    def with_pose(self, c2w: np.ndarray) -> "Camera":
        return replace(self, c2w=np.asarray(c2w, dtype=np.float64).copy())


def invert_pose(T: np.ndarray) -> np.ndarray:
    """Invert a rigid 4x4 transform (rotation + translation)."""
    T = np.asarray(T, dtype=np.float64)
    R, t = T[:3, :3], T[:3, 3]
    out = np.eye(4)
    out[:3, :3] = R.T
    out[:3, 3] = -R.T @ t
    return out


def look_at(center, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """c2w (OpenCV axes) of a camera at ``center`` looking at ``target``; ``up`` is world up."""
    center = np.asarray(center, float)
    z = np.asarray(target, float) - center
    z /= np.linalg.norm(z)
    x = np.cross(z, np.asarray(up, float))
    if np.linalg.norm(x) < 1e-9:  # looking straight along up: pick any perpendicular
        x = np.cross(z, np.array([1.0, 0.0, 0.0]))
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = x, y, z, center
    return c2w


def cameras_to_json(cameras: Iterable[Camera]) -> dict:
    """Serialise cameras to the ``cameras.json`` layout (shared intrinsics at top level)."""
    cameras = list(cameras)
    if not cameras:
        raise ValueError("no cameras to write")
    ref = cameras[0]
    shared = ("width", "height", "fx", "fy", "cx", "cy")
    out = {k: getattr(ref, k) for k in shared}
    frames = []
    for c in cameras:
        fr = {"image": c.image, "set": c.set, "time": c.time, "c2w": c.c2w.tolist()}
        for k in shared:
            if getattr(c, k) != out[k]:
                fr[k] = getattr(c, k)
        if c.dist is not None and c.dist != ref.dist:
            fr["distortion"] = list(c.dist)
        frames.append(fr)
    if ref.dist is not None:
        out["distortion"] = list(ref.dist)
    out["frames"] = frames
    return out


_DIST_KEYS = ("k1", "k2", "p1", "p2", "k3")


def parse_distortion(value, source: str, where: str) -> tuple[float, ...] | None:
    """OpenCV distortion coefficients from a list ``[k1, k2, p1, p2(, k3, ...)]`` or a dict
    with keys ``k1 k2 p1 p2 [k3]`` (missing keys = 0); None for no / all-zero distortion."""
    if value is None:
        return None
    if isinstance(value, dict):
        unknown = sorted(set(value) - set(_DIST_KEYS))
        if unknown:
            raise SceneError(f"{source}: {where}: unknown distortion key(s) {unknown}; give "
                             "k1, k2, p1, p2 and optionally k3 (OpenCV plumb-bob)")
        value = [value.get(k, 0.0) for k in _DIST_KEYS]
    try:
        d = [float(v) for v in value]
    except (TypeError, ValueError):
        raise SceneError(f"{source}: {where}: 'distortion' must be a list of numbers "
                         "[k1, k2, p1, p2(, k3)] (OpenCV plumb-bob)") from None
    if len(d) not in (4, 5, 8) or not np.isfinite(d).all():
        raise SceneError(f"{source}: {where}: 'distortion' has {len(d)} value(s); give 4, 5 "
                         "or 8 finite OpenCV coefficients (k1, k2, p1, p2[, k3[, k4, k5, k6]])")
    return tuple(d) if any(d) else None


def image_root(scene_dir: str | Path | None, cameras_json: str | Path | None) -> Path | None:
    """The folder holding the images named in ``cameras_json`` (or ``sequence/poses.json``):
    its ``image_dir`` (relative to the file; the poses stage's undistorted, resampled or
    upright photos) when set, else ``scene_dir``."""
    if cameras_json is not None:
        data = read_json(cameras_json)
        if data.get("image_dir"):
            return Path(cameras_json).parent / data["image_dir"]
    return None if scene_dir is None else Path(scene_dir)


def cameras_from_json(data: dict, source: str = "cameras.json") -> list[Camera]:
    """Parse the ``cameras.json`` layout; errors name ``source`` and the bad frame."""
    shared = ("width", "height", "fx", "fy", "cx", "cy")
    cams = []
    frames = data.get("frames")
    if not isinstance(frames, list) or not frames:
        raise SceneError(f"{source}: no 'frames' list; see the cameras.json layout in the README")
    for i, fr in enumerate(frames):
        kw = {}
        for k in shared:
            v = fr.get(k, data.get(k))
            if v is None:
                raise SceneError(f"{source}: frame {i} ({fr.get('image')}) has no '{k}' "
                                 "and there is no shared value at the top level")
            kw[k] = v
        c2w = np.asarray(fr.get("c2w", fr.get("transform_matrix")), dtype=np.float64)
        if c2w.shape == (3, 4):
            c2w = np.vstack([c2w, [0, 0, 0, 1]])
        if c2w.shape != (4, 4) or not np.isfinite(c2w).all():
            raise SceneError(f"{source}: frame {i} ({fr.get('image')}): 'c2w' must be a finite "
                             "4x4 camera-to-world matrix")
        st = fr.get("set")
        t = fr.get("time", SET_TIME.get(st) if st else None)
        dist = parse_distortion(fr.get("distortion", data.get("distortion")), source,
                                f"frame {i} ({fr.get('image')})")
        cams.append(Camera(width=int(kw["width"]), height=int(kw["height"]),
                           fx=float(kw["fx"]), fy=float(kw["fy"]), cx=float(kw["cx"]),
                           cy=float(kw["cy"]), c2w=c2w, image=fr.get("image") or fr.get("file"),
                           set=st, time=t, dist=dist))
    return cams


def load_cameras(path: str | Path) -> list[Camera]:
    """Read a gdiff ``cameras.json``."""
    return cameras_from_json(read_json(path), source=str(path))


def save_cameras(path: str | Path, cameras: Iterable[Camera], image_dir: str | None = None
                 ) -> None:
    """Write a gdiff ``cameras.json`` atomically; ``image_dir`` (relative to ``path``) names
    the folder of the (undistorted) images when they are not the scene's own."""
    data = cameras_to_json(cameras)
    if image_dir:
        data = {**{k: v for k, v in data.items() if k != "frames"}, "image_dir": image_dir,
                "frames": data["frames"]}
    write_json(path, data)


def cameras_from_transforms(data: dict, source: str = "transforms.json") -> list[Camera]:
    """Parse a nerfstudio / instant-ngp ``transforms.json`` (OpenGL camera axes).

    Intrinsics come from ``fl_x, fl_y, cx, cy, w, h`` (per frame or shared); ``camera_angle_x``
    is accepted when focal lengths are absent. ``transform_matrix`` is camera-to-world in OpenGL
    axes and is converted to OpenCV axes. ``set``/``time`` are left empty (the caller assigns
    them from the image paths).
    """
    frames = data.get("frames")
    if not isinstance(frames, list) or not frames:
        raise SceneError(f"{source}: no 'frames' list")
    cams = []
    for i, fr in enumerate(frames):
        def get(k, default=None):
            return fr.get(k, data.get(k, default))

        w, h = get("w"), get("h")
        if w is None or h is None:
            raise SceneError(f"{source}: frame {i}: image size 'w'/'h' missing")
        fx, fy = get("fl_x"), get("fl_y")
        if fx is None and get("camera_angle_x") is not None:
            fx = 0.5 * w / np.tan(0.5 * get("camera_angle_x"))
        if fx is None:
            raise SceneError(f"{source}: frame {i}: focal length 'fl_x' missing")
        fy = fy if fy is not None else fx
        cx, cy = get("cx", w / 2.0), get("cy", h / 2.0)
        if "file_path" not in fr or "transform_matrix" not in fr:
            raise SceneError(f"{source}: frame {i} needs 'file_path' and 'transform_matrix'")
        T = np.asarray(fr["transform_matrix"], dtype=np.float64)
        if T.shape == (3, 4):
            T = np.vstack([T, [0, 0, 0, 1]])
        if T.shape != (4, 4):
            raise SceneError(f"{source}: frame {i}: 'transform_matrix' must be 4x4")
        dist = None
        if any(get(k) is not None for k in _DIST_KEYS):
            dist = parse_distortion({k: get(k, 0.0) for k in _DIST_KEYS}, source, f"frame {i}")
        cams.append(Camera(int(w), int(h), float(fx), float(fy), float(cx), float(cy),
                           T @ _GL_TO_CV, dist=dist, image=str(fr["file_path"]).lstrip("./") if
                           str(fr["file_path"]).startswith("./") else str(fr["file_path"])))
    return cams


def cameras_to_transforms(cameras: Iterable[Camera]) -> dict:
    """The nerfstudio ``transforms.json`` layout (OpenGL axes) for ``cameras``."""
    cameras = list(cameras)
    ref = cameras[0]
    return {
        "camera_model": "OPENCV",
        "w": ref.width, "h": ref.height, "fl_x": ref.fx, "fl_y": ref.fy,
        "cx": ref.cx, "cy": ref.cy,
        "frames": [{"file_path": c.image, "transform_matrix": (c.c2w @ _GL_TO_CV).tolist()}
                   for c in cameras],
    }


def stack_for_render(cameras: list[Camera], device=None, dtype=None):
    """Stack cameras into gsplat-style tensors: ``viewmats`` [C, 4, 4] (world-to-camera) and
    ``Ks`` [C, 3, 3]. All cameras must share width/height."""
    import torch

    dtype = dtype or torch.float32
    viewmats = torch.tensor(np.stack([c.w2c for c in cameras]), dtype=dtype, device=device)
    Ks = torch.tensor(np.stack([c.K for c in cameras]), dtype=dtype, device=device)
    return viewmats, Ks
