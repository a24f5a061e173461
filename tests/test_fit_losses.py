"""Image losses of the fit: SSIM against a direct 2D-window implementation, PSNR, TV."""

import math

import numpy as np
import torch
import torch.nn.functional as F

from gdiff.splat.losses import l1, psnr, smoothness, ssim, ssim_map, tv


def _ssim_direct(x, y, window=11, sigma=1.5):
    """Textbook SSIM with a full 2D Gaussian window (zero padding), per channel."""
    ax = torch.arange(window, dtype=torch.float64) - (window - 1) / 2
    g = torch.exp(-ax ** 2 / (2 * sigma ** 2))
    w2 = torch.outer(g, g)
    w2 = (w2 / w2.sum()).float()[None, None].repeat(3, 1, 1, 1)
    x = x.permute(2, 0, 1)[None]
    y = y.permute(2, 0, 1)[None]
    conv = lambda a: F.conv2d(a, w2, padding=window // 2, groups=3)  # noqa: E731
    mx, my = conv(x), conv(y)
    sxx, syy, sxy = conv(x * x) - mx ** 2, conv(y * y) - my ** 2, conv(x * y) - mx * my
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    return ((2 * mx * my + c1) * (2 * sxy + c2) / ((mx ** 2 + my ** 2 + c1) * (sxx + syy + c2)))


def test_ssim_matches_direct_window_and_bounds():
    g = torch.Generator().manual_seed(0)
    a = torch.rand(40, 50, 3, generator=g)
    b = (a + 0.1 * torch.randn(40, 50, 3, generator=g)).clamp(0, 1)
    assert torch.allclose(ssim_map(a, b)[0], _ssim_direct(a, b)[0], atol=1e-5)
    assert abs(float(ssim(a, a)) - 1.0) < 1e-6
    s = float(ssim(a, b))
    assert 0.2 < s < 0.99
    assert float(ssim(a, torch.rand(40, 50, 3, generator=g))) < s


def test_ssim_batch_and_gradient():
    a = torch.rand(2, 16, 16, 3, requires_grad=True)
    b = torch.rand(2, 16, 16, 3)
    (1 - ssim(a, b)).backward()
    assert a.grad is not None and torch.isfinite(a.grad).all()
    assert ssim_map(a, b).shape == (2, 3, 16, 16)


def test_psnr_l1():
    a = torch.zeros(4, 4, 3)
    b = torch.full((4, 4, 3), 0.1)
    assert math.isclose(float(psnr(a, b)), 20.0, rel_tol=1e-5)
    assert math.isclose(float(l1(a, b)), 0.1, rel_tol=1e-6)


def test_tv_and_smoothness():
    ramp = torch.linspace(0, 1, 5).view(1, 1, 5, 1).expand(1, 2, 5, 7)
    assert math.isclose(float(tv(ramp)), 0.25 ** 2, rel_tol=1e-6)
    assert float(smoothness(ramp, dim=2)) < 1e-12  # linear along that axis
    quad = torch.tensor(np.arange(5.0) ** 2).view(1, 1, 5, 1)
    assert math.isclose(float(smoothness(quad, dim=2)), 4.0, rel_tol=1e-6)
    assert float(smoothness(torch.rand(1, 1, 2, 4), dim=2)) == 0.0
