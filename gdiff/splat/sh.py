"""Real spherical harmonics (degree 0..3) for view-dependent Gaussian colour.

The basis and its ordering are the ones used by 3D Gaussian Splatting (and its PLY files): for
degree ``l`` the coefficients ``l*l .. (l+1)*(l+1)-1`` in the order m = -l..l, with the sign
convention of the 3DGS reference code. Colours are ``eval_sh(...) + 0.5`` clamped at 0
(:func:`sh_to_color`), so a degree-0 coefficient ``(rgb - 0.5) / SH_C0`` gives colour ``rgb``.

Shapes: ``coeffs [..., K, 3]`` with ``K >= (degree+1)**2`` (extra bases are ignored),
``dirs [..., 3]`` (need not be normalised; a zero vector gives the degree-0 colour only).
All functions are differentiable torch code that runs on the tensors' device.
"""

from __future__ import annotations

import torch

SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005,
         -1.0925484305920792, 0.5462742152960396)
SH_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
         -0.4570457994644658, 1.445305721320277, -0.5900435899266435)

MAX_SH_DEGREE = 3


def num_sh_bases(degree: int) -> int:
    """Number of SH coefficients per channel for ``degree`` (1, 4, 9 or 16)."""
    if not 0 <= degree <= MAX_SH_DEGREE:
        raise ValueError(f"sh_degree must be in 0..{MAX_SH_DEGREE}, got {degree}")
    return (degree + 1) ** 2


def sh_basis(degree: int, dirs: torch.Tensor) -> torch.Tensor:
    """The real SH basis functions at unit directions.

    Args:
        degree: 0..3.
        dirs: [..., 3] directions (normalised here; zero vectors stay zero).
    Returns:
        [..., (degree+1)**2] basis values (dtype and device of ``dirs``).
    """
    n = num_sh_bases(degree)
    d = torch.nn.functional.normalize(dirs, dim=-1)
    x, y, z = d.unbind(-1)
    out = [torch.full_like(x, SH_C0)]
    if degree >= 1:
        out += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        out += [SH_C2[0] * x * y, SH_C2[1] * y * z, SH_C2[2] * (2.0 * zz - xx - yy),
                SH_C2[3] * x * z, SH_C2[4] * (xx - yy)]
    if degree >= 3:
        out += [SH_C3[0] * y * (3.0 * xx - yy), SH_C3[1] * x * y * z,
                SH_C3[2] * y * (4.0 * zz - xx - yy), SH_C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy),
                SH_C3[4] * x * (4.0 * zz - xx - yy), SH_C3[5] * z * (xx - yy),
                SH_C3[6] * x * (xx - 3.0 * yy)]
    basis = torch.stack(out, dim=-1)
    assert basis.shape[-1] == n
    return basis


def eval_sh(degree: int, coeffs: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
    """Evaluate SH coefficients in the given directions (no offset, no clamp).

    Args:
        degree: 0..3; uses the first ``(degree+1)**2`` coefficients.
        coeffs: [..., K, D] (D = 3 for colour), broadcastable against ``dirs``' batch dims.
        dirs: [..., 3] viewing directions (world frame, from the camera centre to the point).
    Returns:
        [..., D].
    """
    n = num_sh_bases(degree)
    if coeffs.shape[-2] < n:
        raise ValueError(f"SH degree {degree} needs {n} coefficients per channel, "
                         f"got {coeffs.shape[-2]}")
    basis = sh_basis(degree, dirs)
    return (basis.unsqueeze(-1) * coeffs[..., :n, :]).sum(-2)


def sh_to_color(degree: int, coeffs: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
    """3DGS colour: ``max(eval_sh(degree, coeffs, dirs) + 0.5, 0)``, shape [..., D]."""
    return torch.clamp_min(eval_sh(degree, coeffs, dirs) + 0.5, 0.0)


def sh_colors(degree: int, coeffs: torch.Tensor, dirs: torch.Tensor,
              fused: bool = True) -> torch.Tensor:
    """:func:`sh_to_color` of coeffs [N,K,3] seen along dirs [C,N,3]: colours [C,N,3].

    With ``fused`` and CPU tensors the compiled kernel of :mod:`gdiff.splat.csrc` computes it
    (same maths, one loop instead of ~50 small tensors; it falls back here when it is not
    built)."""
    if fused and coeffs.device.type == "cpu" and dirs.device.type == "cpu" and coeffs.dim() == 3:
        from . import csrc

        if csrc.load(required=False) is not None:
            return csrc.sh_to_color_cpp(degree, coeffs, dirs)
    return sh_to_color(degree, coeffs[None], dirs)


def rgb_to_sh(rgb: torch.Tensor) -> torch.Tensor:
    """Degree-0 coefficient giving colour ``rgb`` (inverse of :func:`sh_to_color` at degree 0)."""
    return (rgb - 0.5) / SH_C0


def sh_to_rgb(sh0: torch.Tensor) -> torch.Tensor:
    """Colour of a degree-0 coefficient (before the clamp)."""
    return sh0 * SH_C0 + 0.5
