"""Random scene construction from a preset and a seed (deterministic), and orbit paths."""

from __future__ import annotations

import colorsys
import math
import zlib

import numpy as np

from ..cameras import Camera
from ..errors import GdiffError
from .model import (STATES, Lighting, Orbit, PointLight, Pose2D, Sun, SynthObject,
                    check_state, jittered_pose, kelvin_rgb)
from .presets import SynthPreset, get_preset
from .scene import ROOM_FACES, SynthScene
from .shapes import SHAPES, random_shape
from .textures import OBJECT_TEXTURES


def _random_color(rng, sat=(0.45, 0.9), val=(0.45, 0.92)) -> list[float]:
    """A random sRGB colour from HSV ranges."""
    h = rng.uniform()
    return list(colorsys.hsv_to_rgb(h, rng.uniform(*sat), rng.uniform(*val)))


def _contrast_pair(rng) -> list[list[float]]:
    """Two colours of clearly different hue and value."""
    h = rng.uniform()
    c0 = colorsys.hsv_to_rgb(h, rng.uniform(0.5, 0.9), rng.uniform(0.25, 0.45))
    c1 = colorsys.hsv_to_rgb((h + rng.uniform(0.25, 0.75)) % 1, rng.uniform(0.2, 0.7),
                             rng.uniform(0.8, 0.95))
    return [list(c0), list(c1)]


def _object_texture(rng, kind: str, shape) -> dict:
    """Random parameters (palette, scale, seed, axis) of object texture ``kind``."""
    seed = int(rng.integers(0, 2 ** 31))
    pal = _contrast_pair(rng) + [_random_color(rng) for _ in range(2)]
    axis = rng.normal(size=3)
    axis[2] += 1.5 * np.sign(axis[2] or 1.0)
    axis = (axis / np.linalg.norm(axis)).tolist()
    prm = {"seed": seed, "palette": pal, "offset": rng.uniform(0, 1, 3).tolist(), "axis": axis,
           "scale": float(rng.uniform(0.035, 0.055)),
           "grout": [0.08, 0.08, 0.08]}
    if kind == "marble":
        prm["scale"] = float(rng.uniform(0.06, 0.09))
    elif kind == "noise":
        prm["scale"] = float(rng.uniform(0.05, 0.08))
    elif kind == "bricks":
        prm["brick"] = [float(rng.uniform(0.05, 0.07)), float(rng.uniform(0.025, 0.035))]
        prm["radius"] = float(shape.footprint)
    return prm


def _room_textures(rng) -> dict[str, tuple[str, dict]]:
    """Textures of the floor, ceiling, walls (bricks and tiles in random order) and table."""
    def pal(n, val=(0.35, 0.92)):
        return [_random_color(rng, sat=(0.25, 0.85), val=val) for _ in range(n)]

    def seed():
        return int(rng.integers(0, 2 ** 31))

    floor = ("mosaic", {"seed": seed(), "palette": pal(6), "scale": 0.2, "dims": 2,
                        "grout": [0.85, 0.85, 0.82]})
    bricks = ("wall_bricks", {"seed": seed(), "palette": pal(4, (0.3, 0.7)),
                              "brick": [0.3, 0.12], "grout": [0.8, 0.78, 0.74]})
    tiles = ("tiles", {"seed": seed(), "palette": pal(6), "scale": 0.28,
                       "grout": [0.15, 0.15, 0.15]})
    tiles2 = ("tiles", {"seed": seed(), "palette": pal(5), "scale": 0.34,
                        "grout": [0.9, 0.9, 0.9]})
    bricks2 = ("wall_bricks", {"seed": seed(), "palette": pal(4, (0.4, 0.85)),
                               "brick": [0.26, 0.1], "grout": [0.25, 0.22, 0.2]})
    ceiling = ("noise", {"seed": seed(), "palette": pal(3), "scale": 0.4})
    wood = ("wood", {"seed": seed(), "palette": [[0.36, 0.2, 0.1], [0.62, 0.4, 0.22]],
                     "plank": 0.14, "length": 0.9})
    walls = [bricks, tiles, bricks2, tiles2]
    order = rng.permutation(4)
    return {"floor": floor, "ceiling": ceiling, "table": wood,
            **{f: walls[i] for f, i in zip(ROOM_FACES[2:], order)}}


def _lighting(rng, p: SynthPreset) -> dict[str, Lighting]:
    """Lighting of both states: ``uniform`` (identical soft sun), ``change`` (the sun moves and
    changes colour and strength; ambient changes) or ``lamp`` (identical warm point lamp
    0.5 m under the ceiling above the table, inverse-square fall-off)."""
    mode = p.lighting
    if mode == "lamp":
        lamp = PointLight(position=(float(rng.uniform(-0.4, 0.4)), float(rng.uniform(-0.4, 0.4)),
                                    p.room_height - 0.5),
                          color=kelvin_rgb(3200), strength=1.2 * (p.room_height - 0.5) ** 2)
        L = Lighting(ambient_color=kelvin_rgb(6500), ambient=0.3, suns=(), points=(lamp,),
                     description="warm point lamp above the table (inverse-square fall-off, "
                                 "hard shadows), dim ambient")
        return {"before": L, "after": L}
    if mode == "uniform":
        sun = Sun(azimuth=float(rng.uniform(0, 360)), elevation=float(rng.uniform(62, 75)),
                  color=kelvin_rgb(6000), strength=0.9, angle_deg=20.0)
        L = Lighting(ambient_color=kelvin_rgb(6500), ambient=0.75, suns=(sun,),
                     description="soft uniform light: high soft sun + strong ambient")
        return {"before": L, "after": L}
    az = float(rng.uniform(0, 360))
    before = Lighting(
        ambient_color=kelvin_rgb(6500), ambient=0.45,
        suns=(Sun(azimuth=az, elevation=float(rng.uniform(42, 52)), color=kelvin_rgb(4000),
                  strength=1.3, angle_deg=0.5),),
        description="warm hard sun from one side at mid elevation, moderate ambient")
    after = Lighting(
        ambient_color=kelvin_rgb(10000), ambient=0.12,
        suns=(Sun(azimuth=az + float(rng.uniform(150, 210)),
                  elevation=float(rng.uniform(18, 24)), color=kelvin_rgb(9000),
                  strength=2.6, angle_deg=0.3),),
        description="cold, stronger, low sun from the opposite side (long hard shadows move), "
                    "ambient almost off")
    return {"before": before, "after": after}


class _PlacementFailed(Exception):
    """Internal: a random layout did not fit; the caller retries with another draw."""


class _Placer:
    """Rejection sampling of non-overlapping object footprints on the table top."""
    def __init__(self, rng, preset: SynthPreset, gap: float = 0.06):
        self.rng = rng
        self.hx, self.hy = preset.table_half_size
        self.gap = gap
        self.taken: dict[str, list[tuple[float, float, float]]] = {"before": [], "after": []}

    def free(self, x, y, r, states) -> bool:
        return all(math.hypot(x - a, y - b) >= r + rr + self.gap
                   for st in states for a, b, rr in self.taken[st])

    def place(self, r: float, states, away_from=None, min_shift=0.0) -> Pose2D:
        m = r + 0.05
        for _ in range(500):
            x = float(self.rng.uniform(-self.hx + m, self.hx - m))
            y = float(self.rng.uniform(-self.hy + m, self.hy - m))
            if away_from is not None and math.hypot(x - away_from[0],
                                                    y - away_from[1]) < min_shift:
                continue
            if self.free(x, y, r, states):
                return Pose2D(x, y, float(self.rng.uniform(0, 2 * np.pi)))
        raise _PlacementFailed()

    def take(self, pose: Pose2D, r: float, states) -> None:
        for st in states:
            self.taken[st].append((pose.x, pose.y, r))


def build_scene(preset: str | SynthPreset = "tiny", seed: int = 0) -> SynthScene:
    """Build (but do not render) the scene of ``preset`` (a name of :data:`PRESETS` or a
    :class:`SynthPreset`) for ``seed``. Deterministic: the same arguments give the same scene."""
    p = get_preset(preset)
    base = [int(seed), zlib.crc32(p.name.encode())]
    for attempt in range(50):
        rng = np.random.default_rng(base + [attempt])
        try:
            objects, changes = _layout(rng, p)
            break
        except _PlacementFailed:
            continue
    else:
        raise GdiffError(f"synth preset '{p.name}': could not place the objects on the table "
                         "without overlap; reduce the object counts or enlarge the table")
    room = _room_textures(rng)
    lighting = _lighting(rng, p)
    return _finish_scene(rng, p, int(seed), objects, changes, room, lighting)


def _layout(rng: np.random.Generator, p: SynthPreset) -> tuple[list[SynthObject], list[dict]]:
    """Objects with their poses in both states, and the list of change events."""
    kinds = list(SHAPES)
    tex_cycle = list(rng.permutation(OBJECT_TEXTURES))
    objects: list[SynthObject] = []
    placer = _Placer(rng, p)
    changes: list[dict] = []

    def new_object(kind=None, max_fp=None) -> SynthObject:
        k = kind or kinds[int(rng.integers(len(kinds)))]
        shape = random_shape(rng, k, max_fp)
        tex = str(tex_cycle[len(objects) % len(tex_cycle)])
        oid = len(objects) + 1
        obj = SynthObject(id=oid, name=f"obj{oid:02d}_{k}", shape=shape, texture=tex,
                          texture_params=_object_texture(rng, tex, shape),
                          poses={"before": None, "after": None})
        objects.append(obj)
        return obj

    both = ("before", "after")
    # objects present before: static, removed, moved (old place), replaced (old)
    roles = (["static"] * p.n_static + ["removed"] * p.n_removed + ["moved"] * p.n_moved
             + ["replaced"] * p.n_replaced)
    role_of: dict[int, str] = {}
    for role in roles:
        obj = new_object()
        role_of[obj.id] = role
        r = obj.shape.footprint
        pose = placer.place(r, both)
        obj.poses["before"] = pose
        if role == "static":
            obj.poses["after"] = pose
            placer.take(pose, r, both)
        elif role == "replaced":
            obj.change = "removed"
            placer.take(pose, r, both)  # its replacement will stand here
        else:
            obj.change = role
            placer.take(pose, r, ("before",))
        if role == "removed":
            changes.append({"type": "removed", "object": obj.name, "id": obj.id,
                            "kind": obj.kind, "location_before": [pose.x, pose.y]})
    # after-state placements of moved objects and replacements
    for obj in list(objects):
        b = obj.poses["before"]
        if role_of[obj.id] == "moved":
            pose = placer.place(obj.shape.footprint, both, away_from=(b.x, b.y),
                                min_shift=2 * obj.shape.footprint + 0.1)
            obj.poses["after"] = pose
            placer.take(pose, obj.shape.footprint, ("after",))
            changes.append({"type": "moved", "object": obj.name, "id": obj.id,
                            "kind": obj.kind, "location_before": [b.x, b.y],
                            "location_after": [pose.x, pose.y]})
        elif role_of[obj.id] == "replaced":
            others = [k for k in kinds if k != obj.kind]
            new = new_object(others[int(rng.integers(len(others)))],
                             max_fp=obj.shape.footprint + 0.02)
            new.poses["after"] = Pose2D(b.x, b.y, float(rng.uniform(0, 2 * np.pi)))
            new.change = "added"
            new.replaces, obj.replaced_by = obj.id, new.id
            changes.append({"type": "replaced", "object": obj.name, "id": obj.id,
                            "kind": obj.kind, "new_object": new.name, "new_id": new.id,
                            "new_kind": new.kind, "location": [b.x, b.y]})
    for _ in range(p.n_added):
        obj = new_object()
        pose = placer.place(obj.shape.footprint, both)
        obj.poses["after"] = pose
        obj.change = "added"
        placer.take(pose, obj.shape.footprint, ("after",))
        changes.append({"type": "added", "object": obj.name, "id": obj.id, "kind": obj.kind,
                        "location_after": [pose.x, pose.y]})
    return objects, changes


def _finish_scene(rng, p: SynthPreset, seed: int, objects, changes, room, lighting):
    """Add the camera orbits, training and eval poses and assemble the :class:`SynthScene`."""
    # cameras
    target = (0.0, 0.0, p.table_height + 0.15)
    az_c = float(rng.uniform(0, 360))
    orbits = {
        "before": Orbit(az_c - p.before_span_deg / 2, az_c + p.before_span_deg / 2,
                        *p.elevation_before, p.radius_before, target),
        "after": Orbit(az_c + p.after_shift_deg + p.after_span_deg / 2,
                       az_c + p.after_shift_deg - p.after_span_deg / 2,
                       *p.elevation_after, p.radius_after, target),
    }
    train = {}
    for st, n in (("before", p.n_before), ("after", p.n_after)):
        orb = orbits[st]
        train[st] = [jittered_pose(rng, orb.center(i / (n - 1)), target, p.jitter_m)
                     for i in range(n)]
    lo = max(min(orbits["before"].az0, orbits["before"].az1),
             min(orbits["after"].az0, orbits["after"].az1))
    hi = min(max(orbits["before"].az0, orbits["before"].az1),
             max(orbits["after"].az0, orbits["after"].az1))
    r_eval = 0.5 * (p.radius_before + p.radius_after)
    el_mid = 0.25 * (sum(p.elevation_before) + sum(p.elevation_after))
    eval_c2w = []
    for k in range(p.n_eval):
        az = math.radians(lo + (hi - lo) * (k + 0.5) / p.n_eval + rng.uniform(-2, 2))
        el = math.radians(el_mid + rng.uniform(-3, 3))
        c = np.asarray(target) + r_eval * np.array([math.cos(el) * math.cos(az),
                                                    math.cos(el) * math.sin(az), math.sin(el)])
        eval_c2w.append(jittered_pose(rng, c, target, p.jitter_m))
    return SynthScene(p, seed, objects, lighting, orbits, train, eval_c2w, room, changes)


def orbit_path(scene: SynthScene, state: str, n: int) -> list[Camera]:
    """``n`` cameras evenly spaced along the (jitter-free) training orbit of ``state``, from its
    first to its last view: a smooth path for rendering ground-truth sequences. The cameras
    carry ``set=state`` and ``time`` 0/1 but no image path."""
    check_state(state)
    if n < 1:
        raise ValueError("orbit_path needs n >= 1")
    orb = scene.orbits[state]
    ss = [0.5] if n == 1 else [i / (n - 1) for i in range(n)]
    return [scene._camera(orb.c2w(s), None, state, STATES.index(state)) for s in ss]
