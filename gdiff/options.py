"""Stage options: dataclasses with defaults, filled from a config section.

Every stage module defines a dataclass of its options (e.g. ``FitOptions``) and builds it with
:func:`from_config`, which rejects unknown keys with a message naming the config section, so a
typo in ``config.yaml`` never passes silently.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Mapping, TypeVar

from .errors import ConfigError

T = TypeVar("T")


def from_config(cls: type[T], section: Mapping[str, Any] | None, name: str) -> T:
    """Build ``cls`` (a dataclass) from ``section``; unknown keys raise :class:`ConfigError`."""
    section = dict(section or {})
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(section) - set(fields))
    if unknown:
        raise ConfigError(
            f"config section '{name}': unknown key(s) {', '.join(unknown)}; "
            f"known keys are {', '.join(sorted(fields))}")
    try:
        return cls(**section)
    except (TypeError, ValueError) as e:
        raise ConfigError(f"config section '{name}': {e}") from None
