"""Robot captures with ROS tf poses: per-frame ``/map -> camera optical frame`` transforms in
YAML and a ROS ``CameraInfo`` (intrinsics and plumb-bob distortion).

Expected layout (``SRC``)::

    SRC/before/*.png|jpg              photos of the first visit
    SRC/after/*.png|jpg               photos of the second visit
    SRC/eval/{before,after,masks}/    optional eval views (copied as they are)
    SRC/[robot/]*transformations.yaml the poses (one or more files, e.g. one per visit)
    SRC/[robot/]camera_info.json|yaml ROS CameraInfo (``K``, ``D``, ``width``, ``height``;
                                      or the calibration YAML's ``camera_matrix.data``,
                                      ``distortion_coefficients.data``, ``image_width``, ...)
    SRC/[robot/]provenance.json       optional: ``views`` [{set, name, src_path}] mapping each
                                      photo to the frame file the poses name

A transformations file is a YAML list with one entry per recorded frame::

    - file_name: <image file the pose belongs to>
      origin_frame: /map
      target_frame: /head_rgbd_sensor_rgb_frame    # an optical frame: x right, y down, z fwd
      translation: {x, y, z}                       # camera position in the map frame
      rotation: {w, x, y, z}                       # camera orientation (unit quaternion)

i.e. the pose of the camera's optical frame in the map frame, which is gdiff's OpenCV
camera-to-world. All visits must share one map frame (a robot localising in one map does).
A photo is matched to its entry by the base name of its ``provenance.json`` ``src_path``, or
else by its own file name.

Intrinsics: ROS puts pixel centres at integer coordinates, gdiff at +0.5, so ``cx, cy`` gain
0.5 pixel. The distortion ``D`` goes into ``cameras.json`` as ``distortion``; the poses stage
undistorts the photos once. Only ``plumb_bob`` / ``rational_polynomial`` models are accepted.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import yaml

from ..cameras import Camera, parse_distortion
from ..errors import SceneError
from ._common import SceneWriter, list_images, need_dir

FORMAT = "tf-yaml"
SUMMARY = ("tf-yaml: SRC/{before,after}/ + [robot/]*transformations.yaml (ROS tf /map -> "
           "camera optical frame), camera_info.json|yaml, [provenance.json]")


def _load_yaml(path: Path):
    try:
        return yaml.safe_load(path.read_text())
    except yaml.YAMLError as e:
        raise SceneError(f"{path}: not valid YAML/JSON ({e})") from None


def _find(src: Path, pattern: str) -> list[Path]:
    out = []
    for d in (src, src / "robot"):
        if d.is_dir():
            out += sorted(d.glob(pattern))
    return out


def quat_to_matrix(w: float, x: float, y: float, z: float) -> np.ndarray:
    """Rotation matrix [3, 3] of the quaternion (w, x, y, z) (normalised first)."""
    q = np.array([w, x, y, z], dtype=np.float64)
    n = np.linalg.norm(q)
    if not np.isfinite(n) or n < 1e-9:
        raise ValueError("zero or non-finite quaternion")
    w, x, y, z = q / n
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def read_transforms(path: Path) -> dict[str, np.ndarray]:
    """``file_name -> c2w`` [4, 4] (OpenCV axes, map frame) of a transformations YAML."""
    data = _load_yaml(path)
    if not isinstance(data, list) or not data:
        raise SceneError(f"{path}: expected a YAML list of frames with file_name, translation "
                         "{x, y, z} and rotation {w, x, y, z}")
    out = {}
    for i, fr in enumerate(data):
        try:
            name = str(fr["file_name"])
            t, r = fr["translation"], fr["rotation"]
            c2w = np.eye(4)
            c2w[:3, :3] = quat_to_matrix(r["w"], r["x"], r["y"], r["z"])
            c2w[:3, 3] = [float(t["x"]), float(t["y"]), float(t["z"])]
        except (KeyError, TypeError, ValueError) as e:
            raise SceneError(f"{path}: entry {i}: needs file_name, translation {{x, y, z}} and "
                             f"rotation {{w, x, y, z}} (a non-zero quaternion); problem: "
                             f"{e!r}") from None
        if not np.isfinite(c2w).all():
            raise SceneError(f"{path}: entry {i} ({name}): non-finite pose")
        out[Path(name).name] = c2w
    return out


def read_camera_info(path: Path) -> Camera:
    """Pinhole intrinsics (gdiff pixel centres at +0.5) and distortion of a ROS CameraInfo
    (message as JSON/YAML, or a camera_calibration YAML file)."""
    d = _load_yaml(path)
    if not isinstance(d, dict):
        raise SceneError(f"{path}: expected a ROS CameraInfo mapping")

    def data(key):
        v = d.get(key)
        return v.get("data") if isinstance(v, dict) else v

    K = data("K") or data("k") or data("camera_matrix")
    D = data("D") if "D" in d else (data("d") if "d" in d else data("distortion_coefficients"))
    w = d.get("width", d.get("image_width"))
    h = d.get("height", d.get("image_height"))
    model = str(d.get("distortion_model", "plumb_bob"))
    if K is None or len(K) != 9 or w is None or h is None:
        raise SceneError(f"{path}: needs K (9 numbers, row-major), width and height (ROS "
                         "CameraInfo) or camera_matrix, image_width, image_height")
    if model not in ("plumb_bob", "rational_polynomial"):
        raise SceneError(f"{path}: distortion_model {model!r} is not supported; gdiff takes "
                         "plumb_bob (k1, k2, p1, p2, k3) or rational_polynomial")
    dist = parse_distortion(list(D), str(path), "D") if D else None
    return Camera(int(w), int(h), float(K[0]), float(K[4]), float(K[2]) + 0.5,
                  float(K[5]) + 0.5, dist=dist)


def _provenance(src: Path) -> dict[tuple[str, str], str]:
    files = _find(src, "provenance.json")
    if not files:
        return {}
    data = _load_yaml(files[0])
    out = {}
    for v in (data or {}).get("views", []):
        if "set" in v and "name" in v and "src_path" in v:
            out[(str(v["set"]), str(v["name"]))] = Path(str(v["src_path"])).name
    return out


def build(src: Path, w: SceneWriter) -> None:
    tf_files = _find(src, "*transformations.yaml") or _find(src, "*transformations.yml")
    if not tf_files:
        raise SceneError(f"{src}: no *transformations.yaml in the folder or in robot/; a "
                         "tf-yaml scene needs the robot's camera poses there")
    info = _find(src, "camera_info.json") + _find(src, "camera_info.yaml")
    if not info:
        raise SceneError(f"{src}: no camera_info.json or camera_info.yaml (ROS CameraInfo) in "
                         "the folder or in robot/")
    intr = read_camera_info(info[0])
    poses: dict[str, np.ndarray] = {}
    for f in tf_files:
        for name, c2w in read_transforms(f).items():
            if name in poses and not np.allclose(poses[name], c2w):
                raise SceneError(f"{f}: frame {name} has a different pose in another "
                                 "transformations file")
            poses[name] = c2w
    prov = _provenance(src)
    for st, folder in (("before", "before"), ("after", "after"),
                       ("eval_before", "eval/before"), ("eval_after", "eval/after")):
        d = src / folder
        if st in ("before", "after"):
            need_dir(d, f"the {st} photos", FORMAT)
        elif not d.is_dir():
            continue
        for p in list_images(d):
            key = prov.get((st, p.name), p.name)
            c2w = poses.get(key)
            w.add_image(st, p, None if c2w is None else intr.with_pose(c2w))
    masks = src / "eval" / "masks"
    if masks.is_dir():
        for m in list_images(masks):
            w.add_mask("masks", m.stem, m)
    if w.unposed:
        raise SceneError(f"{src}: no pose in {', '.join(f.name for f in tf_files)} for "
                         f"{len(w.unposed)} photo(s), e.g. {w.unposed[0]}; the entries' "
                         "file_name must match the photo's name or its provenance.json src_path")
    w.note(f"poses from {', '.join(f.name for f in tf_files)} (camera optical frame in the map "
           f"frame); intrinsics from {info[0].name}"
           + (f" with distortion {list(intr.dist)}" if intr.dist else ""))
