"""config/config.yaml, its schema and the stage option dataclasses agree."""

import dataclasses
import importlib
from pathlib import Path

import pytest
import yaml

from gdiff.errors import ConfigError
from gdiff.options import from_config

ROOT = Path(__file__).resolve().parents[1]
SECTIONS = {
    "input": ("gdiff.video", "InputOptions"),
    "poses": ("gdiff.sfm", "PosesOptions"),
    "fit": ("gdiff.splat.train", "FitOptions"),
    "interpolate": ("gdiff.interpolate", "InterpolateOptions"),
    "render": ("gdiff.sequence", "RenderOptions"),
    "segment": ("gdiff.segment", "SegmentOptions"),
    "track": ("gdiff.track", "TrackOptions"),
    "compare": ("gdiff.compare", "CompareOptions"),
    "partition": ("gdiff.partition", "PartitionOptions"),
    "evaluate": ("gdiff.evaluate", "EvalOptions"),
}
CONFIG = yaml.safe_load((ROOT / "config/config.yaml").read_text())
SCHEMA = yaml.safe_load((ROOT / "workflow/schemas/config.schema.yaml").read_text())


def _default(f):
    if f.default is not dataclasses.MISSING:
        return f.default
    return f.default_factory()


@pytest.mark.parametrize("section", sorted(SECTIONS))
def test_section_matches_dataclass(section):
    mod, cls = SECTIONS[section]
    C = getattr(importlib.import_module(mod), cls)
    fields = {f.name: _default(f) for f in dataclasses.fields(C)}
    assert set(CONFIG[section]) == set(fields), f"config.yaml section {section}"
    for k, v in fields.items():
        v = list(v) if isinstance(v, tuple) else v
        assert CONFIG[section][k] == v, f"{section}.{k}: config {CONFIG[section][k]!r} != {v!r}"
    props = SCHEMA["properties"][section]["properties"]
    assert set(props) == set(fields), f"schema section {section}"
    assert SCHEMA["properties"][section]["additionalProperties"] is False
    # the defaults in config.yaml build the dataclass
    from_config(C, CONFIG[section], section)


def test_every_config_key_is_in_schema():
    assert set(CONFIG) <= set(SCHEMA["properties"])
    assert SCHEMA["additionalProperties"] is False


def test_from_config_names_unknown_key():
    from gdiff.interpolate import InterpolateOptions

    with pytest.raises(ConfigError, match=r"section 'interpolate': unknown key\(s\) nn"):
        from_config(InterpolateOptions, {"nn": 3}, "interpolate")
