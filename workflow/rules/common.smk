# Shared helpers: config validation, the scene table, per-scene options, input functions.
import json
import re
from pathlib import Path

import yaml

from snakemake.utils import validate

from gdiff.config import check_keys, command_line_types
from gdiff.errors import GdiffError
from gdiff.scene import check_overrides, discover_scenes


_SCHEMA = str(Path(workflow.basedir) / "workflow/schemas/config.schema.yaml")
with open(_SCHEMA) as _f:
    _SCHEMA_DICT = yaml.safe_load(_f)
try:
    check_keys(config, _SCHEMA_DICT)
    # nested --config values arrive as strings (Snakemake reads them with YAML's base loader)
    config.update(command_line_types(config, _SCHEMA_DICT))
except GdiffError as e:
    raise ValueError(str(e)) from None
validate(config, _SCHEMA)

try:
    SCENES = discover_scenes(config["scenes"], synth_root="resources/synth")
    check_overrides(SCENES, _SCHEMA_DICT)
except GdiffError as e:
    raise ValueError(str(e)) from None


wildcard_constraints:
    scene="|".join(map(re.escape, SCENES)) if SCENES else "[^/]+",


def _use_cuda():
    dev = str(config.get("device", "auto")).lower()
    if dev.startswith("cuda"):
        return True
    if dev == "auto":
        import torch

        return torch.cuda.is_available()
    return False


USE_CUDA = _use_cuda()
GPU = 1 if USE_CUDA else 0


def scene_dir(wildcards):
    """The scene folder (a synth scene is made by rule synth)."""
    return str(SCENES[wildcards.scene].path)


def options(section):
    """Input function: the config section merged with the scene's sheet overrides."""

    def fn(wildcards):
        merged = dict(config.get(section) or {})
        merged.update(SCENES[wildcards.scene].overrides.get(section, {}))
        return merged

    return fn


# synthetic scene folder name (resources/synth/<name>) -> (preset, own seed or None)
SYNTH = {s.path.name: (s.synth_preset, s.synth_seed) for s in SCENES.values() if s.synth_preset}


def synth_params(wildcards):
    """The synth params: preset and seed (config synth_seed unless the scene has its own)."""
    preset, seed = SYNTH[wildcards.synth]
    return {"preset": preset, "seed": config["synth_seed"] if seed is None else seed}


def res(scene, *parts):
    return str(Path("results", scene, *parts))


def scene_targets(name):
    spec = SCENES[name]
    out = [res(name, "partition", "model.pt")]
    if spec.has_eval:
        out.append(res(name, "eval", "metrics.csv"))
    return out


def all_targets():
    out = [t for name in SCENES for t in scene_targets(name)]
    if any(s.has_eval for s in SCENES.values()):
        out += ["results/summary.csv", "results/timings.csv"]
    return out


# The rendered EXR frames: one folder per interpolated path and time (render/p1/t0, ...).
FRAME_DIRS = [(path, t) for path in ("p1", "p2") for t in ("t0", "t1")]


def frame_dirs(wildcards):
    """Input function: the render stage's frame folders of a scene (read by segment, compare)."""
    return [res(wildcards.scene, "render", path, t) for path, t in FRAME_DIRS]


def frames_output(path):
    """A frame folder as a render output: temporary (deleted by Snakemake once segment and
    compare have run) unless ``render.keep_frames`` is set or Snakemake runs with ``--notemp``."""
    if (config.get("render") or {}).get("keep_frames", False):
        return directory(path)
    return temp(directory(path))
