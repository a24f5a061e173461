"""Scene description: object placements and changes, lights, camera orbits."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from ..cameras import look_at
from ..io import srgb_to_linear
from .shapes import Box, Cone, Cylinder, Sphere

STATES = ("before", "after")


def check_state(state: str) -> None:
    """Raise ValueError unless ``state`` is "before" or "after"."""
    if state not in STATES:
        raise ValueError(f"state must be 'before' or 'after', not {state!r}")

@dataclass(frozen=True)
class Pose2D:
    """Placement of an object on the table: centre (x, y) in metres, rotation about z (rad)."""
    x: float
    y: float
    rot_z: float


@dataclass
class SynthObject:
    """One object. ``id`` >= 1 is stable across states; ``poses[state]`` is None if absent.

    ``change`` is None (unchanged), ``"added"``, ``"removed"`` or ``"moved"``; a replaced object
    is ``"removed"`` with ``replaced_by`` set, its replacement ``"added"`` with ``replaces`` set.
    """

    id: int
    name: str
    shape: Box | Sphere | Cylinder | Cone
    texture: str
    texture_params: dict
    poses: dict[str, Pose2D | None]
    change: str | None = None
    replaces: int | None = None
    replaced_by: int | None = None

    @property
    def kind(self) -> str:
        return self.shape.kind

    def present(self, state: str) -> bool:
        return self.poses[state] is not None


@dataclass(frozen=True)
class Sun:
    """Directional light. ``azimuth``/``elevation`` in degrees give the direction *towards* the
    sun (azimuth from +x towards +y); ``angle_deg`` is its angular diameter (soft shadows);
    ``color`` linear RGB, ``strength`` irradiance scale."""

    azimuth: float
    elevation: float
    color: tuple[float, float, float]
    strength: float
    angle_deg: float = 0.5

    @property
    def direction(self) -> np.ndarray:
        """Unit vector [3] from a surface point towards the sun (world)."""
        az, el = math.radians(self.azimuth), math.radians(self.elevation)
        return np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])


@dataclass(frozen=True)
class PointLight:
    """Point light at ``position`` (world, metres), linear RGB ``color``. The irradiance of a
    surface at distance d (metres) is ``strength * color * cos(angle) / d**2`` (inverse-square
    fall-off); shadows are hard."""

    position: tuple[float, float, float]
    color: tuple[float, float, float]
    strength: float


@dataclass(frozen=True)
class Lighting:
    """Ambient (linear RGB colour x strength, brighter for up-facing surfaces), suns and
    point lights."""

    ambient_color: tuple[float, float, float]
    ambient: float
    suns: tuple[Sun, ...]
    description: str = ""
    points: tuple[PointLight, ...] = ()

    def to_json(self) -> dict:
        lights = [{"type": "SUN", **dataclasses.asdict(s),
                   "direction_to_light": s.direction.tolist()} for s in self.suns]
        lights += [{"type": "POINT", **dataclasses.asdict(pt)} for pt in self.points]
        return {"description": self.description,
                "ambient": {"color_linear": list(self.ambient_color), "strength": self.ambient},
                "lights": lights}


def kelvin_rgb(k: float) -> tuple[float, float, float]:
    """Approximate linear RGB (max channel 1) of a black body at ``k`` kelvin (1000-12000 K)."""
    t = k / 100.0
    r = 255.0 if t <= 66 else 329.7 * (t - 60) ** -0.1332
    g = 99.47 * math.log(t) - 161.12 if t <= 66 else 288.12 * (t - 60) ** -0.0755
    b = 255.0 if t >= 66 else (0.0 if t <= 19 else 138.52 * math.log(t - 10) - 305.04)
    srgb = np.clip(np.array([r, g, b]) / 255.0, 0, 1)
    lin = srgb_to_linear(srgb)
    return tuple(float(v) for v in lin / lin.max())


@dataclass(frozen=True)
class Orbit:
    """A smooth camera arc around ``target``: azimuth from ``az0`` to ``az1`` (degrees),
    elevation e(s) = e0 + (e1 - e0) * (1 - cos(pi s)) / 2 over s in [0, 1], fixed radius."""

    az0: float
    az1: float
    e0: float
    e1: float
    radius: float
    target: tuple[float, float, float]

    def center(self, s: float) -> np.ndarray:
        az = math.radians(self.az0 + (self.az1 - self.az0) * s)
        el = math.radians(self.e0 + (self.e1 - self.e0) * 0.5 * (1 - math.cos(math.pi * s)))
        tgt = np.asarray(self.target)
        return tgt + self.radius * np.array([math.cos(el) * math.cos(az),
                                             math.cos(el) * math.sin(az), math.sin(el)])

    def c2w(self, s: float) -> np.ndarray:
        return look_at(self.center(s), self.target)


def jittered_pose(rng: np.random.Generator, center: np.ndarray, target, jitter: float):
    """look-at pose with position/target jitter (uniform +-jitter metres) and roll (+-1.5 deg)."""
    c = center + rng.uniform(-jitter, jitter, 3)
    tg = np.asarray(target) + rng.uniform(-jitter, jitter, 3)
    c2w = look_at(c, tg)
    roll = math.radians(rng.uniform(-1.5, 1.5))
    cr, sr = math.cos(roll), math.sin(roll)
    rz = np.array([[cr, -sr, 0], [sr, cr, 0], [0, 0, 1.0]])
    c2w[:3, :3] = c2w[:3, :3] @ rz
    return c2w
