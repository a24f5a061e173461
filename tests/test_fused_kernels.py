"""The fused C++ projection and SH kernels against their torch references (values, radii and
gradients), on Gaussians that cover the edge cases: behind the camera, far outside the field of
view (Jacobian clamp), near-degenerate scales, colours clamped at zero, zero directions."""

from __future__ import annotations

import pytest
import torch

from gdiff.splat import rasterize as R
from gdiff.splat.sh import sh_colors, sh_to_color


def _csrc():
    try:
        from gdiff.splat import csrc
    except ImportError:
        return None
    return csrc if csrc.load(required=False) is not None else None


csrc = _csrc()
pytestmark = pytest.mark.skipif(csrc is None, reason="C++ kernel could not be built")


def _cameras(dtype):
    g = torch.Generator().manual_seed(3)
    viewmats = torch.eye(4, dtype=dtype).repeat(3, 1, 1)
    viewmats[0, 2, 3] = 3.0
    for c in (1, 2):
        q, _ = torch.linalg.qr(torch.randn(3, 3, generator=g, dtype=dtype))
        viewmats[c, :3, :3] = q * torch.sign(torch.det(q))
        viewmats[c, :3, 3] = torch.randn(3, generator=g, dtype=dtype)
    Ks = torch.tensor([[200.0, 0, 80], [0, 210.0, 60], [0, 0, 1]], dtype=dtype).repeat(3, 1, 1)
    Ks[2, 0, 2] = 50.0  # off-centre principal point: asymmetric clamp limits
    return viewmats, Ks


def _gaussians(n, dtype, seed=0):
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=g, dtype=dtype) * 2.0  # many behind / outside cameras
    quats = torch.randn(n, 4, generator=g, dtype=dtype)
    scales = torch.rand(n, 3, generator=g, dtype=dtype) * 0.3 + 1e-4
    scales[: n // 10, 0] = 1e-6  # flat Gaussians
    return means, quats, scales


@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-12), (torch.float32, 2e-5)])
def test_fused_projection_matches_torch(dtype, tol):
    viewmats, Ks = _cameras(dtype)
    base = _gaussians(4000, dtype)
    n_cam, n = viewmats.shape[0], base[0].shape[0]
    g = torch.Generator().manual_seed(5)
    w_m = torch.randn(n_cam, n, 2, generator=g, dtype=dtype)
    w_c = torch.randn(n_cam, n, 3, generator=g, dtype=dtype)
    w_d = torch.randn(n_cam, n, generator=g, dtype=dtype)
    results = []
    for fused in (False, True):
        params = [p.clone().requires_grad_(True) for p in base]
        if fused:
            out = csrc.project_cpp(*params, viewmats, Ks, 160, 120, near_plane=0.2, eps2d=0.3)
        else:
            out = R.project_gaussians(params[0], R.covariance_3d(params[1], params[2]), viewmats,
                                      Ks, 160, 120, near_plane=0.2, eps2d=0.3)
        loss = (out["means2d"] * w_m).sum() + (out["conics"] * w_c).sum() \
            + (out["depths"] * w_d).sum()
        loss.backward()
        results.append((out, [p.grad for p in params]))
    (ref, ref_g), (got, got_g) = results
    vis = ref["visible"]
    assert 0.05 < vis.float().mean() < 0.95  # both culled and drawn Gaussians are exercised
    assert torch.equal(ref["visible"], got["visible"])
    assert (ref["radii"] - got["radii"]).abs().max() <= (0 if dtype == torch.float64 else 1)
    for key in ("means2d", "conics", "depths", "extents"):
        a, b = ref[key], got[key]
        scale = a.abs().amax().clamp_min(1.0)
        torch.testing.assert_close(b / scale, a / scale, atol=tol, rtol=0, msg=key)
    for name, a, b in zip(("means", "quats", "scales"), ref_g, got_g):
        scale = a.abs().amax()
        torch.testing.assert_close(b / scale, a / scale, atol=tol, rtol=0, msg=name)


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_fused_sh_matches_torch(degree):
    g = torch.Generator().manual_seed(degree)
    coeffs0 = torch.randn(3000, 16, 3, generator=g, dtype=torch.float64) * 2.0
    dirs0 = torch.randn(2, 3000, 3, generator=g, dtype=torch.float64)
    dirs0[0, :10] = 0.0  # zero direction: degree-0 colour, no gradient blow-up
    w = torch.randn(2, 3000, 3, generator=g, dtype=torch.float64)
    results = []
    for fused in (False, True):
        coeffs = coeffs0.clone().requires_grad_(True)
        dirs = dirs0.clone().requires_grad_(True)
        out = sh_colors(degree, coeffs, dirs, fused=fused)
        (out * w).sum().backward()
        gd = dirs.grad if dirs.grad is not None else torch.zeros_like(dirs)
        results.append((out, coeffs.grad, gd))
    ref = sh_to_color(degree, coeffs0[None], dirs0)
    assert (ref == 0).any() and (ref > 0).any()  # the clamp at zero is exercised
    torch.testing.assert_close(results[0][0], ref, atol=0, rtol=0)
    for a, b in zip(results[0], results[1]):
        torch.testing.assert_close(b, a, atol=1e-12, rtol=0)


def test_fused_gradients_do_not_depend_on_threads(torch_threads):
    viewmats, Ks = _cameras(torch.float32)
    base = _gaussians(20000, torch.float32, seed=2)
    sh0 = torch.randn(20000, 16, 3, generator=torch.Generator().manual_seed(1))
    grads = []
    for nt in (1, 3):
        torch_threads(nt)
        params = [p.clone().requires_grad_(True) for p in base]
        sh = sh0.clone().requires_grad_(True)
        out = csrc.project_cpp(*params, viewmats, Ks, 160, 120)
        dirs = params[0][None] - R.camera_centers(viewmats)[:, None]
        col = csrc.sh_to_color_cpp(3, sh, dirs)
        (out["means2d"].sum() + out["conics"].sum() + col.square().sum()).backward()
        grads.append([p.grad for p in params] + [sh.grad])
    for a, b in zip(*grads):
        assert torch.equal(a, b)


def test_fused_mirror_directions_match_torch():
    from gdiff.splat.reflection import reflect, shortest_axis

    dirs0 = torch.randn(2, 2000, 3, dtype=torch.float64) * 3.0
    dirs0[1, :5] = 0.0  # a camera centre on a Gaussian
    quats0, scales0 = _gaussians(2000, torch.float64, seed=4)[1:]
    scales0[:20] = scales0[:20, :1]  # ties: the first smallest axis, as torch.argmin
    w = torch.randn(2, 2000, 3, dtype=torch.float64)
    results = []
    for fused in (False, True):
        dirs, quats = dirs0.clone().requires_grad_(True), quats0.clone().requires_grad_(True)
        if fused:
            r = csrc.reflect_cpp(dirs, quats, scales0)
        else:
            r = reflect(dirs, shortest_axis(quats, scales0)[None])
        (r * w).sum().backward()
        results.append((r, dirs.grad, quats.grad))
    for name, a, b in zip(("r", "grad dirs", "grad quats"), *results):
        torch.testing.assert_close(b, a, atol=1e-10, rtol=1e-10, msg=name)


def test_depth_order_sorts_the_visible_gaussians_stably():
    g = torch.Generator().manual_seed(0)
    depths = torch.rand(2, 500, generator=g)
    depths[:, :50] = 0.5  # ties keep index order
    visible = torch.rand(2, 500, generator=g) < 0.6
    order = csrc.depth_order(depths, visible)
    for c in range(2):
        assert sorted(order[c].tolist()) == list(range(500))
        full = torch.argsort(depths[c], stable=True)
        n_vis = int(visible[c].sum())
        assert torch.equal(order[c, :n_vis], full[visible[c][full]])
        assert not visible[c, order[c, n_vis:]].any()
