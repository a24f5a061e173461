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


def test_command_line_strings_take_the_schema_types():
    """Snakemake reads a nested --config value with YAML's base loader (every scalar a
    string); the schema's types are restored, and validation then passes."""
    from jsonschema import validate as js_validate
    from snakemake.cli import parse_config

    from gdiff.config import check_keys, command_line_types

    given = parse_config(["fit={exposure: true, max_side: 320, hexplane_multires: [1, 2]}",
                          "compare={photo_agree: 1e-3}", "partition={threshold: null, max_side: 64}",
                          "segment={providers: [CPUExecutionProvider]}", "synth_seed=3"])
    assert given["fit"]["exposure"] == "true"  # what Snakemake hands the workflow
    cfg = {**CONFIG, **{k: {**CONFIG.get(k, {}), **v} if isinstance(v, dict) else v
                        for k, v in given.items()}}
    check_keys(cfg, SCHEMA)
    typed = command_line_types(cfg, SCHEMA)
    assert typed["fit"]["exposure"] is True and typed["fit"]["max_side"] == 320
    assert typed["fit"]["hexplane_multires"] == [1, 2]
    assert typed["compare"]["photo_agree"] == 1e-3
    assert typed["partition"]["threshold"] is None and typed["partition"]["max_side"] == 64
    assert typed["segment"]["providers"] == ["CPUExecutionProvider"]
    assert typed["synth_seed"] == 3 and typed["scenes"] == CONFIG["scenes"]
    js_validate(typed, SCHEMA)
    assert cfg["fit"]["exposure"] == "true"  # the input is not changed in place


def test_command_line_values_of_the_wrong_type_are_named():
    from gdiff.config import check_keys, command_line_types

    with pytest.raises(ConfigError, match=r"fit\.exposure = 'maybe' is not boolean"):
        command_line_types({"fit": {"exposure": "maybe"}}, SCHEMA)
    with pytest.raises(ConfigError, match=r"fit\.hexplane_multires\[1\] = 'two' is not integer"):
        command_line_types({"fit": {"hexplane_multires": ["1", "two"]}}, SCHEMA)
    with pytest.raises(ConfigError, match=r"unknown key 'fit\.exposur'\. Known keys in 'fit'"):
        check_keys({"fit": {"exposur": "true"}}, SCHEMA)
    with pytest.raises(ConfigError, match=r"unknown key 'fitt'"):
        check_keys({"fitt": {}}, SCHEMA)
