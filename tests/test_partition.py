"""Tests of the Gaussian partition stage (gdiff.partition, gdiff.knn)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial import cKDTree

from gdiff.knn import NeighbourIndex, knn_indices
from gdiff.partition import (ChangeHead, PartitionOptions, change_probability, mask_bce,
                             neighbour_disagreement, neighbour_kl)


# --------------------------------------------------------------------------- kNN

def test_knn_matches_brute_force_and_excludes_self():
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(300, 3))
    pts[7] = pts[3]  # a duplicated position must still not return the query itself
    q = np.array([3, 7, 11, 250])
    nbr = knn_indices(pts, q, k=6)
    assert nbr.shape == (4, 6)
    d = np.linalg.norm(pts[q][:, None] - pts[None], axis=-1)
    for row, j in zip(nbr, q):
        assert j not in row
        others = np.delete(np.arange(len(pts)), j)
        expect = np.sort(d[list(q).index(j), others])[:6]
        np.testing.assert_allclose(np.sort(d[list(q).index(j), row]), expect)
    with pytest.raises(ValueError):
        knn_indices(pts, q, k=300)


def test_neighbour_index_rebuilds_tree_when_points_move():
    pts = torch.tensor(np.random.default_rng(1).normal(size=(50, 3)), dtype=torch.float32)
    index = NeighbourIndex(k=3, m=10, refresh=2)
    s, n = index.sample(pts)
    assert s.shape == (10,) and n.shape == (10, 3) and s.dtype == torch.int64
    assert len(set(s.tolist())) == 10
    t1 = index._tree
    index.sample(pts)
    assert index._tree is t1  # within the refresh period
    index.sample(pts + 1.0)
    assert index._tree is not t1
    np.testing.assert_allclose(index._pts, (pts + 1.0).numpy(), atol=1e-6)


# --------------------------------------------------------------------------- head and losses

def test_probability_is_two_class_softmax_and_bce_matches_definition():
    logits = torch.randn(4, 5, 2)
    p = change_probability(logits)
    np.testing.assert_allclose(p, torch.softmax(logits, -1)[..., 1], atol=1e-6)
    target = torch.rand(4, 5) > 0.5
    expect = -(target * p.log() + (~target) * (1 - p).log()).mean()
    np.testing.assert_allclose(mask_bce(logits, target).item(), expect.item(), rtol=1e-5)


def test_neighbour_kl_zero_iff_neighbours_agree():
    logits = torch.tensor([[1.0, -1.0], [1.0, -1.0], [-2.0, 2.0]])
    same = neighbour_kl(logits, torch.tensor([0]), torch.tensor([[1]]))
    diff = neighbour_kl(logits, torch.tensor([0]), torch.tensor([[2]]))
    assert same.item() == pytest.approx(0.0, abs=1e-7)
    p, q = torch.softmax(logits[0], 0), torch.softmax(logits[2], 0)
    assert diff.item() == pytest.approx((p * (p / q).log()).sum().item(), rel=1e-5)


def _two_clusters(n_per=400, seed=0):
    rng = np.random.default_rng(seed)
    a = rng.normal(scale=0.1, size=(n_per, 3))
    b = rng.normal(scale=0.1, size=(n_per, 3)) + [2.0, 0, 0]
    pts = torch.tensor(np.concatenate([a, b]), dtype=torch.float32)
    label = torch.cat([torch.zeros(n_per), torch.ones(n_per)])
    return pts, label


def _fit_labels(lambda_3d, seed=0):
    """Train encodings of two clusters with 10 % of the Gaussians supervised (BCE per Gaussian)
    plus ``lambda_3d`` * L3d; return (accuracy on the unsupervised ones, neighbour disagreement)."""
    torch.manual_seed(seed)
    pts, label = _two_clusters(seed=seed)
    n = len(pts)
    sup = torch.zeros(n, dtype=torch.bool)
    sup[torch.randperm(n, generator=torch.Generator().manual_seed(seed))[: n // 10]] = True
    head = ChangeHead(n, 16, seed=seed)
    opt = torch.optim.Adam([{"params": [head.encoding], "lr": 0.01},
                            {"params": head.conv.parameters(), "lr": 0.005}])
    index = NeighbourIndex(k=5, m=400, refresh=50, seed=seed)
    for _ in range(300):
        logits = head.gaussian_logits()
        loss = mask_bce(logits[sup], label[sup])
        if lambda_3d:
            s, nb = index.sample(pts)
            loss = loss + lambda_3d * neighbour_kl(logits, s, nb)
        opt.zero_grad()
        loss.backward()
        opt.step()
    prob = head.gaussian_probability().detach()
    acc = ((prob > 0.5).float() == label)[~sup].float().mean().item()
    probe = np.arange(0, n, 7)
    return acc, neighbour_disagreement(prob, knn_indices(pts, probe, 5), probe)


def test_l3d_propagates_labels_and_reduces_neighbour_disagreement():
    """Only 10 % of the Gaussians are supervised; L3d spreads their class to their 3D neighbours
    and makes neighbours agree, while without it the rest stays at chance."""
    acc0, dis0 = _fit_labels(0.0)
    acc1, dis1 = _fit_labels(2.0)
    assert acc0 < 0.75          # measured ~0.48
    assert acc1 > 0.95          # measured 1.0
    assert dis1 < 0.1 * dis0    # measured 0.0002 vs 0.16


def test_options_validate():
    with pytest.raises(ValueError):
        PartitionOptions(threshold=1.5)
    with pytest.raises(ValueError):
        PartitionOptions(knn_k=0)
    assert PartitionOptions().encoding_dim == 16
