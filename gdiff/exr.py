"""OpenEXR frames: rendered colour (linear), alpha and depth for the later stages.

A rendered frame is one single-part scanline EXR with channels

* ``R``, ``G``, ``B`` — linear radiance, half float (the renderer's sRGB-encoded values
  converted with :func:`gdiff.io.srgb_to_linear`),
* ``A`` — accumulated opacity in [0, 1], half float,
* ``Z`` — expected depth along the camera z axis (OpenCV axes, world units), float32,

readable by any OpenEXR reader (Blender, Nuke, oiiotool, exrheader). Extra header attributes
(e.g. ``worldToCamera`` as a 4x4 float matrix, the standard EXR attribute) can be stored.

Compression (:data:`FRAME_COMPRESSIONS`, the file's ``compression`` attribute): ``zip``,
``zips``, ``piz``, ``rle`` and ``none`` are lossless for every channel. ``dwaa`` / ``dwab``
(OpenEXR's DCT codec, 32- / 256-scanline blocks) are lossy on the half-float colour channels
R, G, B only; OpenEXR's DWA codec stores every other channel (here A and Z) losslessly, so
alpha and the float32 depth read back bit-exact with any of them. The DWA quantisation is set
by ``dwaCompressionLevel`` (OpenEXR's default 45; higher = smaller and coarser).

Inside the code images are sRGB-encoded float32 [H, W, 3]; :func:`write_frame` /
:func:`read_frame` do the conversion so callers never see linear values by accident.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from .errors import SceneError
from .io import atomic_path, linear_to_srgb, srgb_to_linear

# Pixel types OpenEXR can store, by numpy dtype.
_EXR_DTYPES = (np.float16, np.float32, np.uint32)

# Compressions a rendered frame may use: name -> lossless for the colour channels. Left out on
# purpose: PXR24 (rounds float32 depth to 24 bits), B44/B44A (lossy on every half channel,
# alpha included) and the codecs newer than OpenEXR 3.3 (ZSTD, HTJ2K), which older readers
# (Blender, Nuke, oiiotool builds) cannot open.
FRAME_COMPRESSIONS = {"zip": True, "zips": True, "piz": True, "rle": True, "none": True,
                      "dwaa": False, "dwab": False}


def _compression_constant(name: str):
    import OpenEXR

    key = "NO" if name.upper() == "NONE" else name.upper()
    value = getattr(OpenEXR, f"{key}_COMPRESSION", None)
    if value is None:
        raise ValueError(f"unknown OpenEXR compression {name!r}")
    return value


def write_exr(path: str | os.PathLike, channels: dict[str, np.ndarray],
              attributes: dict[str, Any] | None = None, compression: str = "ZIP") -> None:
    """Write named channels to a scanline EXR atomically.

    Args:
        path: output file (``.exr``).
        channels: name -> [H, W] array; all the same shape. The pixel type is the array's
            dtype: float16 -> HALF, float32 -> FLOAT, uint32 -> UINT (float64 is stored as
            FLOAT, other integer types as UINT if non-negative).
        attributes: extra header attributes (str, float, int, or a 4x4 float32 array for
            matrices such as ``worldToCamera``).
        compression: an OpenEXR compression name without ``_COMPRESSION``, any case (ZIP,
            PIZ, DWAA, NO or NONE, ...).
    """
    import OpenEXR

    if not channels:
        raise ValueError("write_exr: no channels")
    out = {}
    shape = None
    for name, arr in channels.items():
        a = np.asarray(arr)
        if a.ndim != 2:
            raise ValueError(f"write_exr: channel {name!r} must be 2-D [H, W], got {a.shape}")
        if shape is None:
            shape = a.shape
        elif a.shape != shape:
            raise ValueError(f"write_exr: channel {name!r} has shape {a.shape}, expected {shape}")
        if a.dtype == np.float64:
            a = a.astype(np.float32)
        elif np.issubdtype(a.dtype, np.integer) and a.dtype != np.uint32:
            if a.min(initial=0) < 0 or a.max(initial=0) > np.iinfo(np.uint32).max:
                raise ValueError(f"write_exr: channel {name!r} has values outside uint32")
            a = a.astype(np.uint32)
        elif a.dtype not in _EXR_DTYPES:
            raise ValueError(f"write_exr: channel {name!r} has unsupported dtype {a.dtype}")
        out[name] = np.ascontiguousarray(a)
    header = {"compression": _compression_constant(compression),
              "type": OpenEXR.scanlineimage}
    for k, v in (attributes or {}).items():
        if isinstance(v, np.ndarray) and v.shape == (4, 4):
            v = v.astype(np.float32)
        header[k] = v
    with atomic_path(path, suffix=".exr") as tmp:
        with OpenEXR.File(header, out) as f:
            f.write(str(tmp))


def read_exr(path: str | os.PathLike, with_header: bool = False):
    """Read every channel of a single-part EXR.

    Returns:
        ``{name: [H, W] array}`` with the stored dtype (float16, float32 or uint32); with
        ``with_header=True`` a tuple ``(channels, header dict)``.
    """
    import OpenEXR

    path = Path(path)
    if not path.is_file():
        raise SceneError(f"{path}: EXR file not found")
    try:
        f = OpenEXR.File(str(path), separate_channels=True)
    except Exception as e:  # OpenEXR raises plain exceptions on corrupt files
        raise SceneError(f"{path}: cannot be read as OpenEXR ({e}); re-run the stage that "
                         "wrote it") from None
    with f:
        chans = {name: np.array(ch.pixels) for name, ch in f.channels().items()}
        header = dict(f.header()) if with_header else None
    return (chans, header) if with_header else chans


def write_frame(path: str | os.PathLike, rgb_srgb: np.ndarray, alpha: np.ndarray,
                depth: np.ndarray, attributes: dict[str, Any] | None = None,
                compression: str = "zip", dwa_level: float | None = None) -> None:
    """Write a rendered frame: R, G, B (linear, half), A (half), Z (float32).

    Args:
        rgb_srgb: [H, W, 3] sRGB-encoded colour in [0, 1] (values above 1 are kept; they are
            converted with the sRGB curve extended by its power law).
        alpha: [H, W] or [H, W, 1] accumulated opacity.
        depth: [H, W] or [H, W, 1] expected depth (world units along the camera z axis).
        compression: one of :data:`FRAME_COMPRESSIONS` (see the module docstring).
        dwa_level: ``dwaCompressionLevel`` for ``dwaa`` / ``dwab`` (None = OpenEXR's default).
    """
    if compression.lower() not in FRAME_COMPRESSIONS:
        raise ValueError(f"write_frame: compression must be one of "
                         f"{', '.join(FRAME_COMPRESSIONS)}, not {compression!r}")
    rgb = np.asarray(rgb_srgb, dtype=np.float32)
    if rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f"write_frame: rgb must be [H, W, 3], got {rgb.shape}")
    alpha = np.asarray(alpha, dtype=np.float32).reshape(rgb.shape[:2])
    depth = np.asarray(depth, dtype=np.float32).reshape(rgb.shape[:2])
    lin = srgb_to_linear(rgb).astype(np.float16)
    attrs = dict(attributes or {})
    if dwa_level is not None and compression.lower().startswith("dwa"):
        attrs["dwaCompressionLevel"] = float(dwa_level)
    write_exr(path, {"R": lin[..., 0], "G": lin[..., 1], "B": lin[..., 2],
                     "A": alpha.astype(np.float16), "Z": depth}, attributes=attrs,
              compression=compression)


def read_frame(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Read a frame written by :func:`write_frame`.

    Returns:
        ``(rgb_srgb float32 [H, W, 3] sRGB-encoded, alpha float32 [H, W], depth float32
        [H, W])``.
    """
    ch = read_exr(path)
    missing = [c for c in ("R", "G", "B", "A", "Z") if c not in ch]
    if missing:
        raise SceneError(f"{path}: EXR frame lacks channel(s) {', '.join(missing)}; expected "
                         "R, G, B, A, Z (re-run the render stage)")
    lin = np.stack([ch["R"], ch["G"], ch["B"]], axis=-1).astype(np.float32)
    rgb = linear_to_srgb(lin).astype(np.float32)
    return rgb, ch["A"].astype(np.float32), ch["Z"].astype(np.float32)
