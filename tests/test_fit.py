"""The fit stage end to end on a small synthetic scene (gdiff.synth 'tiny', reduced size).

The SfM point cloud is made here by back-projecting the synth scene's ground-truth depth (a
test helper: the workflow's points come from the poses stage).
"""

import dataclasses
import re
import shutil
from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest
import torch

from gdiff.cameras import load_cameras, save_cameras
from gdiff.errors import SceneError, TrainingError
from gdiff.io import read_image, write_image
from gdiff.splat.exposure import affine_colour_match
from gdiff.splat.losses import psnr
from gdiff.splat.model import GaussianModel4D, load_model
from gdiff.splat.ply import read_gaussians, write_points
from gdiff.splat.render import render, render_main
from gdiff.splat.train import FitOptions, fit_scene
from gdiff.synth import build_scene, get_preset, make_scene

SEED = 3
DARKEN = 0.7


def backprojected_points(synth, cameras, state, fraction=0.08, noise=0.005, seed=0):
    """SfM-like points: a random fraction of each camera's pixels lifted with true depth."""
    rng = np.random.default_rng(seed)
    pts, cols = [], []
    for cam in cameras:
        r = synth.render(cam, state, supersample=1)
        h, w = r["depth"].shape
        sel = rng.random(h * w) < fraction
        j, i = np.divmod(np.flatnonzero(sel), w)
        z = r["depth"].ravel()[sel]
        x = (i + 0.5 - cam.cx) / cam.fx * z
        y = (j + 0.5 - cam.cy) / cam.fy * z
        p = np.stack([x, y, z, np.ones_like(z)], 1) @ cam.c2w.T
        pts.append(p[:, :3] + rng.normal(0, noise, (len(z), 3)))
        cols.append(r["rgb"].reshape(-1, 3)[sel])
    return np.concatenate(pts), np.concatenate(cols)


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    root = tmp_path_factory.mktemp("fit")
    preset = dataclasses.replace(get_preset("tiny"), width=80, height=60, supersample=2,
                                 n_before=8, n_after=8, n_eval=2)
    make_scene(root / "scene", preset, SEED)
    # a global lighting change on top of the object changes: every after image is darker
    for path in sorted((root / "scene").glob("**/after/*.png")):
        write_image(path, read_image(path) * DARKEN)
    return known_inputs(root, preset, SEED)


def known_inputs(root, preset, seed) -> SimpleNamespace:
    """The fit's inputs for the synth scene in ``root/scene``: ground-truth cameras
    (``root/cameras.json``) and back-projected points (``root/points.ply``)."""
    synth = build_scene(preset, seed)
    cams = sum((synth.cameras(s) for s in ("before", "after", "eval_before", "eval_after")), [])
    save_cameras(root / "cameras.json", cams)
    pb = backprojected_points(synth, synth.cameras("before")[::2], "before")
    pa = backprojected_points(synth, synth.cameras("after")[::2], "after", seed=1)
    write_points(root / "points.ply", np.concatenate([pb[0], pa[0]]),
                 np.concatenate([pb[1], pa[1]]))
    return SimpleNamespace(root=root, dir=root / "scene", cameras=root / "cameras.json",
                           points=root / "points.ply", synth=synth)


def small_options(**kw) -> FitOptions:
    # a short schedule: faster Gaussian learning rates than the full-length defaults
    base = dict(coarse_iters=100, fine_iters=100, max_side=80, densify_from=30,
                densify_every=30, densify_until=170, opacity_reset_every=0,
                sh_degree_interval=50, checkpoint_every=100, log_every=5,
                hexplane_resolution=[16, 16, 16], max_gaussians=4000, lr_sh0=5e-3,
                lr_scales=1e-2)
    base.update(kw)
    return FitOptions(**base)


@pytest.fixture(scope="module")
def fitted(scene):
    out = scene.root / "out"
    summary = fit_scene(scene.dir, scene.cameras, scene.points, out, small_options(),
                        device="cpu")
    return SimpleNamespace(out=out, summary=summary)


def test_fit_outputs_loss_falls_and_quality(scene, fitted):
    out, s = fitted.out, fitted.summary
    for name in ("model.pt", "gaussians_t0.ply", "gaussians_t1.ply", "train_log.csv",
                 "quality.csv"):
        assert (out / name).is_file(), name
    assert not (out / "ckpt" / "last.pt").exists()  # removed after a successful fit
    assert s["iterations"] == 200 and s["resumed_from"] == 0
    assert (s["width"], s["height"]) == (80, 60)
    log = pd.read_csv(out / "train_log.csv")
    assert {"iteration", "phase", "loss", "l1", "ssim", "psnr", "n_gaussians", "seconds",
            "plane_tv", "time_l1"} <= set(log.columns)
    assert log["iteration"].tolist() == list(range(5, 201, 5))
    assert set(log["phase"]) == {"coarse", "fine"}
    # the coarse phase works on half-size images (coarse_downscale=2): compare within it
    coarse = log[log["phase"] == "coarse"]["loss"]
    k = len(coarse) // 4
    assert coarse.iloc[-k:].mean() < 0.7 * coarse.iloc[:k].mean()
    q = pd.read_csv(out / "quality.csv")
    assert len(q) == 16 and set(q["set"]) == {"before", "after"}
    assert set(q["time"]) == {0.0, 1.0}
    # floor for 200 iterations on a heavily textured 80x60 scene (a full run reaches far
    # higher; the SfM initialisation renders at about 15-18 dB)
    for t in (0, 1):
        assert s[f"psnr_t{t}"] > 18.5, s
    assert q["ssim"].min() > 0.5
    # the other time's render at each photo: a guess where the times do not share Gaussians
    # and wrong on the changed objects, so below the own time's, but a render of the scene
    assert q["psnr_other_time"].notna().all()
    assert q["psnr_other_time"].mean() < q["psnr"].mean()
    assert q["psnr_other_time"].min() > 12.0
    assert abs(s["psnr_other_time"] - q["psnr_other_time"].mean()) < 1e-6


def test_affine_colour_match_undoes_an_exposure_and_white_balance():
    g = torch.Generator().manual_seed(0)
    pred = torch.rand(30, 40, 3, generator=g)
    A = torch.tensor([[0.6, 0.05, 0.0], [0.0, 0.5, 0.1], [0.02, 0.0, 0.7]])
    photo = pred @ A.T + torch.tensor([0.05, 0.1, 0.0])
    assert torch.allclose(affine_colour_match(pred, photo), photo, atol=1e-5)
    assert float((pred - photo).abs().mean()) > 0.1  # unmatched, the two differ


def test_densification_changes_the_count(scene, fitted):
    log = pd.read_csv(fitted.out / "train_log.csv")
    n0 = len(read_points_count(scene.points))
    before = log[log["iteration"] < 60]["n_gaussians"]
    assert (before == n0).all()  # nothing changes before the first refinement (iteration 60)
    grown = log[(log["iteration"] >= 60) & (log["iteration"] <= 150)]["n_gaussians"]
    assert grown.max() > n0  # early gradients are high: Gaussians are cloned / split
    assert grown.max() <= 4000  # max_gaussians caps growth
    after = log[log["iteration"] > 150]["n_gaussians"]
    assert after.nunique() == 1  # no density control after densify_until
    assert fitted.summary["n_gaussians"] == int(after.iloc[-1])


def read_points_count(path):
    from gdiff.splat.ply import read_points

    return read_points(path)[0]


def test_model_file_renders_training_views_and_depth(scene, fitted):
    model = load_model(fitted.out / "model.pt", "cpu")
    assert model.meta["camera"]["width"] == 80 and model.deforming
    q = pd.read_csv(fitted.out / "quality.csv").set_index("image")
    cams = [c for c in load_cameras(scene.cameras) if c.set == "after"][:3]
    with torch.no_grad():
        out = render(model, cams, 1.0)
    assert out["rgb"].shape == (3, 60, 80, 3) and out["depth"].shape == (3, 60, 80, 1)
    for i, cam in enumerate(cams):
        gt = scene.synth.render(cam, "after", supersample=1)
        img = torch.from_numpy(read_image(scene.dir / cam.image))
        p = float(psnr(out["rgb"][i].clamp(0, 1), img))
        assert abs(p - q.loc[cam.image, "psnr"]) < 1e-3
        # rendered depth follows the true geometry where the model is opaque
        d = out["depth"][i, ..., 0].numpy()
        ok = out["alpha"][i, ..., 0].numpy() > 0.5
        rel = np.abs(d[ok] - gt["depth"][ok]) / gt["depth"][ok]
        assert ok.mean() > 0.6 and np.median(rel) < 0.05


def test_ply_files_hold_the_deformed_gaussians(fitted):
    model = load_model(fitted.out / "model.pt", "cpu")
    for t in (0, 1):
        g = read_gaussians(fitted.out / f"gaussians_t{t}.ply")
        with torch.no_grad():
            ref = model.at_time(float(t))
        assert len(g) == len(ref) and g.sh.shape == ref.sh.shape
        assert torch.allclose(g.means, ref.means, atol=1e-5)
        assert torch.allclose(g.opacities, ref.opacities, atol=1e-4)
        assert torch.allclose(g.scales, ref.scales, rtol=1e-4)


def test_colour_deformation_absorbs_the_lighting_change(scene, fitted):
    """At eval views (never trained on) the model renders each time with its own lighting:
    t=1 is darker than t=0 by the factor applied to the after images, and matches the after
    image far better than the t=0 render does."""
    model = load_model(fitted.out / "model.pt", "cpu")
    cams = [c for c in load_cameras(scene.cameras) if c.set == "eval_after"]
    with torch.no_grad():
        r0 = render(model, cams, 0.0, render_mode="RGB")["rgb"].clamp(0, 1)
        r1 = render(model, cams, 1.0, render_mode="RGB")["rgb"].clamp(0, 1)
    ratio = float(r1.mean() / r0.mean())
    assert abs(ratio - DARKEN) < 0.08, ratio
    for i, cam in enumerate(cams):
        gt = torch.from_numpy(read_image(scene.dir / cam.image))
        assert float(psnr(r1[i], gt)) > float(psnr(r0[i], gt)) + 2.0


def test_object_changes_show_between_t0_and_t1_at_novel_views(scene, fitted):
    """Added / removed objects: at eval views the t=1 render differs from the t=0 render
    (beyond the global lighting factor) inside the true change mask, not outside it."""
    d_in, d_out, d_true = _change_at_eval_views(scene, load_model(fitted.out / "model.pt",
                                                                  "cpu"))
    assert d_in > 3.0 * d_out, (d_in, d_out)
    assert d_in > 0.5 * d_true, (d_in, d_true)


def _change_at_eval_views(scene, model) -> tuple[float, float, float]:
    """Mean per-pixel change between the t=0 and t=1 renders of ``model`` that the lighting
    factor does not explain, at the eval views, inside and outside the true change masks, and
    the same change of the eval photos inside the masks."""
    from gdiff.io import read_mask

    cams = [c for c in load_cameras(scene.cameras) if c.set == "eval_after"]
    with torch.no_grad():
        r0 = render(model, cams, 0.0, render_mode="RGB")["rgb"].clamp(0, 1)
        r1 = render(model, cams, 1.0, render_mode="RGB")["rgb"].clamp(0, 1)
    inside, outside, truth = [], [], []
    for i, cam in enumerate(cams):
        name = cam.image.split("/")[-1]
        mask = torch.from_numpy(read_mask(scene.dir / "eval" / "masks" / name))
        resid = (r1[i] - DARKEN * r0[i]).abs().mean(-1)
        g0 = torch.from_numpy(read_image(scene.dir / "eval" / "before" / name))
        g1 = torch.from_numpy(read_image(scene.dir / "eval" / "after" / name))
        inside.append(resid[mask])
        outside.append(resid[~mask])
        truth.append((g1 - DARKEN * g0).abs().mean(-1)[mask])
    return (float(torch.cat(inside).mean()), float(torch.cat(outside).mean()),
            float(torch.cat(truth).mean()))


def test_resume_after_interruption_matches_uninterrupted(scene, tmp_path):
    opts = small_options(coarse_iters=25, fine_iters=25, densify_from=10, densify_every=10,
                         densify_until=45, checkpoint_every=15, log_every=5, max_gaussians=4000)
    ref = fit_scene(scene.dir, scene.cameras, scene.points, tmp_path / "ref", opts, "cpu")

    class Stop(Exception):
        pass

    def interrupt(trainer):
        if trainer.iteration == 35:  # in the fine phase, after the checkpoint at 30
            raise Stop

    out = tmp_path / "run"
    with pytest.raises(Stop):
        fit_scene(scene.dir, scene.cameras, scene.points, out, opts, "cpu", callback=interrupt)
    assert (out / "ckpt" / "last.pt").is_file() and not (out / "model.pt").exists()
    shutil.copy(out / "ckpt" / "last.pt", tmp_path / "saved.pt")
    # a process killed while writing the next checkpoint leaves a half-written temporary file
    half = out / "ckpt" / ".last.k1ll3d.tmp.pt"
    half.write_bytes((out / "ckpt" / "last.pt").read_bytes()[:1000])
    res = fit_scene(scene.dir, scene.cameras, scene.points, out, opts, "cpu")
    assert not half.exists() and not list(out.rglob("*.tmp*"))
    assert res["resumed_from"] == 30 and res["iterations"] == ref["iterations"] == 50
    assert res["n_gaussians"] == ref["n_gaussians"]
    for t in (0, 1):
        assert abs(res[f"psnr_t{t}"] - ref[f"psnr_t{t}"]) < 0.3
    a = pd.read_csv(out / "train_log.csv")
    b = pd.read_csv(tmp_path / "ref" / "train_log.csv")
    assert a["iteration"].tolist() == b["iteration"].tolist()
    np.testing.assert_allclose(a["loss"], b["loss"], rtol=1e-3, atol=1e-4)
    # a checkpoint made with other options is not resumed
    shutil.copy(tmp_path / "saved.pt", out / "ckpt" / "last.pt")
    started = []

    def first(trainer):
        started.append(trainer.iteration)
        raise Stop

    other = dataclasses.replace(opts, ssim_lambda=0.3)
    with pytest.raises(Stop):
        fit_scene(scene.dir, scene.cameras, scene.points, out, other, "cpu", callback=first)
    assert started == [1]


def test_divergence_raises_training_error_naming_iteration_and_checkpoint(scene, tmp_path):
    opts = small_options(coarse_iters=30, fine_iters=0, checkpoint_every=10, densify_from=1000)

    def poison(trainer):
        if trainer.iteration == 25:
            with torch.no_grad():
                trainer.model.splats["sh0"].fill_(float("nan"))

    with pytest.raises(TrainingError, match=r"iteration 26.*ckpt.*last\.pt.*iteration 20"):
        fit_scene(scene.dir, scene.cameras, scene.points, tmp_path / "o", opts, "cpu",
                  callback=poison)


def test_divergence_after_an_opacity_reset_names_the_hold(scene, tmp_path):
    """A fit that diverges after the opacity reset (at iteration 20, in the fine phase) names
    the reset and fit.reset_hold; with a hold set, or before the reset, it does not."""
    def poison_at(n):
        def poison(trainer):
            if trainer.iteration == n:
                with torch.no_grad():
                    trainer.model.splats["sh0"].fill_(float("nan"))
        return poison

    def message(hold, n):
        opts = small_options(coarse_iters=10, fine_iters=20, checkpoint_every=0,
                             densify_from=5, densify_every=5, densify_until=30,
                             opacity_reset_every=20, reset_hold=hold)
        with pytest.raises(TrainingError) as e:
            fit_scene(scene.dir, scene.cameras, scene.points, tmp_path / f"o{hold}_{n}", opts,
                      "cpu", callback=poison_at(n))
        return str(e.value)

    assert re.search(r"iteration 26.*opacity reset at iteration 20.*fit\.reset_hold: 100",
                     message(0, 25))
    assert "reset_hold" not in message(0, 15)  # before the reset
    assert "reset_hold" not in message(5, 25)  # already held


def test_fit_that_prunes_every_gaussian_stops_with_a_training_error(scene, tmp_path):
    """A refine step that leaves no Gaussian (every opacity under the prune threshold, as after
    an opacity reset they did not recover from) stops the fit with a clear error, not a model
    of nothing."""
    opts = small_options(coarse_iters=40, fine_iters=0, densify_from=5, densify_every=10,
                         opacity_reset_every=0)

    def fade(trainer):
        if trainer.iteration == 25:
            with torch.no_grad():
                trainer.model.splats["opacities"].fill_(-20.0)

    with pytest.raises(TrainingError, match=r"collapsed at iteration 30.*pruned every "
                                            r"Gaussian.*fit\.seed"):
        fit_scene(scene.dir, scene.cameras, scene.points, tmp_path / "o", opts, "cpu",
                  callback=fade)
    assert not (tmp_path / "o" / "model.pt").exists()


@pytest.mark.parametrize("hold", [15, 0])
def test_deformation_field_is_held_after_an_opacity_reset(scene, tmp_path, hold):
    """For ``reset_hold`` iterations after the opacity reset (after iteration 40) the
    deformation field does not move; before and after that window it learns (and without a
    hold it moves inside the window too)."""
    opts = small_options(coarse_iters=20, fine_iters=45, densify_from=10, densify_every=10,
                         densify_until=60, opacity_reset_every=40, reset_hold=hold,
                         checkpoint_every=0)
    snaps = {}

    def snap(trainer):
        with torch.no_grad():
            snaps[trainer.iteration] = torch.cat(
                [p.detach().flatten().clone() for p in trainer.model.deformation.parameters()])

    fit_scene(scene.dir, scene.cameras, scene.points, tmp_path / "o", opts, "cpu",
              callback=snap)
    moved = {d: not torch.equal(snaps[d], snaps[d - 1]) for d in range(22, 66)}
    assert moved[39] and moved[40]  # learning up to the reset (done 40)
    inside = [moved[d] for d in range(41, 56)]  # steps 40..54, right after the reset
    assert not any(inside) if hold else all(inside)
    assert moved[56] and moved[60]  # and again after the hold


def test_inputs_without_after_images_are_rejected(scene, tmp_path):
    cams = [c for c in load_cameras(scene.cameras) if c.set == "before"]
    save_cameras(tmp_path / "c.json", cams)
    with pytest.raises(SceneError, match="after"):
        fit_scene(scene.dir, tmp_path / "c.json", scene.points, tmp_path / "o", small_options())


def test_render_cli(scene, fitted, tmp_path):
    model_path = fitted.out / "model.pt"
    out = tmp_path / "r"
    assert render_main(["--model", str(model_path), "--cameras", str(scene.cameras),
                        "--set", "eval_after", "--t", "0", "--t", "1", "--out", str(out),
                        "--depth"]) == 0
    assert sorted(p.name for p in (out / "t1").iterdir()) == [
        "00000.png", "00000_depth.npy", "00001.png", "00001_depth.npy"]
    assert (out / "t0" / "00001.png").is_file() and (out / "index.json").is_file()
    c2w = np.stack([c.c2w for c in load_cameras(scene.cameras)[:2]])
    np.save(tmp_path / "poses.npy", c2w)
    assert render_main(["--model", str(model_path), "--c2w", str(tmp_path / "poses.npy"),
                        "--t", "0.5", "--out", str(tmp_path / "p")]) == 0
    assert sorted(p.name for p in (tmp_path / "p" / "t0p5").iterdir()) == ["00000.png",
                                                                          "00001.png"]


@pytest.fixture(scope="module")
def narrow_after(scene, tmp_path_factory):
    """The tiny scene with after images from narrow cameras (1.8x the focal length): the
    border of what the before cameras see is never seen at t=1 (as when the two captures are
    taken from other places). Lighting is the same at both times."""
    root = tmp_path_factory.mktemp("narrow")
    (root / "scene").mkdir()
    shutil.copytree(scene.dir / "before", root / "scene" / "before")
    cams = []
    for cam in load_cameras(scene.cameras):
        if cam.set == "after":
            cam = dataclasses.replace(cam, fx=cam.fx * 1.8, fy=cam.fy * 1.8)
            write_image(root / "scene" / cam.image,
                        scene.synth.render(cam, "after", supersample=1)["rgb"])
        if cam.set in ("before", "after"):
            cams.append(cam)
    save_cameras(root / "cameras.json", cams)
    before = [c for c in cams if c.set == "before"]
    # evaluate at the before views: at t=1 only their middle part was ever seen
    uncovered = []
    for cam in before:
        d = scene.synth.render(cam, "after", supersample=1)["depth"]
        j, i = np.mgrid[:cam.height, :cam.width]
        x = (i + 0.5 - cam.cx) / cam.fx * d
        y = (j + 0.5 - cam.cy) / cam.fy * d
        p = np.stack([x, y, d, np.ones_like(d)], -1).reshape(-1, 4) @ cam.c2w.T
        seen = np.zeros(len(p), bool)
        for a in (c for c in cams if c.set == "after"):
            q = p @ a.w2c.T
            u, v = a.fx * q[:, 0] / q[:, 2] + a.cx, a.fy * q[:, 1] / q[:, 2] + a.cy
            seen |= (q[:, 2] > 0) & (u >= 0) & (u < a.width) & (v >= 0) & (v < a.height)
        uncovered.append(torch.from_numpy(~seen.reshape(d.shape)))
    return SimpleNamespace(dir=root / "scene", cameras=root / "cameras.json", before=before,
                           uncovered=torch.stack(uncovered), points=scene.points, root=root)


@pytest.mark.parametrize("min_views", [2, 0])
def test_parts_seen_at_one_time_only_keep_their_state_at_the_other(narrow_after, min_views):
    """Where no after image looks, the t=1 render must not fall apart. With the time gate
    (``time_min_views`` = 2) it matches the t=0 render there (those Gaussians have no change
    term) more closely than t=0 and t=1 agree where both were seen; without it (0) each t=0
    update moves the shared opacity up and the change term down, so those parts stay near
    their initial opacity at t=1."""
    s = narrow_after
    opts = small_options(coarse_iters=40, fine_iters=30, densify_from=1000,
                         time_min_views=min_views, time_change_weight=0.0)
    fit_scene(s.dir, s.cameras, s.points, s.root / f"out{min_views}", opts, device="cpu")
    model = load_model(s.root / f"out{min_views}" / "model.pt", "cpu")
    with torch.no_grad():
        r0, r1 = (render(model, s.before, t, render_mode="RGB") for t in (0.0, 1.0))
    out = s.uncovered
    assert 0.1 < float(out.float().mean()) < 0.8  # the narrow cameras miss a real border
    a0, a1 = r0["alpha"][..., 0][out], r1["alpha"][..., 0][out]
    diff = (r1["rgb"] - r0["rgb"]).abs().mean(-1)
    d_out, d_in = float(diff[out].mean()), float(diff[~out].mean())
    assert float(a0.mean()) > 0.75  # the t=0 fit covers the border
    if min_views:  # (measured: |alpha change| 0.01, colour change 0.01 vs 0.06 inside)
        assert float((a1 - a0).abs().mean()) < 0.04, float((a1 - a0).abs().mean())
        assert d_out < 0.5 * d_in, (d_out, d_in)
    else:  # the failure the gate prevents (measured: t=1 alpha 0.58 vs 0.88 at t=0)
        assert float(a1.mean()) < float(a0.mean()) - 0.2
        assert d_out > 2.0 * d_in, (d_out, d_in)


def test_time_terms_can_be_switched_off_and_resumed(scene, tmp_path):
    opts = small_options(coarse_iters=10, fine_iters=10, densify_from=1000, checkpoint_every=10,
                         time_opacity=False, time_color=False)
    seen, stop = [], [True]

    class Stop(Exception):
        pass

    def interrupt(trainer):
        seen.append(sorted(trainer.model.splats.keys()))
        if trainer.iteration == 15 and stop:  # only the first run stops
            stop.pop()
            raise Stop

    with pytest.raises(Stop):
        fit_scene(scene.dir, scene.cameras, scene.points, tmp_path, opts, "cpu",
                  callback=interrupt)
    res = fit_scene(scene.dir, scene.cameras, scene.points, tmp_path, opts, "cpu",
                    callback=interrupt)
    assert res["resumed_from"] == 10 and res["iterations"] == 20
    assert all("dopacity" not in k and "dsh0" not in k for k in seen)
    model = load_model(tmp_path / "model.pt", "cpu")  # files load; no change over time
    assert torch.equal(model.splats["dopacity"], torch.zeros(len(model)))


def _opacity_changes(model) -> float:
    """Share of the Gaussians opaque at either time (> 0.3) whose opacity differs between the
    times by more than 0.5."""
    with torch.no_grad():
        o0, o1 = model.at_time(0.0).opacities, model.at_time(1.0).opacities
    vis = torch.maximum(o0, o1) > 0.3
    return float(((o1 - o0).abs()[vis] > 0.5).float().mean())


def test_time_change_weight_shares_gaussians_between_the_times(scene, fitted, tmp_path):
    """The higher ``time_change_weight``, the more the times share their Gaussians: at 0.01 far
    fewer change opacity between t=0 and t=1 than in the default fit (0.001; this short fit
    changes about as many as a free one), the training images are fitted as well, and the
    added and removed objects still show between the t=0 and t=1 renders at novel views."""
    summary = fit_scene(scene.dir, scene.cameras, scene.points, tmp_path,
                        small_options(time_change_weight=0.01), device="cpu")
    default = load_model(fitted.out / "model.pt", "cpu")
    shared = load_model(tmp_path / "model.pt", "cpu")
    c_default, c_shared = _opacity_changes(default), _opacity_changes(shared)
    assert c_shared < 0.5 * c_default, (c_shared, c_default)
    for k in ("psnr_t0", "psnr_t1"):
        assert summary[k] > fitted.summary[k] - 0.5, (k, summary[k], fitted.summary[k])
    # sharing more, each time's render draws the other time's photos better
    assert summary["psnr_other_time"] > fitted.summary["psnr_other_time"], (
        summary["psnr_other_time"], fitted.summary["psnr_other_time"])
    log = pd.read_csv(tmp_path / "train_log.csv")
    assert "time_change" in log.columns and log["time_change"].notna().all()
    d_in, d_out, _ = _change_at_eval_views(scene, shared)
    assert d_in > 3.0 * d_out, (d_in, d_out)


def test_saturating_change_price_keeps_the_objects_and_shares_the_rest(scene, fitted,
                                                                       tmp_path):
    """``time_change_scale``: a price ten times the default's, saturating beyond half a logit,
    shares more Gaussians between the times than the default fit, and the added and removed
    objects still show between the t=0 and t=1 renders at novel views."""
    summary = fit_scene(scene.dir, scene.cameras, scene.points, tmp_path,
                        small_options(time_change_weight=0.01, time_change_scale=0.5),
                        device="cpu")
    shared = load_model(tmp_path / "model.pt", "cpu")
    default = load_model(fitted.out / "model.pt", "cpu")
    assert _opacity_changes(shared) < _opacity_changes(default)
    for k in ("psnr_t0", "psnr_t1"):
        assert summary[k] > fitted.summary[k] - 0.5, (k, summary[k], fitted.summary[k])
    d_in, d_out, _ = _change_at_eval_views(scene, shared)
    assert d_in > 3.0 * d_out, (d_in, d_out)


def test_opacity_change_price_saturates_with_a_scale():
    m = GaussianModel4D(4, sh_degree=0, deform=None)
    with torch.no_grad():
        m.splats["dopacity"].copy_(torch.tensor([0.0, 0.01, -2.0, 6.0]))
    gate = torch.tensor([1.0, 1.0, 1.0, 0.0])  # the last one's change is not learnt
    price = lambda *a: float(m.opacity_change(*a).detach())  # noqa: E731
    assert price(gate) == pytest.approx((0.01 + 2.0) / 3)
    s = 0.5
    want = (s * np.log1p(0.01 / s) + s * np.log1p(2.0 / s)) / 3
    assert price(gate, s) == pytest.approx(want, rel=1e-6)
    # a small change pays about as much either way, a whole one far less
    assert s * np.log1p(0.01 / s) == pytest.approx(0.01, rel=0.02)
    assert price(None, s) < 0.5 * price(None)


def test_short_fit_does_not_depend_on_the_thread_count(scene, tmp_path, torch_threads):
    """A short fit (densification included) gives the same model on one thread and on two:
    every Gaussian parameter and the deformation field bitwise equal, so the compiled kernels
    (rasterizer, projection, colours, HexPlane) sum in an order no thread count changes, and so
    do the deformation MLP's matrix products (MKL's strict mode, which importing gdiff sets;
    without it they parted at the first deformation step on an AVX-512 CPU). A
    full-length fit of a real capture still parts by rounding later on (README, "Repeatable
    results")."""
    opts = small_options(coarse_iters=25, fine_iters=25, densify_from=10, densify_every=10,
                         densify_until=45, checkpoint_every=100, log_every=5)
    models = []
    for nt in (1, 2):
        torch_threads(nt)
        fit_scene(scene.dir, scene.cameras, scene.points, tmp_path / str(nt), opts, "cpu")
        models.append(torch.load(tmp_path / str(nt) / "model.pt", weights_only=False))
    a, b = (m["state_dict"] for m in models)
    assert a.keys() == b.keys()
    for k in a:
        assert torch.equal(a[k], b[k]), k
