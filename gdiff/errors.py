"""User-facing errors.

Every problem caused by the user's input (a file, a folder, a config key) raises
:class:`GdiffError` (or a subclass) with a message that names the file or key, says what is wrong
and what to do. The CLI and the workflow scripts print only that message, never a traceback.
"""

from __future__ import annotations


class GdiffError(Exception):
    """An error in the user's input or configuration, with an actionable message."""


class SceneError(GdiffError):
    """A scene folder is missing, incomplete or holds unusable images."""


class ConfigError(GdiffError):
    """A configuration key or value is invalid."""


class PosesError(GdiffError):
    """Camera registration failed or is too incomplete to continue."""


class TrainingError(GdiffError):
    """Training diverged (NaN/inf) or cannot continue; names the iteration and last checkpoint."""


class ModelFileError(GdiffError):
    """A model file given in the config (e.g. SAM ONNX) is missing or incompatible."""
