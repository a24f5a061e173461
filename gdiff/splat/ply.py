"""PLY input/output: SfM point clouds and Gaussians in the standard 3DGS layout.

* Point clouds (``poses/points.ply``): vertex properties ``x y z`` and ``red green blue``
  (uint8, or float in [0, 1]); read with :func:`read_points`, written with :func:`write_points`.
* Gaussians (``fit/gaussians_t*.ply``): binary little-endian vertex element with float32
  properties ``x y z nx ny nz f_dc_0..2 f_rest_0..M-1 opacity scale_0..2 rot_0..3`` — the
  layout written by the reference 3DGS code and read by common splat viewers. ``f_rest`` is
  channel-major (all higher-order coefficients of red, then green, then blue), ``opacity`` is a
  logit, ``scale_*`` are log standard deviations, ``rot_*`` a wxyz quaternion. Normals are 0.
"""

from __future__ import annotations

import math
import os

import numpy as np
import torch
from plyfile import PlyData, PlyElement, PlyParseError

from ..errors import SceneError
from ..io import atomic_path
from .gaussians import Gaussians, num_sh_coeffs


def read_points(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Read a point cloud PLY: returns xyz float64 [P, 3] and rgb float32 [P, 3] in [0, 1].

    Points without colour get mid grey. Raises :class:`SceneError` naming the file when it is
    missing, unreadable, has no vertices, or lacks x/y/z.
    """
    try:
        ply = PlyData.read(str(path))
    except FileNotFoundError:
        raise SceneError(f"{path}: point cloud not found; run the poses stage first") from None
    except (PlyParseError, ValueError, OSError) as e:
        raise SceneError(f"{path}: not a readable PLY file ({e}); rerun the poses stage") from None
    if "vertex" not in ply:
        raise SceneError(f"{path}: PLY has no 'vertex' element")
    v = ply["vertex"].data
    names = v.dtype.names or ()
    if not {"x", "y", "z"} <= set(names):
        raise SceneError(f"{path}: vertices need x, y, z properties (found {names})")
    if len(v) == 0:
        raise SceneError(f"{path}: point cloud is empty; the poses stage found no 3D points")
    xyz = np.stack([v["x"], v["y"], v["z"]], axis=1).astype(np.float64)
    if {"red", "green", "blue"} <= set(names):
        rgb = np.stack([v["red"], v["green"], v["blue"]], axis=1)
        rgb = rgb.astype(np.float32) / (255.0 if np.issubdtype(rgb.dtype, np.integer) else 1.0)
    else:
        rgb = np.full((len(v), 3), 0.5, dtype=np.float32)
    ok = np.isfinite(xyz).all(axis=1)
    if not ok.all():
        xyz, rgb = xyz[ok], rgb[ok]
        if not len(xyz):
            raise SceneError(f"{path}: no point has finite coordinates")
    return xyz, np.clip(rgb, 0.0, 1.0)


def write_points(path: str | os.PathLike, xyz: np.ndarray, rgb: np.ndarray) -> None:
    """Write xyz [P, 3] and rgb [P, 3] (uint8 or float in [0, 1]) as a binary PLY, atomically."""
    xyz = np.asarray(xyz, dtype=np.float32)
    rgb = np.asarray(rgb)
    if rgb.dtype != np.uint8:
        rgb = (np.clip(rgb, 0, 1) * 255 + 0.5).astype(np.uint8)
    arr = np.empty(len(xyz), dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"),
                                    ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    arr["x"], arr["y"], arr["z"] = xyz.T
    arr["red"], arr["green"], arr["blue"] = rgb.T
    with atomic_path(path) as tmp:
        PlyData([PlyElement.describe(arr, "vertex")], byte_order="<").write(str(tmp))


def _rest_names(k: int) -> list[str]:
    return [f"f_rest_{i}" for i in range(3 * (k - 1))]


def write_gaussians(path: str | os.PathLike, g: Gaussians) -> None:
    """Write activated Gaussians in the standard 3DGS PLY layout (see module docstring).

    All SH coefficients of ``g.sh`` [N, K, 3] are written (those above ``g.sh_degree`` are as
    stored, normally zero); opacities are stored as logits and scales as logs.
    """
    with torch.no_grad():
        means = g.means.detach().float().cpu().numpy()
        n = len(means)
        sh = g.sh.detach().float().cpu().numpy()  # [N, K, 3]
        k = sh.shape[1]
        opa = g.opacities.detach().float().clamp(1e-7, 1 - 1e-7).cpu().numpy()
        scales = g.scales.detach().float().clamp_min(1e-12).cpu().numpy()
        quats = g.quats.detach().float()
        quats = (quats / quats.norm(dim=-1, keepdim=True).clamp_min(1e-12)).cpu().numpy()
    names = (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"] + _rest_names(k)
             + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])
    cols = [means, np.zeros((n, 3), np.float32), sh[:, 0, :],
            sh[:, 1:, :].transpose(0, 2, 1).reshape(n, 3 * (k - 1)),
            np.log(opa / (1 - opa))[:, None], np.log(scales), quats]
    data = np.concatenate(cols, axis=1).astype(np.float32)
    arr = np.empty(n, dtype=[(name, "f4") for name in names])
    for i, name in enumerate(names):
        arr[name] = data[:, i]
    with atomic_path(path) as tmp:
        PlyData([PlyElement.describe(arr, "vertex")], byte_order="<").write(str(tmp))


def read_gaussians(path: str | os.PathLike, device: torch.device | str | None = None) -> Gaussians:
    """Read a 3DGS-layout PLY into activated :class:`Gaussians` (SH degree from f_rest count).

    Raises :class:`SceneError` naming the file when it lacks the 3DGS properties.
    """
    try:
        v = PlyData.read(str(path))["vertex"].data
    except (FileNotFoundError, KeyError, PlyParseError, ValueError, OSError) as e:
        raise SceneError(f"{path}: not a readable Gaussian PLY ({e})") from None
    names = set(v.dtype.names or ())
    need = {"x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1",
            "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"}
    if not need <= names:
        raise SceneError(f"{path}: missing 3DGS properties {sorted(need - names)}")
    m = sum(1 for s in names if s.startswith("f_rest_"))
    k = m // 3 + 1
    degree = int(round(math.sqrt(k))) - 1
    if num_sh_coeffs(degree) != k or m % 3:
        raise SceneError(f"{path}: {m} f_rest properties do not match any SH degree")
    col = lambda *ns: np.stack([np.asarray(v[s], np.float32) for s in ns], axis=1)  # noqa: E731
    n = len(v)
    dc = col("f_dc_0", "f_dc_1", "f_dc_2")[:, None, :]
    rest = col(*_rest_names(k)).reshape(n, 3, k - 1).transpose(0, 2, 1) if k > 1 else \
        np.zeros((n, 0, 3), np.float32)
    t = lambda a: torch.as_tensor(np.ascontiguousarray(a), device=device)  # noqa: E731
    quats = t(col("rot_0", "rot_1", "rot_2", "rot_3"))
    return Gaussians(
        means=t(col("x", "y", "z")),
        quats=quats / quats.norm(dim=-1, keepdim=True).clamp_min(1e-12),
        scales=t(np.exp(col("scale_0", "scale_1", "scale_2"))),
        opacities=torch.sigmoid(t(np.asarray(v["opacity"], np.float32))),
        sh=t(np.concatenate([dc, rest], axis=1)),
        sh_degree=degree,
    )
