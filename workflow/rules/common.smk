# Shared helpers: config validation, the scene table, per-scene options, input functions.
import json
import re
from pathlib import Path

import yaml

from snakemake.utils import validate

from gdiff.errors import GdiffError
from gdiff.scene import check_overrides, discover_scenes


def _check_config_keys(cfg, schema_path):
    """Reject unknown keys with a message naming them (before jsonschema's generic one)."""
    import yaml

    schema = yaml.safe_load(open(schema_path))
    known = schema["properties"]
    for key, value in cfg.items():
        if key not in known:
            raise ValueError(
                f"config: unknown key '{key}'. Known keys: {', '.join(sorted(known))}. "
                "Check the spelling in config/config.yaml or in --config."
            )
        sub = known[key].get("properties")
        if sub is not None and isinstance(value, dict):
            for k in value:
                if k not in sub:
                    raise ValueError(
                        f"config: unknown key '{key}.{k}'. Known keys in '{key}': "
                        f"{', '.join(sorted(sub))}."
                    )


_SCHEMA = str(Path(workflow.basedir) / "workflow/schemas/config.schema.yaml")
_check_config_keys(config, _SCHEMA)
validate(config, _SCHEMA)

try:
    SCENES = discover_scenes(config["scenes"], synth_root="resources/synth")
    with open(_SCHEMA) as _f:
        check_overrides(SCENES, yaml.safe_load(_f))
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
