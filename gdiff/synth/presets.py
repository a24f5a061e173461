"""Scene presets (:data:`PRESETS`) and the ``synth`` options dataclass."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from ..errors import ConfigError

@dataclass(frozen=True)
class SynthPreset:
    """Everything that defines a procedural scene apart from the seed.

    Image size in pixels; angles in degrees; lengths in metres. Orbits are arcs around the
    table centre: the before arc is centred on a random azimuth, the after arc on that azimuth
    plus ``after_shift_deg``; elevations vary smoothly along each arc between the two values.
    ``lighting`` is ``"uniform"`` (the same soft high sun before and after), ``"change"``
    (a hard sun that moves, changes colour and strength; ambient changes too) or ``"lamp"``
    (the same point lamp above the table before and after, inverse-square fall-off).
    """

    name: str
    description: str
    width: int = 192
    height: int = 144
    hfov_deg: float = 52.0
    supersample: int = 2
    n_before: int = 18
    n_after: int = 18
    n_eval: int = 5
    n_static: int = 5
    n_added: int = 1
    n_removed: int = 1
    n_moved: int = 1
    n_replaced: int = 0
    lighting: str = "uniform"
    before_span_deg: float = 120.0
    after_span_deg: float = 110.0
    after_shift_deg: float = 15.0
    radius_before: float = 2.1
    radius_after: float = 2.35
    elevation_before: tuple[float, float] = (26.0, 40.0)
    elevation_after: tuple[float, float] = (34.0, 46.0)
    jitter_m: float = 0.03
    room_half_size: float = 3.2
    room_height: float = 2.8
    table_half_size: tuple[float, float] = (1.0, 0.75)
    table_height: float = 0.08

    def __post_init__(self):
        if self.width < 8 or self.height < 8:
            raise ConfigError(f"synth preset '{self.name}': width/height must be >= 8 pixels")
        if self.supersample < 1:
            raise ConfigError(f"synth preset '{self.name}': supersample must be >= 1")
        if min(self.n_before, self.n_after) < 2 or self.n_eval < 1:
            raise ConfigError(f"synth preset '{self.name}': need n_before, n_after >= 2 and "
                              "n_eval >= 1")
        if self.lighting not in ("uniform", "change", "lamp"):
            raise ConfigError(f"synth preset '{self.name}': lighting must be 'uniform', "
                              f"'change' or 'lamp', not {self.lighting!r}")
        n_changes = self.n_added + self.n_removed + self.n_moved + self.n_replaced
        if min(self.n_static, self.n_added, self.n_removed, self.n_moved, self.n_replaced) < 0:
            raise ConfigError(f"synth preset '{self.name}': object counts must be >= 0")
        if n_changes + self.n_static > 12:
            raise ConfigError(f"synth preset '{self.name}': at most 12 objects fit on the table")
        r_max = max(self.radius_before, self.radius_after)
        if r_max + self.jitter_m >= self.room_half_size - 0.2:
            raise ConfigError(f"synth preset '{self.name}': camera orbits must stay inside the "
                              "room (radius < room_half_size - 0.2)")


PRESETS: dict[str, SynthPreset] = {
    "tiny": SynthPreset(
        name="tiny",
        description="test scene: 128x96, 10+10 training views, 3 eval views; "
                    "1 object added + 1 removed; uniform light",
        width=128, height=96, n_before=10, n_after=10, n_eval=3,
        n_static=4, n_added=1, n_removed=1, n_moved=0,
        before_span_deg=100.0, after_span_deg=90.0, after_shift_deg=12.0),
    "demo": SynthPreset(
        name="demo",
        description="demo scene: 192x144, 18+18 training views, 5 eval views; "
                    "1 object added, 1 removed, 1 moved; uniform light",
        width=192, height=144, n_before=18, n_after=18, n_eval=5,
        n_static=5, n_added=1, n_removed=1, n_moved=1),
    "lightchange": SynthPreset(
        name="lightchange",
        description="lighting-change scene: 192x144, 18+18 training views, 5 eval views; "
                    "1 object replaced, 1 moved; the sun moves, changes colour and strength "
                    "(hard shadows move) - lighting differences are not changes",
        width=192, height=144, n_before=18, n_after=18, n_eval=5,
        n_static=5, n_added=0, n_removed=0, n_moved=1, n_replaced=1, lighting="change"),
}


@dataclass
class SynthOptions:
    """Options of the ``synth`` step (config section ``synth``).

    ``preset`` names an entry of :data:`PRESETS`; the other fields, when not ``None``, override
    that preset's field of the same name.
    """

    preset: str = "demo"
    seed: int = 0
    width: int | None = None
    height: int | None = None
    supersample: int | None = None
    n_before: int | None = None
    n_after: int | None = None
    n_eval: int | None = None

    def to_preset(self) -> SynthPreset:
        """The :class:`SynthPreset` these options describe."""
        base = get_preset(self.preset)
        over = {k: v for k, v in dataclasses.asdict(self).items()
                if k not in ("preset", "seed") and v is not None}
        return dataclasses.replace(base, **over) if over else base


def get_preset(preset: str | SynthPreset) -> SynthPreset:
    """Look up a preset by name (a :class:`SynthPreset` is returned as is)."""
    if isinstance(preset, SynthPreset):
        return preset
    try:
        return PRESETS[preset]
    except KeyError:
        raise ConfigError(f"synth preset {preset!r} is unknown; choose one of "
                          f"{', '.join(PRESETS)}") from None
