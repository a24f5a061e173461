"""Image and grid losses for Gaussian fitting: L1, SSIM, PSNR, total variation, time smoothness.

Images are float tensors in channels-last layout, ``[H, W, 3]`` or ``[B, H, W, 3]``, values in
[0, 1] (sRGB-encoded, see docs/design.md). Grids (HexPlane planes) are ``[..., A, B]`` tensors.
All functions are differentiable and device-agnostic.
"""

from __future__ import annotations

import functools
import math

import torch
import torch.nn.functional as F


def l1(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Mean absolute error over all elements (scalar)."""
    return (pred - target).abs().mean()


def psnr(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Peak signal-to-noise ratio in dB for images in [0, 1] (scalar, over all elements)."""
    mse = (pred - target).pow(2).mean().clamp_min(1e-12)
    return -10.0 * torch.log10(mse)


@functools.lru_cache(maxsize=8)
def _gauss_1d(size: int, sigma: float) -> torch.Tensor:
    x = torch.arange(size, dtype=torch.float64) - (size - 1) / 2.0
    g = torch.exp(-(x ** 2) / (2.0 * sigma ** 2))
    return (g / g.sum()).float()


def _to_nchw(img: torch.Tensor) -> torch.Tensor:
    if img.dim() == 3:
        img = img[None]
    return img.permute(0, 3, 1, 2)


def _blur(x: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
    """Separable Gaussian blur of [B, C, H, W] with zero padding ('same' size)."""
    c = x.shape[1]
    k = g.numel()
    gx = g.view(1, 1, 1, k).expand(c, 1, 1, k)
    gy = g.view(1, 1, k, 1).expand(c, 1, k, 1)
    x = F.conv2d(x, gx, padding=(0, k // 2), groups=c)
    return F.conv2d(x, gy, padding=(k // 2, 0), groups=c)


def ssim_map(pred: torch.Tensor, target: torch.Tensor, window: int = 11,
             sigma: float = 1.5) -> torch.Tensor:
    """Per-pixel SSIM (Wang et al. 2004, Gaussian window, zero padding as in 3DGS).

    pred, target: [H, W, C] or [B, H, W, C] in [0, 1]. Returns [B, C, H, W].
    """
    x, y = _to_nchw(pred), _to_nchw(target)
    g = _gauss_1d(window, sigma).to(device=x.device, dtype=x.dtype)
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    # one blur call for all five moments
    n = x.shape[1]
    stats = _blur(torch.cat([x, y, x * x, y * y, x * y], dim=1), g)
    mu_x, mu_y, exx, eyy, exy = stats.split(n, dim=1)
    sxx = exx - mu_x * mu_x
    syy = eyy - mu_y * mu_y
    sxy = exy - mu_x * mu_y
    num = (2 * mu_x * mu_y + c1) * (2 * sxy + c2)
    den = (mu_x * mu_x + mu_y * mu_y + c1) * (sxx + syy + c2)
    return num / den


def ssim(pred: torch.Tensor, target: torch.Tensor, window: int = 11,
         sigma: float = 1.5) -> torch.Tensor:
    """Mean SSIM (scalar) of images [H, W, C] or [B, H, W, C] in [0, 1]; 1 = identical."""
    return ssim_map(pred, target, window, sigma).mean()


def tv(grid: torch.Tensor) -> torch.Tensor:
    """Total variation (mean squared difference of neighbours) over the last two dims.

    grid: [..., A, B]. Returns a scalar: mean over both axes of squared first differences.
    """
    d_a = (grid[..., 1:, :] - grid[..., :-1, :]).pow(2).mean()
    d_b = (grid[..., :, 1:] - grid[..., :, :-1]).pow(2).mean()
    return d_a + d_b


def smoothness(grid: torch.Tensor, dim: int) -> torch.Tensor:
    """Mean squared second difference along ``dim`` (penalises acceleration, e.g. along time).

    Returns 0 when the axis has fewer than 3 samples (a 2-sample axis is linear already).
    """
    n = grid.shape[dim]
    if n < 3:
        return grid.new_zeros(())
    a = grid.narrow(dim, 0, n - 2)
    b = grid.narrow(dim, 1, n - 2)
    c = grid.narrow(dim, 2, n - 2)
    return (a - 2 * b + c).pow(2).mean()


def psnr_from_mse(mse: float) -> float:
    """PSNR in dB for images in [0, 1] from a mean squared error."""
    return -10.0 * math.log10(max(mse, 1e-12))
