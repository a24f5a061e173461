"""Camera pose interpolation: dense paths through the before poses (P~1) and the after poses (P~2).

Following the paper's Sec. "Camera pose interpolation": the key poses of each set are put in
order, and between consecutive key poses ``p_i`` and ``p_{i+1}`` ``n`` poses are inserted at
``Δ_j = j / (n + 1)``, ``j = 1..n``:

* rotation: spherical linear interpolation of unit quaternions,
  ``Q_ij = sin((1-Δ_j)θ)/sinθ · Q_i + sin(Δ_j θ)/sinθ · Q_{i+1}``, θ the angle between them,
  along the shorter arc (``Q_{i+1}`` is negated when ``Q_i · Q_{i+1} < 0``, since ``q`` and
  ``-q`` are the same rotation);
* position: the camera centres (not the world-to-camera translations) linearly,
  ``C_ij = (1-Δ_j) C_i + Δ_j C_{i+1}``.

The key poses stay in the path. The two paths are separate: nothing is generated between the
last before pose and the first after pose.

"Consecutive" must mean neighbours in space. When the capture order has large jumps, the poses
of a set are reordered into a short open path first (nearest-neighbour tours from every start,
improved with 2-opt) under a cost that adds the centre distance (in units of the scene radius,
the median distance of all key centres from their centroid) and the rotation angle (radians,
times ``rotation_weight``).

Output ``sequence/poses.json`` (see docs/design.md)::

    {"width","height","fx","fy","cx","cy",
     "paths": {"p1": {"set": "before", "order": [key images in path order], "reordered": bool,
                      "frames": [{"c2w": 4x4, "key": true, "image": "before/003.png"},
                                 {"c2w": 4x4, "key": false}, ...]},
               "p2": {"set": "after", ...}}}

A frame carries ``fx, fy, cx, cy`` only when its intrinsics differ from the top level.
"""

from __future__ import annotations

import logging
import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from .align import angle_between_deg, orbit_radius, rotation_angle_deg
from .cameras import Camera, image_root, load_cameras
from .errors import SceneError
from .io import read_json, write_json

log = logging.getLogger("gdiff.interpolate")

PATHS = {"p1": "before", "p2": "after"}
_INTRINSICS = ("fx", "fy", "cx", "cy")


@dataclass
class InterpolateOptions:
    """Options of the interpolate stage (config section ``interpolate``).

    Attributes:
        n: poses inserted at least between consecutive key poses (the paper's fixed n when
            ``max_angle_deg`` and ``max_step`` are null).
        max_angle_deg: if set, each gap gets enough poses that consecutive frames differ by at
            most this rotation angle (degrees).
        max_step: if set, each gap gets enough poses that consecutive camera centres are at most
            this far apart, as a fraction of the scene radius (median distance of the key
            camera centres from their centroid).
        reorder: ``auto`` (reorder a set into a short path when its capture order has a jump),
            ``always`` or ``never``.
        jump_factor: ``auto`` calls a capture order jumpy when its largest step costs more than
            ``jump_factor`` times its median step.
        rotation_weight: weight of the rotation angle (radians) against the centre distance
            (scene radii) in the step cost used for ordering.

    By default the frames are spaced by what the tracker needs (small steps between
    consecutive frames), not by the photo count: photos taken closer together get fewer
    poses between them, so render, segment and compare cost follows the length of the path
    rather than the number of photos.
    """

    n: int = 0
    max_angle_deg: float | None = 2.5
    max_step: float | None = 0.08
    reorder: str = "auto"
    jump_factor: float = 3.0
    rotation_weight: float = 1.0

    def __post_init__(self):
        if self.n < 0:
            raise ValueError("n must be >= 0")
        if self.max_angle_deg is not None and self.max_angle_deg <= 0:
            raise ValueError("max_angle_deg must be > 0 (or null)")
        if self.max_step is not None and self.max_step <= 0:
            raise ValueError("max_step must be > 0 (or null)")
        if self.reorder not in ("auto", "always", "never"):
            raise ValueError(f"reorder must be auto, always or never, not {self.reorder!r}")
        if self.jump_factor <= 1.0:
            raise ValueError("jump_factor must be > 1")
        if self.rotation_weight < 0:
            raise ValueError("rotation_weight must be >= 0")


# --------------------------------------------------------------------------------------------
# Interpolation primitives


def slerp(q0: np.ndarray, q1: np.ndarray, delta: np.ndarray | float) -> np.ndarray:
    """Spherical linear interpolation of unit quaternions along the shorter arc.

    Args:
        q0, q1: unit quaternions [4] (any fixed component order, e.g. scipy's x, y, z, w).
        delta: interpolation parameter(s) in [0, 1], scalar or [M].

    Returns:
        Unit quaternions [4] (scalar delta) or [M, 4]; ``delta = 0`` gives ``q0`` and
        ``delta = 1`` gives ``q1`` or ``-q1`` (the same rotation). Uses the sin-weighted form
        ``sin((1-Δ)θ)/sinθ q0 + sin(Δθ)/sinθ q1``; when θ is tiny (nearly identical
        rotations) the weights tend to ``1-Δ`` and ``Δ`` and the normalised linear form is used.
    """
    q0 = np.asarray(q0, dtype=np.float64)
    q1 = np.asarray(q1, dtype=np.float64)
    q0 = q0 / np.linalg.norm(q0)
    q1 = q1 / np.linalg.norm(q1)
    d = np.asarray(delta, dtype=np.float64)
    dot = float(q0 @ q1)
    if dot < 0.0:  # q and -q are the same rotation: take the shorter arc
        q1, dot = -q1, -dot
    theta = math.acos(min(dot, 1.0))
    if math.sin(theta) < 1e-8:
        w0, w1 = 1.0 - d, d
    else:
        w0 = np.sin((1.0 - d) * theta) / math.sin(theta)
        w1 = np.sin(d * theta) / math.sin(theta)
    q = np.multiply.outer(w0, q0) + np.multiply.outer(w1, q1)
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def interpolate_pair(a: Camera, b: Camera, n: int) -> list[Camera]:
    """The ``n`` cameras strictly between ``a`` and ``b`` (Δ_j = j/(n+1), j = 1..n).

    Rotations (camera-to-world) by :func:`slerp`, camera centres and intrinsics linearly.
    Width/height must match. Returned cameras have ``image = None`` and ``a``'s set/time.
    """
    if n <= 0:
        return []
    if (a.width, a.height) != (b.width, b.height):
        raise SceneError(f"cannot interpolate between {a.image} ({a.width}x{a.height}) and "
                         f"{b.image} ({b.width}x{b.height}): image sizes differ")
    deltas = np.arange(1, n + 1) / (n + 1)
    qa = Rotation.from_matrix(a.c2w[:3, :3]).as_quat()
    qb = Rotation.from_matrix(b.c2w[:3, :3]).as_quat()
    R = Rotation.from_quat(slerp(qa, qb, deltas)).as_matrix()
    C = (1.0 - deltas)[:, None] * a.center + deltas[:, None] * b.center
    out = []
    for k, d in enumerate(deltas):
        c2w = np.eye(4)
        c2w[:3, :3], c2w[:3, 3] = R[k], C[k]
        intr = {f: (1.0 - d) * getattr(a, f) + d * getattr(b, f) for f in _INTRINSICS}
        out.append(Camera(a.width, a.height, c2w=c2w, image=None, set=a.set, time=a.time,
                          **intr))
    return out


# --------------------------------------------------------------------------------------------
# Ordering


def step_costs(cams: list[Camera], scale: float, rotation_weight: float) -> np.ndarray:
    """Pairwise step cost [N, N]: centre distance / ``scale`` + ``rotation_weight`` x angle
    (radians) between the camera rotations."""
    C = np.stack([c.center for c in cams])
    R = np.stack([c.c2w[:3, :3] for c in cams])
    dist = np.linalg.norm(C[:, None] - C[None], axis=2) / scale
    rel = np.einsum("iba,jbc->ijac", R, R)  # R_i^T R_j
    ang = np.radians(rotation_angle_deg(rel))
    return dist + rotation_weight * ang


def path_length(cost: np.ndarray, order) -> float:
    order = list(order)
    return float(sum(cost[i, j] for i, j in zip(order[:-1], order[1:])))


def short_path(cost: np.ndarray) -> list[int]:
    """A short open path visiting every node once (approximate shortest Hamiltonian path).

    Nearest-neighbour tours from every start node, the shortest improved by 2-opt segment
    reversals until no reversal shortens it. ``cost`` is a symmetric [N, N] matrix.
    """
    n = len(cost)
    if n <= 2:
        return list(range(n))
    best, best_len = None, np.inf
    for s in range(n):
        order = [s]
        free = np.ones(n, bool)
        free[s] = False
        for _ in range(n - 1):
            row = np.where(free, cost[order[-1]], np.inf)
            j = int(np.argmin(row))
            order.append(j)
            free[j] = False
        ln = path_length(cost, order)
        if ln < best_len - 1e-12:
            best, best_len = order, ln
    order = np.array(best)
    improved = True
    while improved:
        improved = False
        for i in range(0, n - 1):
            for k in range(i + 1, n):
                # reverse order[i..k]; edges (i-1,i) and (k,k+1) change
                a, b = order[i - 1] if i > 0 else None, order[i]
                c, d = order[k], order[k + 1] if k + 1 < n else None
                old = (cost[a, b] if a is not None else 0) + (cost[c, d] if d is not None else 0)
                new = (cost[a, c] if a is not None else 0) + (cost[b, d] if d is not None else 0)
                if new < old - 1e-12:
                    order[i:k + 1] = order[i:k + 1][::-1].copy()
                    improved = True
    return [int(i) for i in order]


def order_poses(cams: list[Camera], options: InterpolateOptions, scale: float,
                name: str = "") -> tuple[list[int], bool]:
    """Order of the key cameras along the path and whether it differs from capture order.

    With ``reorder = auto`` the capture order is kept unless its largest step costs more than
    ``jump_factor`` x its median step. A reordered path starts at the end nearer to the first
    captured image.
    """
    n = len(cams)
    ident = list(range(n))
    if n <= 2 or options.reorder == "never":
        return ident, False
    cost = step_costs(cams, scale, options.rotation_weight)
    steps = np.array([cost[i, i + 1] for i in range(n - 1)])
    jumpy = steps.max() > options.jump_factor * max(np.median(steps), 1e-12)
    if options.reorder == "auto" and not jumpy:
        return ident, False
    order = short_path(cost)
    if path_length(cost, order) >= path_length(cost, ident) - 1e-12:
        return ident, False
    if cost[0, order[-1]] < cost[0, order[0]]:
        order = order[::-1]
    log.info("%s: capture order %s; reordered into a shorter path (cost %.3g -> %.3g)",
             name, "has a jump" if jumpy else "replaced (reorder: always)",
             path_length(cost, ident), path_length(cost, order))
    return order, order != ident


def _gap_count(a: Camera, b: Camera, options: InterpolateOptions, scale: float) -> int:
    n = options.n
    if options.max_angle_deg is not None:
        ang = angle_between_deg(a.c2w, b.c2w)
        n = max(n, math.ceil(ang / options.max_angle_deg - 1e-9) - 1)
    if options.max_step is not None:
        dist = float(np.linalg.norm(a.center - b.center)) / scale
        n = max(n, math.ceil(dist / options.max_step - 1e-9) - 1)
    return n


# --------------------------------------------------------------------------------------------
# Paths and the poses.json file


def interpolate_path(keys: list[Camera], options: InterpolateOptions, scale: float,
                     name: str = "") -> tuple[list[tuple[Camera, bool]], list[int], bool]:
    """Dense path through ``keys``: ``([(camera, is_key), ...], order, reordered)``.

    Key cameras keep their image; N keys with n poses per gap give ``N + (N-1) n`` frames.
    """
    order, reordered = order_poses(keys, options, scale, name)
    ordered = [keys[i] for i in order]
    frames: list[tuple[Camera, bool]] = []
    for i, cam in enumerate(ordered):
        frames.append((cam, True))
        if i + 1 < len(ordered):
            nxt = ordered[i + 1]
            frames += [(c, False) for c in interpolate_pair(cam, nxt,
                                                            _gap_count(cam, nxt, options, scale))]
    if len(ordered) > 1:
        cost = step_costs(ordered, scale, options.rotation_weight)
        steps = [cost[i, i + 1] for i in range(len(ordered) - 1)]
        k = int(np.argmax(steps))
        a, b = ordered[k], ordered[k + 1]
        order_txt = (", ".join(c.image or "?" for c in ordered) if reordered
                     else "capture order")
        log.info("%s: %d key poses, order: %s; largest step %s -> %s: %.1f deg, %.3f scene "
                 "radii; %d frames", name, len(keys), order_txt, a.image, b.image,
                 angle_between_deg(a.c2w, b.c2w),
                 float(np.linalg.norm(a.center - b.center)) / scale, len(frames))
    return frames, order, reordered


def build_sequence(cameras_json: str | os.PathLike, out_json: str | os.PathLike,
                   options: InterpolateOptions | None = None) -> dict:
    """Interpolated paths P~1 (before poses) and P~2 (after poses) -> ``sequence/poses.json``.

    Args:
        cameras_json: the poses stage's ``cameras.json``.
        out_json: output path (written atomically).
        options: :class:`InterpolateOptions`.

    Returns:
        Summary ``{"p1": {"keys": N1, "frames": F1, "reordered": bool}, "p2": {...}}``.
    """
    opts = options or InterpolateOptions()
    cams = load_cameras(cameras_json)
    keys = {p: [c for c in cams if c.set == st] for p, st in PATHS.items()}
    for p, st in PATHS.items():
        if not keys[p]:
            raise SceneError(f"{cameras_json}: no registered '{st}' cameras; the path {p} "
                             f"needs at least one (check the poses stage log)")
    sizes = {(c.width, c.height) for p in PATHS for c in keys[p]}
    if len(sizes) > 1:
        raise SceneError(f"{cameras_json}: the before/after cameras differ in image size "
                         f"({sorted(sizes)}); the rendered sequences need one size")
    all_keys = keys["p1"] + keys["p2"]
    scale = orbit_radius(np.stack([c.center for c in all_keys]))
    if not scale > 0:
        scale = 1.0
    ref = all_keys[0]
    top = {"width": ref.width, "height": ref.height, **{f: getattr(ref, f) for f in _INTRINSICS}}
    out = dict(top)
    root = image_root(None, cameras_json)
    if root is not None:  # undistorted photos: keep the key frames' image root
        out["image_dir"] = os.path.relpath(root, Path(out_json).parent)
    out["paths"] = {}
    summary = {}
    for p, st in PATHS.items():
        frames, order, reordered = interpolate_path(keys[p], opts, scale, name=p)
        recs = []
        for cam, key in frames:
            fr = {"c2w": cam.c2w.tolist(), "key": key}
            if key:
                fr["image"] = cam.image
            for f in _INTRINSICS:
                if getattr(cam, f) != top[f]:
                    fr[f] = getattr(cam, f)
            recs.append(fr)
        out["paths"][p] = {"set": st, "order": [keys[p][i].image for i in order],
                           "reordered": reordered, "frames": recs}
        summary[p] = {"keys": len(keys[p]), "frames": len(recs), "reordered": reordered}
    write_json(out_json, out)
    log.info("sequence: p1 %d frames (%d keys), p2 %d frames (%d keys) -> %s",
             summary["p1"]["frames"], summary["p1"]["keys"], summary["p2"]["frames"],
             summary["p2"]["keys"], out_json)
    return summary


def load_sequence(poses_json: str | os.PathLike) -> dict[str, list[Camera]]:
    """Read ``sequence/poses.json``: ``{"p1": [Camera, ...], "p2": [...]}`` in frame order.

    A key frame's camera has ``image`` set (its source photo, scene-relative); interpolated
    frames have ``image = None``. ``set``/``time`` are the path's set (before: 0, after: 1).
    """
    data = read_json(poses_json)
    src = str(poses_json)
    if not isinstance(data.get("paths"), dict):
        raise SceneError(f"{src}: no 'paths'; regenerate it with the interpolate stage")
    out = {}
    for p, path in data["paths"].items():
        st = path.get("set")
        cams = []
        for i, fr in enumerate(path.get("frames", [])):
            try:
                intr = {f: float(fr.get(f, data[f])) for f in _INTRINSICS}
                c2w = np.asarray(fr["c2w"], dtype=np.float64)
                cams.append(Camera(int(data["width"]), int(data["height"]), c2w=c2w,
                                   image=fr.get("image") if fr.get("key") else None, set=st,
                                   time=0 if st == "before" else 1, **intr))
            except (KeyError, TypeError, ValueError) as e:
                raise SceneError(f"{src}: path {p} frame {i} is malformed ({e})") from None
        out[p] = cams
    return out
