"""Tests of the Gaussian rasterizer against the dense reference, finite differences and
closed-form single-Gaussian cases, for the torch backend and the compiled C++ backend."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from gdiff.splat import rasterize as R
from gdiff.splat.sh import eval_sh, num_sh_bases, sh_basis

from reference_rasterizer import random_scene, render_dense


def _cpp_available():
    try:
        from gdiff.splat import csrc
    except ImportError:
        return False
    return csrc.load(required=False) is not None


BACKENDS = ["torch", pytest.param("cpp", marks=pytest.mark.skipif(
    not _cpp_available(), reason="C++ kernel could not be built"))]


def _render(scene, backend, **kw):
    args = {k: scene[k] for k in ("means", "quats", "scales", "opacities", "colors", "viewmats",
                                  "Ks", "width", "height")}
    args.update(kw)
    return R.rasterize(**args, backend=backend)


def _reference(scene, sh_degree=None, backgrounds=None, mode="RGB"):
    outs, alphas = [], []
    for c in range(scene["viewmats"].shape[0]):
        f, a, d = render_dense(scene["means"].double(), scene["quats"].double(),
                               scene["scales"].double(), scene["opacities"].double(),
                               scene["colors"].double(), scene["viewmats"][c].double(),
                               scene["Ks"][c].double(), scene["width"], scene["height"],
                               sh_degree=sh_degree)
        if backgrounds is not None:
            f = f + (1 - a) * backgrounds[c].double()
        if mode == "RGB":
            o = f
        elif mode == "D":
            o = d
        elif mode == "ED":
            o = d / a.clamp_min(1e-10)
        elif mode == "RGB+D":
            o = torch.cat([f, d], -1)
        else:
            o = torch.cat([f, d / a.clamp_min(1e-10)], -1)
        outs.append(o)
        alphas.append(a)
    return torch.stack(outs), torch.stack(alphas)


# ------------------------------------------------------------------ forward vs dense reference

@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("D,bg,mode", [(3, False, "RGB"), (3, True, "RGB"), (16, True, "RGB"),
                                       (16, False, "RGB"), (3, True, "D"), (3, False, "ED"),
                                       (3, True, "RGB+D"), (16, True, "RGB+ED")])
def test_matches_dense_reference(backend, D, bg, mode):
    sc = random_scene(40, seed=D * 7 + len(mode) + bg, n_cams=3, D=D)
    C = sc["viewmats"].shape[0]
    backgrounds = torch.rand(C, D, generator=torch.Generator().manual_seed(1)) if bg else None
    out, alpha, meta = _render(sc, backend, backgrounds=backgrounds, render_mode=mode)
    ref, ref_a = _reference(sc, backgrounds=backgrounds, mode=mode)
    X = {"RGB": D, "D": 1, "ED": 1}.get(mode, D + 1)
    assert out.shape == (C, sc["height"], sc["width"], X)
    assert alpha.shape == (C, sc["height"], sc["width"], 1)
    assert meta["backend"] == backend
    assert (alpha > 0.5).float().mean() > 0.1  # the scene covers a good part of the image
    torch.testing.assert_close(alpha.double(), ref_a, atol=2e-5, rtol=0)
    scale = 1.0 if "D" not in mode else float(ref.abs().max())  # depth channel in world units
    torch.testing.assert_close(out.double() / scale, ref / scale, atol=2e-5, rtol=0)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("deg", [0, 1, 2, 3])
def test_sh_matches_reference(backend, deg):
    sc = random_scene(30, seed=100 + deg, n_cams=2, sh_degree=deg)
    out, alpha, _ = _render(sc, backend, sh_degree=deg)
    ref, ref_a = _reference(sc, sh_degree=deg)
    torch.testing.assert_close(out.double(), ref, atol=2e-5, rtol=0)
    if deg > 0:  # view dependence is real: another degree gives another image
        out0, _, _ = _render(sc, backend, sh_degree=0)
        assert (out0 - out).abs().max() > 1e-2


@pytest.mark.parametrize("backend", BACKENDS)
def test_dense_opaque_scene_reaches_transmittance_cutoff(backend):
    """Many opaque layers: early termination (T <= 1e-4) must match the reference."""
    sc = random_scene(60, seed=5, n_cams=1, scale_range=(0.3, 0.6), spread=0.4)
    sc["opacities"] = torch.full_like(sc["opacities"], 0.98)
    out, alpha, _ = _render(sc, backend)
    ref, ref_a = _reference(sc)
    assert float((ref_a > 1 - 2e-4).double().mean()) > 0.1  # transmittance hits the cutoff
    torch.testing.assert_close(alpha.double(), ref_a, atol=2e-5, rtol=0)
    torch.testing.assert_close(out.double(), ref, atol=2e-5, rtol=0)


def test_colors_per_camera_and_meta():
    sc = random_scene(20, seed=9, n_cams=2, D=5)
    C, N = 2, 20
    per_cam = torch.stack([sc["colors"], 1 - sc["colors"]])
    out, _, meta = _render({**sc, "colors": per_cam}, "torch")
    out0, _, _ = _render({**sc, "colors": sc["colors"]}, "torch")
    out1, _, _ = _render({**sc, "colors": 1 - sc["colors"]}, "torch")
    torch.testing.assert_close(out[0], out0[0])
    torch.testing.assert_close(out[1], out1[1])
    assert meta["means2d"].shape == (C, N, 2) and meta["radii"].shape == (C, N)
    assert meta["radii"].dtype == torch.int32 and meta["depths"].shape == (C, N)
    assert meta["conics"].shape == (C, N, 3) and meta["opacities"].shape == (C, N)
    assert meta["width"] == sc["width"] and meta["height"] == sc["height"] and meta["n_cameras"] == C
    # depths are camera-frame z
    z = (sc["viewmats"][:, :3, :3] @ sc["means"].T).transpose(1, 2)[..., 2] + sc["viewmats"][:, None, 2, 3]
    torch.testing.assert_close(meta["depths"], z)


# ------------------------------------------------------------------ single Gaussian, closed form

def _single(mean, scale, opacity=0.8, color=(0.2, 0.5, 0.9), W=41, H=31, f=50.0, quat=(1, 0, 0, 0)):
    K = torch.tensor([[[f, 0, W / 2], [0, f, H / 2], [0, 0, 1]]])
    return dict(means=torch.tensor([mean], dtype=torch.float32),
                quats=torch.tensor([quat], dtype=torch.float32),
                scales=torch.tensor([scale], dtype=torch.float32),
                opacities=torch.tensor([opacity]), colors=torch.tensor([color]),
                viewmats=torch.eye(4)[None], Ks=K, width=W, height=H)


@pytest.mark.parametrize("backend", BACKENDS)
def test_single_gaussian_centre_and_footprint(backend):
    # mean projects exactly onto the centre of pixel (20, 15): u = f x / z + W/2 = 20.5
    W, H, f, z = 41, 31, 50.0, 5.0
    x = (20.5 - W / 2) * z / f
    y = (15.5 - H / 2) * z / f
    s = 0.2  # world std -> f s / z = 2 px std; 2D variance 4 + 0.3 dilation
    sc = _single((x, y, z), (s, s, 1e-3), W=W, H=H, f=f)
    out, alpha, meta = _render(sc, backend)
    assert float(alpha[0, 15, 20, 0]) == pytest.approx(0.8, abs=1e-6)
    torch.testing.assert_close(out[0, 15, 20], torch.tensor([0.2, 0.5, 0.9]) * 0.8)
    var = (f * s / z) ** 2 + 0.3  # the 1e-3 scale along z adds ~1e-6 px^2, below tolerance
    for d in range(1, 7):
        expected = 0.8 * math.exp(-0.5 * d * d / var)
        inside = 0.5 * d * d / var <= 4.5 and expected >= 1 / 255
        assert float(alpha[0, 15, 20 + d, 0]) == pytest.approx(expected if inside else 0.0, abs=2e-6)
        assert float(alpha[0, 15 - d, 20, 0]) == pytest.approx(expected if inside else 0.0, abs=2e-6)
    # footprint: exactly the pixel centres within the 3-sigma circle
    jj, ii = np.mgrid[0:H, 0:W]
    r2 = (ii + 0.5 - 20.5) ** 2 + (jj + 0.5 - 15.5) ** 2
    np.testing.assert_array_equal(alpha[0, ..., 0].numpy() > 0, r2 <= 9 * var)
    assert int(meta["radii"][0, 0]) == math.ceil(3 * math.sqrt(var))
    assert tuple(meta["means2d"][0, 0].tolist()) == pytest.approx((20.5, 15.5), abs=1e-5)


@pytest.mark.parametrize("backend", BACKENDS)
def test_opacity_clamp_and_anisotropic_footprint(backend):
    # rotated elongated Gaussian: 90 degrees about z swaps the x/y extents
    sc = _single((0.0, 0.0, 5.0), (0.4, 0.1, 1e-3), opacity=1.0,
                 quat=(math.cos(math.pi / 4), 0, 0, math.sin(math.pi / 4)))
    _, alpha, _ = _render(sc, backend)
    a = alpha[0, ..., 0]
    assert float(a.max()) == pytest.approx(0.99, abs=1e-6)
    ys, xs = torch.nonzero(a > 0, as_tuple=True)
    assert (ys.max() - ys.min()) > 2 * (xs.max() - xs.min())  # long along image y


@pytest.mark.parametrize("backend", BACKENDS)
def test_behind_camera_offscreen_and_far_contribute_nothing(backend):
    base = _single((0.0, 0.0, 5.0), (0.3, 0.1, 0.2), quat=(0.9, 0.2, 0.3, 0.1))
    out0, a0, _ = _render(base, backend)
    extra = [(0.0, 0.0, -5.0), (30.0, 0.0, 5.0), (0.0, 0.0, 0.005), (0.0, 0.0, 200.0)]
    sc = dict(base)
    n = 1 + len(extra)
    sc["means"] = torch.tensor([[0.0, 0.0, 5.0]] + [list(e) for e in extra], requires_grad=True)
    sc["quats"] = torch.tensor([[0.9, 0.2, 0.3, 0.1]] * n, requires_grad=True)
    sc["scales"] = torch.tensor([[0.3, 0.1, 0.2]] * n, requires_grad=True)
    sc["opacities"] = torch.full((n,), 0.8, requires_grad=True)
    sc["colors"] = torch.rand(n, 3).requires_grad_(True)
    with torch.no_grad():
        sc["colors"][0] = base["colors"][0]
    out, alpha, meta = _render(sc, backend, far_plane=100.0)
    torch.testing.assert_close(out, out0)
    torch.testing.assert_close(alpha, a0)
    assert meta["radii"][0, 0] > 0 and (meta["radii"][0, 1:] == 0).all()
    (out.sum() + alpha.sum()).backward()
    for k in ("means", "quats", "scales", "opacities", "colors"):
        g = sc[k].grad
        assert torch.isfinite(g).all(), k
        assert (g[1:] == 0).all(), k
        assert (g[0] != 0).any(), k


@pytest.mark.parametrize("backend", BACKENDS)
def test_empty_scene_returns_background(backend):
    bg = torch.tensor([[0.1, 0.2, 0.3], [0.9, 0.8, 0.7]])
    vm = torch.eye(4)[None].repeat(2, 1, 1)
    K = torch.tensor([[20.0, 0, 8], [0, 20.0, 6], [0, 0, 1]])[None].repeat(2, 1, 1)
    out, alpha, meta = R.rasterize(torch.zeros(0, 3), torch.zeros(0, 4), torch.zeros(0, 3),
                                   torch.zeros(0), torch.zeros(0, 3), vm, K, 16, 12,
                                   backgrounds=bg, backend=backend)
    assert out.shape == (2, 12, 16, 3)
    torch.testing.assert_close(out, bg[:, None, None, :].expand(2, 12, 16, 3))
    assert (alpha == 0).all()


def test_unknown_options_rejected():
    sc = _single((0.0, 0.0, 5.0), (0.2, 0.2, 0.2))
    with pytest.raises(ValueError, match="render_mode"):
        _render(sc, "torch", render_mode="RGBD")
    with pytest.raises(ValueError, match="backend"):
        _render(sc, "vulkan")
    with pytest.raises(ValueError, match="backgrounds"):
        _render(sc, "torch", backgrounds=torch.zeros(1, 4))


# ------------------------------------------------------------------ gradients

def _grad_scene(seed, sh_degree=None, D=3):
    sc = random_scene(12, seed=seed, n_cams=2, width=14, height=11, dtype=torch.float64,
                      sh_degree=sh_degree, D=D, scale_range=(0.15, 0.4), spread=0.7)
    sc["opacities"] = sc["opacities"].clamp(0.1, 0.9)
    return sc


def _loss_fn(sc, backend, sh_degree=None, mode="RGB", bg=None):
    C = sc["viewmats"].shape[0]
    D = sc["colors"].shape[-1]
    g = torch.Generator().manual_seed(3)
    X = {"RGB": D, "D": 1, "ED": 1}.get(mode, D + 1)
    wts = torch.rand(C, sc["height"], sc["width"], X, generator=g, dtype=torch.float64)
    wa = torch.rand(C, sc["height"], sc["width"], 1, generator=g, dtype=torch.float64)

    def f(means, quats, scales, opacities, colors, backgrounds=bg):
        out, alpha, _ = R.rasterize(means, quats, scales, opacities, colors, sc["viewmats"],
                                    sc["Ks"], sc["width"], sc["height"], sh_degree=sh_degree,
                                    render_mode=mode, backgrounds=backgrounds, backend=backend)
        return (out * wts).sum() + (alpha * wa).sum()

    return f


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("case", ["rgb", "sh2", "feat16_bg", "rgb+d"])
def test_gradients_match_finite_differences(backend, case):
    sh = 2 if case == "sh2" else None
    D = 16 if case == "feat16_bg" else 3
    sc = _grad_scene(11 + len(case), sh_degree=sh, D=D)
    bg = torch.rand(2, D, dtype=torch.float64) if case == "feat16_bg" else None
    mode = "RGB+D" if case == "rgb+d" else "RGB"
    f = _loss_fn(sc, backend, sh, mode, bg)
    params = [sc[k].clone().requires_grad_(True) for k in
              ("means", "quats", "scales", "opacities", "colors")]
    loss = f(*params)
    grads = torch.autograd.grad(loss, params)
    eps = 1e-6
    g = torch.Generator().manual_seed(0)
    for name, p, gr in zip(("means", "quats", "scales", "opacities", "colors"), params, grads):
        assert gr.abs().max() > 0, name
        flat = p.detach().reshape(-1)
        idx = torch.randperm(flat.numel(), generator=g)[:8]
        for i in idx.tolist():
            plus = [q.detach().clone() for q in params]
            minus = [q.detach().clone() for q in params]
            k = ["means", "quats", "scales", "opacities", "colors"].index(name)
            plus[k].view(-1)[i] += eps
            minus[k].view(-1)[i] -= eps
            fd = (f(*plus) - f(*minus)) / (2 * eps)
            assert float(gr.reshape(-1)[i]) == pytest.approx(float(fd), rel=1e-4, abs=1e-6), \
                (name, i)


@pytest.mark.parametrize("backend", BACKENDS)
def test_means2d_grad_and_absgrad(backend):
    sc = random_scene(25, seed=4, n_cams=2)
    means = sc["means"].clone().requires_grad_(True)
    out, alpha, meta = R.rasterize(means, sc["quats"], sc["scales"], sc["opacities"],
                                   sc["colors"], sc["viewmats"], sc["Ks"], sc["width"],
                                   sc["height"], absgrad=True, backend=backend)
    m2d = meta["means2d"]
    m2d.retain_grad()
    target = torch.full_like(out, 0.3)
    ((out - target) ** 2).sum().backward()
    vis = meta["radii"] > 0
    assert m2d.grad.shape == (2, 25, 2)
    assert (m2d.grad[~vis] == 0).all() and (m2d.grad[vis].abs().sum(-1) > 0).any()
    ag = m2d.absgrad
    assert ag.shape == (2, 25, 2)
    assert (ag >= m2d.grad.abs() - 1e-6).all()  # |sum| <= sum |.|
    assert (ag > m2d.grad.abs() + 1e-6).any()  # pixels pull in different directions


# ------------------------------------------------------------------ spherical harmonics

def test_sh_basis_is_orthonormal():
    # Gauss-Legendre in cos(theta) x uniform phi integrates degree <= 6 polynomials exactly
    xs, ws = np.polynomial.legendre.leggauss(8)
    phi = np.arange(16) * 2 * np.pi / 16
    ct, ph = np.meshgrid(xs, phi, indexing="ij")
    st = np.sqrt(1 - ct ** 2)
    dirs = torch.tensor(np.stack([st * np.cos(ph), st * np.sin(ph), ct], -1).reshape(-1, 3))
    w = torch.tensor((ws[:, None] * np.full(16, 2 * np.pi / 16)[None]).reshape(-1))
    Y = sh_basis(3, dirs)
    gram = (Y * w[:, None]).T @ Y
    torch.testing.assert_close(gram, torch.eye(16, dtype=torch.float64), atol=1e-12, rtol=0)


def test_sh_degree1_is_linear_in_direction():
    coeffs = torch.zeros(4, 1, dtype=torch.float64)
    coeffs[3, 0] = 1.0  # the -x basis
    d = torch.tensor([[1.0, 0, 0], [0, 1.0, 0], [-2.0, 0, 0]], dtype=torch.float64)
    v = eval_sh(1, coeffs, d)[:, 0]
    torch.testing.assert_close(v, torch.tensor([-0.4886025119029199, 0, 0.4886025119029199],
                                               dtype=torch.float64))
    assert num_sh_bases(3) == 16
    with pytest.raises(ValueError):
        num_sh_bases(4)


# ------------------------------------------------------------------ C++ kernel vs torch path

@pytest.mark.skipif(not _cpp_available(), reason="C++ kernel could not be built")
@pytest.mark.parametrize("D,mode", [(3, "RGB"), (16, "RGB+ED")])
def test_cpp_matches_torch_on_larger_scene(D, mode):
    """Many small and large Gaussians over several tiles: images and gradients agree."""
    sc = random_scene(1500, seed=21 + D, n_cams=2, width=70, height=45, D=D,
                      scale_range=(0.01, 0.3), spread=1.2)
    names = ("means", "quats", "scales", "opacities", "colors")
    bg = torch.rand(2, D, generator=torch.Generator().manual_seed(2))
    res = {}
    for backend in ("torch", "cpp"):
        params = [sc[k].clone().requires_grad_(True) for k in names]
        out, alpha, meta = R.rasterize(*params, sc["viewmats"], sc["Ks"], sc["width"],
                                       sc["height"], backgrounds=bg, render_mode=mode,
                                       backend=backend)
        m2d = meta["means2d"]
        m2d.retain_grad()
        w = torch.rand(out.shape, generator=torch.Generator().manual_seed(5))
        ((out * w).sum() + alpha.sum()).backward()
        res[backend] = (out.detach(), alpha.detach(), m2d.grad, [p.grad for p in params])
    (o_t, a_t, m_t, g_t), (o_c, a_c, m_c, g_c) = res["torch"], res["cpp"]
    torch.testing.assert_close(a_c, a_t, atol=1e-5, rtol=0)
    torch.testing.assert_close(o_c[..., :D], o_t[..., :D], atol=1e-5, rtol=0)
    if mode != "RGB":
        torch.testing.assert_close(o_c[..., D:], o_t[..., D:], atol=0, rtol=1e-5)
    torch.testing.assert_close(m_c, m_t, atol=1e-4, rtol=1e-3)
    for name, gc, gt in zip(names, g_c, g_t):
        scale = float(gt.abs().max())
        torch.testing.assert_close(gc / scale, gt / scale, atol=1e-4, rtol=0, msg=name)


@pytest.mark.skipif(not _cpp_available(), reason="C++ kernel could not be built")
@pytest.mark.parametrize("D", [3, 8])
def test_cpp_forward_composites_as_the_weights_traversal(D):
    """The float forward kernel (8 pixels at a time on CPUs with AVX2) and the scalar loop of
    rasterize_weights blend the same pairs: same last Gaussian per pixel, features equal to
    the weighted colours; with glibc (whose expf the vector exp reproduces) alpha is bitwise
    equal."""
    import platform

    from gdiff.splat import csrc

    mod = csrc.load(required=True)
    sc = random_scene(3000, seed=11, n_cams=1, width=75, height=41, D=D,
                      scale_range=(0.01, 0.3), spread=1.2)
    W, H = sc["width"], sc["height"]
    proj = R.project_gaussians(sc["means"], R.covariance_3d(sc["quats"], sc["scales"]),
                               sc["viewmats"], sc["Ks"], W, H)
    m2d, con, ext, vis = proj["means2d"], proj["conics"], proj["extents"], proj["visible"]
    op = sc["opacities"][None].contiguous()
    order = csrc.depth_order(proj["depths"], vis)
    out, alpha, _, last, _, ids = mod.rasterize_forward(
        m2d, con, sc["colors"][None].contiguous(), op, ext, vis, order, W, H, csrc.TILE_SIZE)
    counts, gid, weight, w_alpha = mod.rasterize_weights(m2d, con, op, ext, vis, order, W, H,
                                                         csrc.TILE_SIZE, 0.0)
    assert (w_alpha > 0.999).sum() > W * H / 4 and len(gid) > 20 * W * H  # many layers, stops
    pix = torch.repeat_interleave(torch.arange(W * H), counts.long())
    feats = torch.zeros(W * H, D).index_add_(0, pix, weight[:, None] * sc["colors"][gid.long()])
    torch.testing.assert_close(out.reshape(-1, D), feats, atol=1e-5, rtol=0)
    last = last.reshape(-1).long()
    blended = counts > 0
    assert torch.equal(last >= 0, blended)
    ends = torch.cumsum(counts.long(), 0) - 1
    assert torch.equal(ids[last[blended]], gid[ends[blended]])
    if platform.libc_ver()[0] == "glibc":
        assert torch.equal(alpha.reshape(-1), w_alpha)
    else:
        torch.testing.assert_close(alpha.reshape(-1), w_alpha, atol=1e-6, rtol=0)


def test_options_from_config():
    from gdiff.errors import ConfigError
    from gdiff.options import from_config

    opts = from_config(R.RasterizeOptions, {"backend": "torch", "eps2d": 0.3}, "rasterize")
    sc = _single((0.0, 0.0, 5.0), (0.2, 0.2, 0.2))
    out, _, meta = R.rasterize(*(sc[k] for k in ("means", "quats", "scales", "opacities",
                                                  "colors", "viewmats", "Ks", "width",
                                                  "height")), **opts.kwargs())
    assert meta["backend"] == "torch" and out.shape == (1, 31, 41, 3)
    with pytest.raises(ConfigError, match="rasterize"):
        from_config(R.RasterizeOptions, {"backend": "opengl"}, "rasterize")
    with pytest.raises(ConfigError, match="tile"):
        from_config(R.RasterizeOptions, {"tile": 8}, "rasterize")


@pytest.mark.parametrize("backend", BACKENDS)
def test_gradients_are_reproducible_with_threads(backend, torch_threads):
    """Gradients summed over tiles on several threads come out bitwise equal on every run
    (training resumed from a checkpoint must follow the uninterrupted run exactly); those of
    the compiled kernels also for any number of threads (the torch reference's scatter-adds
    are torch's own)."""
    sc = random_scene(3000, seed=7, n_cams=2, width=96, height=64, scale_range=(0.01, 0.3),
                      spread=1.2)
    names = ("means", "quats", "scales", "opacities", "colors")
    w = torch.rand(2, 64, 96, 3, generator=torch.Generator().manual_seed(1))
    grads = []
    # 4: more threads than tiles per thread
    for nt in (4, 4, 4) + ((1, 2, 3, 16) if backend == "cpp" else ()):
        torch_threads(nt)
        params = [sc[k].clone().requires_grad_(True) for k in names]
        out, _, _ = R.rasterize(*params, sc["viewmats"], sc["Ks"], sc["width"],
                                sc["height"], backend=backend, tile_size=8)
        (out * w).sum().backward()
        grads.append([p.grad for p in params])
    for g in grads[1:]:
        for name, a, b in zip(names, grads[0], g):
            assert torch.equal(a, b), name


def test_stale_build_lock_is_removed_and_a_fresh_one_kept(tmp_path):
    import os
    import time

    from gdiff.splat.csrc import clear_stale_lock

    lock = tmp_path / "lock"
    assert not clear_stale_lock(tmp_path)
    lock.write_text("")
    assert not clear_stale_lock(tmp_path) and lock.exists()  # another process is building
    old = time.time() - 3600
    os.utime(lock, (old, old))
    assert clear_stale_lock(tmp_path) and not lock.exists()


_HOLDER = """
import sys, time
from pathlib import Path
from gdiff.splat.csrc import build_guard
d = Path(sys.argv[1])
with build_guard(d):
    (d / "lock").write_text("")  # as torch's builder marks its build
    print("held", flush=True)
    time.sleep(float(sys.argv[2]))
    (d / "lock").unlink()  # the builder's release
    (d / "released").write_text("")
"""


def _hold_build_guard(tmp_path, seconds):
    import subprocess
    import sys

    # run from the checkout's root, as tests/test_parallel.py does, so the child imports it
    child = subprocess.Popen([sys.executable, "-c", _HOLDER, str(tmp_path), str(seconds)],
                             stdout=subprocess.PIPE, text=True,
                             cwd=Path(__file__).resolve().parents[1])
    assert child.stdout.readline().strip() == "held"
    return child


def test_a_build_lock_left_by_a_killed_process_is_removed_at_once(tmp_path):
    from gdiff.splat.csrc import build_guard

    child = _hold_build_guard(tmp_path, 600)
    child.kill()  # as a Ctrl-C'd or killed job mid-build
    child.wait()
    assert (tmp_path / "lock").exists()  # torch's builder would wait for it forever
    with build_guard(tmp_path):
        assert not (tmp_path / "lock").exists()


def test_the_build_guard_waits_for_a_live_build(tmp_path):
    from gdiff.splat.csrc import build_guard

    child = _hold_build_guard(tmp_path, 1)
    with build_guard(tmp_path):  # entered only once the child's build released its lock
        assert (tmp_path / "released").exists() and not (tmp_path / "lock").exists()
    assert child.wait() == 0


def test_each_version_of_the_kernel_sources_has_its_own_build(tmp_path, monkeypatch):
    """The build's name follows every kernel source, the included files too (a checkout of
    another version must not rebuild over this one's build, nor reuse it)."""
    from gdiff.splat import csrc

    files = []
    for name in ("kernels.cpp", "rasterize_cpu.cpp", "normalize.h"):
        f = tmp_path / name
        f.write_text(f"// {name}\n")
        files.append(f)
    monkeypatch.setattr(csrc, "_SOURCES", files)
    first = csrc.build_name()
    assert first == csrc.build_name() and first.startswith("gdiff_splat_cpu_")
    files[2].write_text("// normalize.h, edited\n")  # a header only kernels.cpp includes
    second = csrc.build_name()
    assert second != first
    files[2].write_text("// normalize.h\n")
    assert csrc.build_name() == first
