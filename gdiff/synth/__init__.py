"""Procedural change-detection scenes with exact ground truth (a small vectorised ray tracer).

A scene is a closed textured room (floor, four walls, ceiling) with a slab table in the middle
and a handful of analytic objects (boxes, spheres, cylinders, cones) on it, each with its own
procedural solid texture. The scene has two *states*, ``before`` and ``after``, differing by
object changes (added, removed, moved, replaced) and optionally by the lighting (sun direction,
colour and strength, so hard shadows move).

World frame: z up, metres, floor at z = 0 (the same frame as the shared path-traced scenes).
Cameras use the project conventions (``gdiff.cameras.Camera``): OpenCV axes (x right, y down,
z forward), ``c2w`` camera-to-world, pinhole, pixel (col i, row j) centred at (i+0.5, j+0.5).

Rendering (:meth:`SynthScene.render`):

* colour: ``supersample x supersample`` rays per pixel on a regular sub-pixel grid,
  Lambertian albedo x (hemispherical ambient + sun with cast shadows, a soft sun is sampled
  over its angular disc), an exponential tone curve, averaged in linear space and returned
  sRGB-encoded in [0, 1];
* ground truth (instance ids, depth, normals, changed mask, cast-shadow mask): one ray through
  every pixel centre, so it is pixel-exact and independent of the anti-aliasing.

Walls and ceiling do not cast shadows (the sun shines "through" them, as in the shared scenes);
the table and the objects do.

:func:`make_scene` writes a gdiff scene folder with the layout of the shared scenes (see
``../shared/scenes/README.md``)::

    before/NNN.png after/NNN.png eval/before/NNN.png eval/after/NNN.png
    eval/masks/NNN.png eval/mask_before/NNN.png eval/mask_after/NNN.png
    gt_cameras.json meta.json timing.json

Everything is deterministic for a given preset and seed (``timing.json`` aside).

Modules: :mod:`.presets` (presets, options), :mod:`.noise` and :mod:`.textures` (procedural
albedo), :mod:`.shapes` (analytic intersections), :mod:`.model` (objects, lights, orbits),
:mod:`.scene` (:class:`SynthScene`: cameras and the ray tracer), :mod:`.build` (random scene
from a seed), :mod:`.writer` (scene folder and CLI).
"""

from .build import build_scene, orbit_path
from .model import STATES, Lighting, Orbit, PointLight, Pose2D, Sun, SynthObject
from .presets import PRESETS, SynthOptions, SynthPreset, get_preset
from .scene import SynthScene
from .shapes import SHAPES, Box, Cone, Cylinder, Sphere
from .textures import OBJECT_TEXTURES, TEXTURES, texture_albedo
from .writer import make_scene, main

__all__ = ["PRESETS", "SHAPES", "STATES", "OBJECT_TEXTURES", "TEXTURES", "Box", "Cone",
           "Cylinder", "Lighting", "Orbit", "PointLight", "Pose2D", "Sphere", "Sun",
           "SynthObject", "SynthOptions", "SynthPreset", "SynthScene", "build_scene",
           "get_preset", "main", "make_scene", "orbit_path", "texture_albedo"]
