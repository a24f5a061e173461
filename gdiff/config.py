"""The workflow's configuration checked against its schema (``workflow/schemas/config.schema.yaml``,
loaded as a dict) before Snakemake validates it.

* :func:`check_keys`: a key the schema does not have is named, with the keys it could have
  meant (jsonschema's own message for ``additionalProperties`` lists no alternatives).
* :func:`command_line_types`: Snakemake reads a nested ``--config`` value
  (``--config fit='{exposure: true}'``) with YAML's base loader, so every scalar in it arrives
  as a string ("true", "0.5") and fails the schema's types. Where the schema asks for a
  boolean, a number, an integer, null or an array, such a string is read as a YAML scalar;
  one that reads as none of the allowed types is an error naming the key and the value.
* :func:`sections`: the configuration sections (objects with keys) and their keys, also what a
  scene sheet may override (:func:`gdiff.scene.check_overrides`).
"""

from __future__ import annotations

from typing import Any

import jsonschema
import yaml

from .errors import ConfigError

# JSON Schema's types as the validator Snakemake uses checks them
_IS_TYPE = jsonschema.Draft202012Validator.TYPE_CHECKER.is_type


def sections(schema: dict) -> dict[str, dict]:
    """``{section: {key: key schema}}`` for the top-level keys of ``schema`` that are objects
    with properties (the stages' sections)."""
    return {k: v["properties"] for k, v in schema.get("properties", {}).items()
            if isinstance(v, dict) and "properties" in v}


def check_keys(cfg: dict, schema: dict) -> None:
    """Raise :class:`ConfigError` naming the first key of ``cfg`` (top level, or a section's
    key) that ``schema`` does not have, with the keys it has there."""
    known = schema.get("properties", {})
    secs = sections(schema)
    for key, value in cfg.items():
        if key not in known:
            raise ConfigError(f"config: unknown key '{key}'. Known keys: "
                              f"{', '.join(sorted(known))}. Check the spelling in "
                              "config/config.yaml or in --config.")
        if key in secs and isinstance(value, dict):
            for k in value:
                if k not in secs[key]:
                    raise ConfigError(f"config: unknown key '{key}.{k}'. Known keys in "
                                      f"'{key}': {', '.join(sorted(secs[key]))}.")


def _types(node: dict) -> list[str]:
    t = node.get("type", [])
    return [t] if isinstance(t, str) else list(t)


def _scalar(text: str) -> Any:
    """A command-line string as a YAML scalar; numbers also in the forms YAML 1.1 reads as
    strings ("1e-3", ".5e2")."""
    for parse in (int, float):
        try:
            return parse(text)
        except ValueError:
            pass
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError:
        return text


def _typed(value: Any, node: dict, where: str) -> Any:
    types = _types(node)
    if isinstance(value, str) and types and "string" not in types:
        read = _scalar(value)
        if not any(_IS_TYPE(read, t) for t in types):
            raise ConfigError(f"config: {where} = {value!r} is not {' or '.join(types)}; "
                              "write it as in config/config.yaml (e.g. true, 0.5, 3, null)")
        value = read
    if isinstance(value, list) and isinstance(node.get("items"), dict):
        return [_typed(v, node["items"], f"{where}[{i}]") for i, v in enumerate(value)]
    if isinstance(value, dict) and isinstance(node.get("properties"), dict):
        props = node["properties"]
        return {k: _typed(v, props[k], f"{where}.{k}") if k in props else v
                for k, v in value.items()}
    return value


def command_line_types(cfg: dict, schema: dict) -> dict:
    """A copy of ``cfg`` with every string that stands where ``schema`` asks for another type
    read as a YAML scalar (see the module docstring); keys the schema does not have are left
    as they are (:func:`check_keys` names them). Raises :class:`ConfigError` naming the key
    when a string reads as none of its types."""
    props = schema.get("properties", {})
    return {k: _typed(v, props.get(k, {}), k) for k, v in cfg.items()}
