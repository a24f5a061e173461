"""The procedural scene in two states, its cameras and its ray tracer (numpy, vectorised)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from ..cameras import Camera
from ..io import linear_to_srgb, srgb_to_linear
from .model import STATES, Lighting, Orbit, Sun, SynthObject, check_state
from .noise import hash01
from .presets import SynthPreset
from .shapes import box_hit, safe_dir
from .textures import texture_albedo

_SHADOW_OFFSET = 1e-4  # shadow-ray origin offset along the normal (metres)

ROOM_FACES = ("floor", "ceiling", "wall_+x", "wall_-x", "wall_+y", "wall_-y")
_TABLE = 6  # primitive code of the table; objects are 7 + index into SynthScene.objects
_FIRST_OBJECT = 7


class SynthScene:
    """A procedural scene in two states, with cameras and a ray tracer.

    Build with :func:`build_scene`. Objects are in :attr:`objects`; :attr:`changed_ids` lists
    the ids of every changed object (added, removed, moved, replaced and replacement);
    :attr:`change_types` maps id -> ``"added" | "removed" | "moved"``; :attr:`changes` lists the
    change events (with ``"replaced"`` events pairing two ids).
    """

    def __init__(self, preset: SynthPreset, seed: int, objects: list[SynthObject],
                 lighting: dict[str, Lighting], orbits: dict[str, Orbit],
                 train_c2w: dict[str, list[np.ndarray]], eval_c2w: list[np.ndarray],
                 room_textures: dict[str, tuple[str, dict]], changes: list[dict]):
        self.preset = preset
        self.seed = seed
        self.objects = objects
        self.lighting = lighting
        self.orbits = orbits
        self._train_c2w = train_c2w
        self._eval_c2w = eval_c2w
        self.room_textures = room_textures
        self.changes = changes
        self.table_lo = np.array([-preset.table_half_size[0], -preset.table_half_size[1], 0.0])
        self.table_hi = np.array([preset.table_half_size[0], preset.table_half_size[1],
                                  preset.table_height])
        self._by_id = {o.id: o for o in objects}

    # -- bookkeeping --------------------------------------------------------------------------
    @property
    def target(self) -> np.ndarray:
        """The point all cameras look at (table centre, slightly raised), world [3]."""
        return np.array([0.0, 0.0, self.preset.table_height + 0.15])

    @property
    def changed_ids(self) -> list[int]:
        return sorted(o.id for o in self.objects if o.change is not None)

    @property
    def change_types(self) -> dict[int, str]:
        return {o.id: o.change for o in self.objects if o.change is not None}

    def object(self, obj_id: int) -> SynthObject:
        return self._by_id[obj_id]

    def objects_in(self, state: str) -> list[SynthObject]:
        check_state(state)
        return [o for o in self.objects if o.present(state)]

    def object_transform(self, obj: SynthObject, state: str) -> tuple[np.ndarray, np.ndarray]:
        """Rotation R [3, 3] and translation T [3] with world = R @ local + T (None if absent)."""
        pose = obj.poses[state]
        if pose is None:
            raise ValueError(f"object {obj.id} is not present in state {state!r}")
        c, s = math.cos(pose.rot_z), math.sin(pose.rot_z)
        R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        return R, np.array([pose.x, pose.y, self.preset.table_height])

    def object_center(self, obj: SynthObject, state: str) -> np.ndarray:
        """World centre [3] of the object's local bounding box in ``state``."""
        R, T = self.object_transform(obj, state)
        return R @ (0.5 * (obj.shape.lo + obj.shape.hi)) + T

    def object_top(self, obj: SynthObject, state: str) -> np.ndarray:
        """World point [3] at the top of the object's axis (its highest surface point)."""
        R, T = self.object_transform(obj, state)
        return R @ np.array([0.0, 0.0, obj.shape.hi[2]]) + T

    def object_bbox(self, obj: SynthObject, state: str) -> np.ndarray:
        """World axis-aligned bounding box [2, 3] (min, max) in ``state``."""
        R, T = self.object_transform(obj, state)
        lo, hi = obj.shape.lo, obj.shape.hi
        corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])
                            for z in (lo[2], hi[2])]) @ R.T + T
        return np.stack([corners.min(0), corners.max(0)])

    # -- cameras ------------------------------------------------------------------------------
    def intrinsics(self) -> dict:
        """Shared pinhole intrinsics (pixels; principal point at the image centre)."""
        p = self.preset
        f = 0.5 * p.width / math.tan(math.radians(p.hfov_deg) / 2)
        return {"width": p.width, "height": p.height, "fx": f, "fy": f,
                "cx": p.width / 2.0, "cy": p.height / 2.0}

    def _camera(self, c2w, image=None, set_=None, time_=None) -> Camera:
        return Camera(**self.intrinsics(), c2w=c2w, image=image, set=set_, time=time_)

    def cameras(self, split: str) -> list[Camera]:
        """Cameras of ``split``: ``before``/``after`` (training views, with image paths, set and
        time), ``eval`` (evaluation viewpoints, no image/state), or ``eval_before`` /
        ``eval_after`` (the eval viewpoints as the frames of that state)."""
        if split in STATES:
            return [self._camera(c, f"{split}/{i:03d}.png", split, STATES.index(split))
                    for i, c in enumerate(self._train_c2w[split])]
        if split == "eval":
            return [self._camera(c) for c in self._eval_c2w]
        if split in ("eval_before", "eval_after"):
            st = split[5:]
            return [self._camera(c, f"eval/{st}/{i:03d}.png", split, STATES.index(st))
                    for i, c in enumerate(self._eval_c2w)]
        raise ValueError(f"unknown split {split!r}; use before, after, eval, eval_before or "
                         "eval_after")

    # -- ray tracing --------------------------------------------------------------------------
    def _casters(self, state: str):
        """(code, intersect fn, R, T, bounding-sphere centre [3], radius) for the table and
        every object present in ``state`` (world = R @ local + T)."""
        lo, hi = self.table_lo, self.table_hi
        out = [(_TABLE, lambda o, d: box_hit(o, d, lo, hi), np.eye(3), np.zeros(3),
                0.5 * (lo + hi), 0.5 * float(np.linalg.norm(hi - lo)))]
        for k, obj in enumerate(self.objects):
            if obj.present(state):
                R, T = self.object_transform(obj, state)
                lo_, hi_ = obj.shape.lo, obj.shape.hi
                out.append((_FIRST_OBJECT + k, obj.shape.intersect, R, T,
                            R @ (0.5 * (lo_ + hi_)) + T, 0.5 * float(np.linalg.norm(hi_ - lo_))))
        return out

    def _room_hit(self, o, d):
        """Exit point of rays from inside the room box: t [N], face code [N], inward normal."""
        R, H = self.preset.room_half_size, self.preset.room_height
        lo = np.array([-R, -R, 0.0])
        hi = np.array([R, R, H])
        dd = safe_dir(d)
        bound = np.where(dd > 0, hi, lo)
        ts = (bound - o) / dd
        ax = ts.argmin(axis=1)
        t = ts[np.arange(len(o)), ax]
        pos = dd[np.arange(len(o)), ax] > 0
        # faces: z- floor 0, z+ ceiling 1, x+ 2, x- 3, y+ 4, y- 5
        code = np.select([ax == 2, ax == 0, ax == 1], [np.where(pos, 1, 0), np.where(pos, 2, 3),
                                                        np.where(pos, 4, 5)])
        n = np.zeros_like(o)
        n[np.arange(len(o)), ax] = np.where(pos, -1.0, 1.0)
        return t, code, n

    def trace(self, o: np.ndarray, d: np.ndarray, state: str):
        """Nearest hit of rays ``o``, ``d`` [N, 3] (world, unit directions) in ``state``.

        Returns ``t`` [N] (ray parameter, metres), ``code`` [N] (0-5 room faces, 6 table,
        7 + k object k of :attr:`objects`) and world normals ``n`` [N, 3] facing the ray.
        """
        t, code, n = self._room_hit(o, d)
        cull = _RayCull(o, d)
        for c, fn, R, T, bc, br in self._casters(state):
            idx = cull.candidates(bc, br, t)
            if len(idx) == 0:
                continue
            tl, nl = fn((o[idx] - T) @ R, d[idx] @ R)
            better = tl < t[idx]
            sel = idx[better]
            t[sel] = tl[better]
            code[sel] = c
            n[sel] = nl[better] @ R.T
        return t, code.astype(np.int64), n

    def occluded(self, o: np.ndarray, d: np.ndarray, state: str,
                 t_max: np.ndarray | None = None) -> np.ndarray:
        """Whether rays ``o``, ``d`` [N, 3] hit the table or an object before ``t_max`` [N]
        (default: anywhere) -> bool [N]. Walls and ceiling never block (shadow rays)."""
        occ = np.zeros(len(o), dtype=bool)
        far = np.full(len(o), np.inf) if t_max is None else np.asarray(t_max, dtype=float)
        cull = _RayCull(o, d)
        for _, fn, R, T, bc, br in self._casters(state):
            idx = cull.candidates(bc, br, far)
            idx = idx[~occ[idx]]
            if len(idx) == 0:
                continue
            tl, _ = fn((o[idx] - T) @ R, d[idx] @ R)
            occ[idx[tl < far[idx]]] = True
        return occ

    def _albedo(self, p: np.ndarray, code: np.ndarray, state: str) -> np.ndarray:
        """sRGB albedo [N, 3] at world points ``p`` on primitives ``code``."""
        out = np.zeros_like(p)
        for c in np.unique(code):
            m = code == c
            q = p[m]
            if c < _TABLE:
                kind, prm = self.room_textures[ROOM_FACES[c]]
                if c in (0, 1):
                    uv = q[:, [0, 1]]
                elif c in (2, 3):
                    uv = q[:, [1, 2]]
                else:
                    uv = q[:, [0, 2]]
                local = np.concatenate([uv, np.zeros((len(q), 1))], 1)
            elif c == _TABLE:
                kind, prm = self.room_textures["table"]
                local = q
            else:
                obj = self.objects[c - _FIRST_OBJECT]
                R, T = self.object_transform(obj, state)
                kind, prm, local = obj.texture, obj.texture_params, (q - T) @ R
            out[m] = texture_albedo(kind, local, prm)
        return out

    def _light_dirs(self, p: np.ndarray, state: str, sun_dirs=None):
        """For each light of ``state``: (unit directions [N, 3] from ``p`` to the light,
        distance [N] or None for suns, strength x fall-off ([N] or scalar), colour [3]).
        ``sun_dirs`` optionally gives per-sun sampled directions [N, 3]."""
        L = self.lighting[state]
        for k, sun in enumerate(L.suns):
            ld = np.broadcast_to(sun.direction, p.shape) if sun_dirs is None else sun_dirs[k]
            yield ld, None, sun.strength, np.asarray(sun.color)
        for pt in L.points:
            v = np.asarray(pt.position) - p
            dist = np.linalg.norm(v, axis=1)
            yield v / dist[:, None], dist, pt.strength / dist ** 2, np.asarray(pt.color)

    def _visible(self, p, n, ld, dist, state, shadows: bool):
        """cos(angle) [N] (0 when facing away) and whether the light is unblocked [N]."""
        ndl = np.maximum(np.einsum("ij,ij->i", n, ld), 0.0)
        vis = ndl > 0
        if shadows and vis.any():
            idx = np.flatnonzero(vis)
            vis[idx] = ~self.occluded(p[idx] + _SHADOW_OFFSET * n[idx], ld[idx], state,
                                      None if dist is None else dist[idx])
        return ndl, vis

    def irradiance(self, p: np.ndarray, n: np.ndarray, state: str, shadows: bool = True,
                   sun_dirs=None) -> np.ndarray:
        """Linear RGB irradiance [N, 3] at world points ``p`` [N, 3] with unit normals ``n``:
        hemispherical ambient + every sun (towards its centre, or ``sun_dirs``) and point light
        (inverse-square fall-off), with cast shadows unless ``shadows`` is false."""
        L = self.lighting[state]
        e = np.outer(L.ambient * (0.75 + 0.25 * n[:, 2]), np.asarray(L.ambient_color))
        for ld, dist, strength, color in self._light_dirs(p, state, sun_dirs):
            ndl, vis = self._visible(p, n, ld, dist, state, shadows)
            e += np.outer(strength * ndl * vis, color)
        return e

    def render(self, camera: Camera, state: str, supersample: int | None = None,
               shadows: bool = True) -> dict[str, np.ndarray]:
        """Render ``camera`` in ``state`` ("before" | "after").

        Returns a dict of numpy arrays:

        * ``rgb`` float32 [H, W, 3]: sRGB-encoded colour in [0, 1], ``supersample`` x
          ``supersample`` rays per pixel (default: the preset's);
        * ``depth`` float32 [H, W]: z-depth along the camera's +z axis (metres), pixel centres;
        * ``normal`` float32 [H, W, 3]: world unit normal facing the camera, pixel centres;
        * ``ids`` int32 [H, W]: object id (>= 1) or 0 (room, table), pixel centres;
        * ``changed`` bool [H, W]: pixel centre shows an object of :attr:`changed_ids`;
        * ``shadow`` bool [H, W]: the pixel-centre surface faces a light but the light (the
          sun's centre) is blocked by the table or an object (a cast shadow).

        ``shadows=False`` skips shadow rays (no cast shadows; for tests and comparisons).
        """
        check_state(state)
        ss = int(supersample or self.preset.supersample)
        H, W = camera.height, camera.width
        gt = self._trace_centres(camera, state, shadows)

        o, d = _camera_rays(camera, ss)
        t, code, n = self.trace(o, d, state)
        p = o + t[:, None] * d
        alb = srgb_to_linear(self._albedo(p, code, state))
        L = self.lighting[state]
        dirs = [_sun_disc_dirs(s, H, W, ss, self.seed + 31 * k) for k, s in enumerate(L.suns)]
        e = self.irradiance(p, n, state, shadows, dirs)
        radiance = 1.0 - np.exp(-alb * e)  # exponential tone curve (linear in, linear out)
        lin = radiance.reshape(H, W, ss * ss, 3).mean(axis=2)
        gt["rgb"] = linear_to_srgb(lin).astype(np.float32)
        return gt

    def _trace_centres(self, camera: Camera, state: str, shadows: bool) -> dict:
        H, W = camera.height, camera.width
        o, d = _camera_rays(camera, 1)
        t, code, n = self.trace(o, d, state)
        zaxis = camera.c2w[:3, 2]
        depth = t * (d @ zaxis)
        ids = np.zeros(len(o), dtype=np.int32)
        obj_ids = np.array([ob.id for ob in self.objects], dtype=np.int32)
        is_obj = code >= _FIRST_OBJECT
        ids[is_obj] = obj_ids[code[is_obj] - _FIRST_OBJECT]
        shadow = np.zeros(len(o), dtype=bool)
        if shadows:
            p = o + t[:, None] * d
            for ld, dist, _, _ in self._light_dirs(p, state):
                ndl, vis = self._visible(p, n, ld, dist, state, True)
                shadow |= (ndl > 0) & ~vis
        changed = np.isin(ids, np.asarray(self.changed_ids, dtype=np.int32))
        return {"depth": depth.reshape(H, W).astype(np.float32),
                "normal": n.reshape(H, W, 3).astype(np.float32),
                "ids": ids.reshape(H, W),
                "changed": changed.reshape(H, W),
                "shadow": shadow.reshape(H, W)}

    # -- metadata -----------------------------------------------------------------------------
    def meta(self) -> dict:
        """JSON-ready description of the scene (objects, changes, lighting, cameras, room)."""
        p = self.preset
        objs = []
        for o in self.objects:
            entry = {"name": o.name, "id": o.id, "kind": o.kind,
                     "dimensions": dataclasses.asdict(o.shape),
                     "footprint_radius": o.shape.footprint, "height": float(o.shape.hi[2]),
                     "texture": o.texture, "texture_params": o.texture_params,
                     "changed": o.change is not None, "change": o.change}
            if o.replaces is not None:
                entry["replaces"] = o.replaces
            if o.replaced_by is not None:
                entry["replaced_by"] = o.replaced_by
            for st in STATES:
                if o.present(st):
                    bb = self.object_bbox(o, st)
                    pose = o.poses[st]
                    entry[st] = {"present": True,
                                 "location": [pose.x, pose.y, p.table_height],
                                 "rotation_z": pose.rot_z, "support": "table",
                                 "bbox_world": bb.tolist(),
                                 "bbox_center_world": self.object_center(o, st).tolist(),
                                 "anchor_world": self.object_top(o, st).tolist()}
                else:
                    entry[st] = {"present": False}
            objs.append(entry)
        light_changes = self.lighting["before"] != self.lighting["after"]
        return {
            "scene_center": self.target.tolist(),
            "room": {"room_half_size": p.room_half_size, "wall_height": p.room_height,
                     "support": "table slab {:.2f}x{:.2f}x{:.2f} m (wood)".format(
                         2 * p.table_half_size[0], 2 * p.table_half_size[1], p.table_height),
                     "textures": {k: {"kind": v[0], "params": v[1]}
                                  for k, v in self.room_textures.items()},
                     "note": "walls and ceiling do not cast shadows; table and objects do"},
            "changes": self.changes,
            "changed_objects": [self.object(i).name for i in self.changed_ids],
            "changed_ids": self.changed_ids,
            "n_objects": {st: len(self.objects_in(st)) for st in STATES},
            "objects": objs,
            "lighting": {"mode": p.lighting, "changes": light_changes,
                         "before": self.lighting["before"].to_json(),
                         "after": self.lighting["after"].to_json()},
            "cameras": {"n_before": p.n_before, "n_after": p.n_after, "n_eval": p.n_eval,
                        "hfov_deg": p.hfov_deg,
                        "orbits": {st: dataclasses.asdict(self.orbits[st]) for st in STATES},
                        "jitter_m": p.jitter_m,
                        "eval_min_distance_to_training_camera_m":
                            self.eval_min_distance_to_training()},
        }

    def eval_min_distance_to_training(self) -> float:
        """Smallest distance (metres) from an eval camera centre to a training camera centre."""
        tr = np.array([c[:3, 3] for st in STATES for c in self._train_c2w[st]])
        ev = np.array([c[:3, 3] for c in self._eval_c2w])
        return float(np.linalg.norm(ev[:, None] - tr[None], axis=2).min())


class _RayCull:
    """Cheap bounding-sphere culling for a batch of rays ``o``, ``d`` [N, 3] (unit ``d``)."""
    def __init__(self, o: np.ndarray, d: np.ndarray):
        self.o, self.d = o, d
        self.od = np.einsum("ij,ij->i", o, d)
        self.oo = np.einsum("ij,ij->i", o, o)

    def candidates(self, centre: np.ndarray, radius: float, t_max: np.ndarray) -> np.ndarray:
        """Indices of rays passing within ``radius`` of ``centre`` at some t in (0, t_max)."""
        tca = self.d @ centre - self.od
        d2 = centre @ centre - 2.0 * (self.o @ centre) + self.oo - tca * tca
        ok = (d2 <= radius * radius) & (tca + radius > 0) & (tca - radius < t_max)
        return np.flatnonzero(ok)


def _camera_rays(cam: Camera, ss: int) -> tuple[np.ndarray, np.ndarray]:
    """World ray origins and unit directions [H*W*ss*ss, 3], ordered (row, col, sub-sample).

    Sub-sample (a, b) of pixel (col i, row j) passes through pixel coordinates
    (i + (a + 0.5)/ss, j + (b + 0.5)/ss); ss = 1 gives the pixel centres (i + 0.5, j + 0.5).
    """
    off = (np.arange(ss) + 0.5) / ss
    jj, ii, bb, aa = np.meshgrid(np.arange(cam.height), np.arange(cam.width), off, off,
                                 indexing="ij")
    u = (ii + aa).ravel()
    v = (jj + bb).ravel()
    dc = np.stack([(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, np.ones_like(u)], 1)
    d = dc @ cam.c2w[:3, :3].T
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    o = np.broadcast_to(cam.c2w[:3, 3], d.shape).copy()
    return o, d


def _sun_disc_dirs(sun: Sun, H: int, W: int, ss: int, seed: int) -> np.ndarray:
    """Directions [H*W*ss*ss, 3] to points on the sun's disc, one per colour ray.

    Sub-sample k of a pixel takes the k-th point of a golden-angle spiral over the disc,
    rotated by a per-pixel hash angle, so averaged penumbrae are smooth and deterministic.
    """
    n = ss * ss
    centre = sun.direction
    if sun.angle_deg <= 0:
        return np.broadcast_to(centre, (H * W * n, 3)).copy()
    half = math.radians(sun.angle_deg) / 2
    a = np.cross(centre, [0.0, 0.0, 1.0])
    if np.linalg.norm(a) < 1e-6:
        a = np.cross(centre, [1.0, 0.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(centre, a)
    k = np.arange(n)
    rad = np.sqrt((k + 0.5) / n) * math.tan(half)
    ang0 = k * 2.39996322972865332
    jj, ii = np.meshgrid(np.arange(H), np.arange(W), indexing="ij")
    rot = hash01(seed, jj.ravel(), ii.ravel()) * 2 * np.pi
    ang = (rot[:, None] + ang0[None, :]).ravel()
    r = np.tile(rad, H * W)
    dirs = centre + (r * np.cos(ang))[:, None] * a + (r * np.sin(ang))[:, None] * b
    return dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
