"""Tests of the Gaussian partition stage (gdiff.partition, gdiff.knn)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

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
    assert PartitionOptions(threshold=None).threshold is None  # chosen from the key views
    with pytest.raises(ValueError):
        PartitionOptions(knn_k=0)
    assert PartitionOptions().encoding_dim == 16


def test_threshold_chosen_from_key_views_maximises_pooled_f1():
    """Under-confident maps (changed pixels at 0.32-0.45, background below 0.2): the threshold
    that best reproduces the masks lies between the two, and its F1 equals a brute-force
    count; masks without a changed pixel choose nothing."""
    from gdiff.metrics import confusion, scores_from_counts
    from gdiff.partition import choose_threshold

    rng = np.random.default_rng(0)
    masks = [np.zeros((20, 30), bool) for _ in range(3)]
    masks[0][5:10, 5:12] = masks[2][2:8, 20:28] = True
    probs = [np.where(m, rng.uniform(0.32, 0.45, m.shape), rng.uniform(0.0, 0.2, m.shape))
             for m in masks]
    probs[1][0, 0] = 0.5  # one false positive that a threshold below 0.5 keeps
    best = choose_threshold(probs, masks)
    assert 0.2 <= best["threshold"] <= 0.32 and best["f1"] == pytest.approx(1 - 1 / 167)
    th = best["threshold"]
    brute = scores_from_counts(*np.sum([confusion(p > th, m) for p, m in zip(probs, masks)], 0))
    assert best["f1"] == pytest.approx(brute["F1"])
    assert best["curve"].set_index("threshold").loc[0.5, "F1"] == 0.0
    none = choose_threshold(probs, [np.zeros_like(m) for m in masks])
    assert none["threshold"] is None


# --------------------------------------------------------------------------- hand-made Gaussians

def _static_model(means, colors, opacity=0.9, scale=0.05):
    """A static (no deformation) GaussianModel4D with isotropic Gaussians of SH degree 0."""
    from gdiff.splat.gaussians import rgb_to_sh0
    from gdiff.splat.model import GaussianModel4D

    means = torch.as_tensor(means, dtype=torch.float32)
    n = len(means)
    m = GaussianModel4D(n, sh_degree=0, deform=None)
    with torch.no_grad():
        m.splats["means"].copy_(means)
        m.splats["scales"].fill_(np.log(scale))
        m.splats["opacities"].fill_(float(np.log(opacity / (1 - opacity))))
        m.splats["sh0"].copy_(rgb_to_sh0(torch.as_tensor(colors, dtype=torch.float32))[:, None])
    m.meta = {}
    return m


def _front_camera(w=40, h=30):
    from gdiff.cameras import Camera, look_at

    return Camera(w, h, 40.0, 40.0, w / 2, h / 2, look_at([0, -2.0, 0], [0, 0, 0]))


def test_features_are_alpha_blended_without_background_and_match_colour_render():
    from gdiff.partition import render_features
    from gdiff.splat.render import render

    model = _static_model([[0.0, 0.0, 0.0]], [[0.2, 0.6, 0.4]], opacity=0.9, scale=0.1)
    cam = _front_camera()
    enc = torch.tensor([[1.0, -2.0, 3.0, 0.5]])
    with torch.no_grad():
        out = render_features(model.at_time(0.0), enc, cam, background=torch.ones(3))
        ref = render(model, [cam], 0.0, background=torch.ones(3), render_mode="RGB")["rgb"][0]
    a = out["alpha"]
    # F = alpha * e for a single Gaussian; no background term in the features
    np.testing.assert_allclose(out["features"], a[..., None] * enc[0], atol=1e-5)
    assert a[0, 0] == 0 and out["features"][0, 0].abs().max() == 0
    assert 0.8 < a[15, 20] <= 0.9 + 1e-6  # opacity 0.9, half a pixel off the centre
    # the colour channels are what the fit stage's renderer produces
    np.testing.assert_allclose(out["rgb"], ref, atol=1e-5)


def _varied_model(rng, n: int, scale: float, opacity_mean: float, opacity_sd: float,
                  scale_sd: float = 0.0, opacity: float = 0.8):
    """A static model of ``n`` random Gaussians (positions around the origin, random colours)
    with normally distributed opacity logits and, with ``scale_sd``, log-scales jittered per
    axis (anisotropic shapes)."""
    model = _static_model(rng.normal(scale=0.3, size=(n, 3)), rng.random((n, 3)),
                          opacity=opacity, scale=scale)
    with torch.no_grad():
        model.splats["opacities"].copy_(torch.tensor(rng.normal(opacity_mean, opacity_sd,
                                                                size=n), dtype=torch.float32))
        if scale_sd:
            model.splats["scales"].add_(torch.tensor(rng.normal(scale=scale_sd, size=(n, 3)),
                                                     dtype=torch.float32))
    return model


def test_cached_blend_weights_reproduce_the_rasterizer():
    """Frozen geometry: features blended with cached weights equal the rasterized features of
    overlapping, partly transparent Gaussians, and the blended change logit equals the head
    applied to the rasterized feature map (bias included where nothing is hit)."""
    from gdiff.partition import (blend_weights, blended_change_logit, change_logit,
                                 render_blended, render_features)

    n = 300
    model = _varied_model(np.random.default_rng(3), n, 0.06, 0.0, 1.0, 0.5, opacity=0.6)
    cam = _front_camera(48, 36)
    g = model.at_time(0.0)
    head = ChangeHead(n, 8, seed=1)
    with torch.no_grad():
        ref = render_features(g, head.encoding, cam, with_rgb=False)
        bw = blend_weights(g, cam)
        feats = render_blended(bw, head.encoding)
        z = blended_change_logit(head, bw)
    assert bw.pix.dtype == torch.int32 and len(bw.pix) > 5 * 48 * 36  # many layers per pixel
    assert 0 < (ref["alpha"] > 0.5).float().mean() < 1  # hit and empty pixels both present
    np.testing.assert_allclose(feats, ref["features"], atol=2e-5)
    np.testing.assert_allclose(bw.alpha.reshape(36, 48), ref["alpha"], atol=2e-5)
    with torch.no_grad():
        zref = change_logit(head.classify(ref["features"]))
    np.testing.assert_allclose(z, zref, atol=5e-5)


def test_compact_blend_weights_equal_the_exact_ones():
    """Row bands (bounded memory) give the same weights as one pass; float16 weights and
    dropping each pixel's faintest pairs up to a tolerance keep the blend within their bounds
    and shrink the cache."""
    from gdiff.partition import blend_weights, render_blended, render_features

    rng = np.random.default_rng(5)
    n = 400
    model = _varied_model(rng, n, 0.07, 1.0, 1.5)
    cam = _front_camera(48, 36)
    g = model.at_time(0.0)
    vals = torch.tensor(rng.normal(scale=3.0, size=n), dtype=torch.float32)
    with torch.no_grad():
        ref = render_features(g, vals[:, None], cam, with_rgb=False)["features"][..., 0]
        exact = blend_weights(g, cam)
        banded = blend_weights(g, cam, band_pairs=2000, backend="torch")  # bands of a few rows
        tol = 1e-3
        compact = blend_weights(g, cam, tolerance=tol, dtype=torch.float16)
    assert torch.equal(exact.counts, banded.counts) and torch.equal(exact.gid, banded.gid)
    # (``exact`` is the compiled kernel's when it is built: float rounding apart)
    np.testing.assert_allclose(banded.weight, exact.weight, rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(banded.alpha, exact.alpha, rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(render_blended(exact, vals), ref, atol=2e-5)
    assert compact.weight.dtype == torch.float16
    np.testing.assert_allclose(compact.alpha, exact.alpha, rtol=1e-6, atol=1e-9)
    assert len(compact.gid) < 0.9 * len(exact.gid)  # faint pairs behind surfaces dropped
    assert compact.nbytes < 0.7 * exact.nbytes
    # error <= dropped weight (<= tol) x max |value| + float16 rounding of the kept weights
    bound = tol * vals.abs().max() + 2.0 ** -11 * (exact.alpha * vals.abs().max()).reshape(36, 48)
    err = (render_blended(compact, vals) - ref).abs()
    assert (err <= bound + 1e-5).all() and err.max() > 0


def test_compiled_blend_weights_equal_the_torch_ones():
    """The C++ kernel's pairs (its own tile traversal) are the torch implementation's: the same
    pixels, Gaussians and order, weights and alpha equal to float rounding, also with faint
    pairs dropped."""
    from gdiff.partition import blend_weights
    from gdiff.splat import csrc

    if csrc.load() is None:
        pytest.skip("C++ kernels not built")
    n = 500
    model = _varied_model(np.random.default_rng(7), n, 0.06, 0.5, 2.0, 0.5)
    cam = _front_camera(53, 37)  # not a multiple of the tile size
    g = model.at_time(0.0)
    with torch.no_grad():
        for tol in (0.0, 1e-3):
            ref = blend_weights(g, cam, tolerance=tol, backend="torch")
            got = blend_weights(g, cam, tolerance=tol, backend="cpp")
            assert len(got.gid) > 5 * 53 * 37
            assert torch.equal(got.counts, ref.counts) and torch.equal(got.gid, ref.gid)
            np.testing.assert_allclose(got.weight, ref.weight, rtol=1e-5, atol=1e-7)
            np.testing.assert_allclose(got.alpha, ref.alpha, rtol=1e-5, atol=1e-6)


def test_balanced_bce_is_mean_of_per_class_means():
    from gdiff.partition import bce_on_change_logit, changed_fraction

    z = torch.randn(6, 7)
    target = torch.zeros(6, 7)
    target[1:3, 2:4] = 1.0  # 4 of 42 pixels changed
    f = changed_fraction([target])
    assert f == pytest.approx(4 / 42)
    per = torch.nn.functional.binary_cross_entropy_with_logits(z, target, reduction="none")
    expect = 0.5 * per[target > 0].mean() + 0.5 * per[target == 0].mean()
    assert bce_on_change_logit(z, target, f).item() == pytest.approx(expect.item(), rel=1e-5)
    plain = per.mean().item()
    assert bce_on_change_logit(z, target, None).item() == pytest.approx(plain, rel=1e-6)
    assert bce_on_change_logit(z, target, 0.0).item() == pytest.approx(plain, rel=1e-6)
    # mask_bce on two-class logits is the same loss on their difference
    logits = torch.stack([torch.zeros_like(z), z], -1)
    assert mask_bce(logits, target, f).item() == pytest.approx(expect.item(), rel=1e-5)


def test_balanced_bce_keeps_minority_gaussians_confident():
    """A changed Gaussian covering 5 changed pixels in one view and 10 pixels marked unchanged
    in another (a mask that misses part of the object, or a boundary): with the plain mean BCE
    its optimum is 5 / 15 = 0.33, below the 0.5 threshold, because changed pixels are rare;
    the balanced BCE weighs the rare class up and keeps it changed, background unchanged."""
    from gdiff.partition import BlendWeights, bce_on_change_logit, blended_change_logit, \
        changed_fraction

    def view(obj_pix):  # 100 pixels, one opaque Gaussian each: 1 = object, 0 = background
        gid = [1 if p in obj_pix else 0 for p in range(100)]
        return BlendWeights.from_pairs(torch.arange(100, dtype=torch.int32),
                                       torch.tensor(gid, dtype=torch.int32), torch.ones(100),
                                       torch.ones(100), 100, 1)

    views = [view(range(5)), view(range(10, 20))]
    targets = [torch.zeros(1, 100), torch.zeros(1, 100)]
    targets[0][0, :5] = 1.0

    def train(balanced):
        head = ChangeHead(2, 4, seed=0)
        opt = torch.optim.Adam(head.parameters(), lr=0.05)
        f = changed_fraction(targets) if balanced else None
        for _ in range(200):
            loss = sum(bce_on_change_logit(blended_change_logit(head, v), t, f)
                       for v, t in zip(views, targets))
            opt.zero_grad()
            loss.backward()
            opt.step()
        return head.gaussian_probability().detach()

    plain, bal = train(False), train(True)
    assert plain[1].item() == pytest.approx(1 / 3, abs=0.03)   # under-confident
    assert bal[1] > 0.9 and bal[0] < 0.1                         # 100/105 at the optimum
    assert plain[0] < 0.1


def test_ignoring_other_time_pixels_keeps_reused_gaussians_changed():
    """The 4D fit draws a new object (t=1) with Gaussian 1, which at t=0 is visible as part of
    the table it will cover. Two t=1 views see it changed; four t=0 views see it in 10 pixels
    that only the t=1 mask marks. Supervised there as unchanged it ends below 0.5 (20
    changed vs 40 unchanged pixels); with those pixels left out it is changed, and the table
    Gaussian 0 stays unchanged either way."""
    from gdiff.partition import (BlendWeights, bce_on_change_logit, blended_change_logit,
                                 ignore_weight)

    def view(obj_pix):  # 100 pixels, one opaque Gaussian each: 1 = the object, 0 = table
        gid = [1 if p in obj_pix else 0 for p in range(100)]
        return BlendWeights.from_pairs(torch.arange(100, dtype=torch.int32),
                                       torch.tensor(gid, dtype=torch.int32), torch.ones(100),
                                       torch.ones(100), 100, 1)

    obj = torch.zeros(1, 100)
    obj[0, 40:50] = 1.0
    views = [view(range(40, 50))] * 6
    own = [obj, obj] + [torch.zeros(1, 100)] * 4             # t=1 views, then t=0 views
    other = [torch.zeros(1, 100)] * 2 + [obj] * 4
    weights = [torch.from_numpy(ignore_weight(o, x)) for o, x in zip(own, other)]
    assert weights[2][0, 45] == 0 and weights[2][0, 5] == 1 and weights[0].min() == 1

    def train(ignore):
        head = ChangeHead(2, 4, seed=0)
        opt = torch.optim.Adam(head.parameters(), lr=0.05)
        for _ in range(150):
            loss = sum(bce_on_change_logit(blended_change_logit(head, v), t,
                                           weight=w if ignore else None)
                       for v, t, w in zip(views, own, weights))
            opt.zero_grad()
            loss.backward()
            opt.step()
        return head.gaussian_probability().detach()

    plain, ign = train(False), train(True)
    assert plain[1] < 0.4 and ign[1] > 0.9, (plain, ign)
    assert plain[0] < 0.1 and ign[0] < 0.1


def test_change_map_union_split_and_save_load(tmp_path):
    """Two Gaussians labelled changed / unchanged by hand: the union map, per-time maps, the
    PLY split and a save/load round trip."""
    from gdiff.partition import (PartitionModel, load_partition_model, render_change_map,
                                 save_partition_model, split_gaussians, write_split_ply)
    from gdiff.splat.ply import read_gaussians

    model = _static_model([[-0.3, 0.0, 0.0], [0.3, 0.0, 0.0]], [[1, 0, 0], [0, 0, 1]])
    head = ChangeHead(2, 16)
    with torch.no_grad():  # encoding 0 -> unchanged, encoding 1 -> changed
        head.encoding.zero_()
        head.encoding[1, 0] = 1.0
        head.conv.weight.zero_()
        head.conv.bias.copy_(torch.tensor([2.0, -2.0]))
        head.conv.weight[1, 0] = 8.0
    cam = _front_camera()
    pm = PartitionModel(model, head, cam, threshold=0.5)
    r = render_change_map(pm, cam, None, with_image=True)
    assert r["prob"].shape == (30, 40) and r["prob"].dtype == np.float32
    np.testing.assert_array_equal(r["prob"], np.maximum(r["prob_t0"], r["prob_t1"]))
    # the right Gaussian (+x = image right) is the changed one
    assert r["mask"][15, 26] and not r["mask"][15, 14] and not r["mask"][0, 0]
    r0 = render_change_map(pm, cam, 0.0)
    assert r0["prob_t1"] is None and np.array_equal(r0["mask"], r["mask"])
    changed, unchanged = split_gaussians(pm, 0.0)
    assert len(changed) == 1 and len(unchanged) == 1
    assert changed.means[0, 0] > 0
    counts = write_split_ply(pm, tmp_path)
    assert counts["n_changed"] == 2 and counts["n_unchanged"] == 1  # changed at t=0 and t=1
    assert sorted(p.name for p in tmp_path.glob("*.ply")) == [
        "changed.ply", "changed_t0.ply", "changed_t1.ply", "unchanged.ply"]
    g = read_gaussians(tmp_path / "changed_t0.ply")
    np.testing.assert_allclose(g.means.numpy(), [[0.3, 0.0, 0.0]], atol=1e-6)
    save_partition_model(pm, tmp_path / "model.pt")
    pm2 = load_partition_model(tmp_path / "model.pt", "cpu")
    r2 = render_change_map(pm2, cam, None)
    np.testing.assert_allclose(r2["prob"], r["prob"], atol=1e-6)
    # saving the same model again gives the same bytes (the archive is not named after the
    # temporary file), so repeated runs can be compared file by file
    save_partition_model(pm, tmp_path / "again.pt")
    assert (tmp_path / "again.pt").read_bytes() == (tmp_path / "model.pt").read_bytes()


def test_load_partition_model_errors(tmp_path):
    from gdiff.errors import ModelFileError
    from gdiff.partition import load_partition_model
    from gdiff.splat.model import save_model

    with pytest.raises(ModelFileError, match="not found"):
        load_partition_model(tmp_path / "nope.pt", "cpu")
    save_model(_static_model([[0, 0, 0]], [[1, 1, 1]]), tmp_path / "fit.pt")
    with pytest.raises(ModelFileError, match="fit-stage model"):
        load_partition_model(tmp_path / "fit.pt", "cpu")


def test_divergence_raises_training_error_naming_iteration(tmp_path):
    from gdiff.errors import TrainingError
    from gdiff.partition import PartitionModel, fine_tune

    model = _static_model([[-0.3, 0, 0], [0.3, 0, 0]], [[1, 0, 0], [0, 0, 1]])
    cam = _front_camera()
    pm = PartitionModel(model, ChangeHead(2, 16), cam)
    data = [{"camera": cam, "time": 0, "image": torch.zeros(30, 40, 3),
             "target": torch.zeros(30, 40)}]
    with torch.no_grad():
        pm.head.encoding[0, 0] = float("nan")
    with pytest.raises(TrainingError, match="iteration 0"):
        fine_tune(pm, data, PartitionOptions(iterations=3, knn_k=1, knn_samples=2), tmp_path)


# --------------------------------------------------------------------------- tiny synth scene

def _keyframes_from_ground_truth(scene, results):
    """What the compare stage writes, from the synthetic ground truth: per training photo the
    changed-object masks at t=0 and t=1 at its pose, and ``change/keyframes.csv``."""
    import pandas as pd

    from gdiff.io import write_csv, write_mask

    rows = []
    for st, path in (("before", "p1"), ("after", "p2")):
        for i, cam in enumerate(scene.cameras(st)):
            m = {"t0": scene.render(cam, "before", supersample=1)["changed"],
                 "t1": scene.render(cam, "after", supersample=1)["changed"]}
            m["union"] = m["t0"] | m["t1"]
            rel = {k: f"change/{path}/{k}/{i:05d}.png" for k in m}
            for k in m:
                write_mask(results / rel[k], m[k])
            rows.append({"path": path, "frame": i, "image": cam.image, "set": st,
                         "time": cam.time, **{f"mask_{k}": rel[k] for k in m}})
    write_csv(results / "change" / "keyframes.csv", pd.DataFrame(rows))


def _points_from_ground_truth(scene, n_per_view=400, seed=0):
    """Coloured 3D points back-projected from ground-truth depth of every other training view
    (standing in for the poses stage's SfM points)."""
    rng = np.random.default_rng(seed)
    xyz, rgb = [], []
    for st in ("before", "after"):
        for cam in scene.cameras(st)[::2]:
            r = scene.render(cam, st, supersample=1)
            h, w = r["depth"].shape
            sel = rng.choice(h * w, n_per_view, replace=False)
            v, u = np.divmod(sel, w)
            z = r["depth"].reshape(-1)[sel]
            pc = np.stack([(u + 0.5 - cam.cx) / cam.fx * z, (v + 0.5 - cam.cy) / cam.fy * z, z], 1)
            xyz.append(pc @ cam.c2w[:3, :3].T + cam.c2w[:3, 3])
            rgb.append(r["rgb"].reshape(-1, 3)[sel])
    return np.concatenate(xyz), np.concatenate(rgb)


@pytest.fixture(scope="module")
def tiny_fit(synth_tiny_scene, synth_tiny_dir, tmp_path_factory):
    """A quickly fitted 4D model of the tiny scene (ground-truth poses, 64 px working size,
    no densification) with compare-stage inputs made from the ground truth."""
    from gdiff.cameras import save_cameras
    from gdiff.splat.ply import write_points
    from gdiff.splat.train import FitOptions, fit_scene

    sc = synth_tiny_scene
    res = tmp_path_factory.mktemp("partition") / "results"
    cams = sum((sc.cameras(s) for s in ("before", "after", "eval_before", "eval_after")), [])
    save_cameras(res / "poses" / "cameras.json", cams)
    write_points(res / "poses" / "points.ply", *_points_from_ground_truth(sc))
    _keyframes_from_ground_truth(sc, res)
    fit_scene(synth_tiny_dir, res / "poses" / "cameras.json", res / "poses" / "points.ply",
              res / "fit", FitOptions(coarse_iters=100, fine_iters=100, max_side=64,
                                      densify_until=0, opacity_reset_every=0, sh_degree=0,
                                      init_opacity=0.5, hexplane_resolution=[16, 16, 16],
                                      hexplane_multires=[1], deform_width=32,
                                      checkpoint_every=0), device="cpu")
    return res, synth_tiny_dir


@pytest.fixture(scope="module")
def tiny_partition(tiny_fit):
    from gdiff.partition import train_partition

    res, scene_dir = tiny_fit
    summary = train_partition(res / "fit" / "model.pt", res / "poses" / "cameras.json",
                              res / "change" / "keyframes.csv", scene_dir, res / "partition",
                              PartitionOptions(iterations=150, checkpoint_every=100,
                                               log_every=25),
                              device="cpu")
    return res, summary


def test_tiny_change_map_at_held_out_views_overlaps_ground_truth(tiny_partition,
                                                                 synth_tiny_scene):
    from gdiff.io import read_mask
    from gdiff.metrics import confusion, scores_from_counts
    from gdiff.partition import load_partition_model, render_change_map

    res, summary = tiny_partition
    out = res / "partition"
    for f in ("model.pt", "changed.ply", "unchanged.ply", "changed_t1.ply", "probability.npy",
              "train_log.csv", "keypose_scores.csv", "summary.json"):
        assert (out / f).is_file(), f
    prob = np.load(out / "probability.npy")
    n = summary["gaussians"]
    assert prob.shape == (n,) and 0 < (prob > 0.5).sum() < 0.2 * n
    key = "p1_00003"
    for kind in ("t0", "t1", "union", "union_prob", "overlay"):
        assert (out / "maps" / kind / f"{key}.png").is_file()
    assert read_mask(out / "maps" / "union" / f"{key}.png").any()
    assert summary["keypose_iou_union"] > 0.3

    pm = load_partition_model(out / "model.pt", "cpu")
    counts = np.zeros(3)
    for cam in synth_tiny_scene.cameras("eval"):  # not among the training views
        gt = (synth_tiny_scene.render(cam, "before", supersample=1)["changed"]
              | synth_tiny_scene.render(cam, "after", supersample=1)["changed"])
        r = render_change_map(pm, cam, None)
        assert r["mask"].shape == gt.shape
        counts += confusion(r["mask"], gt)
    s = scores_from_counts(*counts)
    # default options (geometry frozen throughout): IoU 0.81 / P 0.95 / R 0.85 when written
    # (pooled over the 3 eval views; 0.74 / 0.96 / 0.76 with the other time's changed pixels
    # supervised as unchanged); an untrained head predicts nothing (IoU 0) and a random split
    # IoU ~0.04 (changed fraction)
    assert s["IoU"] > 0.7 and s["P"] > 0.85 and s["R"] > 0.75, s
    # by default the change maps render from the fit's own geometry, untouched
    from gdiff.splat.model import load_model

    fit = load_model(res / "fit" / "model.pt", "cpu")
    for name, value in fit.splats.items():
        assert torch.equal(pm.fit.splats[name], value), name


def test_operating_point_moves_off_one_half_only_for_a_real_gain():
    from gdiff.partition import operating_point

    assert operating_point(0.26, 0.823, 0.786, 0.01)[0] == 0.26  # under-confident head
    th, why = operating_point(0.37, 0.903, 0.902, 0.01)  # flat curve: stays
    assert th == 0.5 and "0.37" in why
    assert operating_point(None, float("nan"), float("nan"), 0.01)[0] == 0.5  # no masks
    assert operating_point(0.37, 0.903, 0.902, 0.0)[0] == 0.37
    # a capture with next to no change: one stray ID in the masks, a flat low curve
    th, why = operating_point(0.01, 0.019, 0.0, 0.01)
    assert th == 0.5 and "no threshold reproduces" in why
    assert operating_point(0.22, 0.609, 0.482, 0.01)[0] == 0.22  # sparse capture: moves


def test_threshold_null_is_chosen_from_the_key_views(tiny_fit, tmp_path):
    """partition.threshold null: the stage picks the key-view F1 maximum, saves it in the model
    and threshold.json, and thresholds the key-pose maps with it."""
    import json

    from gdiff.partition import load_partition_model, train_partition

    res, scene_dir = tiny_fit
    out = tmp_path / "partition"
    summary = train_partition(res / "fit" / "model.pt", res / "poses" / "cameras.json",
                              res / "change" / "keyframes.csv", scene_dir, out,
                              PartitionOptions(iterations=30, frozen_iterations=20,
                                               threshold=None, threshold_gain=0.0),
                              device="cpu")
    info = json.loads((out / "threshold.json").read_text())
    th = info["threshold"]
    assert info["source"].startswith("max F1 over the key views")
    assert th == info["key_view_best_threshold"]
    assert 0 < th < 1 and summary["threshold"] == th
    assert load_partition_model(out / "model.pt", "cpu").threshold == th
    curve = {r["threshold"]: r["f1"] for r in info["curve"]}
    assert info["key_view_f1"] == pytest.approx(max(curve.values()))
    assert info["key_view_f1"] >= info["key_view_f1_at_0.5"]
    assert (out / "maps" / "union" / "p1_00003.png").is_file()


def test_before_gate_is_kept_with_the_model_and_left_off_under_a_change_of_light(
        tiny_fit, tmp_path, caplog):
    """The union maps' before-map gate (partition.before_gate) is saved with the model, so
    every later map (evaluate, the CLI) applies it, and it only removes pixels from the plain
    union. When the compare stage took the scene for a change of light (``light_changed`` in
    keyframes.csv) the two times' renders differ everywhere, and the plain union is kept."""
    import logging
    import shutil

    import pandas as pd

    from gdiff.partition import (load_partition_model, read_key_views, render_change_map,
                                 train_partition)

    res, scene_dir = tiny_fit
    opts = PartitionOptions(iterations=30, frozen_iterations=20)
    summary = train_partition(res / "fit" / "model.pt", res / "poses" / "cameras.json",
                              res / "change" / "keyframes.csv", scene_dir, tmp_path / "a", opts,
                              device="cpu")
    assert summary["before_gate"] == opts.before_gate == 0.95
    pm = load_partition_model(tmp_path / "a" / "model.pt", "cpu")
    assert pm.before_gate == 0.95
    for v in read_key_views(res / "change" / "keyframes.csv", res / "poses" / "cameras.json",
                            scene_dir):
        cam = v.camera
        gated = render_change_map(pm, cam, None)
        pm.before_gate = 0.0
        plain = render_change_map(pm, cam, None)
        pm.before_gate = 0.95
        assert not (gated["mask"] & ~plain["mask"]).any()

    work = tmp_path / "results"
    shutil.copytree(res / "change", work / "change")
    kf = pd.read_csv(work / "change" / "keyframes.csv")
    kf["light_changed"] = True
    kf.to_csv(work / "change" / "keyframes.csv", index=False)
    with caplog.at_level(logging.INFO, logger="gdiff.partition"):
        summary = train_partition(res / "fit" / "model.pt", res / "poses" / "cameras.json",
                                  work / "change" / "keyframes.csv", scene_dir, tmp_path / "b",
                                  opts, device="cpu")
    assert summary["before_gate"] == 0.0
    assert load_partition_model(tmp_path / "b" / "model.pt", "cpu").before_gate == 0.0
    assert "change of light" in caplog.text


def test_scene_with_no_change_gives_an_empty_partition_without_warnings(tiny_fit, tmp_path):
    """Key-view masks with no changed pixel (compare found nothing): the partition marks no
    Gaussian, its maps are empty and its summary says the key-view IoU is undefined (NaN)
    without a numpy warning in the log."""
    import json
    import shutil
    import warnings

    import pandas as pd

    from gdiff.io import read_mask, write_mask
    from gdiff.partition import train_partition

    res, scene_dir = tiny_fit
    work = tmp_path / "results"
    shutil.copytree(res / "change", work / "change")
    kf = pd.read_csv(work / "change" / "keyframes.csv")
    for col in ("mask_t0", "mask_t1", "mask_union"):
        for rel in kf[col]:
            write_mask(work / rel, np.zeros_like(read_mask(work / rel)))
    out = tmp_path / "partition"
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        summary = train_partition(res / "fit" / "model.pt", res / "poses" / "cameras.json",
                                  work / "change" / "keyframes.csv", scene_dir, out,
                                  PartitionOptions(iterations=30, frozen_iterations=20),
                                  device="cpu")
    assert summary["n_changed"] == 0
    assert np.isnan(summary["keypose_iou_union"])
    assert np.isnan(json.loads((out / "summary.json").read_text())["keypose_iou_union"])
    assert not any(read_mask(f).any() for f in (out / "maps" / "union").glob("*.png"))


@pytest.mark.parametrize("geometry_lr_scale,frozen_iterations",
                         [(0.0, 4), (1.0, 4), (1.0, 0)], ids=["frozen", "two-phase", "joint"])
def test_resume_gives_the_same_model_as_an_uninterrupted_run(tiny_fit, tmp_path,
                                                            geometry_lr_scale,
                                                            frozen_iterations):
    """Frozen geometry throughout (cached blend weights), frozen then joint (resumed at the
    phase boundary: steps 0-3 frozen, 4-6 joint) and joint throughout; the fitted Gaussians
    move only with a joint phase."""
    from gdiff.partition import (PartitionModel, _load_image, _load_mask, fine_tune,
                                 read_key_views)
    from gdiff.splat.model import load_model

    res, scene_dir = tiny_fit
    views = read_key_views(res / "change" / "keyframes.csv", res / "poses" / "cameras.json",
                           scene_dir, max_side=32)[::5]
    data = [{"camera": v.camera, "time": v.time,
             "image": torch.from_numpy(_load_image(v.image, v.camera)),
             "target": torch.from_numpy(_load_mask(v.target, v.camera))} for v in views]
    opts = dict(checkpoint_every=3, log_every=1, l3d_every=1, knn_refresh=2, knn_samples=300,
                geometry_lr_scale=geometry_lr_scale, frozen_iterations=frozen_iterations)

    def run(ckdir, iterations):
        fit = load_model(res / "fit" / "model.pt", "cpu")
        pm = PartitionModel(fit, ChangeHead(len(fit), 16, seed=0), data[0]["camera"])
        rows = fine_tune(pm, data, PartitionOptions(iterations=iterations, **opts), ckdir,
                         extent=fit.meta["extent"])
        return pm, rows

    a, rows_a = run(tmp_path / "a", 7)
    run(tmp_path / "b", 4)  # "interrupted" after the checkpoint at iteration 3 (and 4)
    assert sorted(p.name for p in (tmp_path / "b").iterdir()) == ["ckpt_000003.pt",
                                                                  "ckpt_000004.pt"]
    (tmp_path / "b" / "ckpt_000004.pt").unlink()  # resume from 3, mid-way between refreshes
    # as if killed while writing checkpoint 4: a half-written temporary file is left
    (tmp_path / "b" / ".ckpt_000004.x.tmp.pt").write_bytes(b"PK\x03\x04")
    b, rows_b = run(tmp_path / "b", 7)
    assert not list((tmp_path / "b").glob(".*.tmp*"))
    fresh, _ = run(tmp_path / "c", 0)
    assert not torch.allclose(a.head.encoding, fresh.head.encoding)
    torch.testing.assert_close(b.head.encoding, a.head.encoding, atol=1e-5, rtol=1e-4)
    torch.testing.assert_close(b.head.conv.weight, a.head.conv.weight, atol=1e-5, rtol=1e-4)
    torch.testing.assert_close(b.fit.splats["means"], a.fit.splats["means"], atol=1e-6,
                               rtol=1e-5)
    moved = (a.fit.splats["means"] - fresh.fit.splats["means"]).abs().max().item()
    assert (moved > 0) == (geometry_lr_scale > 0), moved
    l1_logged = np.isfinite([r["l1"] for r in rows_a])  # L1 is computed in the joint phase
    frozen_until = frozen_iterations if geometry_lr_scale > 0 else 7
    np.testing.assert_array_equal(l1_logged, np.arange(7) >= frozen_until)
    assert [r["iteration"] for r in rows_b] == [r["iteration"] for r in rows_a]
    np.testing.assert_allclose([r["bce"] for r in rows_b], [r["bce"] for r in rows_a],
                               rtol=1e-4)


def test_blend_weight_cache_keeps_the_training_size_while_it_fits_its_budget(tiny_fit, caplog):
    """frozen_scale null: the key views' weights are cached at their training size when they
    fit in cache_max_mb, else at the scale whose pixels fit; a number fixes the scale."""
    from gdiff.partition import PartitionModel, _load_mask, read_key_views
    from gdiff.partition.train import _cache_weights
    from gdiff.splat.model import load_model

    res, scene_dir = tiny_fit
    views = read_key_views(res / "change" / "keyframes.csv", res / "poses" / "cameras.json",
                           scene_dir, max_side=64)[::3]
    data = [{"camera": v.camera, "time": v.time,
             "target": torch.from_numpy(_load_mask(v.target, v.camera))} for v in views]
    fit = load_model(res / "fit" / "model.pt", "cpu")
    pm = PartitionModel(fit, ChangeHead(len(fit), 16, seed=0), data[0]["camera"])
    size = (views[0].camera.width, views[0].camera.height)

    def cached(scale, max_mb):
        _, out = _cache_weights(pm, data, scale, max_mb)
        assert len(out) == len(data)
        for bw, target, _ in out:
            assert tuple(target.shape) == (bw.height, bw.width)
        return (out[0][0].width, out[0][0].height), sum(w[0].nbytes for w in out)

    full, full_bytes = cached(None, 1024.0)
    assert full == size
    assert cached(1.0, 1e-6) == (full, full_bytes)  # a fixed scale ignores the budget
    budget = full_bytes / 4 / 2**20  # a quarter: about half the width and height fit
    with caplog.at_level("INFO", logger="gdiff.partition"):
        (w, h), nbytes = cached(None, budget)
    assert w < size[0] and h < size[1]
    assert abs(w / size[0] - 0.5) < 0.15, (w, size)
    assert nbytes < 1.3 * budget * 2**20
    assert "over partition.cache_max_mb" in caplog.text
    half, _ = cached(0.5, 1024.0)
    assert half == (round(size[0] / 2), round(size[1] / 2))


def test_cli_renders_change_map_at_an_arbitrary_pose(tiny_partition, tmp_path, capsys):
    from scipy.spatial.transform import Rotation

    from gdiff.cameras import look_at
    from gdiff.cli import main as gdiff_main
    from gdiff.io import read_image, read_mask, write_json
    from gdiff.partition import change_map_main, load_partition_model, render_change_map

    res, _ = tiny_partition
    model = res / "partition" / "model.pt"
    pm = load_partition_model(model, "cpu")
    # a viewpoint on no training path: high above the table, looking down at its centre
    c2w = look_at([0.4, -0.9, 2.2], [0.0, 0.0, 0.2])
    q = Rotation.from_matrix(c2w[:3, :3]).as_quat(scalar_first=True)
    pose = [str(x) for x in [*c2w[:3, 3], *q]]
    out = tmp_path / "m.png"
    assert change_map_main(["--model", str(model), "--pose", *pose, "--t", "1", "--out",
                            str(out), "--prob-out", str(tmp_path / "p.npy"),
                            "--image-out", str(tmp_path / "i.png"),
                            "--overlay-out", str(tmp_path / "o.png")]) == 0
    expect = render_change_map(pm, pm.camera.with_pose(c2w), 1.0)
    mask = read_mask(out)
    assert mask.shape == (pm.camera.height, pm.camera.width)
    np.testing.assert_array_equal(mask, expect["mask"])
    np.testing.assert_allclose(np.load(tmp_path / "p.npy"), expect["prob"], atol=1e-5)
    assert read_image(tmp_path / "i.png").std() > 0.02  # the scene, not an empty render
    assert "changed" in capsys.readouterr().out
    # the same camera from a c2w file, union of both times, resized, through `gdiff`
    write_json(tmp_path / "pose.json", {"c2w": c2w})
    out2 = tmp_path / "u.png"
    assert gdiff_main(["change-map", "--model", str(model), "--c2w", str(tmp_path / "pose.json"),
                       "--out", str(out2), "--width", "64", "--height", "48"]) == 0
    union = render_change_map(pm, pm.camera.with_pose(c2w).scaled(0.5), None)["mask"]
    np.testing.assert_array_equal(read_mask(out2), union)
    # a camera of a cameras.json (an eval view), picked by its image path
    from gdiff.cameras import load_cameras

    cams = res / "poses" / "cameras.json"
    ev = [c for c in load_cameras(cams) if c.image == "eval/after/001.png"][0]
    assert gdiff_main(["change-map", "--model", str(model), "--cameras", str(cams), "--frame",
                       "eval/after/001.png", "--t", "0", "--out", str(out2)]) == 0
    np.testing.assert_array_equal(read_mask(out2), render_change_map(pm, ev, 0.0)["mask"])
    # user errors are one-line messages with status 2
    assert gdiff_main(["change-map", "--model", str(res / "fit" / "model.pt"), "--pose",
                       *pose, "--out", str(out2)]) == 2
    assert "fit-stage model" in capsys.readouterr().err


def test_checkpoint_of_other_options_is_not_resumed(tmp_path, caplog):
    from gdiff.partition import PartitionModel, fine_tune

    rng = np.random.default_rng(0)
    means, cols = rng.normal(scale=0.3, size=(100, 3)), rng.random((100, 3))
    cam = _front_camera()
    data = [{"camera": cam, "time": 0, "image": torch.rand(30, 40, 3),
             "target": (torch.rand(30, 40) > 0.7).float()}]

    def run(iterations, lambda_2d):
        pm = PartitionModel(_static_model(means, cols), ChangeHead(100, 16), cam)
        opts = PartitionOptions(iterations=iterations, lambda_2d=lambda_2d, checkpoint_every=2,
                                log_every=1, knn_samples=20)
        return fine_tune(pm, data, opts, tmp_path)

    run(2, 1.0)
    with caplog.at_level("INFO", logger="gdiff.partition"):
        rows = run(3, 2.0)
    assert "other options" in caplog.text and "resuming" not in caplog.text
    assert len(rows) == 3  # trained from iteration 0
    caplog.clear()
    with caplog.at_level("INFO", logger="gdiff.partition"):
        run(4, 2.0)
    assert "resuming" in caplog.text and "iteration 3" in caplog.text


def test_blend_and_neighbour_gradients_are_reproducible_with_threads(torch_threads):
    """The gradients of the cached-weight blend and of L3d gather repeated Gaussians; they sum
    those repeats in the same order on every run with several threads, so training (and its
    resume from a checkpoint) is reproducible."""
    from gdiff.partition import BlendWeights, neighbour_kl, render_blended

    g = torch.Generator().manual_seed(0)
    n, pairs, side = 20000, 400_000, 200
    bw = BlendWeights.from_pairs(pix=torch.randint(0, side * side, (pairs,), generator=g),
                                 gid=torch.randint(0, n, (pairs,), generator=g).int(),
                                 weight=torch.rand(pairs, generator=g),
                                 alpha=torch.ones(side * side), width=side, height=side)
    sample = torch.randint(0, n, (5000,), generator=g)
    nbr = torch.randint(0, n, (5000, 16), generator=g)
    w = torch.randn(side, side, generator=g)
    logits0 = torch.randn(n, 2, generator=g)
    torch_threads(4)
    grads = []
    for _ in range(4):
        z = torch.randn(n, generator=torch.Generator().manual_seed(1)).requires_grad_(True)
        logits = logits0.clone().requires_grad_(True)
        ((render_blended(bw, z) * w).sum() + neighbour_kl(logits, sample, nbr)).backward()
        grads.append((z.grad, logits.grad))
    for gz, gl in grads[1:]:
        assert torch.equal(gz, grads[0][0]) and torch.equal(gl, grads[0][1])
