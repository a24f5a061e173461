"""The ``gdiff`` command.

Sub-commands (each has ``--help``)::

    gdiff synth OUT --preset demo        make a synthetic scene with ground truth
    gdiff validate SCENE                 check a scene folder, print its image counts
    gdiff render ...                     render a fitted 4D model at any pose and time
    gdiff change-map ...                 render a change map at any pose from a partition model
    gdiff import FORMAT SRC DST          convert a public dataset's layout into a scene folder

User errors print one clear message (no traceback) and exit with status 2.
"""

from __future__ import annotations

import argparse
import importlib
import sys

# name -> (module, function taking argv, one-line help)
COMMANDS = {
    "synth": ("gdiff.synth", "main", "make a synthetic scene with ground truth"),
    "validate": ("gdiff.cli", "validate_main", "check a scene folder and summarise it"),
    "render": ("gdiff.splat.render", "render_main", "render a fitted 4D model at any pose/time"),
    "change-map": ("gdiff.partition", "change_map_main",
                   "render a change map at any pose from a partition model"),
    "import": ("gdiff.importers", "main", "convert a public dataset into a gdiff scene folder"),
}


def validate_main(argv=None) -> int:
    """``gdiff validate SCENE``: run the scene checks of the workflow's first rule."""
    from .scene import validate_scene

    p = argparse.ArgumentParser(prog="gdiff validate", description=validate_main.__doc__)
    p.add_argument("scene", help="scene folder (before/, after/, optional eval/)")
    args = p.parse_args(argv)
    m = validate_scene(args.scene)
    counts: dict[str, int] = {}
    for rec in m["images"]:
        counts[rec["set"]] = counts.get(rec["set"], 0) + 1
    sizes = " / ".join(f"{w}x{h}" for w, h in m["sizes"])
    print(f"{args.scene}: OK, {sizes} px"
          + (" (different cameras: the poses stage resamples them to one)"
             if len(m["sizes"]) > 1 else "") + ", "
          + ", ".join(f"{k}: {v}" for k, v in counts.items()))
    return 0


def main(argv=None) -> int:
    from .errors import GdiffError

    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help"):
        print(__doc__.strip())
        return 0
    if argv[0] in ("-V", "--version"):
        from . import __version__

        print(f"gdiff {__version__}")
        return 0
    cmd, rest = argv[0], argv[1:]
    if cmd not in COMMANDS:
        print(f"gdiff: unknown command {cmd!r}; commands: {', '.join(COMMANDS)}", file=sys.stderr)
        return 2
    module, func, _ = COMMANDS[cmd]
    try:
        fn = getattr(importlib.import_module(module), func)
        return int(fn(rest) or 0)
    except GdiffError as e:
        print(f"gdiff {cmd}: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
