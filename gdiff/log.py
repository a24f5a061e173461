"""Logging and progress for stages.

Stage functions log through ``logging.getLogger("gdiff.<module>")`` and wrap long loops in
:func:`progress`. The workflow scripts call :func:`setup_logging` with the rule's log file, so
messages and tqdm progress land in ``logs/<scene>/<rule>.log``.
"""

from __future__ import annotations

import logging
import os
import sys
from pathlib import Path
from typing import Iterable, TypeVar

from tqdm.auto import tqdm

T = TypeVar("T")


def setup_logging(log_path: str | os.PathLike | None = None, level: int = logging.INFO) -> None:
    """Send gdiff log messages (and tqdm progress, which writes to stderr) to ``log_path``.

    Without a path, messages go to stderr. Safe to call more than once.
    """
    root = logging.getLogger("gdiff")
    root.setLevel(level)
    for h in list(root.handlers):
        root.removeHandler(h)
    if log_path is not None:
        Path(log_path).parent.mkdir(parents=True, exist_ok=True)
        stream = open(log_path, "a", buffering=1)
        sys.stderr = stream
    else:
        stream = sys.stderr
    handler = logging.StreamHandler(stream)
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s",
                                           "%H:%M:%S"))
    root.addHandler(handler)
    root.propagate = False


class _LineStream:
    """File-like wrapper that turns tqdm's carriage-return redraws into one line per update,
    so a log file shows a readable history of the progress bar."""

    def __init__(self, stream):
        self._stream = stream

    def write(self, s: str) -> int:
        s = s.replace("\r", "\n")
        lines = [ln for ln in s.split("\n") if ln.strip()]
        if lines:
            self._stream.write("\n".join(lines) + "\n")
        return len(s)

    def flush(self) -> None:
        self._stream.flush()


def progress(iterable: Iterable[T] | None = None, desc: str = "", total: int | None = None,
             **kw) -> "tqdm[T]":
    """A tqdm progress bar on stderr that stays readable in log files.

    In a non-interactive stream (a log file) it updates at most every 10 s and writes a new
    line per update instead of carriage returns.
    """
    interactive = hasattr(sys.stderr, "isatty") and sys.stderr.isatty()
    kw.setdefault("mininterval", 0.5 if interactive else 10.0)
    kw.setdefault("dynamic_ncols", interactive)
    kw.setdefault("ascii", not interactive)
    kw.setdefault("disable", os.environ.get("GDIFF_NO_PROGRESS") == "1")
    stream = sys.stderr if interactive else _LineStream(sys.stderr)
    return tqdm(iterable, desc=desc, total=total, file=stream, **kw)
