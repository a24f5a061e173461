"""Mirror-direction specular term: glare and highlights that move with the viewpoint.

Per-Gaussian spherical harmonics model view-dependent colour independently for every Gaussian,
from the few directions its training views saw it; at a novel view a highlight on a glossy
floor is then guessed, and a fit tends to explain glare with floaters. Here the highlight is
shared: every Gaussian reflects one distant environment per time, looked up in the mirror
direction of the viewing ray about the Gaussian's normal (its shortest axis), and scaled by a
per-Gaussian strength. A glossy plane then shows the light's highlight where the reflection
geometry puts it, at any viewpoint, as in reflective Gaussian splatting (GaussianShader,
3DGS-DR) reduced to its simplest form.

Colour of Gaussian i seen from camera centre ``c``::

    d = normalise(mean_i - c)                  # viewing direction, world frame
    n = axis of R_i with the smallest scale    # sign does not matter below
    r = d - 2 (d . n) n                        # mirror direction
    colour = max(SH_i(d) + 0.5, 0) + s_i * E(r, t)

``s_i = sigmoid(splats["reflectivity"][i])`` in (0, 1); ``E(r, t) = (1 - t) E_0(r) + t E_1(r)``
with ``E_k`` an equirectangular map (azimuth ``atan2(y, x)`` across, polar angle from +z
down) of ``softplus`` radiance in sRGB-encoded units, sampled bilinearly and wrapping in
azimuth. The world frame is the pose stage's (any up axis): the maps only need to be smooth.
"""

from __future__ import annotations

import math

import torch
from torch import nn
from torch.nn import functional as F

from .gaussians import quat_to_rotmat
from .sh import sh_colors

INIT_RADIANCE_RAW = -5.0  # softplus(-5) ~ 0.007: no visible effect before it is learnt


class Environment(nn.Module):
    """Distant radiance over directions at t = 0 and t = 1 (see module docstring).

    Args:
        height: rows of each equirectangular map (polar angle); the width is twice that.
    Parameters: ``maps`` [2, 3, height, 2 height], raw values (softplus gives the radiance).
    """

    def __init__(self, height: int = 16):
        super().__init__()
        if height < 2:
            raise ValueError(f"environment height must be >= 2, got {height}")
        self.maps = nn.Parameter(torch.full((2, 3, int(height), 2 * int(height)),
                                            INIT_RADIANCE_RAW))

    @property
    def height(self) -> int:
        return int(self.maps.shape[2])

    def radiance(self, dirs: torch.Tensor, t) -> torch.Tensor:
        """Radiance [..., 3] arriving from directions ``dirs`` [..., 3] (world frame, any norm)
        at time ``t`` (float or 0-d tensor in [0, 1]); differentiable in both."""
        shape = dirs.shape[:-1]
        d = dirs.reshape(-1, 3)
        x, y, z = d.unbind(-1)
        rho = torch.sqrt(x * x + y * y + 1e-12)
        u = torch.atan2(y, x) / math.pi  # [-1, 1] across the azimuth
        v = torch.atan2(rho, z) / math.pi * 2.0 - 1.0  # -1 at +z, 1 at -z
        maps = F.softplus(self.maps)
        m = (1.0 - t) * maps[0] + t * maps[1]  # [3, H, W]
        w = m.shape[-1]
        m = torch.cat([m[..., -1:], m, m[..., :1]], dim=-1)  # wrap in azimuth
        grid = torch.stack([u * (w / (w + 2.0)), v], dim=-1).view(1, 1, -1, 2).to(m)
        out = F.grid_sample(m[None], grid, mode="bilinear", padding_mode="border",
                            align_corners=False)  # [1, 3, 1, M]
        return out[0, :, 0].transpose(0, 1).reshape(shape + (3,))


def shortest_axis(quats: torch.Tensor, scales: torch.Tensor) -> torch.Tensor:
    """Unit axis [N, 3] (world frame) of each Gaussian's smallest scale; quats [N, 4] wxyz
    (any norm), scales [N, 3]. The sign is arbitrary."""
    R = quat_to_rotmat(quats)  # columns are the axes
    k = scales.argmin(dim=-1)
    return torch.gather(R, 2, k.view(-1, 1, 1).expand(-1, 3, 1)).squeeze(-1)


def reflect(dirs: torch.Tensor, normals: torch.Tensor) -> torch.Tensor:
    """Mirror ``dirs`` [..., 3] (normalised here) about planes with unit ``normals`` [..., 3]."""
    d = F.normalize(dirs, dim=-1)
    return d - 2.0 * (d * normals).sum(-1, keepdim=True) * normals


def shade(g, campos: torch.Tensor, fused: bool = False) -> torch.Tensor:
    """Colours [C, N, 3] of Gaussians ``g`` (:class:`~gdiff.splat.gaussians.Gaussians`) seen
    from camera centres ``campos`` [C, 3] (world frame): SH colour plus, when ``g`` carries a
    specular term (``g.reflectivity`` [N], ``g.environment`` a callable direction -> radiance),
    the mirror-direction highlight. ``fused``: SH colours and mirror directions by the C++
    kernels (:mod:`gdiff.splat.csrc`, CPU tensors, the kernels built)."""
    dirs = g.means[None] - campos[:, None]  # [C, N, 3], camera centre -> Gaussian
    color = sh_colors(g.sh_degree, g.sh, dirs, fused=fused)
    if g.environment is None:
        return color
    if fused and dirs.device.type == "cpu":
        from . import csrc

        r = csrc.reflect_cpp(dirs, g.quats, g.scales)
    else:
        r = reflect(dirs, shortest_axis(g.quats, g.scales)[None])
    return color + g.reflectivity[None, :, None] * g.environment(r)


__all__ = ["Environment", "shortest_axis", "reflect", "shade"]
