"""Per-image colour correction in the fit (gdiff.splat.exposure).

A synthetic scene with no change is photographed with auto exposure: every training image gets
its own gain of up to +-1 stop. Fitted with the correction, the model renders one scene at both
times (no difference a later stage could take for a change) and the true colours at novel
views; fitted without, the gains are learnt as changes over time.
"""

import dataclasses

import cv2
import numpy as np
import pandas as pd
import pytest
import torch

from gdiff.io import linear_to_srgb, read_image, srgb_to_linear, write_image
from gdiff.splat.exposure import ExposureCorrection
from gdiff.splat.losses import psnr
from gdiff.splat.model import load_model
from gdiff.splat.render import render
from gdiff.synth import get_preset, make_scene

from test_fit import known_inputs, small_options

SEED = 5
STOPS = 1.0


def test_identity_at_start_and_regularizer():
    ex = ExposureCorrection(3)
    img = torch.rand(4, 5, 3)
    assert torch.equal(ex(img, 1), img)
    assert float(ex.regularizer(2).detach()) == 0.0
    with torch.no_grad():
        ex.matrix[2] *= 2.0
        ex.bias[2] += 0.1
    assert torch.allclose(ex(img, 2), 2.0 * img + 0.1)
    assert float(ex.regularizer(2).detach()) == pytest.approx(3 * 1.0 + 3 * 0.01)
    table = ex.table(["a.png", "b.png", "c.png"])
    assert list(table["gain"].round(6)) == [1.0, 1.0, 2.0]
    with pytest.raises(ValueError):
        ex.table(["a.png"])


@pytest.fixture(scope="module")
def jittered(tmp_path_factory):
    """A no-change scene; every training photo brightened or darkened by up to 1 stop."""
    root = tmp_path_factory.mktemp("exposure")
    preset = dataclasses.replace(get_preset("tiny"), width=80, height=60, supersample=2,
                                 n_before=8, n_after=8, n_eval=3, n_added=0, n_removed=0,
                                 n_moved=0)
    make_scene(root / "scene", preset, SEED)
    rng = np.random.default_rng(SEED)
    for set_ in ("before", "after"):
        for path in sorted((root / "scene" / set_).glob("*.png")):
            gain = 2.0 ** rng.uniform(-STOPS, STOPS)
            write_image(path, linear_to_srgb(np.clip(srgb_to_linear(read_image(path)) * gain,
                                                     0, 1)))
    return known_inputs(root, preset, SEED)


def _affine_fit(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """``src`` [H, W, 3] mapped by the least-squares global affine colour transform onto
    ``dst`` (removes the gauge: a fit's overall colour scale is a choice, not an error)."""
    x = np.concatenate([src.reshape(-1, 3), np.ones((src.size // 3, 1))], 1)
    a, *_ = np.linalg.lstsq(x, dst.reshape(-1, 3), rcond=None)
    return (x @ a).reshape(src.shape)


def _fit_and_score(scene, out, exposure: bool, **options):
    """(fraction of changed 4x4 blocks between t=0 and t=1, PSNR against the true photos) at
    the eval views, both up to one global colour transform per view."""
    from gdiff.splat.train import fit_scene

    fit_scene(scene.dir, scene.cameras, scene.points, out,
              small_options(exposure=exposure, checkpoint_every=0, **options), device="cpu")
    model = load_model(out / "model.pt", "cpu")
    changed, quality = [], []
    with torch.no_grad():
        for cam in scene.synth.cameras("eval_before"):
            r0, r1 = (render(model, [cam], t)["rgb"][0].clamp(0, 1).numpy() for t in (0.0, 1.0))
            small = [cv2.resize(r, (cam.width // 4, cam.height // 4), interpolation=cv2.INTER_AREA)
                     for r in (r0, r1)]
            diff = np.abs(_affine_fit(small[1], small[0]) - small[0]).max(-1)
            changed.append(float((diff > 0.1).mean()))
            truth = read_image(scene.dir / cam.image)
            aligned = _affine_fit(r0, truth).astype(np.float32)
            quality.append(float(psnr(torch.from_numpy(aligned), torch.from_numpy(truth))))
    return float(np.mean(changed)), float(np.mean(quality))


def test_exposure_jitter_is_not_learnt_as_a_change(jittered, tmp_path, torch_threads):
    """The default fit renders one scene at both times. The correction's own share is measured
    with the price on change over time off (``time_change_weight`` 0), which otherwise also
    takes up part of the jitter: without the correction the gains are then learnt as change."""
    torch_threads(1)  # the fits as measured (one thread); the worker's count comes back after
    changed, _ = _fit_and_score(jittered, tmp_path / "default", True)
    changed_on, psnr_on = _fit_and_score(jittered, tmp_path / "on", True, time_change_weight=0.0)
    changed_off, psnr_off = _fit_and_score(jittered, tmp_path / "off", False,
                                           time_change_weight=0.0)
    print(f"changed blocks default {changed:.4f}, free on/off {changed_on:.4f}/"
          f"{changed_off:.4f}, eval PSNR on/off {psnr_on:.2f}/{psnr_off:.2f}")
    gains = pd.read_csv(tmp_path / "default" / "exposure.csv")["gain"]
    assert gains.std() > 0.03  # the transforms took up the jitter ...
    assert not (tmp_path / "off" / "exposure.csv").exists()
    assert changed <= 0.02 and changed_on <= 0.02  # ... so the two times render one scene
    assert changed_on < 0.5 * changed_off
    assert psnr_on > psnr_off
