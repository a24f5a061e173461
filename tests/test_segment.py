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
