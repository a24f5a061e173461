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
