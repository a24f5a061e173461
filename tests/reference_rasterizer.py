"""A plain dense Gaussian-splatting renderer used as the test oracle.

Every pixel is tested against every Gaussian; Gaussians are visited one by one in depth order
with an explicit transmittance variable, exactly as the maths reads. Written independently of
``gdiff.splat.rasterize`` (own projection, own SH), slow and only for small scenes.
"""

from __future__ import annotations

import math

import torch

SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199


def rotmat(q):
    """Rotation matrix from one quaternion (w, x, y, z), any norm."""
    q = q / torch.linalg.norm(q)
    w, x, y, z = q
    return torch.stack([
        torch.stack([w * w + x * x - y * y - z * z, 2 * (x * y - w * z), 2 * (x * z + w * y)]),
        torch.stack([2 * (x * y + w * z), w * w - x * x + y * y - z * z, 2 * (y * z - w * x)]),
        torch.stack([2 * (x * z - w * y), 2 * (y * z + w * x), w * w - x * x - y * y + z * z]),
    ])


def sh_colour(deg, coeffs, d):
    """SH colour (degree <= 3) for one Gaussian: coeffs [K,3], d unit direction [3]."""
    x, y, z = d
    basis = [SH_C0 * torch.ones_like(x)]
    if deg >= 1:
        basis += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if deg >= 2:
        basis += [1.0925484305920792 * x * y, -1.0925484305920792 * y * z,
                  0.31539156525252005 * (2 * z * z - x * x - y * y),
                  -1.0925484305920792 * x * z, 0.5462742152960396 * (x * x - y * y)]
    if deg >= 3:
        basis += [-0.5900435899266435 * y * (3 * x * x - y * y),
                  2.890611442640554 * x * y * z,
                  -0.4570457994644658 * y * (4 * z * z - x * x - y * y),
                  0.3731763325901154 * z * (2 * z * z - 3 * x * x - 3 * y * y),
                  -0.4570457994644658 * x * (4 * z * z - x * x - y * y),
                  1.445305721320277 * z * (x * x - y * y),
                  -0.5900435899266435 * x * (x * x - 3 * y * y)]
    b = torch.stack(basis)
    return torch.clamp_min((b[:, None] * coeffs[: len(basis)]).sum(0) + 0.5, 0.0)


def render_dense(means, quats, scales, opacities, colors, viewmat, K, width, height,
                 near=0.01, far=1e10, sh_degree=None, eps2d=0.3):
    """Render one camera. Returns (features [H,W,D] without background, alpha [H,W,1],
    depth-weighted sum [H,W,1]). ``colors`` [N,D] features or [N,K,3] SH."""
    N = means.shape[0]
    Rw, tw = viewmat[:3, :3], viewmat[:3, 3]
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    campos = -Rw.T @ tw
    js, is_ = torch.meshgrid(torch.arange(height, dtype=means.dtype),
                             torch.arange(width, dtype=means.dtype), indexing="ij")
    pcx, pcy = (is_ + 0.5).reshape(-1), (js + 0.5).reshape(-1)
    items = []
    for n in range(N):
        pc = Rw @ means[n] + tw
        z = pc[2]
        if not (near <= float(z) <= far):
            continue
        lxp = (width - cx) / fx + 0.3 * (0.5 * width / fx)
        lxn = cx / fx + 0.3 * (0.5 * width / fx)
        lyp = (height - cy) / fy + 0.3 * (0.5 * height / fy)
        lyn = cy / fy + 0.3 * (0.5 * height / fy)
        u = torch.clamp(pc[0] / z, -lxn, lxp) * z
        v = torch.clamp(pc[1] / z, -lyn, lyp) * z
        zero = torch.zeros((), dtype=means.dtype)
        J = torch.stack([torch.stack([fx / z, zero, -fx * u / z ** 2]),
                         torch.stack([zero, fy / z, -fy * v / z ** 2])])
        Rg = rotmat(quats[n])
        S = torch.diag(scales[n])
        cov = J @ Rw @ (Rg @ S @ S @ Rg.T) @ Rw.T @ J.T + eps2d * torch.eye(2, dtype=means.dtype)
        inv = torch.linalg.inv(cov)
        mu = torch.stack([fx * pc[0] / z + cx, fy * pc[1] / z + cy])
        d = torch.stack([pcx - mu[0], pcy - mu[1]], dim=-1)  # [P,2]
        sigma = 0.5 * torch.einsum("pi,ij,pj->p", d, inv, d)
        if sh_degree is None:
            col = colors[n]
        else:
            dirv = means[n] - campos
            col = sh_colour(sh_degree, colors[n], dirv / torch.linalg.norm(dirv))
        items.append((float(z), n, sigma, col, z))
    items.sort(key=lambda it: (it[0], it[1]))
    P = height * width
    D = colors.shape[-1]
    out = torch.zeros(P, D, dtype=means.dtype)
    dep = torch.zeros(P, dtype=means.dtype)
    T = torch.ones(P, dtype=means.dtype)
    done = torch.zeros(P, dtype=torch.bool)
    for _, n, sigma, col, z in items:
        alpha = torch.clamp_max(opacities[n] * torch.exp(-sigma), 0.99)
        valid = (sigma <= 4.5) & (alpha >= 1.0 / 255.0) & ~done
        nT = T * (1 - alpha)
        stop = valid & (nT <= 1e-4)
        done = done | stop
        use = valid & ~stop
        w = torch.where(use, alpha * T, torch.zeros_like(T))
        out = out + w[:, None] * col[None, :]
        dep = dep + w * z
        T = torch.where(use, nT, T)
    return (out.reshape(height, width, D), (1 - T).reshape(height, width, 1),
            dep.reshape(height, width, 1))


def look_at_w2c(center, target, up=(0.0, 0.0, 1.0), dtype=torch.float64):
    """World-to-camera 4x4 (OpenCV axes) of a camera at ``center`` looking at ``target``."""
    c = torch.tensor(center, dtype=dtype)
    zc = torch.tensor(target, dtype=dtype) - c
    zc = zc / zc.norm()
    xc = torch.linalg.cross(zc, torch.tensor(up, dtype=dtype))
    xc = xc / xc.norm()
    yc = torch.linalg.cross(zc, xc)
    R = torch.stack([xc, yc, zc])  # rows: camera axes in world
    w2c = torch.eye(4, dtype=dtype)
    w2c[:3, :3] = R
    w2c[:3, 3] = -R @ c
    return w2c


def random_scene(n, seed, n_cams=2, width=24, height=18, dtype=torch.float32, sh_degree=None,
                 D=3, scale_range=(0.03, 0.25), spread=1.0):
    """Random Gaussians around the origin and cameras on a ring looking at it."""
    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=g, dtype=torch.float64) - 0.5) * 2 * spread
    quats = torch.randn(n, 4, generator=g, dtype=torch.float64) * 2
    lo, hi = scale_range
    scales = torch.exp(torch.rand(n, 3, generator=g, dtype=torch.float64)
                       * (math.log(hi) - math.log(lo)) + math.log(lo))
    opac = torch.rand(n, generator=g, dtype=torch.float64) * 0.9 + 0.05
    if sh_degree is None:
        colors = torch.rand(n, D, generator=g, dtype=torch.float64)
    else:
        colors = torch.randn(n, (sh_degree + 1) ** 2, 3, generator=g, dtype=torch.float64) * 0.4
    vms, Ks = [], []
    for k in range(n_cams):
        ang = 2 * math.pi * k / n_cams + 0.3
        vms.append(look_at_w2c((3.5 * math.cos(ang), 3.5 * math.sin(ang), 1.0), (0.0, 0.0, 0.0)))
        f = 0.9 * width
        Ks.append(torch.tensor([[f, 0, width / 2 + 0.3], [0, f * 1.05, height / 2 - 0.2],
                                [0, 0, 1]], dtype=torch.float64))
    cast = lambda t: t.to(dtype)  # noqa: E731
    return dict(means=cast(means), quats=cast(quats), scales=cast(scales), opacities=cast(opac),
                colors=cast(colors), viewmats=cast(torch.stack(vms)), Ks=cast(torch.stack(Ks)),
                width=width, height=height)
