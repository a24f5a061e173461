"""The rendered paths on disk, as the ``segment`` and ``compare`` stages read them.

Frames are keyed ``(path, t, i)`` with ``t`` in ``{"t0", "t1"}`` and ``i`` the frame number.

* ``sequence/poses.json`` (the interpolate stage): per path its cameras and which frames are
  key frames (training photos) of which set (:func:`read_sequence`, :func:`key_frames`);
* ``render/<path>/<t>/NNNNN.exr`` (the render stage): R, G, B linear, A, Z depth
  (:func:`render_files`, :func:`read_frame`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .cameras import Camera
from .errors import SceneError
from .io import read_json

TIMES = ("t0", "t1")
Key = tuple  # (path, "t0" | "t1", frame index)


def read_sequence(poses_json) -> tuple[dict[str, list[Camera]], dict[str, list[dict]]]:
    """Cameras per path and the frame records of ``sequence/poses.json`` (each with the set
    of its path under ``set``)."""
    data = read_json(poses_json)
    try:
        paths = data["paths"]
        shared = {k: data[k] for k in ("width", "height", "fx", "fy", "cx", "cy")}
    except KeyError as e:
        raise SceneError(f"{poses_json}: key {e} missing; see sequence/poses.json in "
                         "docs/design.md, re-run the interpolate stage") from None
    cams, meta = {}, {}
    for p, entry in paths.items():
        cams[p] = [Camera(**{k: fr.get(k, v) for k, v in shared.items()}, c2w=fr["c2w"])
                   for fr in entry["frames"]]
        meta[p] = [dict(fr, set=entry.get("set")) for fr in entry["frames"]]
    return cams, meta


def read_frame(path: Path):
    """(rgb sRGB float32 [H, W, 3], alpha [H, W] | None, depth [H, W] | None) of a frame."""
    try:
        from .exr import read_frame as exr_frame
    except ImportError:  # the exr module is optional for reading; OpenEXR directly otherwise
        exr_frame = _read_exr_openexr
    return exr_frame(path)


def _read_exr_openexr(path):
    import OpenEXR

    from .io import linear_to_srgb

    with OpenEXR.File(str(path)) as f:
        ch = f.channels()  # OpenEXR groups R, G, B(, A) into "RGB" / "RGBA"
        alpha = None
        if "RGBA" in ch:
            px = np.asarray(ch["RGBA"].pixels, np.float32)
            lin, alpha = px[..., :3], px[..., 3]
        elif "RGB" in ch:
            lin = np.asarray(ch["RGB"].pixels, np.float32)
        elif all(c in ch for c in "RGB"):
            lin = np.stack([np.asarray(ch[c].pixels, np.float32) for c in "RGB"], -1)
        else:
            raise SceneError(f"{path}: no R, G, B channels (has {', '.join(ch)}); re-run render")
        if alpha is None and "A" in ch:
            alpha = np.asarray(ch["A"].pixels, np.float32)
        depth = np.asarray(ch["Z"].pixels, np.float32) if "Z" in ch else None
    return linear_to_srgb(lin).astype(np.float32), alpha, depth


def render_files(render_dir: Path, cams: dict[str, list[Camera]]) -> dict[Key, Path]:
    """``{(path, t, i): EXR path}`` of every frame of ``cams`` (per path), both times; a
    missing frame is an error naming it."""
    files = {}
    for p, cl in cams.items():
        for t in TIMES:
            for i in range(len(cl)):
                f = render_dir / p / t / f"{i:05d}.exr"
                if not f.exists():
                    raise SceneError(f"{f}: rendered frame missing (sequence/poses.json has "
                                     f"{len(cl)} frames on path {p}); re-run the render stage")
                files[(p, t, i)] = f
    return files


def key_frames(meta: dict[str, list[dict]]) -> dict[tuple[str, int], int]:
    """``{(path, i): time}`` of the key frames (training cameras) of sequence/poses.json
    (``meta`` from :func:`read_sequence`): time 1 for an ``after`` set, else 0."""
    return {(p, i): (1 if (fr.get("set") or "").endswith("after") else 0)
            for p, frs in meta.items() for i, fr in enumerate(frs) if fr.get("key")}
