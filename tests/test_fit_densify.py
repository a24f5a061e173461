"""Adaptive density control on tensors: clone, split, prune, opacity reset, optimiser state."""

import math

import numpy as np
import torch
from torch import nn

from gdiff.splat.gaussians import (DensifyStats, DensifyThresholds, camera_extent, init_params,
                                   knn_scales, refine, reset_opacity, split)


def _setup(n=6, scale=0.005):
    params = nn.ParameterDict({
        "means": nn.Parameter(torch.arange(n, dtype=torch.float32)[:, None].repeat(1, 3)),
        "scales": nn.Parameter(torch.full((n, 3), math.log(scale))),
        "quats": nn.Parameter(torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1)),
        "opacities": nn.Parameter(torch.zeros(n)),
        "sh0": nn.Parameter(torch.zeros(n, 1, 3)),
        "shN": nn.Parameter(torch.zeros(n, 3, 3)),
        "encoding": nn.Parameter(torch.arange(n, dtype=torch.float32)[:, None].repeat(1, 4)),
    })
    opt = torch.optim.Adam([{"params": [p], "lr": 1e-3, "name": k} for k, p in params.items()])
    # one step so every parameter has Adam moments
    sum((p ** 2).sum() for p in params.values()).backward()
    opt.step()
    opt.zero_grad()
    return params, opt


def _check_optimizer(params, opt):
    for g in opt.param_groups:
        p = g["params"][0]
        assert p is params[g["name"]]
        st = opt.state[p]
        assert st["exp_avg"].shape == p.shape and st["exp_avg_sq"].shape == p.shape


def test_knn_scales_and_init():
    xyz = np.array([[0, 0, 0], [1, 0, 0], [0, 2, 0], [0, 0, 0]], float)
    s = knn_scales(xyz, k=1)
    assert s[1] == 1.0 and s[2] == 2.0
    assert s[0] > 0 and s[3] > 0  # duplicates get the smallest positive distance
    p = init_params(xyz, np.full((4, 3), 0.5), sh_degree=2, init_opacity=0.1)
    assert p["shN"].shape == (4, 8, 3) and torch.allclose(p["sh0"], torch.zeros(4, 1, 3))
    assert torch.allclose(torch.sigmoid(p["opacities"]), torch.full((4,), 0.1))
    assert math.isclose(camera_extent(np.array([[1.0, 0, 0], [-1.0, 0, 0]])), 1.1)


def test_stats_accumulate_in_ndc_units():
    st = DensifyStats(3)
    grad = torch.tensor([[[0.001, 0.0], [0.0, 0.002], [1.0, 1.0]]])
    radii = torch.tensor([[2, 3, 0]], dtype=torch.int32)
    st.update(grad, radii, width=200, height=100)
    assert torch.allclose(st.grad2d, torch.tensor([0.1, 0.1, 0.0]))
    assert torch.equal(st.count, torch.tensor([1.0, 1.0, 0.0]))
    assert torch.allclose(st.max_radius, torch.tensor([0.01, 0.015, 0.0]))


def test_refine_clones_small_splits_large_prunes_transparent():
    params, opt = _setup(6)
    with torch.no_grad():
        params["scales"][3:5] = math.log(0.5)  # large Gaussians (extent 1 -> > 0.01)
        params["opacities"][5] = -10.0  # transparent
    st = DensifyStats(6)
    st.grad2d[:] = torch.tensor([1e-3, 1e-3, 0.0, 1e-3, 0.0, 0.0])
    st.count[:] = 1
    ev = refine(params, opt, st, DensifyThresholds(), extent=1.0, prune_large=False)
    assert ev == {"cloned": 2, "split": 1, "pruned": 1, "n": 6 - 1 + 2 + 2 - 1}
    n = ev["n"]
    assert all(p.shape[0] == n for p in params.values())
    _check_optimizer(params, opt)
    assert len(st) == n and float(st.grad2d.abs().sum()) == 0.0
    # the split parent (index 3) is gone, its two children have shrunk scales
    enc = params["encoding"][:, 0].detach()
    assert sorted(round(x) for x in enc.tolist()) == [0, 0, 1, 1, 2, 3, 3, 4]
    kids = (enc.round() == 3).nonzero().flatten()
    assert torch.allclose(params["scales"][kids].exp(), torch.full((2, 3), 0.5 / 1.6))
    # clones keep their values; new Gaussians start with zero moments
    assert torch.allclose(opt.state[params["means"]]["exp_avg"][-4:], torch.zeros(4, 3))


def test_refine_cap_and_prune_large():
    params, opt = _setup(6)
    st = DensifyStats(6)
    st.grad2d[:] = torch.tensor([1.0, 2.0, 3.0, 4.0, 5.0, 6.0]) * 1e-3
    st.count[:] = 1
    st.max_radius[0] = 0.5  # huge on screen
    th = DensifyThresholds(max_gaussians=8)
    ev = refine(params, opt, st, th, extent=1.0, prune_large=True)
    assert ev["cloned"] == 2  # only the two highest gradients fit under the cap
    assert ev["pruned"] == 1 and ev["n"] == 7
    enc = sorted(round(x) for x in params["encoding"][:, 0].tolist())
    assert enc == [1, 2, 3, 4, 4, 5, 5]


def test_split_samples_inside_the_parent():
    torch.manual_seed(0)
    params, opt = _setup(1, scale=0.1)
    split(params, opt, torch.tensor([True]), n=400)
    d = params["means"].detach() - torch.zeros(3)
    assert params["means"].shape == (400, 3)
    assert abs(float(d.std()) - 0.1) < 0.02
    _check_optimizer(params, opt)


def test_reset_opacity_caps_and_clears_moments():
    params, opt = _setup(4)
    with torch.no_grad():
        params["opacities"][:2] = -8.0
    reset_opacity(params, opt, 0.01)
    o = torch.sigmoid(params["opacities"].detach())
    assert torch.allclose(o[2:], torch.full((2,), 0.01), atol=1e-6)
    assert float(o[0]) < 0.01
    st = opt.state[params["opacities"]]
    assert float(st["exp_avg"].abs().sum()) == 0.0
    _check_optimizer(params, opt)


def test_opacity_reset_caps_every_time_and_stats_skip_absent_gaussians():
    params, opt = _setup(4)
    params["dopacity"] = nn.Parameter(torch.tensor([0.0, 4.0, -4.0, 0.0]))
    with torch.no_grad():
        params["opacities"][:] = torch.tensor([3.0, 0.0, 0.0, -8.0])
    reset_opacity(params, opt, 0.01)
    cap = math.log(0.01 / 0.99)
    top = params["opacities"] + params["dopacity"].abs()  # largest logit over t in [0, 1]
    assert torch.all(top <= cap + 1e-5)
    assert math.isclose(float(params["opacities"].detach()[3]), -8.0)  # below the cap: kept
    assert float(opt.state[params["opacities"]]["exp_avg"].abs().sum()) == 0.0
    # a Gaussian marked absent in a view adds neither gradient nor count
    st = DensifyStats(3)
    grad = torch.tensor([[[0.001, 0.0], [0.001, 0.0], [0.001, 0.0]]])
    radii = torch.tensor([[2, 2, 2]], dtype=torch.int32)
    st.update(grad, radii, 200, 100, present=torch.tensor([True, False, True]))
    assert torch.equal(st.count, torch.tensor([1.0, 0.0, 1.0]))
    assert float(st.grad2d[1]) == 0.0 and float(st.grad2d[0]) > 0.0


def test_view_counts_per_time_follow_clones_splits_and_pruning():
    """``seen`` counts the views of each time in which a Gaussian projects into the image (any
    opacity; with centres given, its centre must be inside); clones and split children
    inherit their parent's counts, pruned rows go, and a refinement keeps the counts (only the
    window statistics restart)."""
    params, opt = _setup(6)
    with torch.no_grad():
        params["scales"][3] = math.log(0.5)  # large: split
        params["opacities"][5] = -10.0  # transparent: pruned
    st = DensifyStats(6, n_times=2)
    st.observe(torch.tensor([[1, 1, 0, 2, 0, 3]], dtype=torch.int32), 0)
    st.observe(torch.tensor([[1, 0, 0, 1, 0, 0], [1, 0, 0, 0, 0, 4]], dtype=torch.int32), 1)
    st.observe(torch.tensor([[[1, 0], [0, 0], [0, 0], [0, 0], [2, 2], [0, 0]]],
                            dtype=torch.int32), 1)  # [C, N, 2] radii
    # with the centres given, a Gaussian that only reaches into the image is not counted
    m2d = torch.tensor([[[5.0, 5.0], [-1.0, 5.0], [5.0, 5.0], [5.0, 9.5], [5.0, 10.0],
                         [10.0, 5.0]]])
    st.observe(torch.tensor([[1, 1, 0, 1, 1, 1]], dtype=torch.int32), 0, m2d, 10, 10)
    expected = {0: [2, 3], 1: [1, 0], 2: [0, 0], 3: [2, 1], 4: [0, 1], 5: [1, 1]}
    assert st.seen.tolist() == [expected[i] for i in range(6)]
    assert st.seen_at_all_times(1).tolist() == [True, False, False, True, False, True]
    assert st.seen_at_all_times(2).tolist() == [True] + [False] * 5
    st.grad2d[:] = torch.tensor([1e-3, 0.0, 0.0, 1e-3, 0.0, 0.0])
    st.count[:] = 1
    ev = refine(params, opt, st, DensifyThresholds(), extent=1.0, prune_large=False)
    assert ev == {"cloned": 1, "split": 1, "pruned": 1, "n": 7}
    enc = [round(x) for x in params["encoding"][:, 0].tolist()]
    assert st.seen.tolist() == [expected[i] for i in enc]
    assert len(st) == 7 and float(st.count.sum()) == 0.0
    st.reset()
    assert st.seen.tolist() == [expected[i] for i in enc]
    back = DensifyStats(0)
    back.load_state_dict(st.state_dict())
    assert torch.equal(back.seen, st.seen)
