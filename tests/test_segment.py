"""Geometric (weight-free) segmenter on synthetic renders with exact instance ground truth."""

import dataclasses

import numpy as np
import pytest

from gdiff import synth
from gdiff.errors import ConfigError
from gdiff.segment import Instance, Segmenter, SegmentOptions, make_segmenter
from gdiff.segment.geometric import GeometricSegmenter, crease_edges, depth_edges


@pytest.fixture(scope="module")
def light_scene():
    p = dataclasses.replace(synth.get_preset("lightchange"), width=160, height=120, supersample=1)
    return synth.build_scene(p, 3)


def _best_iou(gt_mask, instances):
    best = 0.0
    for inst in instances:
        inter = (inst.mask & gt_mask).sum()
        if inter:
            best = max(best, inter / (inst.mask | gt_mask).sum())
    return best


def test_objects_recovered_with_depth_under_both_lightings(light_scene):
    seg = make_segmenter(SegmentOptions())
    cam = synth.orbit_path(light_scene, "before", 3)[1]
    ious = []
    for state in ("before", "after"):
        r = light_scene.render(cam, state)
        inst = seg.segment(r["rgb"], r["depth"], None, cam.K)
        assert all(isinstance(i, Instance) for i in inst)
        # masks do not overlap
        stack = np.stack([i.mask for i in inst])
        assert stack.sum(0).max() <= 1
        for oid in np.unique(r["ids"]):
            m = r["ids"] == oid
            if oid == 0 or m.sum() < 80:
                continue
            ious.append(_best_iou(m, inst))
    assert len(ious) >= 6
    assert np.median(ious) > 0.75, ious
    assert np.mean(np.array(ious) > 0.5) >= 0.8, ious


def test_plane_has_no_edges_and_step_has():
    # a tilted plane seen by a pinhole camera: inverse depth affine -> no edges anywhere
    H, W = 60, 80
    K = np.array([[70.0, 0, 40], [0, 70, 30], [0, 0, 1]])
    jj, ii = np.mgrid[0:H, 0:W]
    w = 0.2 + 0.004 * (ii + 0.5) + 0.006 * (jj + 0.5)
    z = (1 / w).astype(np.float32)
    valid = np.ones_like(z, bool)
    assert not depth_edges(z, valid, 0.04, 1.0).any()
    assert not crease_edges(z, valid, K, 35.0, 1.0).any()
    z2 = z.copy()
    z2[20:40, 30:50] *= 0.7  # a box in front: occlusion boundary
    e = depth_edges(z2, valid, 0.04, 1.0)
    assert e[20:40, 28:32].any() and e[18:22, 30:50].any()
    assert not e[:10].any()


def test_color_only_without_depth(light_scene):
    cam = synth.orbit_path(light_scene, "before", 3)[1]
    r = light_scene.render(cam, "before")
    inst = GeometricSegmenter(SegmentOptions()).segment(r["rgb"])
    assert len(inst) >= 3
    assert isinstance(GeometricSegmenter(), Segmenter)


def test_factory_errors():
    with pytest.raises(ConfigError, match="segment.backend"):
        SegmentOptions(backend="nope")
    with pytest.raises(ConfigError, match="sam_encoder"):
        make_segmenter(SegmentOptions(backend="sam"))


def _grow_into_whole_image(labels, todo, feat, max_iter=50):
    """grow_into as first written, on whole-image masks (the reference)."""
    from gdiff.segment.geometric import _shifted

    labels = labels.copy()
    n = int(labels.max())
    C = feat.shape[-1]
    flat = labels.ravel()
    means = np.zeros((n + 1, C), np.float64)
    counts = np.bincount(flat, minlength=n + 1).astype(np.float64)
    for c in range(C):
        means[:, c] = np.bincount(flat, weights=feat[..., c].ravel(), minlength=n + 1)
    means /= np.maximum(counts, 1)[:, None]
    todo = todo & (labels == 0)
    for _ in range(max_iter):
        if not todo.any():
            break
        best = np.full(labels.shape, np.inf, np.float32)
        new = np.zeros_like(labels)
        for dy in (-1, 0, 1):
            for dx in (-1, 0, 1):
                if dy == 0 and dx == 0:
                    continue
                nb = _shifted(labels, dy, dx)
                cand = todo & (nb > 0)
                if not cand.any():
                    continue
                d = np.abs(feat[cand] - means[nb[cand]]).sum(-1).astype(np.float32)
                better = d < best[cand]
                idx = np.flatnonzero(cand.ravel())[better]
                best.ravel()[idx] = d[better]
                new.ravel()[idx] = nb[cand][better]
        grown = new > 0
        if not grown.any():
            break
        labels[grown] = new[grown]
        todo &= ~grown
    return labels


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_grow_into_touches_only_the_pixels_to_do_and_grows_as_on_the_whole_image(seed):
    from gdiff.segment.geometric import grow_into

    rng = np.random.default_rng(seed)
    H, W = 37, 53
    labels = np.zeros((H, W), np.int32)
    for k in range(1, 6):  # a few seed blobs, one touching the border
        y, x = rng.integers(0, H), rng.integers(0, W)
        labels[max(0, y - 2):y + 3, max(0, x - 3):x + 4] = k
    labels[0, :4] = 6
    feat = rng.random((H, W, 2)).astype(np.float32)
    todo = rng.random((H, W)) < 0.9
    for max_iter in (3, 50):
        out = grow_into(labels, todo, feat, max_iter)
        np.testing.assert_array_equal(out, _grow_into_whole_image(labels, todo, feat, max_iter))
    assert (out[todo & (labels == 0)] > 0).mean() > 0.5  # it grew
    np.testing.assert_array_equal(out[~todo], labels[~todo])  # nothing else moved


def _pair_frames(shape=(96, 128)):
    """Two renders of one pose: a grey plane (depth 2) with a grey box (depth 1.6) that the
    second render draws 12 px to the right (a sparse fit's ghost), and at the right a grey box
    at the first time where the second shows a flat red square instead (a change)."""
    H, W = shape
    z0, z1 = np.full(shape, 2.0, np.float32), np.full(shape, 2.0, np.float32)
    z0[30:70, 10:40] = 1.6
    z1[30:70, 22:52] = 1.6
    z0[40:60, 90:110] = 1.6
    rgb0 = np.full(shape + (3,), 0.5, np.float32)
    rgb1 = rgb0.copy()
    rgb1[30:70, 80:120] = (0.8, 0.15, 0.1)
    K = np.array([[W, 0, W / 2], [0, W, H / 2], [0, 0, 1]], np.float64)
    return (rgb0, z0), (rgb1, z1), K


def _same_partition(a, b, mask):
    """Share of the pixels of ``mask`` whose label pair is the commonest of both labels (1.0
    when ``a`` and ``b`` cut ``mask`` into the same regions)."""
    la, lb = a[mask].astype(np.int64), b[mask].astype(np.int64)
    pairs, counts = np.unique(np.stack([la, lb]), axis=1, return_counts=True)
    best_a = {x: 0 for x in pairs[0]}
    best_b = {y: 0 for y in pairs[1]}
    for (x, y), c in zip(pairs.T, counts):
        best_a[x], best_b[y] = max(best_a[x], c), max(best_b[y], c)
    good = sum(c for (x, y), c in zip(pairs.T, counts) if c == best_a[x] == best_b[y])
    return good / mask.sum()


def test_two_times_cut_together_share_their_regions():
    (rgb0, z0), (rgb1, z1), K = _pair_frames()
    seg = GeometricSegmenter(SegmentOptions(min_region_area=16))
    whole = np.ones(z0.shape, bool)
    own0, own1 = seg.label(rgb0, z0, None, K), seg.label(rgb1, z1, None, K)
    pair0 = seg.label(rgb0, z0, None, K, other=(rgb1, z1, None))
    pair1 = seg.label(rgb1, z1, None, K, other=(rgb0, z0, None))
    # each time cuts the ghosted box where its own render has it; together, at both edges,
    # and the red square of the second time along the first time's box there
    assert _same_partition(own0, own1, whole) < 0.9
    assert _same_partition(pair0, pair1, whole) > 0.97
    assert len(np.unique(own1[33:67, 83:117])) == 1 and len(np.unique(pair1[33:67, 83:117])) > 1
    with pytest.raises(ValueError, match="one size"):
        seg.label(rgb0, z0, None, K, other=(rgb1[:50], z1[:50], None))


def test_shared_pose():
    from gdiff.segment.pair import depths_agree, shared_pose

    (_, z0), (_, z1), _ = _pair_frames()
    valid = np.ones(z0.shape, bool)
    assert depths_agree(z0, z0 * 1.01, valid, 0.05) == 1.0
    assert depths_agree(z0, z0 * 1.2, valid, 0.05) == 0.0
    assert np.isnan(depths_agree(z0, np.full_like(z0, np.nan), valid, 0.05))
    f0 = dict(depth=z0, alpha=np.ones_like(z0))
    assert not shared_pose(f0, dict(depth=z1, alpha=np.ones_like(z0)), 0.05, 0.25)
    assert shared_pose(f0, dict(depth=z0 * 1.1, alpha=np.ones_like(z0)), 0.05, 0.25)
    # pixels one time does not show are left out of the share
    holes = np.ones_like(z0)
    holes[:, 20:] = 0
    far = z0 * 1.1
    far[:, :20] = z0[:, :20]
    assert not shared_pose(f0, dict(depth=far, alpha=holes), 0.05, 0.25)
    assert not shared_pose(dict(depth=None), f0, 0.05, 0.25)
    with pytest.raises(ConfigError, match="shared_partition"):
        SegmentOptions(shared_partition="on")
