"""Glue for the workflow scripts: logging to the rule's log, threads, clean user errors.

Workflow scripts stay thin::

    from gdiff.stage import run_stage
    run_stage(snakemake, lambda: some_gdiff_function(...))

:func:`run_stage` sends log messages and tqdm progress to ``snakemake.log[0]``, limits torch
to the rule's ``threads``, keeps freed memory for reuse (:mod:`gdiff.memory`), and turns a :class:`~gdiff.errors.GdiffError` into its message (in
the log and on the console) and exit status 1, instead of a traceback.
"""

from __future__ import annotations

import logging
import sys
import time
from typing import Any, Callable


def run_stage(smk: Any, fn: Callable[[], Any], name: str | None = None) -> Any:
    """Run ``fn`` for a Snakemake rule object ``smk`` (the ``snakemake`` script global)."""
    from .device import set_threads
    from .errors import GdiffError
    from .log import setup_logging
    from .memory import keep_freed_memory

    console = sys.stderr
    log_path = smk.log[0] if len(smk.log) else None
    setup_logging(log_path)
    set_threads(getattr(smk, "threads", None))
    keep_freed_memory()
    log = logging.getLogger("gdiff.stage")
    name = name or getattr(smk, "rule", "stage")
    log.info("rule %s: start (wildcards %s)", name, dict(smk.wildcards.items()))
    t0 = time.time()
    try:
        result = fn()
    except GdiffError as e:
        log.error("%s", e)
        print(f"\ngdiff error in rule {name}: {e}\n", file=console)
        sys.exit(1)
    except Exception:
        log.exception("rule %s failed with an unexpected error", name)
        raise
    log.info("rule %s: done in %.1f s", name, time.time() - t0)
    return result
