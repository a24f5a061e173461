"""Tests of the before-map gate of the union change map (gdiff.partition.gate)."""

from __future__ import annotations

import numpy as np
import torch

from gdiff.cameras import Camera, look_at
from gdiff.partition import ChangeHead, PartitionModel, render_change_map
from gdiff.partition.gate import gate_before_map, render_difference


def test_render_difference_ignores_exposure_and_finds_a_changed_patch():
    rng = np.random.default_rng(0)
    a = rng.uniform(0.2, 0.8, (60, 80, 3)).astype(np.float32)
    b = a * np.float32([0.7, 0.8, 0.9])  # darker and bluer: another exposure, same scene
    b[20:40, 30:50] = [0.9, 0.1, 0.1]
    ref = np.ones((60, 80), bool)
    ref[20:40, 30:50] = False
    d = render_difference(a, b, ref)
    assert d.shape == (60, 80) and d.dtype == np.float32
    assert np.percentile(d[ref], 90) < 0.03  # the exposure is matched out
    assert d[25:35, 35:45].min() > 0.2


class _TwoStates:
    """Stand-in for a fitted 4D model: its Gaussians drawn at t = 0 and at t = 1."""

    def __init__(self, g0, g1):
        self.g0, self.g1 = g0, g1

    def __len__(self) -> int:
        return len(self.g0.means)

    def at_time(self, t: float):
        return self.g0 if t < 0.5 else self.g1


def _gaussians(means, colours, opacities, scale=0.04):
    from gdiff.splat.gaussians import Gaussians, rgb_to_sh0

    n = len(means)
    quats = torch.zeros(n, 4)
    quats[:, 0] = 1.0
    return Gaussians(torch.as_tensor(means, dtype=torch.float32), quats,
                     torch.full((n, 3), scale), torch.as_tensor(opacities, dtype=torch.float32),
                     rgb_to_sh0(torch.as_tensor(colours, dtype=torch.float32))[:, None],
                     sh_degree=0)


def _scene():
    """A grey wall (y = 0.3) seen from y = -2, unchanged but for render noise between the times,
    and three Gaussians labelled changed in front of it:
    A (x = -0.5): grey like the wall at t=0, gone at t=1 (a surface labelled changed that looks
    the same at both times: what an added object hid from the before photos);
    C (x = +0.5): red at t=0, gone at t=1 (a removed object);
    D (z = +0.3): absent at t=0, blue at t=1 (an added object)."""
    rng = np.random.default_rng(1)
    xs, zs = np.meshgrid(np.linspace(-1.2, 1.2, 49), np.linspace(-0.9, 0.9, 37))
    wall = np.stack([xs.ravel(), np.full(xs.size, 0.3), zs.ravel()], 1)
    grey = np.full((len(wall), 3), 0.5)
    grey1 = np.clip(grey + rng.normal(0, 0.02, grey.shape), 0, 1)  # the other fit's noise
    obj = np.array([[-0.5, 0.0, 0.0], [0.5, 0.0, 0.0], [0.0, 0.0, 0.3]])
    means = np.concatenate([wall, obj])
    col0 = np.concatenate([grey, [[0.5, 0.5, 0.5], [0.9, 0.1, 0.1], [0.1, 0.1, 0.9]]])
    col1 = np.concatenate([grey1, [[0.5, 0.5, 0.5], [0.9, 0.1, 0.1], [0.1, 0.1, 0.9]]])
    n = len(wall)
    op0 = np.concatenate([np.full(n, 0.95), [0.95, 0.95, 0.0]])
    op1 = np.concatenate([np.full(n, 0.95), [0.0, 0.0, 0.95]])
    fit = _TwoStates(_gaussians(means, col0, op0, 0.1 / 3), _gaussians(means, col1, op1, 0.1 / 3))
    fit.g0.scales[n:] = 0.1
    fit.g1.scales[n:] = 0.1
    head = ChangeHead(len(means), 4)
    with torch.no_grad():  # encoding[:, 0] = 1 -> changed
        head.encoding.zero_()
        head.encoding[n:, 0] = 1.0
        head.conv.weight.zero_()
        head.conv.bias.copy_(torch.tensor([2.0, -2.0]))
        head.conv.weight[1, 0] = 8.0
    cam = Camera(80, 60, 60.0, 60.0, 40.0, 30.0, look_at([0, -2.0, 0], [0, 0, 0]))
    return fit, head, cam


def _spot(cam, point, r=1):
    c = np.asarray(point, float) - cam.c2w[:3, 3]
    x = c @ cam.c2w[:3, :3]  # world-to-camera rotation applied: OpenCV camera coordinates
    u, v = cam.fx * x[0] / x[2] + cam.cx, cam.fy * x[1] / x[2] + cam.cy
    u, v = int(np.floor(u)), int(np.floor(v))  # the pixel holding the projection
    return slice(v - r, v + r + 1), slice(u - r, u + r + 1)


def test_union_keeps_removed_and_added_objects_and_drops_a_before_label_that_looks_unchanged():
    fit, head, cam = _scene()
    a, c, d = (_spot(cam, p) for p in ([-0.5, 0, 0], [0.5, 0, 0], [0, 0, 0.3]))
    plain = render_change_map(PartitionModel(fit, head, cam), cam, None)
    for s in (a, c, d):  # the plain union marks all three
        assert plain["mask"][s].all()
    assert plain["prob_t0"][a].min() > 0.5 and plain["prob_t1"][a].max() < 0.5

    gated = render_change_map(PartitionModel(fit, head, cam, before_gate=0.95), cam, None,
                              with_image=True)
    assert gated["mask"][c].all() and gated["mask"][d].all()
    assert gated["mask"][a].mean() < 0.2
    # only the union is gated; the per-time maps stay as labelled
    np.testing.assert_array_equal(gated["prob_t0"], plain["prob_t0"])
    np.testing.assert_array_equal(gated["prob_t1"], plain["prob_t1"])
    assert not (gated["mask"] & ~plain["mask"]).any()
    # a single time is never gated
    np.testing.assert_array_equal(
        render_change_map(PartitionModel(fit, head, cam, before_gate=0.95), cam, 0.0)["mask"],
        render_change_map(PartitionModel(fit, head, cam), cam, 0.0)["mask"])


def test_gate_keeps_everything_when_nothing_is_unchanged():
    p = np.full((10, 10), 0.9, np.float32)
    rgb = np.zeros((10, 10, 3), np.float32)
    keep = gate_before_map(p, p, rgb, rgb, np.ones((10, 10)), np.ones((10, 10)), 0.5, 0.95)
    assert keep.all()


def test_light_changed_is_read_from_keyframes_and_bad_values_are_named(tmp_path):
    import pandas as pd
    import pytest

    from gdiff.errors import SceneError
    from gdiff.partition.data import light_changed

    f = tmp_path / "keyframes.csv"
    base = {"path": ["p1", "p2"], "frame": [0, 3]}
    pd.DataFrame(base).to_csv(f, index=False)
    assert light_changed(f) is False  # keyframes written before the column existed
    pd.DataFrame({**base, "light_changed": [True, True]}).to_csv(f, index=False)
    assert light_changed(f) is True
    pd.DataFrame({**base, "light_changed": [False, False]}).to_csv(f, index=False)
    assert light_changed(f) is False
    pd.DataFrame({**base, "light_changed": ["yes", None]}).to_csv(f, index=False)
    with pytest.raises(SceneError, match=r"keyframes\.csv: column light_changed"):
        light_changed(f)
