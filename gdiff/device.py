"""Torch device selection (``device: auto | cpu | cuda`` in the config)."""

from __future__ import annotations

import torch

from .errors import ConfigError


def resolve_device(spec: str | torch.device | None = "auto") -> torch.device:
    """``auto`` -> CUDA when available, else CPU; ``cpu``/``cuda``/``cuda:N`` as given.

    Asking for CUDA on a machine without it is a :class:`ConfigError` naming the key.
    """
    if isinstance(spec, torch.device):
        return spec
    spec = (spec or "auto").lower()
    if spec == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if spec.startswith("cuda"):
        if not torch.cuda.is_available():
            raise ConfigError("config key 'device' is 'cuda' but no CUDA device is available; "
                              "set device: auto or device: cpu")
        return torch.device(spec)
    if spec == "cpu":
        return torch.device("cpu")
    raise ConfigError(f"config key 'device': unknown value {spec!r}; use auto, cpu or cuda")


def set_threads(n: int | None) -> None:
    """Limit torch's intra-op CPU threads (Snakemake's ``threads`` for the rule)."""
    if n and n > 0:
        torch.set_num_threads(int(n))
