"""HexPlane + MLP deformation field and the 4D model built on it."""

import numpy as np
import pytest
import torch

from gdiff.splat.deform import PLANES, DeformConfig, Deformation, HexPlane
from gdiff.splat.model import GaussianModel4D, load_model, save_model


def _points(n=300, seed=0):
    rng = np.random.default_rng(seed)
    return rng.uniform(-1, 1, (n, 3)), rng.uniform(0, 1, (n, 3))


def test_plane_order_and_grid_axes():
    assert PLANES == ((0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3))
    hp = HexPlane(resolution=(8, 6, 4), time_resolution=3, multires=[1], features=2)
    shapes = [tuple(p.shape) for p in hp.grids]
    # [1, F, res(second axis), res(first axis)]
    assert shapes == [(1, 2, 6, 8), (1, 2, 4, 8), (1, 2, 3, 8), (1, 2, 4, 6), (1, 2, 3, 6),
                      (1, 2, 3, 4)]
    # a ramp along x in the xy plane must show up as a function of x only
    with torch.no_grad():
        for p in hp.grids:
            p.fill_(1.0)
        hp.grids[0].copy_(torch.linspace(0, 1, 8).view(1, 1, 1, 8).expand(1, 2, 6, 8))
    xyz = torch.tensor([[-1.0, 0.3, 0.0], [0.0, -0.7, 0.5], [1.0, 0.9, -1.0]])
    f = hp(xyz, 0.5)
    assert torch.allclose(f[:, 0], torch.tensor([0.0, 0.5, 1.0]), atol=1e-6)


def test_time_rows_are_exact_at_t0_and_t1():
    hp = HexPlane(resolution=(8, 8, 8), time_resolution=2, multires=[1, 2], features=4)
    xyz = torch.rand(50, 3) * 2 - 1
    f0, f1 = hp(xyz, 0.0), hp(xyz, 1.0)
    assert f0.shape == (50, 8)
    assert torch.allclose(f0, f1), "time planes start at 1: t must have no effect"
    with torch.no_grad():  # change only the t = 1 row of the xt plane
        hp.grids[2][:, :, 1, :] = 2.0
    assert torch.allclose(hp(xyz, 0.0), f0)
    assert torch.allclose(hp(xyz, 1.0)[:, :4], 2 * f0[:, :4])
    assert torch.allclose(hp(xyz, 1.0)[:, 4:], f0[:, 4:])  # the other level is untouched


def test_points_outside_the_box_are_clamped():
    hp = HexPlane(resolution=(8, 8, 8), multires=[1], features=2)
    hp.set_aabb(torch.tensor([0.0, 0, 0]), torch.tensor([1.0, 1, 1]))
    inside = hp(torch.tensor([[1.0, 1.0, 1.0]]), 0.0)
    outside = hp(torch.tensor([[5.0, 3.0, 1.5]]), 0.0)
    assert torch.allclose(inside, outside)


@torch.no_grad()
def test_regularisers():
    hp = HexPlane(resolution=(8, 8, 8), time_resolution=3, multires=[1], features=2)
    assert float(hp.time_l1()) == 0.0
    assert float(hp.time_smoothness()) == 0.0
    assert float(hp.plane_tv()) > 0.0  # random spatial planes are not smooth
    for p in hp.grids:
        p.fill_(0.3)
    assert float(hp.plane_tv()) == 0.0
    hp.grids[2][:, :, 1, :] = 1.0  # a kink along t in the xt plane
    assert float(hp.time_smoothness()) > 0.0
    assert float(hp.time_l1()) > 0.0


def test_heads_start_at_zero_and_are_switchable():
    d = Deformation(DeformConfig(resolution=[8, 8, 8], sh_coeffs=16))
    xyz = torch.rand(20, 3)
    out = d(xyz, 1.0)
    assert set(out) == {"means", "scales", "quats", "opacities", "sh"}
    assert out["means"].shape == (20, 3) and out["quats"].shape == (20, 4)
    assert out["opacities"].shape == (20,) and out["sh"].shape == (20, 1, 3)
    assert all(float(v.detach().abs().max()) == 0.0 for v in out.values())
    d2 = Deformation(DeformConfig(resolution=[8, 8, 8], opacity=False, color=False,
                                  color_degree=1))
    assert set(d2(xyz, 0.0)) == {"means", "scales", "quats"}
    d3 = Deformation(DeformConfig(resolution=[8, 8, 8], color_degree=1, sh_coeffs=16))
    assert d3(xyz, 0.0)["sh"].shape == (20, 4, 3)


def test_model_is_static_until_deformation_is_switched_on():
    xyz, rgb = _points()
    m = GaussianModel4D.from_points(xyz, rgb, 3, DeformConfig(resolution=[8, 8, 8]))
    g0 = m.at_time(0.0)
    # perturb a head so the deformation is non-zero
    with torch.no_grad():
        m.deformation.heads["means"][-1].bias.fill_(0.1)
    assert torch.equal(m.at_time(1.0).means, g0.means), "deform_on is off"
    m.deform_on.fill_(True)
    assert torch.allclose(m.at_time(1.0).means, g0.means + 0.1)
    # colour from points: degree-0 colour equals the point colour
    from gdiff.splat.gaussians import sh0_to_rgb
    assert torch.allclose(sh0_to_rgb(g0.sh[:, 0]), torch.tensor(rgb, dtype=torch.float32),
                          atol=1e-6)


def test_deformation_learns_a_change_at_t1_only():
    """Fit Δopacity so that a region fades out at t = 1 while t = 0 stays unchanged."""
    torch.manual_seed(0)
    xyz, rgb = _points(200)
    m = GaussianModel4D.from_points(xyz, rgb, 0, DeformConfig(resolution=[8, 8, 8],
                                                               time_resolution=2))
    m.deform_on.fill_(True)
    region = torch.tensor(xyz[:, 0] > 0.3)
    base = m.at_time(0.0).opacities.detach()
    target1 = torch.where(region, torch.full_like(base, 0.01), base)
    opt = torch.optim.Adam(m.deformation.parameters(), lr=2e-2)
    for _ in range(60):
        loss = ((m.at_time(1.0).opacities - target1) ** 2).mean() \
            + ((m.at_time(0.0).opacities - base) ** 2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    with torch.no_grad():
        o1, o0 = m.at_time(1.0).opacities, m.at_time(0.0).opacities
    assert float(o1[region].mean()) < 0.04
    assert float((o1[~region] - base[~region]).abs().mean()) < 0.02
    assert float((o0 - base).abs().mean()) < 0.02


def test_save_load_round_trip_with_extra_per_gaussian_entries(tmp_path):
    xyz, rgb = _points(50)
    m = GaussianModel4D.from_points(xyz, rgb, 2, DeformConfig(resolution=[8, 8, 8]))
    m.deform_on.fill_(True)
    m.active_sh_degree.fill_(2)
    with torch.no_grad():
        m.deformation.heads["scales"][-1].bias.fill_(0.2)
    m.splats["encoding"] = torch.nn.Parameter(torch.randn(50, 16))
    save_model(m, tmp_path / "model.pt", meta={"note": "x"})
    back = load_model(tmp_path / "model.pt")
    assert back.meta == {"note": "x"} and back.sh_degree == 2
    assert torch.equal(back.splats["encoding"], m.splats["encoding"])
    a, b = m.at_time(1.0), back.at_time(1.0)
    assert b.sh_degree == 2
    for name in ("means", "quats", "scales", "opacities", "sh"):
        assert torch.allclose(getattr(a, name), getattr(b, name)), name


def test_static_model_and_bad_files(tmp_path):
    from gdiff.errors import ModelFileError

    xyz, rgb = _points(10)
    m = GaussianModel4D.from_points(xyz, rgb, 0, None)
    assert m.deformation is None
    assert torch.equal(m.at_time(0.0).means, m.at_time(1.0).means)
    with pytest.raises(ModelFileError, match="not found"):
        load_model(tmp_path / "none.pt")
    torch.save({"something": 1}, tmp_path / "other.pt")
    with pytest.raises(ModelFileError, match="other.pt"):
        load_model(tmp_path / "other.pt")


def test_time_opacity_term_and_files_without_it(tmp_path):
    """``dopacity`` moves the opacity logit by -d at t=0 and +d at t=1 (static model too),
    is saved, and a model file from before the term loads with no change over time."""
    xyz, rgb = _points(30)
    m = GaussianModel4D.from_points(xyz, rgb, 0, None, init_opacity=0.5)
    assert torch.equal(m.splats["dopacity"], torch.zeros(30))
    with torch.no_grad():
        m.splats["dopacity"][:10] = 3.0
    o0, o1, oh = (m.at_time(t).opacities.detach() for t in (0.0, 1.0, 0.5))
    assert torch.allclose(o0[:10], torch.sigmoid(torch.tensor(-3.0)).expand(10))
    assert torch.allclose(o1[:10], torch.sigmoid(torch.tensor(3.0)).expand(10))
    assert torch.allclose(oh, torch.full((30,), 0.5)) and torch.allclose(o0[10:], o1[10:])
    # the price on change: mean |dopacity| over all, or over the gated Gaussians
    assert m.opacity_change().item() == 1.0
    assert m.opacity_change((torch.arange(30) < 20).float()).item() == 1.5
    save_model(m, tmp_path / "m.pt")
    assert torch.equal(load_model(tmp_path / "m.pt").splats["dopacity"], m.splats["dopacity"])
    old = {k: v for k, v in m.state_dict().items() if k != "splats.dopacity"}
    back = GaussianModel4D.from_state(m.config(), old)
    assert torch.equal(back.splats["dopacity"], torch.zeros(30))
    assert torch.equal(back.at_time(0.0).opacities, back.at_time(1.0).opacities)
    back.splats.pop("dopacity")
    assert back.opacity_change() is None


def test_view_dependent_time_term_gate_and_files_without_it(tmp_path):
    """``dshN`` changes the higher SH coefficients by -d at t=0 and +d at t=1; a time gate of
    0 removes every per-Gaussian time term of that Gaussian, and folding the gate into the
    parameters renders the same; files without ``dshN`` load with no view-dependent change."""
    xyz, rgb = _points(20)
    m = GaussianModel4D.from_points(xyz, rgb, 2, None, init_opacity=0.5)
    assert m.splats["dshN"].shape == (20, 8, 3)
    with torch.no_grad():
        m.splats["dshN"][:] = 0.25
        m.splats["dsh0"][:] = 0.5
        m.splats["dopacity"][:] = 2.0
    sh0, sh1 = (m.at_time(t).sh.detach() for t in (0.0, 1.0))
    torch.testing.assert_close(sh1[:, 1:] - sh0[:, 1:], torch.full((20, 8, 3), 0.5))
    torch.testing.assert_close(sh1[:, :1] - sh0[:, :1], torch.full((20, 1, 3), 1.0))
    gate = (torch.arange(20) < 12).float()
    g0, g1 = (m.at_time(t, gate) for t in (0.0, 1.0))
    assert torch.equal(g0.sh[12:], g1.sh[12:]) and torch.equal(g0.opacities[12:],
                                                               g1.opacities[12:])
    assert torch.equal(g1.sh[:12], m.at_time(1.0).sh[:12])
    m.apply_time_gate(gate)
    for t, g in ((0.0, g0), (1.0, g1)):
        torch.testing.assert_close(m.at_time(t).sh, g.sh)
        torch.testing.assert_close(m.at_time(t).opacities, g.opacities)
    old = {k: v for k, v in m.state_dict().items() if k != "splats.dshN"}
    back = GaussianModel4D.from_state(m.config(), old)
    assert torch.equal(back.splats["dshN"], torch.zeros(20, 8, 3))
    assert torch.equal(back.at_time(0.0).sh[:, 1:], back.at_time(1.0).sh[:, 1:])


def _random_hexplane(seed, resolution, time_resolution, features, lo, hi):
    """A two-level HexPlane with random planes and the given box (skips the test when the C++
    kernel cannot be built)."""
    from gdiff.splat import csrc

    if csrc.load(required=False) is None:
        pytest.skip("C++ kernel not available")
    torch.manual_seed(seed)
    hp = HexPlane(resolution=resolution, time_resolution=time_resolution, multires=[1, 2],
                  features=features)
    with torch.no_grad():
        for p in hp.grids:
            p.add_(torch.randn_like(p) * 0.3)
        hp.set_aabb(torch.tensor(lo), torch.tensor(hi))
    return hp


def test_compiled_lookup_matches_grid_sample_values_and_gradients():
    """The CPU kernel (positions without gradient) equals the grid_sample reference (used when
    the positions carry a gradient), for odd plane sizes, points outside the box, t between
    rows, and a zero texel (the product rule must not divide)."""
    hp = _random_hexplane(1, (7, 5, 4), 3, 3, [-1.0, -0.5, 0.0], [1.0, 0.5, 2.0])
    with torch.no_grad():
        hp.grids[0][0, 1, 2, 3] = 0.0
    xyz = torch.rand(400, 3) * torch.tensor([2.6, 1.4, 2.6]) - torch.tensor([1.3, 0.7, 0.3])
    xyz[0] = torch.tensor([0.0 / 3, 0.0, 1.0])
    w = torch.randn(400, 6)
    for t in (0.0, 0.37, 1.0):
        hp.zero_grad()
        fast = hp(xyz, t)
        (fast * w).sum().backward()
        g_fast = [p.grad.clone() for p in hp.grids]
        hp.zero_grad()
        ref = hp(xyz.clone().requires_grad_(), t)
        (ref * w).sum().backward()
        torch.testing.assert_close(fast, ref.detach(), rtol=1e-5, atol=1e-6)
        for a, b in zip(g_fast, (p.grad for p in hp.grids)):
            torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-5)


def test_compiled_lookup_gradient_is_the_same_for_any_thread_count(torch_threads):
    """The backward kernel scatters parts of the points in parallel into their own tables:
    the table gradient must be bitwise the same with 1 and 2 threads (9000 points: 2 parts)."""
    hp = _random_hexplane(2, (9, 8, 6), 4, 4, [-1.0, -1.0, -1.0], [1.0, 1.0, 1.0])
    xyz = torch.rand(9000, 3) * 2 - 1
    w = torch.randn(9000, 8)
    grads = []
    for k in (1, 2):
        torch_threads(k)
        hp.zero_grad()
        (hp(xyz, 0.6) * w).sum().backward()
        grads.append([p.grad.clone() for p in hp.grids])
    for a, b in zip(*grads):
        assert torch.equal(a, b)
    assert any(bool(g.abs().sum() > 0) for g in grads[0])


def test_heads_evaluated_together_equal_head_by_head():
    """With one-layer heads the forward pass applies all heads in one matrix product; values
    and gradients must be those of the heads applied one by one."""
    torch.manual_seed(0)
    d = Deformation(DeformConfig(resolution=[8, 8, 8], color_degree=1, sh_coeffs=16)).double()
    for head in d.heads.values():
        torch.nn.init.normal_(head[-1].weight)
        torch.nn.init.normal_(head[-1].bias)
    means = torch.rand(500, 3, dtype=torch.float64) * 2 - 1
    got = d(means, 0.7)
    h = d.trunk(d.field(means, 0.7))
    want = {name: head(h) for name, head in d.heads.items()}
    want["opacities"] = want["opacities"][:, 0]
    want["sh"] = want["sh"].view(-1, 4, 3)
    assert list(got) == list(want)
    w = {k: torch.randn_like(v) for k, v in want.items()}
    grads = []
    for out in (got, want):
        d.zero_grad()
        sum((out[k] * w[k]).sum() for k in out).backward(retain_graph=True)
        grads.append({n: p.grad.clone() for n, p in d.named_parameters()})
    for k in want:
        torch.testing.assert_close(got[k], want[k], atol=1e-12, rtol=1e-12)
    for n in grads[1]:
        torch.testing.assert_close(grads[0][n], grads[1][n], atol=1e-10, rtol=1e-10, msg=n)
